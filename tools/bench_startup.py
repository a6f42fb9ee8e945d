#!/usr/bin/env python
"""Cold vs warm wall time of a `bftaichi run` command (Taichi JIT vs its offline cache).

Runs the command in a subprocess with an empty Taichi offline cache (cold: every kernel is
compiled), then again with the cache the first run filled (warm), and prints both times::

    python tools/bench_startup.py                      # bftaichi run (the default scene)
    python tools/bench_startup.py --repeats 3 -- run scenes/seed_sphere.toml
    python tools/bench_startup.py --repeats 5 --ab BFTAICHI_TAICHI_POSITIONS=full

``--ab NAME=VALUE`` then times ``--repeats`` warm runs with that environment variable set and
as many without, alternating (the same filled cache), and prints both with their medians: an
A/B of a start-up setting on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time


def _time(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=2, help="cold/warm pairs; the best is printed")
    ap.add_argument("command", nargs="*", default=["run"],
                    help="bftaichi arguments (after --), default: run")
    ap.add_argument("--ab", metavar="NAME=VALUE",
                    help="also time warm runs with and without this environment variable")
    args = ap.parse_args(argv)
    if args.ab is not None and "=" not in args.ab:
        ap.error(f"--ab {args.ab!r}: expected NAME=VALUE")
    exe = [sys.executable, "-m", "bftaichi.cli"]
    cold, warm, with_var, without = [], [], [], []
    for i in range(args.repeats):
        cache = tempfile.mkdtemp(prefix="ti-cache-")
        out = tempfile.mkdtemp(prefix="bftaichi-out-")
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=cache)
        cmd = exe + args.command + ["--out", out, "--overwrite", "--quiet"]
        try:
            cold.append(_time(cmd, env))
            warm.append(_time(cmd, env))
            if args.ab is not None and i == 0:  # the A/B: warm runs on this filled cache
                name, value = args.ab.split("=", 1)
                for _ in range(args.repeats):
                    with_var.append(_time(cmd, dict(env, **{name: value})))
                    without.append(_time(cmd, {k: v for k, v in env.items() if k != name}))
        finally:
            shutil.rmtree(cache, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
    print(f"command: bftaichi {' '.join(args.command)}")
    print(f"cold (empty Taichi cache): {min(cold):.2f} s   (all: {', '.join(f'{t:.2f}' for t in cold)})")
    print(f"warm (offline cache):      {min(warm):.2f} s   (all: {', '.join(f'{t:.2f}' for t in warm)})")
    print(f"JIT overhead saved by the cache: {min(cold) - min(warm):.2f} s")
    if args.ab is not None:
        name = args.ab.split("=", 1)[0]
        for label, times in ((f"warm, {args.ab}", with_var), (f"warm, {name} unset", without)):
            print(f"{label}: median {statistics.median(times):.2f} s   "
                  f"(all: {', '.join(f'{t:.2f}' for t in times)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
