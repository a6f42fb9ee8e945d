"""Frames close in time share their pose error (bftaichi.stages.sharednoise): the noise fit
finds how many frames in a row one error spans where the poses drift, and none where each
frame's error is its own; the data's part of the variance then counts those frames as one."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

import bftaichi as bf
from bftaichi.frame import local_frames
from bftaichi.running.pipeline import open_frames
from bftaichi.stages.band import build_band
from bftaichi.stages.observe import estimate_extra_noise
from bftaichi.stages.sharednoise import shared_noise_factor

RMS_M = 0.01 / np.sqrt(2)  # each frame's error along its camera axis
SPAN = 12.0  # the drift's correlation: exp(-(g / 17)^2), 30 frames per independent error


def _tabletop():
    """The tabletop from 48 views on a quarter turn of a spiral (all see the table)."""
    return bf.load_config(None, [
        "synthetic.width=160", "synthetic.height=120", "synthetic.fx=131.25",
        "synthetic.fy=131.25", "synthetic.cx=79.5", "synthetic.cy=59.5",
        "synthetic.n_views=48", "synthetic.trajectory=spiral", "synthetic.turns=0.25",
        "tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04"])


def _fit(cfg, frames, offsets):
    """The noise fit of ``frames`` fused at poses moved ``offsets`` along the camera axis."""
    recon = bf.Reconstructor(cfg)
    for f, o in zip(frames, offsets):
        T = np.array(f.T_W_C, np.float64)
        T[:3, 3] += o * T[:3, 2]
        recon.integrate(f.depth_m, f.K, T, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    return estimate_extra_noise(local_frames(recon.frames, recon.origin), band,
                                cfg.observation, cfg.tsdf.voxel_size_m,
                                cfg.tsdf.bootstrap_trunc_m, (0.1, 10.0))


@pytest.fixture(scope="module")
def fits():
    cfg = _tabletop()
    frames = list(open_frames(cfg))
    white = np.random.default_rng(0).normal(0, 1, len(frames))
    drift = gaussian_filter1d(white, SPAN / np.sqrt(2), mode="wrap")
    unordered = bf.load_config(None, ["observation.in_time_order=false"]).observation
    shuffle = np.random.default_rng(1).permutation(len(frames))
    return {"drift": _fit(cfg, frames, drift / drift.std() * RMS_M),
            "jitter": _fit(cfg, frames, white / white.std() * RMS_M),
            "none": _fit(cfg, frames, np.zeros(len(frames))),
            "unordered": _fit(replace(cfg, observation=unordered), frames,
                              drift / drift.std() * RMS_M),
            "shuffled": _fit(cfg, [frames[i] for i in shuffle],
                             (drift / drift.std() * RMS_M)[shuffle])}


def test_drifting_poses_share_their_error_over_many_frames(fits):
    """A smooth drift (correlation exp(-(g / 17)^2): L = 30 frames per error) is found as
    such: L within a factor 2.5 of it, significantly (z >= 4)."""
    fit = fits["drift"]
    assert 12 <= fit["frames_sharing_noise"] <= 75, fit
    assert fit["sharing_z"] >= 4 and fit["shared_fraction"] > 0.5


@pytest.mark.parametrize("kind", ["jitter", "none"])
def test_independent_or_no_pose_error_is_not_shared(fits, kind):
    """The same rms jittered independently per frame, or no pose error: L = 1, so the
    variance is what independent frames give."""
    fit = fits[kind]
    assert fit["frames_sharing_noise"] == 1.0, fit
    assert shared_noise_factor(np.full(10, 40.0), fit) is None


def test_drifting_poses_given_out_of_time_order_share_nothing(fits):
    """The same drifting frames shuffled: neighbours in the list are no longer neighbours in
    time, and the fit finds no sharing (L = 1) rather than inventing it."""
    assert fits["shuffled"]["frames_sharing_noise"] == 1.0, fits["shuffled"]


def test_frames_out_of_order_are_not_tested(fits):
    """observation.in_time_order = false: the fit does not look for sharing, so the variance
    counts the drifting frames as independent, and the fit's noise is the same."""
    assert "frames_sharing_noise" not in fits["unordered"]
    assert shared_noise_factor(np.full(3, 40.0), fits["unordered"]) is None
    assert fits["unordered"]["sigma_extra_m"] == fits["drift"]["sigma_extra_m"]


def test_shared_noise_factor_counts_a_run_of_frames_as_one():
    """kappa = 1 + (min(L, n) - 1) f: n frames that share all their noise (f = 1, n <= L)
    tell a voxel what one frame does (kappa = n); beyond L frames the errors average again."""
    n = np.array([1.0, 5.0, 30.0, 200.0])
    np.testing.assert_allclose(shared_noise_factor(n, {"frames_sharing_noise": 50.0,
                                                      "shared_fraction": 1.0}),
                               [1.0, 5.0, 30.0, 50.0])
    np.testing.assert_allclose(shared_noise_factor(n, {"frames_sharing_noise": 50.0,
                                                      "shared_fraction": 0.5}),
                               [1.0, 3.0, 15.5, 25.5])


def _sphere(order: str):
    """A 0.15 m sphere from 48 views on a quarter turn of a spiral, 1 cm voxels."""
    return bf.load_config(None, [
        "synthetic.mesh=sphere", "synthetic.radius_m=0.15", "synthetic.trajectory=spiral",
        "synthetic.turns=0.25", "synthetic.n_views=48", "synthetic.cam_radius_m=0.7",
        "synthetic.cam_height_m=0.2", "synthetic.cam_height_end_m=0.4",
        "synthetic.width=160", "synthetic.height=120", "synthetic.fx=140", "synthetic.fy=140",
        "synthetic.cx=79.5", "synthetic.cy=59.5", "tsdf.voxel_size_m=0.01",
        "tsdf.trunc_m=0.02", f"observation.in_time_order={order}"])


