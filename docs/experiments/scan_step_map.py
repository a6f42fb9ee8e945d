#!/usr/bin/env python
"""A scan step's solve after one more view, and what its MAP did (issue 18; docs/measurements.md,
"A scan step's MAP from the last step's active set").

Fuses a scan scene's initial views and the first ``EXTRA - 1`` other candidates, solves, fuses
one more candidate, solves again (warm-started, as a scan step does) and prints the second
solve's seconds per sub-stage and its MAP statistics (PCG iterations, local solves, free-space
passes, anchored voxels)::

    python docs/experiments/scan_step_map.py scenes/clutter.toml 6
    git apply docs/experiments/warm_active_set.patch     # then, with the patch:
    BT_WARMSET=1 python docs/experiments/scan_step_map.py scenes/clutter.toml 6
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's bftaichi first


def main(argv=None) -> int:
    import bftaichi as bf
    from bftaichi.planning.scan import _Scene
    from bftaichi.reconstructor import Reconstructor

    args = sys.argv[1:] if argv is None else argv
    cfg = bf.load_config(args[0], args[2:])
    scene = _Scene(cfg)
    recon = Reconstructor(cfg)
    views = scene.initial + [c for c in range(len(scene.poses))
                             if c not in scene.initial][:int(args[1])]
    for c in views[:-1]:
        f = scene.frame(c)
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    recon.solve(variance=True)
    f = scene.frame(views[-1])
    recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    t0 = time.perf_counter()
    post = recon.solve(variance=True)
    print(f"solve after one more view {time.perf_counter() - t0:.2f} s",
          {k: round(v, 2) for k, v in post.seconds.items()})
    print(json.dumps({k: v for k, v in post.solver.items() if k != "residual_history"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
