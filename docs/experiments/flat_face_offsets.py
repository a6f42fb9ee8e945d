#!/usr/bin/env python
"""Where a synthetic run's vertices lie on the true mesh's axis-aligned flat faces (a diagnosis
of the held-out disk's F-score, docs/measurements.md, "The MAP's noise in the robust prior's
reweighting").

For each flat face orientation (true face normal within 8 degrees of an axis, at least 500
vertices), prints for ``tsdf_mesh.ply`` and ``mesh.ply`` the vertices' signed offsets from the
true surface (exact closest point, along its face normal): their mean, their spread, the share
within 1 mm, and the share within 0.05 mm of the offset that holds the most of them (the pile
marching cubes makes where noise flips the sign of a layer of voxel centres near a face:
vertices on that layer's edges, all at the layer's distance from the face). Then, for faces
normal to an axis, the zero crossing of each column of band voxels along that axis that
crosses the face's layer pair, for the posterior's mean and the TSDF (``band.npz``), its
mean and spread (crossings more than a voxel from the face are left out)::

    python tools/suite.py --heldout --meshes disk --conditions few_views --keep runs
    python docs/experiments/flat_face_offsets.py runs/disk-few_views
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's bftaichi first


def main(argv=None) -> int:
    import igl
    import trimesh

    import bftaichi as bf
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    run = Path((argv or sys.argv[1:])[0])
    cfg = bf.load_config(run / "config.toml", [])
    gt = load_gt_mesh(cfg, open_frames(cfg))
    h = cfg.tsdf.voxel_size_m
    V, F = np.ascontiguousarray(gt.vertices, np.float64), np.ascontiguousarray(gt.faces, np.int64)
    print(f"{run}: voxel {1e3 * h:g} mm")
    faces = {}
    for name in ("tsdf_mesh.ply", "mesh.ply"):
        v = np.asarray(trimesh.load(run / name, process=False).vertices, np.float64)
        _, tri, closest = igl.point_mesh_squared_distance(v, V, F)
        n = gt.face_normals[tri]
        offset = np.einsum("ij,ij->i", v - closest, n) * 1e3  # mm, outward positive
        axis, sign = np.abs(n).argmax(axis=1), np.sign(n[np.arange(len(n)), np.abs(n).argmax(1)])
        flat = np.abs(n).max(axis=1) > np.cos(np.radians(8))
        for a in range(3):
            for s in (1, -1):
                sel = flat & (axis == a) & (sign == s)
                if sel.sum() < 500:
                    continue
                o = offset[sel]
                hist, edges = np.histogram(o, bins=np.arange(-5.0, 5.0001, 0.05))
                peak = edges[hist.argmax()] + 0.025
                plane = float(np.median(closest[sel, a]))
                faces[(a, s)] = plane
                print(f"  {name:13s} face {'xyz'[a]}{'+' if s > 0 else '-'} at {1e3 * plane:+.1f}"
                      f" mm: {sel.sum()} vertices, offset mean {o.mean():+.3f} std {o.std():.3f}"
                      f" mm, within 1 mm {np.mean(np.abs(o) < 1):.3f}, at {peak:+.3f} mm "
                      f"+-0.05 {np.mean(np.abs(o - peak) < 0.05):.3f}")
    band = np.load(run / "band.npz")
    ijk = band["ijk"].astype(np.int64)
    centre = (ijk + 0.5) * h + band["origin"]
    for (a, s), plane in sorted(faces.items()):
        lo = int(np.floor((plane - band["origin"][a]) / h - 0.5))  # the layer just below
        others = [b for b in range(3) if b != a]
        key = ijk[:, others[0]] * (1 << 21) + ijk[:, others[1]]
        for field in ("mean", "tsdf"):
            vals = band[field].astype(np.float64)
            below, above = (ijk[:, a] == lo), (ijk[:, a] == lo + 1)
            kb, ka = key[below], key[above]
            common, ib, ia = np.intersect1d(kb, ka, return_indices=True)
            f0, f1 = vals[below][ib], vals[above][ia]
            cross = (f0 * f1 < 0)
            z0 = centre[below][ib][cross, a]
            z = z0 + h * f0[cross] / (f0[cross] - f1[cross])
            z = z[np.abs(z - plane) < h]
            print(f"  band {field:4s} face {'xyz'[a]}{'+' if s > 0 else '-'}: {len(z)} column "
                  f"crossings, mean {1e3 * (z.mean() - plane):+.3f} mm from the face, std "
                  f"{1e3 * z.std():.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
