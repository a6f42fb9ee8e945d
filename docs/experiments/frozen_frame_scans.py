"""What ``bftaichi.backend._skip_frozen_frame_scans`` saves a process (issue 16; the default:
docs/measurements.md, "Start-up: Taichi's decorators scanned every module").

Each round times, in fresh processes, ``import bftaichi`` followed by what a command imports
(:func:`bftaichi.process.freeze_heap`: Taichi and the pipeline) and the kernel modules, once
as the package does it and once with the fix undone right after ``import bftaichi`` (the
two cache entries taken out of :mod:`inspect` again), alternating, and prints both medians::

    python docs/experiments/frozen_frame_scans.py             # 5 rounds
    python docs/experiments/frozen_frame_scans.py --rounds 9

``--reads`` instead runs ``bftaichi run`` (the default scene, warm once the offline cache is
filled) in one process and counts what ``bftaichi.backend._remembered_source_lines`` spares:
how often Taichi's front end asked for a function's source lines, how often they were read
(for how many functions), and the seconds those reads took::

    python docs/experiments/frozen_frame_scans.py --reads
    python docs/experiments/frozen_frame_scans.py --reads --undo     # without the memo
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
    for name in bftaichi.backend._FROZEN_FILES:
        inspect.modulesbyfile.pop(name, None)
from bftaichi.process import freeze_heap
freeze_heap()
import kernels.band, kernels.carve, kernels.compact, kernels.coverage, kernels.dataterm
import kernels.embed, kernels.observe, kernels.pcg, kernels.prior, kernels.probes
import kernels.raycast, kernels.tsdf
print(time.perf_counter() - t)
"""


READS = """\
import tempfile, time
import bftaichi
from taichi.lang import kernel_impl
read, reads = kernel_impl.getsourcelines, []
def timed(func):
    t = time.perf_counter()
    found = read(func)
    reads.append((func, time.perf_counter() - t))
    return found
kernel_impl.getsourcelines = timed      # what bftaichi.init's memo calls on a miss
if {undo}:
    bftaichi.backend._remembered_source_lines = lambda: None
bftaichi.init()
asked = [0]
memo = kernel_impl.getsourcelines
def counted(func):
    asked[0] += 1
    return memo(func)
kernel_impl.getsourcelines = counted    # what Taichi's front end calls
from bftaichi.cli import main
main(["run", "--out", tempfile.mkdtemp(), "--overwrite", "--quiet"])
print(f"front end asked {{asked[0]}} times; read {{len(reads)}} times "
      f"({{len(set(f for f, _ in reads))}} functions), {{sum(t for _, t in reads):.3f}} s")
"""


def seconds(undo: bool) -> float:
    res = subprocess.run([sys.executable, "-c", CODE.format(undo=undo)], cwd=ROOT,
                         capture_output=True, text=True, check=True)
    return float(res.stdout.split()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=5, help="pairs of processes (default 5)")
    ap.add_argument("--reads", action="store_true", help="count the source reads of a run")
    ap.add_argument("--undo", action="store_true", help="with --reads: without the memo")
    args = ap.parse_args(argv)
    if args.reads:
        res = subprocess.run([sys.executable, "-c", READS.format(undo=args.undo)], cwd=ROOT,
                             capture_output=True, text=True, check=True)
        print(res.stdout.strip().splitlines()[-1])
        return 0
    fixed, undone = [], []
    for r in range(args.rounds):
        undone.append(seconds(True))
        fixed.append(seconds(False))
        print(f"round {r + 1}: scans {undone[-1]:.3f} s, without them {fixed[-1]:.3f} s")
    slow, fast = statistics.median(undone), statistics.median(fixed)
    print(f"median: scans {slow:.3f} s, without them {fast:.3f} s, saved {slow - fast:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
