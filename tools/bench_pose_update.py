#!/usr/bin/env python
"""Pose updates after a loop closure against re-fusing (issue 19, item 3), side by side.

The redkitchen frames (``../shared/data/rgbd/7scenes-redkitchen``, preloaded) are fused with
the recorded poses of all but the last ``n`` frames, whose poses carry a simulated drift: a
rotation about the vertical growing to ``--drift-deg`` and a translation growing to
``--drift-m`` along the last ``n`` frames, what a loop closure then corrects. Timed, on the
same machine in one run (best of ``--repeats`` each, alternating; every run printed):

* **update**: ``Reconstructor.update_poses`` of the ``n`` frames back to their recorded poses
  (each subtracted at its drifted pose and added at the corrected one);
* **re-fuse**: a new ``Reconstructor`` integrating all frames at the corrected poses;

each once for the TSDF alone and once followed by ``solve()`` (the posterior; after an update
it starts cold, as the re-fuse's does, and must equal it bitwise). The updated volume and
posterior are checked against the re-fused ones, and the ratios update / re-fuse printed::

    python tools/bench_pose_update.py                      # 500 frames, 2 cm, 50 and 5 poses
    python tools/bench_pose_update.py --frames 100 --moved 10 --no-solve
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DEFAULT_DATA = ROOT / ".." / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def drift(T: np.ndarray, s: float, deg: float, metres: float) -> np.ndarray:
    """``T`` moved by a fraction ``s`` of the drift (rotation about world z, then a shift)."""
    a = np.deg2rad(deg * s)
    D = np.eye(4)
    D[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    D[:3, 3] = np.array([1.0, -0.5, 0.3]) / np.sqrt(1.34) * metres * s
    return D @ T


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--moved", type=int, nargs="+", default=[50, 5],
                    help="numbers of frames (the last ones) whose poses are corrected")
    ap.add_argument("--drift-deg", type=float, default=2.0)
    ap.add_argument("--drift-m", type=float, default=0.05)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-solve", action="store_true", help="time the TSDF only")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    import bftaichi as bf

    bf.init("cpu")
    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={args.voxel}",
                                f"tsdf.trunc_m={2 * args.voxel}"])
    frames = list(bf.open_dataset(args.data, depth_min_m=cfg.scene.depth_min_m,
                                  depth_max_m=cfg.scene.depth_max_m,
                                  frames=slice(0, args.frames)))
    n = len(frames)
    print(f"{n} frames of {args.data.name}, {args.voxel * 100:g} cm voxels; drift up to "
          f"{args.drift_deg} deg and {args.drift_m * 100:g} cm over the moved frames")

    def refuse(solve: bool):
        t0 = time.perf_counter()
        r = bf.Reconstructor(cfg)
        for f in frames:
            r.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
        t1 = time.perf_counter()
        if solve:
            r.solve()
        return r, t1 - t0, time.perf_counter() - t0

    results = {"frames": n, "voxel_m": args.voxel, "cases": []}
    solves = [False] if args.no_solve else [False, True]
    refuse(False)  # compile every kernel before timing
    for m in args.moved:
        for solve in solves:
            upd, ref, ref_tsdf = [], [], []
            for rep in range(args.repeats):
                r = bf.Reconstructor(cfg)
                for i, f in enumerate(frames):
                    s = max(0.0, (i - (n - m) + 1) / m)
                    T = drift(f.T_W_C, s, args.drift_deg, args.drift_m) if s > 0 else f.T_W_C
                    r.integrate(f.depth_m, f.K, T, name=f.name)
                if solve:
                    r.solve()  # the map before the loop closure
                t0 = time.perf_counter()
                moved = r.update_poses({f.name: f.T_W_C for f in frames[n - m:]})
                if solve:
                    r.solve()
                upd.append(time.perf_counter() - t0)
                if solve:  # where the update's solve spends its time (Reconstructor.solve)
                    print(f"  {m} poses, the solve after the update: "
                          + ", ".join(f"{k} {v:.2f} s" for k, v in r.posterior.seconds.items()))
                assert len(moved) == m
                fresh, t_tsdf, t_all = refuse(solve)
                ref.append(t_all)
                ref_tsdf.append(t_tsdf)
                if rep == 0:  # the exactness the tests assert, on real frames
                    a, b = r.voxels, fresh.voxels
                    same = all(np.array_equal(a[k], b[k]) for k in b)
                    print(f"  {m} poses: updated TSDF bitwise equal to the re-fused one: {same}")
                    if solve:
                        seen = fresh.posterior.weight > 0
                        dm = np.abs(r.posterior.mean - fresh.posterior.mean)[seen].max() \
                            if np.array_equal(r.posterior.ijk, fresh.posterior.ijk) else np.nan
                        print(f"  posterior: max |mean difference| {dm / args.voxel:.2e} voxel")
                del r, fresh
            what = "TSDF + solve" if solve else "TSDF only"
            ratio = min(upd) / min(ref)
            print(f"{m:4d} poses, {what:13s}: update {min(upd):7.2f} s, re-fuse {min(ref):7.2f} s"
                  f" -> ratio {ratio:.3f}   (runs: update {[round(x, 2) for x in upd]}, "
                  f"re-fuse {[round(x, 2) for x in ref]})")
            results["cases"].append({"moved": m, "solve": solve, "update_s": upd,
                                     "refuse_s": ref, "ratio": ratio})
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
