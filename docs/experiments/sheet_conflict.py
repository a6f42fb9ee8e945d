#!/usr/bin/env python
"""The beetle's vertex errors: a sheet seen from both sides (issue 15; measured, not built).

For suite cases (``tools/suite.py``'s meshes and capture conditions), solve the posterior and
print how far its mesh's vertices and the TSDF mesh's lie from the true surface, in voxels;
``--section FILE`` also draws three cross-sections (planes of constant y through the true
mesh's centre, +5 cm and -8 cm) of the true mesh, the TSDF mesh and the posterior mesh.

Then a candidate extra vertex variance, computed from the frames in numpy (no kernel): each
band voxel's projective observations as the TSDF takes them (nearest pixel, ``sdf = D - z``,
observed for ``sdf >= -tau_b``, clamped at ``tau_b``), each scaled by ``|<n, ray>|`` (``n`` the
pixel normal from central differences of the back-projected depth) so that a consistent
surface gives every view the same value; their spread beyond the modelled noise, ``excess =
max(0, var(y) - mean(sigma_k^2))``, kept only where the observations disagree in sign:
``conflict = 2 min(W+, W-) / (W+ + W-)`` over the observations beyond ``T`` voxels either side,
``excess * conflict^POW``. A vertex gets ``sigma^2 + excess`` interpolated over its cell's
corners, or the corners' largest (``--unsigned``: the spread alone; ``--no-scale``: without the normal's
scaling; ``--reach R``: observed to R voxels behind a surface instead of ``tau_b``). Coverage at 1 / 2 / 3 sigma and the NLL minus the best
constant's are printed for sigma alone and with each::

    python docs/experiments/sheet_conflict.py beetle/dense_near --section section.png
    python docs/experiments/sheet_conflict.py beetle/dense_near homer/dense_near --T 2 --pow 2
    python docs/experiments/sheet_conflict.py beetle/dense_near homer/dense_near --reach 2 --T 1
    python docs/experiments/sheet_conflict.py homer/dense_near --unsigned --no-scale
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))


def _nll_minus_const(e, s) -> float:
    def nll(sig):
        return float(np.mean(0.5 * np.log(2 * np.pi * sig ** 2) + 0.5 * (e / sig) ** 2))
    return nll(s) - nll(np.full_like(e, np.sqrt(np.mean(e ** 2))))


def _line(name, e, s) -> str:
    z = e / s
    return (f"  {name:22s} within 1 / 2 / 3 sigma {100 * np.mean(z <= 1):5.1f} / "
            f"{100 * np.mean(z <= 2):5.1f} / {100 * np.mean(z <= 3):5.1f} %, NLL - const "
            f"{_nll_minus_const(e, s):+.3f}")


def _bins(name, err, h) -> str:
    edges = (0, 0.5, 1, 2, 3, 6, np.inf)
    counts = [int(np.sum((err >= lo * h) & (err < hi * h))) for lo, hi in zip(edges, edges[1:])]
    return (f"  {name}: {len(err)} vertices; farther than 1 / 2 / 3 voxels from the true surface "
            f"{100 * sum(counts[2:]) / len(err):.1f} / {100 * sum(counts[3:]) / len(err):.1f} / "
            f"{100 * sum(counts[4:]) / len(err):.1f} %")


def _normals(depth: np.ndarray, K: np.ndarray, vectors: bool = False) -> np.ndarray:
    """(H, W) |<n, ray>| of each pixel (ray = K^-1 (u, v, 1)); |ray| where no normal forms.
    ``vectors``: (H, W, 3) the unit normals themselves (camera frame, facing the camera), 0
    where none forms."""
    H, W = depth.shape
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    P = depth.astype(np.float64)[..., None] * rays
    tu, tv = np.zeros_like(P), np.zeros_like(P)
    tu[:, 1:-1], tv[1:-1] = P[:, 2:] - P[:, :-2], P[2:] - P[:-2]
    n = np.cross(tu, tv)
    ok = depth > 0
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = (ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
                         & ok[1:-1, 1:-1])
    if vectors:
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
        n = np.where((n * rays).sum(-1, keepdims=True) > 0, -n, n)  # facing the camera
        return np.where(inner[..., None], n, 0.0)
    cos = np.abs((n * rays).sum(-1)) / np.maximum(np.linalg.norm(n, axis=-1), 1e-30)
    return np.where(inner, cos, np.linalg.norm(rays, axis=-1))


def projective_sdf(X: np.ndarray, frame, T_C: np.ndarray, behind_m: float):
    """The TSDF's projective observation of the points ``X`` (N, 3; the frame of ``T_C``, the
    camera-to-that-frame pose) by ``frame``: the nearest pixel ``floor(K x / z + 0.5)``, its
    depth ``d`` and ``sdf = d - z``, observed where ``z > 0``, the pixel is in the image, ``d >
    0`` and ``sdf >= -behind_m``. Returns ``(ok, d, sdf, v, u)`` (pixel indices clipped to the
    image)."""
    Xc = (X - T_C[:3, 3]) @ T_C[:3, :3]
    z = Xc[:, 2]
    ok = z > 1e-6
    zs = np.where(ok, z, 1.0)
    u = np.floor(frame.K[0, 0] * Xc[:, 0] / zs + frame.K[0, 2] + 0.5).astype(np.int64)
    v = np.floor(frame.K[1, 1] * Xc[:, 1] / zs + frame.K[1, 2] + 0.5).astype(np.int64)
    H, W = frame.depth_m.shape
    ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    vc, uc = np.clip(v, 0, H - 1), np.clip(u, 0, W - 1)
    d = np.where(ok, frame.depth_m[vc, uc], 0.0)
    ok &= (d > 0) & (d - z >= -behind_m)
    return ok, d, d - z, vc, uc


def _excess(post, cfg, frames, T: float, power: float, reach: float, signed: bool,
            scaled: bool, facing: bool = False) -> np.ndarray:
    h, tb = post.voxel_size, cfg.tsdf.bootstrap_trunc_m
    behind = reach * h if reach > 0 else tb
    X = (post.ijk.astype(np.float64) + 0.5) * h
    N = len(X)
    n, s1, s2, ev, wp, wn = (np.zeros(N) for _ in range(6))
    nsum, nnear = np.zeros((N, 3)), np.zeros(N)  # facing: camera-facing normals near the surface
    extra2 = post.sigma_extra_m ** 2 + post.sigma_corr_m ** 2
    for f in frames:
        T_C = np.asarray(f.T_W_C, np.float64).copy()
        T_C[:3, 3] -= post.origin
        ok, d, sdf, vc, uc = projective_sdf(X, f, T_C, behind)
        y = np.minimum(sdf, tb)
        if scaled:
            y = y * _normals(f.depth_m, f.K)[vc, uc]
        n += ok
        s1 += np.where(ok, y, 0)
        s2 += np.where(ok, y * y, 0)
        ev += np.where(ok, cfg.observation.axial_sigma_m(np.where(ok, d, 1.0)) ** 2 + extra2, 0)
        wp += ok & (y > T * h)
        wn += ok & (y < -T * h)
        if facing:
            near = ok & (np.abs(sdf) <= T * h)
            nw = _normals(f.depth_m, f.K, vectors=True)[vc, uc] @ T_C[:3, :3].T
            nsum += np.where(near[:, None], nw, 0.0)
            nnear += near & (np.abs(nw).sum(1) > 0)
    m = np.maximum(n, 1)
    excess = np.where(n >= 2, np.maximum(s2 / m - (s1 / m) ** 2 - ev / m, 0.0), 0.0)
    if facing:  # 1 - |mean normal|: 0 where every view sees one side, ~1 for two sides
        conflict = np.where(nnear >= 2, 1 - np.linalg.norm(nsum, axis=1) / np.maximum(nnear, 1),
                            0.0)
        return excess * conflict ** power
    conflict = 2 * np.minimum(wp, wn) / np.maximum(wp + wn, 1)
    return excess * conflict ** power if signed else excess


def _at_vertices(post, values, vertices) -> tuple[np.ndarray, np.ndarray]:
    """(trilinear interpolation over the cell's band corners, the corners' largest)."""
    h = post.voxel_size
    ijk = post.ijk.astype(np.int64)
    lo = ijk.min(0) - 1
    shape = ijk.max(0) - lo + 2
    lookup = np.full(int(np.prod(shape)), -1, np.int64)
    lookup[np.ravel_multi_index((ijk - lo).T, shape)] = np.arange(len(ijk))
    g = np.asarray(vertices, np.float64) / h - 0.5
    c0 = np.floor(g).astype(np.int64)
    fr = g - c0
    acc, wsum, top = (np.zeros(len(g)) for _ in range(3))
    for corner in np.ndindex(2, 2, 2):
        c = np.clip(c0 + corner - lo, 0, shape - 1)
        idx = lookup[np.ravel_multi_index(c.T, shape)]
        w = np.prod(np.where(np.array(corner) == 1, fr, 1 - fr), axis=1)
        val = np.where(idx >= 0, values[np.maximum(idx, 0)], 0.0)
        acc += w * val
        wsum += w * (idx >= 0)
        top = np.maximum(top, val)
    return acc / np.maximum(wsum, 1e-12), top


def _section(path, gt, tsdf_mesh, mesh) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh

    centre = gt.bounds.mean(0)
    fig, axes = plt.subplots(1, 3, figsize=(18, 6))
    for ax, dy in zip(axes, (0.0, 0.05, -0.08)):
        for m, colour, width in ((gt, "k", 2.0), (tsdf_mesh, "tab:blue", 1.0),
                                 (mesh, "tab:red", 1.0)):
            for seg in trimesh.intersections.mesh_plane(m, [0, 1.0, 0], centre + [0, dy, 0]):
                ax.plot(seg[:, 0], seg[:, 2], color=colour, lw=width)
        ax.set_aspect("equal")
        ax.grid(True)
        ax.set_title(f"y = centre {dy * 100:+g} cm: true (black), TSDF (blue), posterior (red)",
                     fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("cases", nargs="+", help="MESH/CONDITION, e.g. beetle/dense_near")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--T", type=float, default=2.0, help="voxels beyond which a sign counts")
    ap.add_argument("--pow", type=float, default=1.0, help="power of the conflict")
    ap.add_argument("--reach", type=float, default=0.0, help="voxels observed behind a surface "
                    "(default 0: the bootstrap's tau_b)")
    ap.add_argument("--unsigned", action="store_true", help="the spread alone, no conflict")
    ap.add_argument("--no-scale", action="store_true", help="no |<n, ray>| scaling")
    ap.add_argument("--facing", action="store_true", help="conflict = 1 - the length of the "
                    "mean camera-facing normal of the pixels seeing the voxel within T voxels "
                    "(two sides of a sheet), instead of the sign disagreement")
    ap.add_argument("--section", type=Path, help="draw the first case's cross-sections here")
    args = ap.parse_args(argv)

    import suite
    import bftaichi as bf
    from bftaichi.evaluation.metrics import vertex_errors
    from bftaichi.formats.synthetic import SyntheticDataset
    from bftaichi.geometry import mesh_in_local

    for k, case in enumerate(args.cases):
        mesh_name, condition = case.split("/")
        cfg = bf.load_config(None, suite.case_sets(mesh_name, condition, args.data))
        dataset = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
        frames = list(dataset)
        recon = bf.Reconstructor(cfg)
        for f in frames:
            recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
        post = recon.solve()
        mesh, tsdf_mesh = post.extract_mesh(local=True), recon.tsdf_mesh(local=True)
        gt = mesh_in_local(dataset.gt_mesh, post.origin)
        err = vertex_errors(mesh.vertices, gt)
        sigma = np.asarray(mesh.vertex_attributes["sigma"], np.float64)
        h = cfg.tsdf.voxel_size_m
        print(f"{case} ({h * 1e3:g} mm voxels)")
        print(_bins("posterior mesh", err, h))
        print(_bins("TSDF mesh", vertex_errors(tsdf_mesh.vertices, gt), h))
        interp, top = _at_vertices(post, _excess(post, cfg, frames, args.T, args.pow, args.reach,
                                           not args.unsigned, not args.no_scale,
                                           args.facing),
                                   mesh.vertices)
        print(_line("sigma", err, sigma))
        print(_line("+ excess, interpolated", err, np.sqrt(sigma ** 2 + interp)))
        print(_line("+ excess, corners' max", err, np.sqrt(sigma ** 2 + top)))
        sys.stdout.flush()
        if args.section and k == 0:
            _section(args.section, gt, tsdf_mesh, mesh)
    return 0


if __name__ == "__main__":
    sys.exit(main())
