#!/usr/bin/env python
"""The observation pass per frame: the rays model, the voxel model, the free-space count and the
TSDF, side by side.

Fuses real frames into the TSDF, builds the posterior's band from it, then times, frame by
frame and alternating, what each ``observation.model`` costs to add one frame to the data term
(``Observer.integrate``: :mod:`kernels.observe`'s samples along every pixel's ray, and
:mod:`kernels.voxelobs`'s per-voxel gather) and what counting the frame's free space costs
(:mod:`kernels.carve`, ``prior.carve``, in the same pass as either model) against
integrating the same frame into the TSDF::

    python tools/bench_observe.py                              # redkitchen, 2 cm
    python tools/bench_observe.py --voxel 0.01 --timed 20
    python tools/bench_observe.py --voxel 0.01 --set observation.aggregate=0.5

Frames are preloaded (no PNG decoding is timed), kernels compiled before timing, the noise
model is the default with no fitted extra noise. Printed: the median and best milliseconds
per frame of each, the ratios of the medians to the TSDF's (issue 16's target for the
whole observation pass: at most 1.5x the TSDF), and the rays model's accepted samples per frame
(the super-pixels of ``observation.aggregate`` set how many rays a frame casts). The machine may
be shared: the four run interleaved, frame by frame.

``--loop SECONDS`` instead calls the rays model's ``Observer.integrate`` (with ``--misfit``,
``Observer.misfit``, the local-noise pass, against the bootstrap TSDF) on the timed frames
round and round for that long and prints its mean milliseconds per frame: one figure steady
enough to compare two builds by alternating runs (one run of the table above moved by 20 %
between identical builds), and a process to sample with ``perf record -p PID`` (printed
first; docs/measurements.md, "The observation pass's block lookup, profiled with perf")::

    python tools/bench_observe.py --timed 40 --loop 15
    python ../before/tools/bench_observe.py --timed 40 --loop 15   # a worktree of another build
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA), help="a dataset folder")
    ap.add_argument("--voxel", type=float, default=0.02, help="voxel size, metres")
    ap.add_argument("--frames", type=int, default=500, help="fuse the first N frames")
    ap.add_argument("--timed", type=int, default=50, help="time this many of them, evenly spread")
    ap.add_argument("--loop", type=float, default=0.0, metavar="SECONDS",
                    help="loop the rays model over the timed frames this long, print ms per frame")
    ap.add_argument("--misfit", action="store_true",
                    help="with --loop: loop the local-noise misfit pass instead (the bootstrap "
                    "TSDF as the mean)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config override (repeatable), e.g. observation.aggregate=0.5")
    args = ap.parse_args(argv)
    if args.misfit and args.loop <= 0:
        ap.error("--misfit times the misfit pass in the --loop: give --loop SECONDS as well")

    import bftaichi as bf
    from bftaichi.frame import local_frames
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import free_space_rows, make_observer
    from kernels.carve import FreeSpaceCounter

    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={args.voxel}",
                                f"tsdf.trunc_m={2 * args.voxel}", *args.sets])
    ds = bf.open_dataset(args.data, frames=slice(0, args.frames))
    recon = bf.Reconstructor(cfg)
    for f in ds:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, x0 = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)
    picks = np.unique(np.linspace(0, len(frames) - 1, args.timed).round().astype(int))
    vs, tau = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m
    observers = {}
    for model in ("rays", "voxels"):
        cfg.observation.model = model
        observers[model] = make_observer(band, cfg.observation, vs, tau)
    tsdf = bf.TSDFVolume(vs, cfg.tsdf.bootstrap_trunc_m)
    todo = free_space_rows(band, tau)  # what the solve counts
    carve = FreeSpaceCounter(band.ijk[todo], vs, cfg.tsdf.bootstrap_trunc_m)
    f0 = frames[int(picks[0])]
    carve.add(f0.depth_m, f0.K, f0.T_W_C)
    for obs in observers.values():  # compile
        obs.integrate(f0.depth_m, f0.K, f0.T_W_C)
    tsdf.integrate(f0.depth_m, f0.K, f0.T_W_C, name="warm-up")
    if args.loop > 0:
        fields = None
        if args.misfit:  # the bootstrap as the mean, a quarter voxel^2 as its variance
            fields = (x0, np.full(len(band), 0.25 * vs * vs, np.float32))
            observers["rays"].misfit(f0.depth_m, f0.K, f0.T_W_C, *fields)  # compile
        return _loop(observers["rays"], [frames[int(i)] for i in picks], args.loop, args.sets,
                     fields)
    ms = {"tsdf": [], "rays": [], "voxels": [], "carve": []}
    samples = {"rays": []}  # the voxel model observes voxels, not samples
    for n, i in enumerate(picks):
        f = frames[int(i)]
        t = time.perf_counter()
        tsdf.integrate(f.depth_m, f.K, f.T_W_C, name=f"t{n}")
        ms["tsdf"].append(1e3 * (time.perf_counter() - t))
        for model, obs in observers.items():
            t = time.perf_counter()
            counts = obs.integrate(f.depth_m, f.K, f.T_W_C)
            ms[model].append(1e3 * (time.perf_counter() - t))
            if model in samples:
                samples[model].append(counts["samples_accepted"])
        t = time.perf_counter()
        carve.add(f.depth_m, f.K, f.T_W_C)
        ms["carve"].append(1e3 * (time.perf_counter() - t))
    print(f"{args.voxel * 100:g} cm: band {len(band):,} voxels ({len(todo):,} counted for "
          f"free space), {len(picks)} of {len(frames)} frames timed (ms per frame)")
    if args.sets:
        print("overrides: " + " ".join(args.sets))
    print("| | median | best | median / TSDF | samples per frame (mean) |\n|---|---|---|---|---|")
    base = float(np.median(ms["tsdf"]))
    for k, v in ms.items():
        n = f"{np.mean(samples[k]):,.0f}" if k in samples else "-"
        print(f"| {k} | {np.median(v):.1f} | {min(v):.1f} | {np.median(v) / base:.2f} | {n} |")
    return 0


def _loop(observer, frames, seconds: float, sets, fields=None) -> int:
    """``--loop``: ``observer.integrate`` over ``frames`` (``observer.misfit`` against
    ``fields = (mu, var)`` when given), round and round for ``seconds``."""
    import os

    print(f"pid {os.getpid()}: looping for {seconds:g} s", flush=True)
    t0, cpu0, n = time.perf_counter(), time.process_time(), 0
    while time.perf_counter() - t0 < seconds:
        for f in frames:
            if fields is None:
                observer.integrate(f.depth_m, f.K, f.T_W_C)
            else:
                observer.misfit(f.depth_m, f.K, f.T_W_C, *fields)
            n += 1
    cpu = 1e3 * (time.process_time() - cpu0) / n  # every thread's CPU time
    what = "rays" if fields is None else "misfit"
    print(f"{' '.join(sets) or 'defaults'}: {what} {1e3 * (time.perf_counter() - t0) / n:.2f} ms "
          f"per frame ({n} frames; {cpu:.2f} ms of CPU time)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
