"""Kernel calls of a scan step's solve (issue 18's 0.5 s step; a profile): the scene's initial
views plus six more candidates fused, the posterior solved once to compile, then solved again
with every Taichi kernel call counted and timed (its launch and run)::

    python docs/experiments/solve_kernel_calls.py                      # scenes/bowl.toml
    python docs/experiments/solve_kernel_calls.py scenes/shelf.toml

On a small band most of a call's time is Taichi's Python argument handling, not the kernel.
"""
import collections
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(scene: str) -> int:
    import taichi.lang.kernel_impl as ki

    import bftaichi as bf
    from bftaichi.planning.scan import _Scene

    calls, seconds = collections.Counter(), collections.Counter()
    original = ki.Kernel.__call__

    def counted(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return original(self, *args, **kwargs)
        finally:
            calls[self.func.__qualname__] += 1
            seconds[self.func.__qualname__] += time.perf_counter() - t0

    ki.Kernel.__call__ = counted
    cfg = bf.load_config(scene, [])
    sc = _Scene(cfg)
    recon = bf.Reconstructor(cfg)
    views = sc.initial + [c for c in range(len(sc.poses)) if c not in sc.initial][:6]
    for c in views:
        f = sc.frame(c)
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    recon.solve(variance=True)
    calls.clear()
    seconds.clear()
    t0 = time.perf_counter()
    post = recon.solve(variance=True)
    wall = time.perf_counter() - t0
    print(f"{Path(scene).name}: {len(post.ijk):,} band voxels; solve {wall:.3f} s, "
          f"{sum(calls.values())} kernel calls taking {sum(seconds.values()):.3f} s")
    print("| kernel | calls | seconds | ms a call |\n|---|---|---|---|")
    for name, n in calls.most_common(12):
        parts = name.split(".")
        label = parts[-1] if len(parts) == 1 else f"{parts[0]}.{parts[-1]}"
        print(f"| {label} | {n} | {seconds[name]:.3f} | "
              f"{1e3 * seconds[name] / n:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "scenes" / "bowl.toml")))
