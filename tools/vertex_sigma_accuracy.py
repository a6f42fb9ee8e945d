"""Accuracy of the probe estimate of the vertex variance ``a_v^T Q^-1 a_v`` (DESIGN.md 3.7,
section 6 "estimator accuracy") against the exact value, on small scenes.

For each scene: fuse and solve (MAP only), rebuild Q (tests/conftest.py's stage calls), mesh the
mean, and for up to ``--vertices`` edge vertices (fixed seed) compute the exact
``(1-t)^2 C_ii + 2 t (1-t) C_ij + t^2 C_jj`` from columns of Q^-1 (scipy splu), then the same
from the probe estimate (:func:`kernels.probes.probe_moments` through
:func:`bftaichi.stages.variance.estimate_variance`) at each K, and from the trilinear
interpolation of the voxel variances (the old bound, exact variances). Prints one markdown row
per (scene, estimator): median and 90th percentile of the relative error of the vertex
variance and of the vertex sigma, and the seconds of the probe stage (``estimate_variance``,
second run).

    PYTHONPATH=. python tools/vertex_sigma_accuracy.py --probes 16 27 32
    PYTHONPATH=. python tools/vertex_sigma_accuracy.py --set observation.behind=incidence
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # conftest: the stage calls and Q of the tests
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
from test_vertex_sigma import SPHERE_SETS  # noqa: E402

#: Small scenes (--set overrides of the default config): N of 3k-30k band voxels
#: (``sphere-tiny`` is tests/test_vertex_sigma.py's sphere, for the smoke test).
SCENES = {
    "sphere-tiny": list(SPHERE_SETS),
    "sphere-3cm": ["synthetic.mesh=sphere", "synthetic.radius_m=0.3",
                   "synthetic.trajectory=sphere", "synthetic.n_views=16",
                   "synthetic.cam_radius_m=1.0", "synthetic.width=96", "synthetic.height=72",
                   "synthetic.fx=78.75", "synthetic.fy=78.75", "synthetic.cx=47.5",
                   "synthetic.cy=35.5", "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06"],
    "tabletop-2cm": ["synthetic.width=160", "synthetic.height=120", "synthetic.fx=262.5",
                     "synthetic.fy=262.5", "synthetic.cx=79.5", "synthetic.cy=59.5",
                     "synthetic.n_views=8", "tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04"],
}


def exact_columns(S, nbr, far, cols):
    """Columns ``cols`` of Q^-1 (N, len(cols)) float64 by one sparse LU of Q."""
    import scipy.sparse.linalg as spla
    from conftest import to_csr

    n = len(S)
    lu = spla.splu(to_csr(S, nbr, far).tocsc())
    out = np.empty((n, len(cols)))
    for s in range(0, len(cols), 512):
        E = np.zeros((n, len(cols[s:s + 512])))
        E[cols[s:s + 512], np.arange(E.shape[1])] = 1.0
        out[:, s:s + 512] = lu.solve(E)
    return out


def measure(name, sets, probes, n_vertices, seed=0):
    """Rows ``(scene, N, V, estimator, med var, p90 var, med sigma, p90 sigma, seconds)``."""
    from conftest import posterior_system, solved

    import bftaichi as bf
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.surface import (VertexEdges, extract_mesh, sample_field,
                                         vertex_variance)
    from bftaichi.stages.variance import estimate_variance
    from kernels.probes import FACE_PLUS

    cfg = bf.load_config(None, sets)
    recon, post = solved(cfg, open_frames(cfg), variance=False)
    band, system = posterior_system(recon)
    n = len(band.ijk)
    verts, _, edges = extract_mesh(band.ijk, post.mean, band.weight > 0, post.voxel_size,
                                   return_edges=True)
    keep = np.flatnonzero((edges.axis >= 0) & (edges.axis < 3))
    keep = np.sort(np.random.default_rng(seed).choice(keep, min(n_vertices, len(keep)),
                                                      replace=False))
    sub = VertexEdges(edges.ijk[keep], edges.axis[keep], edges.t[keep])
    # the voxels the sampled vertices need, and their exact var / cov with +x +y +z
    key = {tuple(v): k for k, v in enumerate(band.ijk.tolist())}
    i = np.array([key[tuple(v)] for v in sub.ijk.tolist()])  # V <= a few thousand
    need = np.unique(np.concatenate([i, system.nbr[i][:, list(FACE_PLUS)].ravel()]))
    need = need[need >= 0]
    t0 = time.perf_counter()
    C = exact_columns(system.S, system.nbr, system.far, need)
    t_exact = time.perf_counter() - t0
    var = np.zeros(n)
    cov = np.zeros((n, 3))
    var[need] = C[need, np.arange(len(need))]
    for e, o in enumerate(FACE_PLUS):
        j = system.nbr[need, o]
        cov[need[j >= 0], e] = C[j[j >= 0], np.flatnonzero(j >= 0)]
    exact = vertex_variance(band.ijk, var, cov, sub)
    assert np.all(np.isfinite(exact)), "a sampled vertex lacks an exact value"
    rows = []

    def row(label, est, sec):
        r = np.abs(est / exact - 1.0)
        rs = np.abs(np.sqrt(est / exact) - 1.0)
        rows.append((name, n, len(keep), label, np.median(r), np.percentile(r, 90),
                     np.median(rs), np.percentile(rs, 90), sec))

    bound = sample_field(band.ijk, var, np.ones(n, bool), post.voxel_size, verts[keep])
    row("interpolated var (exact)", bound.astype(np.float64), float("nan"))
    for k in probes:
        solver = copy.deepcopy(cfg.solver)
        solver.probes = k
        sec = []
        for _ in range(2):  # the second run: kernels compiled
            t0 = time.perf_counter()
            v_est, c_est, _ = estimate_variance(system, solver, band.ijk)
            sec.append(time.perf_counter() - t0)
        sec = sec[-1]
        row(f"probes K={k} (cov)", vertex_variance(band.ijk, v_est, c_est, sub), sec)
        row(f"probes K={k} (var only, cov=0)",
            vertex_variance(band.ijk, v_est, np.zeros_like(c_est), sub), sec)
    print(f"# {name}: N={n}, exact columns {len(need)} in {t_exact:.1f} s", file=sys.stderr)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES)[1:], choices=list(SCENES))
    ap.add_argument("--probes", nargs="+", type=int, default=[16, 27, 32])
    ap.add_argument("--vertices", type=int, default=2000, help="vertices sampled per scene")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config override added to every scene (repeatable), e.g. "
                         "observation.behind=incidence")
    args = ap.parse_args(argv)
    from bftaichi.backend import init

    init("cpu")
    print("| scene | N | vertices | estimator | var: median | var: p90 | sigma: median "
          "| sigma: p90 | probe s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.scenes:
        for r in measure(name, [*SCENES[name], *args.sets], args.probes, args.vertices):
            print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {100 * r[4]:.1f} % | "
                  f"{100 * r[5]:.1f} % | {100 * r[6]:.1f} % | {100 * r[7]:.1f} % | "
                  f"{r[8]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