@pytest.mark.parametrize("seed", [1, 3])
def test_sigma_covers_the_error_of_drifting_poses(seed):
    """Poses that drift (6 mm rms along the camera axis, correlated over ~17 frames) move
    the whole surface together. Counted as independent frames, sigma leaves most of that out
    (58 / 62 % of the vertices within 2 sigma); counted as runs of frames that share one
    error, at least 95 % are within 2 sigma (wider than a Gaussian's 68 % within 1 sigma on
    this small scene: 87-92 %), and the surface is the same."""
    within, means = {}, {}
    for order in ("true", "false"):
        post = _drifted_sphere(_sphere(order), 0.006, seed)
        within[order] = _within_2_sigma(post)
        means[order] = post.mean
    assert within["true"] >= 0.95 and within["false"] <= 0.7, within
    np.testing.assert_array_equal(means["true"], means["false"])


def _drifted_sphere(cfg, rms_m: float, seed: int = 1):
    """:func:`_sphere` ``cfg``'s frames at poses drifting ``rms_m`` along the camera axis
    (correlated over ~17 frames), solved: the Posterior."""
    from conftest import solved

    off = gaussian_filter1d(np.random.default_rng(seed).normal(0, 1, 48), SPAN / np.sqrt(2),
                            mode="nearest")
    off = off / off.std() * rms_m
    frames = []
    for f, o in zip(open_frames(cfg), off):
        T = np.array(f.T_W_C, np.float64)
        T[:3, 3] += o * T[:3, 2]
        frames.append(type(f)(index=f.index, name=f.name, depth_m=f.depth_m, K=f.K,
                              T_W_C=T, rgb=None))
    return solved(cfg, frames)[1]


def _within_2_sigma(post) -> float:
    """The share of the sphere's mesh vertices within 2 sigma of the true surface."""
    mesh = post.extract_mesh()
    error = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.15)
    sigma = np.asarray(mesh.vertex_attributes["sigma"], np.float64)
    return float(np.mean(error <= 2 * sigma))


def _shared_in_map(on: bool):
    """:func:`_sphere` in time order, with ``observation.shared_in_map = on``."""
    cfg = _sphere("true")
    return replace(cfg, observation=replace(cfg.observation, shared_in_map=on))


def test_the_map_counts_a_run_of_frames_once_only_where_frames_share_their_error():
    """observation.shared_in_map: with the drift of the test above (L > 1) the MAP weighs
    each frame's shared error as one of a run of L, so the mean moves, and sigma still covers
    the error (at least 95 % of the vertices within 2 sigma); with poses that do not drift the
    fit finds L = 1 and the posterior is the same, bit for bit."""
    drifted = {s: _drifted_sphere(_shared_in_map(s), 0.006) for s in (False, True)}
    assert drifted[True].observations["noise_fit"]["frames_sharing_noise"] > 1.0
    assert not np.array_equal(drifted[True].mean, drifted[False].mean)
    assert _within_2_sigma(drifted[True]) >= 0.95
    still = {s: _drifted_sphere(_shared_in_map(s), 0.0) for s in (False, True)}
    assert still[True].observations["noise_fit"]["frames_sharing_noise"] == 1.0
    for field in ("mean", "var", "cov"):
        np.testing.assert_array_equal(getattr(still[True], field), getattr(still[False], field))


def _fit_extra_reference(r, s, t, steps):
    """The noise fit's bisection with the median of every pair at every step."""
    from bftaichi.stages.pairmodel import pair_quantile

    def stat(e):
        return float(np.median(pair_quantile(r, s, t, e)))

    if stat(0.0) <= 0.5:
        return 0.0
    lo, hi = 0.0, max(float(np.median(r)) / 0.6744897501960817, 1e-6)
    while stat(hi) > 0.5 and hi < 1.0:
        hi *= 2.0
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stat(mid) > 0.5 else (lo, mid)
    return hi


@pytest.mark.parametrize("seed", range(6))
def test_the_noise_fit_finds_the_plain_bisections_noise_bit_for_bit(seed):
    """fit_extra computes each step's median over fewer pairs (those that can still be the
    median): the same extra noise, to the bit, as the bisection over every pair, on even
    and odd counts, tied residuals, no extra noise and a heavy truncation."""
    from bftaichi.stages.pairmodel import fit_extra

    rng = np.random.default_rng(seed)
    n = [101, 5000, 40001, 2000, 3000, 60000][seed]
    s = rng.uniform(0.001, 0.01, n)
    e = [0.004, 0.0, 0.01, 0.003, 0.02, 0.002][seed]
    d = rng.normal(0.0, np.sqrt(s * s + 2 * e * e))
    if seed == 3:
        d = np.round(d, 3)  # many ties
    t = np.maximum(0.04 if seed != 4 else 0.005, 3 * s)  # seed 4: heavily truncated
    r = np.abs(d)
    keep = r < t
    r, s, t = r[keep], s[keep], t[keep]
    for steps in (40, 16):
        assert fit_extra(r, s, t, steps) == _fit_extra_reference(r, s, t, steps)
    if seed == 1:
        assert fit_extra(r, s, t) < 1e-3  # the sensor model alone, nearly
