#!/usr/bin/env python
"""Time per step of examples/particles_collide.py: the fused SDF (kernels.SDFField) against the
exact analytic SDF of the same tabletop, in one process::

    python tools/bench_embed.py                       # 10k particles, 200 steps, best of 5
    python tools/bench_embed.py --particles 2000 --repeats 3

The scene is fused once (the example's ``fuse_scene``). Each scene's step kernel is compiled
and run once untimed (warm-up), then each repeat restarts the drop from the same initial
positions and times every step (``ti.sync`` after each, so the times are kernel wall times).
The repeats of the two scenes alternate so that machine noise hits both alike; the best repeat
of each is printed. Two figures per scene: the mean over the whole run (particles fall for
the first ~85 steps of 4 ms, mostly outside the band, then land) and over its second half
(resting contact: every particle looks up the band every step).
"""

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

import particles_collide as ex  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--particles", type=int, default=10000, help="number of particles")
    ap.add_argument("--steps", type=int, default=200, help=f"steps of {ex.DT_S} s per repeat")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats; the best is printed")
    args = ap.parse_args(argv)
    if args.particles < 1 or args.steps < 2 or args.repeats < 1:
        ap.error("need --particles >= 1, --steps >= 2, --repeats >= 1")
    ex.bf.init("cpu")
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        post = ex.fuse_scene(tmp)
        t_fuse = time.perf_counter() - t
    field = ex.kernels.SDFField.from_posterior(post)
    scenes = {"fused": field, "analytic": ex.TabletopSDF()}
    particles = ex.Particles(args.particles)
    for scene in scenes.values():  # warm-up: compile and touch the memory
        particles.reset()
        particles.run(scene, args.steps)
    best = {name: {"all": np.inf, "rest": np.inf} for name in scenes}
    half = args.steps // 2
    for _ in range(args.repeats):
        for name, scene in scenes.items():
            particles.reset()
            times = np.array(particles.run(scene, args.steps))
            best[name]["all"] = min(best[name]["all"], times.mean())
            best[name]["rest"] = min(best[name]["rest"], times[half:].mean())
    print(f"scene: tabletop fused in {t_fuse:.1f} s, {field.n_voxels} band voxels of "
          f"{field.voxel_size * 100:.0f} cm in {field.n_blocks} blocks")
    print(f"{args.particles} particles, {args.steps} steps of {ex.DT_S * 1e3:.0f} ms, "
          f"best of {args.repeats} repeats, time per step:")
    print("  scene     whole run   resting (2nd half)")
    for name in scenes:
        print(f"  {name:<9} {best[name]['all'] * 1e3:7.3f} ms  {best[name]['rest'] * 1e3:7.3f} ms")
    ratio = {k: best["fused"][k] / best["analytic"][k] for k in ("all", "rest")}
    print(f"ratio fused / analytic: whole run {ratio['all']:.2f}, "
          f"resting {ratio['rest']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
