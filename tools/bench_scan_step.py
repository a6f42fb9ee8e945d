#!/usr/bin/env python
"""Where a ``bayes`` scan step's time goes (issue 18's 0.5 s target), warm: every kernel is
compiled before it is timed (the solve by a first solve, the planner's by a first candidate).

The scene's initial views plus ``--extra`` more candidate views are fused, the posterior is
solved once to compile, then timed: the solve with its variance (band, observations, MAP,
probes), building the planner, predicting the depth of every candidate, scoring every
candidate at the full stride by its expected variance reduction
(:meth:`bftaichi.planning.nbv.Planner.utility`), and the ranking a scan step makes
(:meth:`~bftaichi.planning.nbv.Planner.rank`: with ``nbv.rerank = k > 0``, a screen at twice
the stride, then the k best scored again).
One run on a shared machine: a profile, not a benchmark::

    python tools/bench_scan_step.py                       # scenes/bowl.toml
    python tools/bench_scan_step.py scenes/bunny.toml --extra 4
    python tools/bench_scan_step.py scenes/bowl.toml --extra 6 --set nbv.rerank=4
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(ROOT / "scenes" / "bowl.toml"))
    ap.add_argument("--extra", type=int, default=3, help="candidate views fused besides the "
                    "initial ones (default 3)")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    metavar="SECTION.KEY=VALUE", help="config override, e.g. nbv.rerank=4")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.planning.nbv import Planner, coverage_grid, region_of_interest
    from bftaichi.planning.scan import _Scene
    from bftaichi.reconstructor import Reconstructor

    cfg = bf.load_config(args.scene, args.sets)
    scene = _Scene(cfg)
    recon = Reconstructor(cfg)
    views = scene.initial + [c for c in range(len(scene.poses))
                             if c not in scene.initial][:args.extra]
    for c in views:
        f = scene.frame(c)
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    recon.solve(variance=True)  # compiles the kernels
    t0 = time.perf_counter()
    post = recon.solve(variance=True)
    solve = time.perf_counter() - t0
    roi = region_of_interest(post.ijk, post.voxel_size, cfg.nbv.roi_scale, scene.target,
                             post.origin)
    grid = coverage_grid(cfg, *roi, cfg.tsdf.voxel_size_m)
    for c in views:  # what the fused views saw, as a scan marks it (bftaichi.planning.scan)
        f = scene.frame(c)
        grid.mark(f.depth_m, f.K, f.T_W_C, stride=cfg.observation.stride)
    warm = Planner(post, cfg, scene.K, scene.size, grid)  # compiles the planner's kernels
    warm.predict_depth(scene.poses[0])
    warm.utility(scene.poses[0])
    warm.utility(scene.poses[0], 2 * warm.stride)  # the screen's stride (nbv.rerank)
    t0 = time.perf_counter()
    planner = Planner(post, cfg, scene.K, scene.size, grid)
    init = time.perf_counter() - t0
    n = len(scene.poses)
    t0 = time.perf_counter()
    for c in range(n):
        planner.predict_depth(scene.poses[c])
    predict = time.perf_counter() - t0
    t0 = time.perf_counter()
    for c in range(n):
        planner.utility(scene.poses[c])
    full = time.perf_counter() - t0
    t0 = time.perf_counter()
    ranked = planner.rank(scene.poses)
    rank = time.perf_counter() - t0
    screened = sum(r["stride"] != planner.stride for r in ranked)
    parts = ", ".join(f"{k} {v:.2f}" for k, v in post.seconds.items())
    print(f"{Path(args.scene).name}: {len(views)} views fused, {len(post.ijk):,} band voxels, "
          f"{n} candidates")
    print(f"solve with variance {solve:.2f} s ({parts})")
    print(f"planner {init:.2f} s; predict depth x{n} {predict:.2f} s; "
          f"utility (incl. its depth) x{n} {full:.2f} s = {1000 * full / n:.0f} ms each")
    print(f"rank (nbv.rerank = {cfg.nbv.rerank}: {n - screened} of {n} candidates scored at "
          f"stride {planner.stride}, {screened} only by the screen at stride "
          f"{2 * planner.stride}) {rank:.2f} s; a step: solve + planner + rank = "
          f"{solve + init + rank:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
