"""How many frames in a row share one error of the fitted extra noise (recorded poses drift, so
neighbours in time are wrong together), from the noise fit's own pairs of frames
(:func:`frames_sharing_noise`), and what it does to the data's part of the variance
(:func:`shared_noise_factor`)."""

from __future__ import annotations

import numpy as np

from .pairmodel import fit_extra, pair_quantile

__all__ = ["frames_sharing_noise", "shared_noise_factor"]

#: Pairs a gap of picked frames needs before its noise is fitted on its own.
MIN_GAP_PAIRS = 300
#: How far the near frames' pairs must sit below the far ones' model (cluster-robust z-score,
#: clusters = pairs of frames) before the frames are said to share their noise.
Z_SHARED = 4.0


def frames_sharing_noise(pairs: list, cut, e: float) -> dict:
    """``L``, the frames in a row that one error of the extra noise ``e`` spans, from pairs of
    frames that see one point (:func:`~.observe.estimate_extra_noise`'s candidates, each
    ending with its two frames' positions ``(a, b)``, ``a < b``, in the fused sequence, their
    time order): the fit's frames spread over the sequence, and each of them with the frame
    after it. ``cut(pairs)`` gives the pairs' ``|d|, s, t`` as the fit keeps them; the extra
    noise they hold is :func:`.pairmodel.fit_extra`'s.

    Two frames ``g = b - a`` apart differ by ``2 s^2 + 2 e^2 (1 - rho(g))``, ``rho`` the
    correlation of their extra noise: the noise ``e_g`` fitted to the pairs of one gap alone
    grows with the gap where frames share it. The gaps are grouped by the spread frames'
    spacing (the frames after them apart); ``e_far`` is the fit of the farthest third of the
    groups (each of at least :data:`MIN_GAP_PAIRS` pairs) together; ``rho_g = 1 - e_g^2 /
    e_far^2`` (clipped to [0, 1]) and ``rho(g) = exp(-(g / l)^2)``, ``l`` minimising ``sum
    n_g (rho_g - rho(g))^2`` on a log grid; ``L = 1 + 2 sum_{g >= 1} rho(g)``, the frames one
    independent error is worth.

    ``L`` is 1 unless the nearest group's pairs sit significantly below the far ones' model:
    the share of them whose ``|d|`` lies below its model median at ``e_far`` (1/2 where they
    hold as much noise) against the far pairs' own, ``z`` their difference over its standard
    error with the pairs of one pair of frames as one cluster (a frame's pixels share its
    pose), at least :data:`Z_SHARED`. Independent noise, and views too far apart to share
    points (a ring around an object: fewer than 3 groups of :data:`MIN_GAP_PAIRS` pairs),
    give ``L = 1``.

    Returns ``{"frames_sharing_noise": L, "sharing_z": z or None, "sharing_length": l or
    None}``."""
    none = {"frames_sharing_noise": 1.0, "sharing_z": None, "sharing_length": None}
    if e <= 0.0:  # no extra noise to share
        return none
    spread = [p[-1][1] - p[-1][0] for p in pairs if p[-1][1] - p[-1][0] > 1]
    spacing = float(min(spread)) if spread else 1.0
    groups: dict[int, list] = {}
    for p in pairs:
        g = p[-1][1] - p[-1][0]
        groups.setdefault(0 if g == 1 and spacing >= 2 else max(1, round(g / spacing)),
                          []).append(p)
    fits = []  # (the group's pairs, its mean gap, kept pairs, e_g)
    for k in sorted(groups):
        r, s, t = cut(groups[k])
        if len(r) >= MIN_GAP_PAIRS:
            gap = float(np.mean([p[-1][1] - p[-1][0] for p in groups[k]]))
            fits.append((groups[k], gap, len(r), _fit(r, s, t)))
    if len(fits) < 3:
        return none
    far = [p for f in fits[-max(1, len(fits) // 3):] for p in f[0]]
    e_far = _fit(*cut(far))
    if e_far <= 0.0:
        return none
    z = _below_far(fits[0][0], far, cut, e_far)
    if z < Z_SHARED:
        return dict(none, sharing_z=z)
    g = np.array([f[1] for f in fits])
    n = np.array([f[2] for f in fits], np.float64)
    rho = np.clip(1.0 - (np.array([f[3] for f in fits]) / e_far) ** 2, 0.0, 1.0)
    ells = np.geomspace(0.1, 10.0 * g.max(), 400)
    cost = [(n * (rho - np.exp(-(g / ell) ** 2)) ** 2).sum() for ell in ells]
    ell = float(ells[int(np.argmin(cost))])
    lags = np.arange(1, int(10 * ell) + 2)
    return {"frames_sharing_noise": float(1.0 + 2.0 * np.exp(-(lags / ell) ** 2).sum()),
            "sharing_z": z, "sharing_length": ell}


def _fit(r: np.ndarray, s: np.ndarray, t: np.ndarray) -> float:
    """:func:`.pairmodel.fit_extra` to 16 bisections (~1e-5 of the bracket: enough for a
    correlation)."""
    return fit_extra(r, s, t, steps=16)


def _below_far(near: list, far: list, cut, e_far: float) -> float:
    """The z-score of the near pairs' share below their model median at ``e_far`` against the
    far pairs' (clusters: the pairs of one pair of frames; see :func:`frames_sharing_noise`)."""
    def shares(pairs):  # per pair of frames: pairs below their model median, and all kept
        below, kept = [], []
        for p in pairs:
            r, s, t = cut([p])
            if len(r):
                below.append(np.count_nonzero(pair_quantile(r, s, t, e_far) < 0.5))
                kept.append(len(r))
        b, m = np.array(below, np.float64), np.array(kept, np.float64)
        p = b.sum() / m.sum()
        return p, ((b - p * m) ** 2).sum() / m.sum() ** 2

    p_near, v_near = shares(near)
    p_far, v_far = shares(far)
    return float((p_near - p_far) / np.sqrt(max(v_near + v_far, 1e-30)))


def shared_noise_factor(weight: np.ndarray, noise: dict) -> np.ndarray | None:
    """``kappa`` (N,) float64: how much more the data tell a voxel's variance than independent
    frames would, ``1 + (min(L, n) - 1) f``, ``n`` the frames that observed it (the bootstrap
    ``weight``), ``L`` the frames one error spans (:func:`frames_sharing_noise`) and ``f`` the
    share of a frame's variance that is the shared noise (``noise["shared_fraction"]``). The
    variance of a mean of ``n`` frames, each ``sigma^2`` of which ``f sigma^2`` is common to
    runs of ``L`` frames, is ``kappa sigma^2 / n``. None where ``L`` = 1 (nothing shared)."""
    L = float(noise.get("frames_sharing_noise", 1.0))
    f = float(noise.get("shared_fraction", 0.0))
    if L <= 1.0 or f <= 0.0:
        return None
    n = np.maximum(np.asarray(weight, np.float64), 1.0)
    return 1.0 + (np.minimum(L, n) - 1.0) * f
