"""What ``bftaichi.backend.skip_frozen_frame_scans`` saves a process (issue 16; the default:
docs/measurements.md, "Start-up: Taichi's decorators scanned every module").

Each round times, in fresh processes, ``import bftaichi`` followed by what a command imports
(:func:`bftaichi.process.freeze_heap`: Taichi and the pipeline) and the kernel modules, once
as the package does it and once with the fix undone right after ``import bftaichi`` (the
two cache entries taken out of :mod:`inspect` again), alternating, and prints both medians::

    python docs/experiments/frozen_frame_scans.py             # 5 rounds
    python docs/experiments/frozen_frame_scans.py --rounds 9
"""
import argparse
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CODE = """\
import time
t = time.perf_counter()
import inspect
import bftaichi
if {undo}:
    for name in ("<frozen importlib._bootstrap>", "<frozen importlib._bootstrap_external>"):
        inspect.modulesbyfile.pop(name, None)
from bftaichi.process import freeze_heap
freeze_heap()
import kernels.band, kernels.carve, kernels.compact, kernels.coverage, kernels.dataterm
import kernels.embed, kernels.observe, kernels.pcg, kernels.prior, kernels.probes
import kernels.raycast, kernels.tsdf
print(time.perf_counter() - t)
"""


def seconds(undo: bool) -> float:
    res = subprocess.run([sys.executable, "-c", CODE.format(undo=undo)], cwd=ROOT,
                         capture_output=True, text=True, check=True)
    return float(res.stdout.split()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5, help="pairs of processes (default 5)")
    args = ap.parse_args(argv)
    fixed, undone = [], []
    for r in range(args.rounds):
        undone.append(seconds(True))
        fixed.append(seconds(False))
        print(f"round {r + 1}: scans {undone[-1]:.3f} s, without them {fixed[-1]:.3f} s")
    print(f"median: scans {statistics.median(undone):.3f} s, without them "
          f"{statistics.median(fixed):.3f} s, saved {statistics.median(undone) - statistics.median(fixed):.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
