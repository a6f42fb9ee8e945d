#!/usr/bin/env python
"""The rays model's observation pass per frame, in a loop long enough to compare two builds.

Fuses the first 500 redkitchen frames at 2 cm into the TSDF, builds the band, then calls
``Observer.integrate`` on 40 frames spread over the sequence, round and round for SECONDS, and
prints the mean milliseconds per frame. One run of ``tools/bench_observe.py`` moved by 20 %
between identical builds on the shared 2-core machine; alternating runs of this loop, one per
build, are what docs/measurements.md ("The observation pass's block lookup, profiled with
perf") quotes::

    python docs/experiments/observe_loop.py 20                        # this checkout
    python ../before/docs/experiments/observe_loop.py 20              # a worktree of another
    python docs/experiments/observe_loop.py 12 observation.gate=0     # with config overrides

While it loops, ``perf record -F 2999 -p PID -- sleep 8`` samples the kernels (the PID is
printed first) and ``gdb -p PID -batch -ex "x/80i ADDRESS"`` disassembles a hot address.
"""

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = checkout.ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    seconds, sets = float(argv[0]), argv[1:]
    import bftaichi as bf
    from bftaichi.frame import local_frames
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import make_observer

    cfg = bf.load_config(None, ["tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04", *sets])
    ds = bf.open_dataset(str(DATA), frames=slice(0, 500))
    recon = bf.Reconstructor(cfg)
    for f in ds:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)
    picks = np.unique(np.linspace(0, len(frames) - 1, 40).round().astype(int))
    obs = make_observer(band, cfg.observation, cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m)
    first = frames[int(picks[0])]
    obs.integrate(first.depth_m, first.K, first.T_W_C)  # compiled before the clock starts
    print(f"pid {os.getpid()}: looping for {seconds:g} s", flush=True)
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        for i in picks:
            f = frames[int(i)]
            obs.integrate(f.depth_m, f.K, f.T_W_C)
            n += 1
    print(f"{' '.join(sets) or 'defaults'}: {1e3 * (time.perf_counter() - t0) / n:.2f} ms per "
          f"frame ({n} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
