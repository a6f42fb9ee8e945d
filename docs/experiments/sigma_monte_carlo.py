#!/usr/bin/env python
"""Sigma against what noise draws show: how much of the error is noise, how much bias (issue
15; a diagnosis).

One development-suite case (``tools/suite.py``'s mesh and capture condition, ``--data``'s
meshes) is fused ``--draws`` times, each with its own noise (``synthetic.seed``), and solved
four ways (``--set`` overrides go to all four): the default model; ``solver.prior_bias=false``
(the blend without the bias term: ``blend``); ``solver.variance=posterior
solver.prior_bias=false`` (the probes' ``B = Q^-1``); ``solver.variance=blend-sampled
solver.prior_bias=false``, from which the perturbation solves' sandwich ``S = Q^-1 D Q^-1``
and the data share ``rho = D_ii / Q_ii`` are kept. The draws then show, per band voxel kept
(observed) by every draw:

- ``noise``: the variance of the posterior mean over the draws;
- ``bias^2``: the squared difference between the draws' average mean and the true signed
  distance, less the noise of that average;
- ``mse = noise + bias^2``: what a calibrated variance equals on average.

Three tables, their columns the means over the rows' voxels or edges in mm^2:

1. the band voxels within ``--near`` voxels of the true surface, by quintiles of ``rho``;
2. the grid edges the true surface crosses: the mean interpolated at the crossing (true value
   0) against each variance interpolated there with its face covariance, ``(1 - t)^2 v0 + t^2
   v1 + 2 t (1 - t) c01`` (the mesh vertices' sigma, DESIGN.md 3.7), and the 1-sigma coverage
   of that value over all draws. Rows ``near``: the edges where every draw's value is within a
   voxel, i.e. where the posterior has a surface and so its mesh has vertices (the suite's
   vertex errors are measured there); ``far``: the true surface has no posterior surface
   within a voxel (holes, bridged gaps), which the vertex errors never see;
3. the near edges' signed bias by the true SDF's Laplacian times the voxel size (> 0 convex),
   from the voxels whose six face neighbours every draw keeps; beside it the bootstrap TSDF's
   value at the crossing, the same way.

Usage::

    python docs/experiments/sigma_monte_carlo.py suzanne sparse_far --draws 6
    python docs/experiments/sigma_monte_carlo.py suzanne sparse_far --draws 6 --exact
    python docs/experiments/sigma_monte_carlo.py suzanne dense_near --draws 6 \
        --set observation.local_noise=false --set observation.fit_noise=false
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

VARIANTS = {"default": [], "blend": ["solver.prior_bias=false"],
            "B": ["solver.variance=posterior", "solver.prior_bias=false"],
            "S": ["solver.variance=blend-sampled", "solver.prior_bias=false"]}
CAPTURED = {}


def _capture(exact: bool = False):
    """Keep the sandwich ``S`` the perturbation solves estimate and the data share ``rho``
    (the ``S`` variant's ``var`` is replaced by them: ``var`` = S, ``cov[:, 0]`` = rho).
    ``exact``: ``S`` is instead ``diag(Q^-1 D Q^-1)`` with ``D`` the accumulated data stencil
    itself (not the perturbations' box-spread one), by the colouring probes: ``X = Q^-1 D
    Q^-1 Z``, two batched solves, deterministic (docs/experiments/exact_sandwich.patch)."""
    import kernels.probes as probes
    from bftaichi.stages import variance

    moments, share = probes.perturbation_moments, variance._data_share
    if exact:
        moments = _exact_sandwich()

    def perturbation_moments(*a, **k):
        out = moments(*a, **k)
        CAPTURED["S"] = np.asarray(out[0], np.float64)
        CAPTURED["S_cov"] = np.asarray(out[1], np.float64)
        return out

    def data_share(*a, **k):
        CAPTURED["rho"] = share(*a, **k)
        return CAPTURED["rho"]

    probes.perturbation_moments, variance._data_share = perturbation_moments, data_share


def _exact_sandwich():
    """A stand-in for :func:`kernels.probes.perturbation_moments` returning the exact
    sandwich's diagonal and face covariances (:func:`_capture`); the data stencil and the
    band's voxels are kept as :func:`bftaichi.stages.bandsolve.add_prior` receives them."""
    import kernels.probes as probes
    from bftaichi.stages import bandsolve
    from kernels.pcg import pcg_batched
    from kernels.stencil import apply_Q_batched

    add = bandsolve.add_prior

    def add_prior(S, h, band, *a, **k):
        CAPTURED["D"], CAPTURED["ijk"] = S.copy(), band.ijk
        return add(S, h, band, *a, **k)

    bandsolve.add_prior = add_prior

    def moments(S, nbr, W, n_probes=16, seed=0, *, tol, maxiter, far=None):
        Z = probes.probe_vectors(len(S), n_probes, seed, method="coloring", ijk=CAPTURED["ijk"])
        U, _ = pcg_batched(S, nbr, Z, None, tol, maxiter, np.float32, check=False, far=far)
        DU = apply_Q_batched(CAPTURED["D"], nbr, U).astype(np.float32)
        X, info = pcg_batched(S, nbr, DU, None, tol, maxiter, np.float32, check=False, far=far)
        den = np.einsum("ij,ij->i", Z, Z, dtype=np.float64)
        s = (np.einsum("ij,ij->i", Z, X, dtype=np.float64) / den).astype(np.float32)
        return s, probes.probe_covariance(Z, X, nbr, den), info

    return moments


def _keys(ijk) -> np.ndarray:
    """One int64 per voxel (21 bits an axis)."""
    c = np.asarray(ijk, np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def solve(sets):
    """(post, gt) of one configuration, in memory (no files)."""
    import bftaichi as bf
    from bftaichi.reconstructor import Reconstructor
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    cfg = bf.load_config(None, sets)
    frames = open_frames(cfg)
    gt = load_gt_mesh(cfg, frames)
    recon = Reconstructor(cfg)
    for i in range(len(frames)):
        f = frames[i]
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name, keep=False)
    return recon.solve(frames), gt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh")
    ap.add_argument("condition")
    ap.add_argument("--draws", type=int, default=6)
    ap.add_argument("--near", type=float, default=1.0, help="voxels from the true surface")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--exact", action="store_true", help="S: the exact sandwich by colouring "
                    "probes and the data stencil itself, not the perturbation solves")
    args = ap.parse_args(argv)

    from suite import case_sets

    from bftaichi.evaluation.metrics import band_sdf

    _capture(args.exact)
    base = case_sets(args.mesh, args.condition, args.data) + args.sets + ["run.plots=false"]
    runs = {k: [] for k in VARIANTS}
    phi = None
    for d in range(args.draws):
        for name, extra in VARIANTS.items():
            post, gt = solve(base + [f"synthetic.seed={d}"] + extra)
            if name == "S":
                post.var = CAPTURED["S"]
                post.cov = np.repeat(CAPTURED["rho"][:, None], 3, axis=1)
                post.S_cov = CAPTURED["S_cov"]
            keys = _keys(post.ijk)
            runs[name].append((keys, post))
            if phi is None:
                sdf = band_sdf(gt, post.origin, post.voxel_size, 0)
                origin, vs = post.origin, post.voxel_size
        print(f"draw {d}: {len(post.ijk)} band voxels", flush=True)
    common = None
    for name in VARIANTS:
        for keys, post in runs[name]:
            assert np.array_equal(post.origin, origin)
            k = keys[post.weight > 0]
            common = k if common is None else np.intersect1d(common, k)

    def at(name, field):
        out = []
        for keys, post in runs[name]:
            order = np.argsort(keys)
            idx = order[np.searchsorted(keys, common, sorter=order)]
            out.append(np.asarray(getattr(post, field), np.float64)[idx])
        return np.array(out)  # (draws, n)

    keys0, post0 = runs["default"][0]
    order = np.argsort(keys0)
    ijk = post0.ijk[order[np.searchsorted(keys0, common, sorter=order)]]
    phi, valid = sdf((ijk.astype(np.float64) + 0.5) * vs)
    near = valid & (np.abs(phi) <= args.near * vs)
    mean = at("default", "mean")[:, near]
    var = at("default", "var")[:, near].mean(0)
    blend = at("blend", "var")[:, near].mean(0)
    B = at("B", "var")[:, near].mean(0)
    S = at("S", "var")[:, near].mean(0)
    rho = at("S", "cov")[:, near, 0].mean(0)
    phi = phi[near]
    noise = mean.var(0, ddof=1)
    bias2 = (mean.mean(0) - phi) ** 2 - noise / args.draws  # unbiased for the squared bias
    mse = noise + bias2
    mm2 = 1e6
    print(f"\n{args.mesh}/{args.condition}: {near.sum()} voxels within {args.near} voxel of "
          f"the surface in every draw, {args.draws} draws; means in mm^2")
    cols = {"noise": noise, "S": S, "rho B": rho * B, "B": B, "bias^2": bias2,
            "(1-rho)^2 B": (1 - rho) ** 2 * B, "bias term": var - blend, "var": var, "mse": mse}
    print("| rho | voxels | " + " | ".join(cols) + " | S / noise | var / mse |")
    print("|---|---|" + "---|" * (len(cols) + 2))
    edges = np.quantile(rho, np.linspace(0, 1, 6))
    for lo, hi in [(edges[0], edges[-1])] + list(zip(edges[:-1], edges[1:])):
        m = (rho >= lo) & (rho <= hi)
        print(f"| {lo:.2f}-{hi:.2f} | {m.sum()} | "
              + " | ".join(f"{x[m].mean() * mm2:.3f}" for x in cols.values())
              + f" | {S[m].mean() / noise[m].mean():.2f} | {var[m].mean() / mse[m].mean():.2f} |")

    # On the grid edges the true surface crosses (both ends kept by every draw): the SDF
    # interpolated at the true crossing, whose true value is 0, against its modelled variance
    # ((1 - t)^2 v0 + t^2 v1 + 2 t (1 - t) c01, the mesh vertices' sigma of DESIGN.md 3.7).
    phi_all, _ = sdf((ijk.astype(np.float64) + 0.5) * vs)
    order = np.argsort(common)
    skeys = common[order]
    mean_all = at("default", "mean")
    tsdf_all = np.array([np.asarray(p.band.tsdf, np.float64)[order0[np.searchsorted(
        k, common, sorter=order0)]] for k, p in runs["default"]
        for order0 in [np.argsort(k)]])
    fields = {k: (at(k, "var"), at(k, "cov")) for k in ("default", "blend", "B")}
    fields["S"] = (at("S", "var"), at("S", "S_cov"))
    rho_draws = at("S", "cov")[:, :, 0]
    rho_all = rho_draws.mean(0)
    S_all = at("S", "var").mean(0)
    rows = []
    for axis, step in enumerate((1 << 42, 1 << 21, 1)):
        pos = np.searchsorted(skeys, common + step)
        pos = np.minimum(pos, len(skeys) - 1)
        has = skeys[pos] == common + step
        i0 = np.flatnonzero(has)
        i1 = order[pos[has]]
        p0, p1 = phi_all[i0], phi_all[i1]
        cross = (np.sign(p0) != np.sign(p1)) & (np.abs(p0 - p1) > 0)
        i0, i1, p0, p1 = i0[cross], i1[cross], p0[cross], p1[cross]
        t = p0 / (p0 - p1)
        val = (1 - t) * mean_all[:, i0] + t * mean_all[:, i1]  # (draws, edges)
        boot = (1 - t) * tsdf_all[:, i0] + t * tsdf_all[:, i1]  # the bootstrap's, the same way
        # the two ends' noise over the draws: their variances and covariance
        a0, a1 = mean_all[:, i0], mean_all[:, i1]
        ends = np.stack([a0.var(0, ddof=1), a1.var(0, ddof=1),
                         ((a0 - a0.mean(0)) * (a1 - a1.mean(0))).sum(0) / (len(a0) - 1)])
        model = {}
        for k, (v, c) in fields.items():
            m = (1 - t) ** 2 * v[:, i0] + t ** 2 * v[:, i1] + 2 * t * (1 - t) * c[:, i0, axis]
            model[k] = m.mean(0)
        # the blend's two parts, each with B's correlation: rho B (its noise part) and
        # (1 - rho)^2 B (its prior part)
        vb, cb = fields["B"]
        r0, r1 = rho_draws[:, i0], rho_draws[:, i1]
        for k, f0, f1 in (("rho B", r0, r1), ("(1-rho)^2 B", (1 - r0) ** 2, (1 - r1) ** 2)):
            m = ((1 - t) ** 2 * f0 * vb[:, i0] + t ** 2 * f1 * vb[:, i1]
                 + 2 * t * (1 - t) * np.sqrt(f0 * f1) * cb[:, i0, axis])
            model[k] = m.mean(0)
        mv = {k: np.stack([v[:, i0].mean(0), v[:, i1].mean(0), c[:, i0, axis].mean(0)])
              for k, (v, c) in fields.items()}
        rows.append((val, model, 0.5 * (rho_all[i0] + rho_all[i1]), ends, mv, boot))
    val = np.concatenate([r[0] for r in rows], axis=1)
    model = {k: np.concatenate([r[1][k] for r in rows]) for k in rows[0][1]}
    erho = np.concatenate([r[2] for r in rows])
    eboot = np.concatenate([r[5] for r in rows], axis=1)
    ends = np.concatenate([r[3] for r in rows], axis=1)
    mends = {k: np.concatenate([r[4][k] for r in rows], axis=1) for k in rows[0][4]}
    enoise = val.var(0, ddof=1)
    ebias2 = val.mean(0) ** 2 - enoise / args.draws
    emse = enoise + ebias2
    print(f"\nat the true surface's crossings of {val.shape[1]} grid edges (mm^2; var/mse "
          "and the 1-sigma coverage of |value| over all draws):")
    cols = {"noise": enoise, "bias^2": ebias2, "mse": emse, **model}
    print("| rho | edges | " + " | ".join(cols) + " | var/mse | cov1 (var) | cov1 (blend) |")
    print("|---|---|" + "---|" * (len(cols) + 3))
    # where every draw's surface passes within a voxel (|value| < h): where the mesh has its
    # vertices; beyond, the true surface has no posterior surface near it (holes, bridged gaps)
    close = np.all(np.abs(val) < vs, axis=0)
    print(f"({close.sum()} of the edges have every draw's value within a voxel: the rows "
          "'near'; the others 'far')")
    edges = np.quantile(erho[close], np.linspace(0, 1, 6))
    bins = [("all", np.ones_like(close)), ("far", ~close), ("near", close)] + [
        (f"near {lo:.2f}-{hi:.2f}", close & (erho >= lo) & (erho <= hi))
        for lo, hi in zip(edges[:-1], edges[1:])]
    for label, m in bins:
        lo = hi = label
        c1 = np.mean(np.abs(val[:, m]) <= np.sqrt(model["default"][m]))
        c1b = np.mean(np.abs(val[:, m]) <= np.sqrt(model["blend"][m]))
        print(f"| {label} | {m.sum()} | "
              + " | ".join(f"{x[m].mean() * mm2:.3f}" for x in cols.values())
              + f" | {model['default'][m].mean() / emse[m].mean():.2f} | {100 * c1:.0f} % | "
              f"{100 * c1b:.0f} % |")

    # The correlation of the two ends of a crossing edge (one voxel each side of the surface):
    # over the draws (sum of covariances / sqrt of the sums of variances over the edges) and
    # in each model (its face covariance the same way).
    def corr(e, m):
        return e[2][m].sum() / np.sqrt(e[0][m].sum() * e[1][m].sum())

    print("\ncorrelation of the two voxels across the surface at the near crossings: draws "
          + ", ".join(f"{k} " for k in mends))
    for label, m in bins:
        if label == "far":
            continue
        print(f"| {label} | draws {corr(ends, m):+.2f} | "
              + " | ".join(f"{k} {corr(mends[k], m):+.2f}" for k in mends) + " |")

    # The bias against the true surface's curvature: the Laplacian of the true SDF (twice the
    # mean curvature of its level sets; > 0 convex, < 0 concave) at the edge's two voxels,
    # times the voxel size, from the face neighbours the common set holds.
    lap = np.full(len(common), np.nan)
    acc, cnt = np.zeros(len(common)), np.zeros(len(common))
    for step in (1 << 42, 1 << 21, 1):
        lo_ = np.searchsorted(skeys, common - step)
        hi_ = np.searchsorted(skeys, common + step)
        lo_, hi_ = np.minimum(lo_, len(skeys) - 1), np.minimum(hi_, len(skeys) - 1)
        ok = (skeys[lo_] == common - step) & (skeys[hi_] == common + step)
        acc[ok] += phi_all[order[lo_[ok]]] + phi_all[order[hi_[ok]]] - 2 * phi_all[ok]
        cnt[ok] += 1
    full = cnt == 3
    lap[full] = acc[full] / vs  # sum of second differences / h^2, times h: per voxel
    curv = []
    for axis, step in enumerate((1 << 42, 1 << 21, 1)):
        pos = np.minimum(np.searchsorted(skeys, common + step), len(skeys) - 1)
        has = skeys[pos] == common + step
        i0 = np.flatnonzero(has)
        i1 = order[pos[has]]
        p0, p1 = phi_all[i0], phi_all[i1]
        cross = (np.sign(p0) != np.sign(p1)) & (np.abs(p0 - p1) > 0)
        curv.append(0.5 * (lap[i0[cross]] + lap[i1[cross]]))
    curv = np.concatenate(curv)
    ok = close & np.isfinite(curv)
    bias = val.mean(0)
    print(f"\nsigned bias at the near crossings by the true SDF's Laplacian x voxel (> 0: convex; "
          f"{ok.sum()} edges with both voxels' 6 neighbours kept)")
    tbias = eboot.mean(0)
    print("| h lap phi | edges | mean bias (mm) | rms bias (mm) | rms noise (mm) | "
          "rms var default (mm) | TSDF: mean bias | rms bias |")
    print("|---|---|---|---|---|---|---|---|")
    qs = np.quantile(curv[ok], np.linspace(0, 1, 8))
    for lo, hi in zip(qs[:-1], qs[1:]):
        m = ok & (curv >= lo) & (curv <= hi)
        print(f"| {lo:+.3f} .. {hi:+.3f} | {m.sum()} | {1e3 * bias[m].mean():+.3f} | "
              f"{1e3 * np.sqrt(np.mean(bias[m] ** 2)):.3f} | "
              f"{1e3 * np.sqrt(enoise[m].mean()):.3f} | "
              f"{1e3 * np.sqrt(model['default'][m].mean()):.3f} | "
              f"{1e3 * tbias[m].mean():+.3f} | {1e3 * np.sqrt(np.mean(tbias[m] ** 2)):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
