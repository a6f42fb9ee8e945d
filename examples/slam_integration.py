#!/usr/bin/env python
"""SLAM integration: fuse frames as they arrive, correct poses after a loop closure without
re-fusing, and query the map from numpy.

    python examples/slam_integration.py                  # built-in tabletop, 4 frames drifted
    python examples/slam_integration.py --set tsdf.voxel_size_m=0.02

The frames are rendered from the default synthetic scene. The last ``--drifted`` of them are
fused at poses that drifted (as odometry does before a loop closes); ``update_poses`` then gives
them their corrected poses: each is subtracted from the TSDF at its old pose and added at its new
one, so the map equals fusing every frame at its corrected pose, bitwise, and so does the
posterior the next ``solve`` gives (it starts cold after an update, as a fresh fuse does; the
example checks both).
"""

from __future__ import annotations

import argparse
import time


def drift(T, s):
    """``T`` moved by a fraction ``s`` of 2 degrees about z and 4 cm: odometry's drift."""
    import numpy as np

    a = np.deg2rad(2.0 * s)
    D = np.eye(4)
    D[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    D[:3, 3] = [0.04 * s, -0.02 * s, 0.0]
    return D @ T


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--set", dest="sets", action="append", default=[], help="config override")
    ap.add_argument("--drifted", type=int, default=4, help="frames fused at drifted poses")
    args = ap.parse_args(argv)

    import numpy as np

    import bftaichi as bf
    from bftaichi.formats.synthetic import SyntheticDataset

    bf.init("cpu")
    config = bf.load_config(None, args.sets)
    frames = list(SyntheticDataset(config.synthetic))
    n, m = len(frames), min(args.drifted, len(frames) - 1)

    recon = bf.Reconstructor(config)
    for i, f in enumerate(frames):  # odometry: the last m poses drift more and more
        s = max(0, i - (n - m) + 1) / m
        recon.integrate(f.depth_m, f.K, drift(f.T_W_C, s) if s else f.T_W_C, name=f.name)
    post = recon.solve()
    print(f"{n} frames fused, {m} at drifted poses: band {len(post.ijk):,} voxels")

    # The loop closes: the SLAM back end hands over corrected poses by frame name.
    corrected = {f.name: f.T_W_C for f in frames[n - m:]}
    t0 = time.perf_counter()
    moved = recon.update_poses(corrected)
    t1 = time.perf_counter()
    post = recon.solve()  # band rebuilt where the surface moved
    t2 = time.perf_counter()
    print(f"update_poses moved {len(moved)} frames in {t1 - t0:.2f} s; solve {t2 - t1:.2f} s "
          f"({post.solver['iterations']} PCG iterations, converged {post.solver['converged']})")

    scratch = bf.Reconstructor(config)  # what the update must equal: every frame re-fused
    for f in frames:
        scratch.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    same = all(np.array_equal(recon.voxels[k], scratch.voxels[k]) for k in scratch.voxels)
    print(f"TSDF after the update equals re-fusing all {n} frames bitwise: {same}")
    ref = scratch.solve()
    same = all(np.array_equal(getattr(post, k), getattr(ref, k)) for k in ("ijk", "mean", "var"))
    print(f"posterior after the update equals the re-fused one's bitwise: {same}")

    mesh = post.extract_mesh()
    sdf, normal, sigma, seen = post.query(mesh.vertices)  # world metres in, metres out
    print(f"query at the {len(mesh.vertices):,} mesh vertices: median |sdf| "
          f"{1000 * float(np.median(np.abs(sdf[seen]))):.3f} mm, median sigma "
          f"{1000 * float(np.median(sigma[seen])):.2f} mm")
    lo, hi = mesh.bounds
    box = post.to_dense(lo, hi)  # dense (X, Y, Z) mean and std, NaN where unobserved
    print(f"dense box {box['sdf'].shape}, {np.isfinite(box['sdf']).mean():.0%} observed")
    return {"posterior": post, "moved": moved, "same": same}


if __name__ == "__main__":
    main()
