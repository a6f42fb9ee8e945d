#!/usr/bin/env python
"""Where a suite case's vertex sigma stands against its errors, in the bulk and on average.

For one case of ``tools/suite.py`` (a mesh and a capture condition), the posterior is solved
in-process and its mesh judged against the exact vertex errors (libigl, as the suite): the
median and the RMS of the errors against those of sigma (a Gaussian sigma has ``median |e| =
0.674 sigma`` and ``RMS e = sigma``), the coverage at 1 / 2 / 3 sigma (and of ``sigma_pos``,
with the mean's gradient at the vertices it divides by), and, on the voxels
within one voxel of the mean's surface, what the variance is made of: the probe variance
before the local-noise step and the misfit term ``b^2`` (bftaichi/stages/bandsolve.py), with
the data's median chi2 over the band; the 5 % largest errors against the rest; and the
vertices by kind: smooth, creased, on the mesh's boundary, near a thin part of the true surface
(:func:`tail`)::

    python tools/sigma_breakdown.py homer few_views
    python tools/sigma_breakdown.py stanford-bunny sparse_far --set prior.curvature=0.5
    python tools/sigma_breakdown.py scenes/seed_sphere.toml      # a synthetic scene file
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("mesh", help="a mesh of the suite, e.g. homer, or a synthetic scene file "
                                 "such as scenes/seed_sphere.toml (then no condition)")
    ap.add_argument("condition", nargs="?", help="a capture condition of the suite, e.g. few_views")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args(argv)

    import suite
    import bftaichi as bf
    from bftaichi.evaluation.metrics import vertex_errors
    from bftaichi.geometry import mesh_in_local

    if args.mesh.endswith(".toml"):
        if args.condition:
            ap.error("a scene file takes no condition")
        cfg = bf.load_config(args.mesh, args.sets)
        if cfg.scene.source != "synthetic":
            ap.error(f"{args.mesh} is not a synthetic scene: no true mesh to judge against")
    elif args.condition not in suite.CONDITIONS:
        ap.error(f"unknown condition {args.condition!r}; one of {', '.join(suite.CONDITIONS)}")
    else:
        cfg = bf.load_config(None, [*suite.case_sets(args.mesh, args.condition, args.data),
                                    *args.sets])
    frames, post, seen = solve_seeing_misfit(cfg)
    mesh = post.extract_mesh(local=True)
    gt = mesh_in_local(frames.gt_mesh, post.origin)
    err = vertex_errors(mesh.vertices, gt)
    sigma = np.asarray(mesh.vertex_attributes["sigma"], np.float64)
    mm = 1e3
    print(f"{args.mesh}{'/' + args.condition if args.condition else ''}: {len(err)} vertices")
    print(f"  error: median {np.median(err) * mm:.3f} mm, RMS {np.sqrt(np.mean(err ** 2)) * mm:.3f} mm"
          f"; sigma: median {np.median(sigma) * mm:.3f} mm, RMS "
          f"{np.sqrt(np.mean(sigma ** 2)) * mm:.3f} mm")
    print(f"  median |e| / (0.674 median sigma) = {np.median(err) / (0.674 * np.median(sigma)):.2f}"
          f"; mean e^2 / mean sigma^2 = {np.mean(err ** 2) / np.mean(sigma ** 2):.2f}"
          " (1 and 1 for a calibrated Gaussian)")
    z = err / np.maximum(sigma, 1e-12)
    print("  within 1 / 2 / 3 sigma: " + " / ".join(f"{100 * np.mean(z <= k):.1f}" for k in (1, 2, 3))
          + " %")
    grad = sigma / np.maximum(np.asarray(mesh.vertex_attributes["sigma_pos"], np.float64), 1e-30)
    z_pos = z * grad  # the errors over sigma_pos = sigma / |grad mean|
    print("  |grad mean| at the vertices, 5 / 50 / 95th percentile: "
          + " / ".join(f"{x:.2f}" for x in np.percentile(grad, [5, 50, 95]))
          + "; within 1 / 2 / 3 sigma_pos: "
          + " / ".join(f"{100 * np.mean(z_pos <= k):.1f}" for k in (1, 2, 3)) + " %")
    if seen:
        near = np.abs(post.mean) < cfg.tsdf.voxel_size_m
        v0, b2 = seen["var0"][near], seen["b2"][near].astype(np.float64)
        print(f"  {int(near.sum())} voxels within a voxel of the surface: sqrt(probe variance) "
              f"median {np.median(np.sqrt(v0)) * mm:.3f} mm, the data's chi2 median (band) "
              f"{seen['chi2']:.3f}, b^2 > 0 on {100 * np.mean(b2 > 0):.0f} %, "
              f"b^2 / final variance median {np.median(b2 / post.var[near]):.2f}")
    print(f"  fitted noise: extra {post.sigma_extra_m * mm:.3f} mm, shared {post.sigma_corr_m * mm:.3f} mm")
    tail(mesh, err, sigma, gt, cfg.tsdf.voxel_size_m)
    return 0


def solve_seeing_misfit(cfg) -> tuple:
    """``(frames, post, seen)``: a synthetic scene's frames and posterior, solved in-process
    with :func:`bftaichi.stages.misfit.local_misfit` watched: ``seen`` holds ``var0`` (the
    variance before the local noise, (N,) float64), its ``b2`` and ``chi2`` (the median), empty
    when ``observation.local_noise`` is off."""
    import bftaichi as bf
    import bftaichi.stages.bandsolve as bandsolve
    from bftaichi.formats.synthetic import SyntheticDataset

    seen = {}
    local_misfit = bandsolve.local_misfit

    def spy(observer, frames, mean, var, nbr, stride):  # the variance before the local noise
        b2, stats = local_misfit(observer, frames, mean, var, nbr, stride)
        seen.update(var0=np.array(var, np.float64), b2=b2, chi2=stats["median_chi2"])
        return b2, stats

    bandsolve.local_misfit = spy
    try:
        frames = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
        recon = bf.Reconstructor(cfg)
        for f in frames:
            recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
        post = recon.solve()
    finally:
        bandsolve.local_misfit = local_misfit
    return frames, post, seen


def thin_parts(vertices: np.ndarray, gt, radius_m: float, n_samples: int = 400_000) -> np.ndarray:
    """(V,) bool: the true surface ``gt`` faces both ways within ``radius_m`` of the vertex
    (two of its area samples there, seed 0, have normals more than 120 degrees apart): a sheet
    or a gap thinner than about ``2 radius_m``, which one voxel grid cannot hold on both sides."""
    import trimesh
    from scipy.spatial import cKDTree

    pts, face = trimesh.sample.sample_surface(gt, n_samples, seed=0)
    normals = gt.face_normals[face]
    near = cKDTree(pts).query_ball_point(np.asarray(vertices, np.float64), radius_m)
    return np.array([len(ix) > 1 and float((normals[ix] @ normals[ix[0]]).min()) < -0.5
                     for ix in near], bool)


def normal_angle(mesh) -> np.ndarray:
    """(V,) the mean angle (radians) between each vertex's normal and its neighbours' of a
    ``trimesh.Trimesh``: a crease or a crumpled patch, from the mesh alone."""
    normals, pairs = mesh.vertex_normals, mesh.edges_unique
    edge_angle = np.arccos(np.clip(np.einsum("ij,ij->i", normals[pairs[:, 0]],
                                             normals[pairs[:, 1]]), -1.0, 1.0))
    degree = np.bincount(pairs.ravel(), minlength=len(normals))
    return np.bincount(pairs.ravel(), np.repeat(edge_angle, 2), minlength=len(normals)) \
        / np.maximum(degree, 1)


def tail(mesh, err: np.ndarray, sigma: np.ndarray, gt, voxel_m: float | None = None) -> None:
    """The 5 % largest errors against the rest: sigma and two features of the mesh itself, the
    mean angle between a vertex's normal and its neighbours' (a crease or a crumpled patch) and
    lying on the mesh boundary (the edge of what was observed); Spearman of each with the error;
    and on which side of the true mesh ``gt`` the tail lies (outside: a false surface in free
    space; libigl's generalised winding number, so open meshes are judged too). Then the
    coverage of the vertices by kind; with ``voxel_m``, also those near a thin part of the true
    surface (:func:`thin_parts` within one voxel)."""
    import igl
    from scipy.stats import spearmanr

    angle = normal_angle(mesh)
    edges, count = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    boundary = np.zeros(len(err))
    boundary[edges[count == 1].ravel()] = 1.0
    top = err > np.quantile(err, 0.95)
    print(f"  the 5 % largest errors: median {np.median(err[top]) * 1e3:.2f} mm against "
          f"{np.median(err[~top]) * 1e3:.2f} mm for the rest")
    for name, x, unit in (("sigma", sigma * 1e3, " mm"), ("normal angle", angle, " rad"),
                          ("on the boundary", boundary, "")):
        stat = (f"{100 * x[top].mean():.1f} % against {100 * x[~top].mean():.1f} %" if not unit
                else f"median {np.median(x[top]):.3f}{unit} against {np.median(x[~top]):.3f}{unit}")
        print(f"    {name}: {stat}; Spearman with the error {spearmanr(x, err).statistic:.2f}")
    inside = igl.winding_number(np.asarray(gt.vertices, np.float64),
                                np.asarray(gt.faces, np.int64),
                                np.asarray(mesh.vertices, np.float64)[top]) > 0.5
    print(f"    outside the true surface: {100 * (1 - inside.mean()):.1f} % of the tail")
    z = err / np.maximum(sigma, 1e-12)
    creased, edge = angle > 0.5, boundary > 0
    groups = [("smooth interior (normal angle <= 0.5 rad, not on the boundary)",
               ~creased & ~edge), ("creased (normal angle > 0.5 rad)", creased),
              ("on the boundary", edge)]
    if voxel_m is not None:
        groups.append(("near a thin part (the true surface faces both ways within a voxel)",
                       thin_parts(mesh.vertices, gt, voxel_m)))
    for name, sel in groups:
        if sel.any():
            print(f"  {name}: {int(sel.sum())} vertices, median error "
                  f"{np.median(err[sel]) * 1e3:.2f} mm, median sigma "
                  f"{np.median(sigma[sel]) * 1e3:.2f} mm, within 1 / 2 / 3 sigma "
                  + " / ".join(f"{100 * np.mean(z[sel] <= k):.0f}" for k in (1, 2, 3)) + " %")


if __name__ == "__main__":
    sys.exit(main())
