#!/usr/bin/env python
"""The memory check's scene sample, timed (issue 16): for a dataset folder at each voxel size,
the seconds of :class:`bftaichi.running.resources.SceneSample` (reading 40 frames and
back-projecting them), of its ``measure`` and of ``estimate_memory`` on it, and a hash of the
estimate without its seconds (the same hash from two checkouts = the same estimate). Run it from
two checkouts to compare them::

    python docs/experiments/scene_sample_timing.py ../shared/data/rgbd/7scenes-redkitchen
    python ../before/docs/experiments/scene_sample_timing.py ../shared/data/rgbd/7scenes-redkitchen
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's bftaichi first


def main(argv=None) -> int:
    from bftaichi.cli import _dataset_overrides
    from bftaichi.config import load_config
    from bftaichi.running.pipeline import open_frames
    from bftaichi.running.resources import SceneSample, estimate_memory

    args = sys.argv[1:] if argv is None else argv
    data = args[0]
    for voxel in [float(v) for v in (args[1:] or ["0.02", "0.01"])]:
        cfg = load_config(None, _dataset_overrides(data, "auto", voxel, None, None, None, None))
        frames = open_frames(cfg)
        t0 = time.perf_counter()
        sample = SceneSample(frames, voxel, cfg.scene.depth_max_m)
        t1 = time.perf_counter()
        sample.measure(voxel, cfg.tsdf.bootstrap_trunc_m)
        t2 = time.perf_counter()
        est = estimate_memory(cfg, frames, sample=sample)
        t3 = time.perf_counter()
        digest = hashlib.sha256(json.dumps({k: v for k, v in est.items() if k != "seconds"},
                                           sort_keys=True, default=str).encode()).hexdigest()
        print(f"{voxel:g} m: sample {t1 - t0:.3f} s, measure {t2 - t1:.3f} s, estimate "
              f"{t3 - t2:.3f} s; estimate sha256 {digest[:12]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
