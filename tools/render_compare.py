#!/usr/bin/env python
"""Held-out depth error of one ``evalviews`` run, each reconstruction rendered both ways.

``bftaichi evalviews`` scores bftaichi by ray casting its posterior mean (the first
front-facing zero crossing through observed band cells, :func:`kernels.raycast.raycast_depth`)
and the TSDF by rendering its mesh (Embree). This tool renders both reconstructions both ways
on the same held-out frames, so that a difference between the methods can be told from a
difference between the renderers:

- ``posterior, ray cast``: what ``evalviews`` reports for bftaichi;
- ``posterior, mesh.ply``: the mesh a user gets;
- ``tsdf, ray cast``: the band's bootstrap TSDF ray cast exactly like the posterior;
- ``tsdf, tsdf_mesh.ply``: what ``evalviews`` reports for the TSDF.

Printed per rendering: the mean absolute error over the pixels where it and the measurement
have a depth, and over the pixels where all four do (the same pixels for every rendering); then
the small connected components of each mesh (closed shells around a voxel or two)::

    python tools/evalviews_table.py --voxels 0.02 --no-open3d --out out/ev
    python tools/render_compare.py out/ev/evalviews-2cm --frames 500 --every 10
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def small_components(vertices, faces, max_faces: int = 8) -> tuple[int, int, int]:
    """``(components, small ones, faces in the small ones)`` of a mesh: connected by shared
    edges after merging coincident vertices; small means at most ``max_faces`` faces."""
    import numpy as np
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=True)
    comps = trimesh.graph.connected_components(mesh.face_adjacency,
                                               nodes=np.arange(len(mesh.faces)), min_len=1)
    sizes = np.array([len(c) for c in comps])
    small = sizes <= max_faces
    return len(sizes), int(small.sum()), int(sizes[small].sum())


def isolated_negative(ijk, field, observed):
    """Observed voxels with ``field < 0`` whose 6 face neighbours are all positive or outside
    the band: (N,) bool. The mesh closes a small shell around such a voxel unless a diagonal
    neighbour is negative too."""
    import numpy as np

    from kernels.layout import block_key_np

    ijk = np.asarray(ijk, np.int64)
    keys = block_key_np(ijk)  # a band's voxels are sorted: ascending keys
    alone = observed & (field < 0)
    for axis in range(3):
        for step in (-1, 1):
            q = ijk.copy()
            q[:, axis] += step
            k = block_key_np(q)
            pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
            alone &= (keys[pos] != k) | (field[pos] > 0)
    return alone


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("run", type=Path,
                    help="evalviews run folder (band.npz, mesh.ply, tsdf_mesh.ply)")
    ap.add_argument("--data", default=str(DATA), help="the dataset the run fused")
    ap.add_argument("--frames", type=int, default=500, help="first N frames of the dataset")
    ap.add_argument("--every", type=int, default=10, help="frame step from frame 1 (odd "
                    "frames: held out by evalviews' default split)")
    args = ap.parse_args(argv)

    import numpy as np
    import trimesh

    from bftaichi.backend import init
    from bftaichi.formats import open_dataset
    from bftaichi.formats.synthetic import DepthRenderer
    from bftaichi.geometry import nearest_rigid, points_in_local, pose_in_local
    from bftaichi.io import read_mesh_ply
    from bftaichi.posterior import Posterior
    from kernels.raycast import raycast_depth

    init("cpu")
    for name in ("band.npz", "mesh.ply", "tsdf_mesh.ply"):
        if not (args.run / name).exists():
            sys.exit(f"error: {args.run / name} does not exist (an evalviews run folder?)")
    post = Posterior.load(args.run / "band.npz")
    meshes = {m: read_mesh_ply(args.run / m)[:2] for m in ("mesh.ply", "tsdf_mesh.ply")}
    renderers = {m: DepthRenderer(trimesh.Trimesh(points_in_local(v, post.origin), f,
                                                  process=False))
                 for m, (v, f) in meshes.items()}
    band, observed = post.band, (post.weight > 0).astype(np.uint8)
    fields = {"posterior, ray cast": post.mean,
              "tsdf, ray cast": np.asarray(post.tsdf, np.float32)}
    names = ["posterior, ray cast", "posterior, mesh.ply", "tsdf, ray cast",
             "tsdf, tsdf_mesh.ply"]
    own = {n: [0, 0.0] for n in names}
    common = {n: [0, 0.0] for n in names}
    ds = open_dataset(args.data)
    held = range(1, min(args.frames, len(ds)), args.every)
    for i in held:
        fr = ds[i]
        h, w = fr.depth_m.shape
        T = np.array(pose_in_local(fr.T_W_C, post.origin), np.float64)
        z = {n: raycast_depth(band.block_keys, band.block_table, f, observed, post.voxel_size,
                              fr.K, T, w, h, 0.1, 6.0) for n, f in fields.items()}
        T = nearest_rigid(T)
        z["posterior, mesh.ply"] = renderers["mesh.ply"].render(fr.K, T, w, h)
        z["tsdf, tsdf_mesh.ply"] = renderers["tsdf_mesh.ply"].render(fr.K, T, w, h)
        D = fr.depth_m
        everywhere = D > 0
        for n in names:
            everywhere &= z[n] > 0
        for n in names:
            sel = (z[n] > 0) & (D > 0)
            err = np.abs(z[n] - D)
            own[n][0] += int(sel.sum())
            own[n][1] += float(err[sel].sum())
            common[n][0] += int(everywhere.sum())
            common[n][1] += float(err[everywhere].sum())
    print(f"{len(held)} held-out frames of {Path(args.data).name} (from frame 1, every "
          f"{args.every}); mean absolute depth error, mm:")
    print(f"{'rendering':22s} {'own pixels':>22s} {'pixels all four have':>26s}")
    for n in names:
        a = f"{1000 * own[n][1] / max(own[n][0], 1):.2f} ({own[n][0]:,d} px)"
        b = f"{1000 * common[n][1] / max(common[n][0], 1):.2f} ({common[n][0]:,d} px)"
        print(f"{n:22s} {a:>24s} {b:>26s}")
    vs, tsdf, seen = post.voxel_size, np.asarray(post.tsdf, np.float32), post.weight > 0
    free = seen & (tsdf > post.trunc_m)
    alone = isolated_negative(post.ijk, post.mean, seen)
    print(f"band: {int(np.sum(free & (post.mean < 0))):,} voxels the bootstrap calls free (tsdf > "
          f"tau) have a negative mean; negative voxels whose 6 neighbours are positive: "
          f"posterior {int(alone.sum()):,}, TSDF "
          f"{int(isolated_negative(post.ijk, tsdf, seen).sum()):,}")
    if alone.any():
        print(f"  at the posterior's: median TSDF {np.median(tsdf[alone]) / vs:+.2f} voxel, "
              f"bootstrap weight {np.median(post.weight[alone]):.0f}, mean "
              f"{np.median(post.mean[alone]) / vs:+.2f} voxel")
    for m, (v, f) in meshes.items():
        n, small, faces = small_components(v, f)
        print(f"{m}: {len(f):,} faces in {n:,} components; {small:,} of them have at most 8 "
              f"faces ({faces:,} faces)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
