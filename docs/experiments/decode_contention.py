#!/usr/bin/env python
"""A command timed while another process takes some of the CPU (issue 16; docs/measurements.md,
"Frames decoded beside the kernels").

Starts a load in a child process at the given ``--nice``, runs the command after ``--``, then
stops the load. ``--load decode``: two threads, each decoding a redkitchen depth PNG (Pillow,
without the GIL), then sleeping ``--sleep`` seconds, over and over (the pipeline's two reader
threads do that work beside the kernels). ``--load busy``: one thread summing 10,000 integers in
Python, then sleeping ``--sleep`` seconds::

    python tools/bench_observe.py ../shared/data/rgbd/7scenes-redkitchen --timed 40 --loop 8
    python docs/experiments/decode_contention.py --load decode --sleep 0.012 -- \\
        python tools/bench_observe.py ../shared/data/rgbd/7scenes-redkitchen --timed 40 --loop 8
    python docs/experiments/decode_contention.py --load decode --sleep 0.012 --nice 19 -- ...
    python docs/experiments/decode_contention.py --load busy --sleep 0.002 --nice 19 -- ...
"""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the layout rule of docs/experiments (no bftaichi import here)
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def _load(kind: str, sleep: float, data: str) -> None:
    """The load itself (the child process): runs until killed."""
    import numpy as np
    from PIL import Image

    files = sorted(glob.glob(os.path.join(data, "*.depth.png")))

    def decode():
        i = 0
        while True:
            np.asarray(Image.open(files[i % len(files)]))
            i += 1
            time.sleep(sleep)

    def busy():
        x = 0
        while True:
            for i in range(10_000):
                x += i
            time.sleep(sleep)

    threads = [threading.Thread(target=decode, daemon=True) for _ in range(2)] \
        if kind == "decode" else [threading.Thread(target=busy, daemon=True)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--child" in argv:
        kind, sleep, data = argv[argv.index("--child") + 1:argv.index("--child") + 4]
        _load(kind, float(sleep), data)
        return 0
    split = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--load", choices=("decode", "busy"), default="decode")
    ap.add_argument("--sleep", type=float, default=0.012, help="seconds between work items")
    ap.add_argument("--nice", type=int, default=0, help="the load's niceness (0-19)")
    ap.add_argument("--data", default=str(DATA), help="a folder of *.depth.png (decode)")
    args = ap.parse_args(argv[:split])
    command = argv[split + 1:]
    if not command:
        ap.error("give the command to time after --")
    load = subprocess.Popen([sys.executable, __file__, "--child", args.load, str(args.sleep),
                             args.data], preexec_fn=lambda: os.nice(args.nice))
    try:
        time.sleep(1.0)  # the load running before the command starts
        return subprocess.call(command)
    finally:
        load.kill()
        load.wait()


if __name__ == "__main__":
    sys.exit(main())
