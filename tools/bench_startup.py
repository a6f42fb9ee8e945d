#!/usr/bin/env python
"""Cold vs warm wall time of a `bftaichi run` command (Taichi JIT vs its offline cache).

Runs the command in a subprocess with an empty Taichi offline cache (cold: every kernel is
compiled), then again with the cache the first run filled (warm), and prints both times::

    python tools/bench_startup.py                      # bftaichi run (the default scene)
    python tools/bench_startup.py --repeats 3 -- run scenes/seed_sphere.toml
    python tools/bench_startup.py --repeats 5 --ab BFTAICHI_TAICHI_POSITIONS=full
    python tools/bench_startup.py --repeats 3 --ab BFTAICHI_TAICHI_OPT=full

``--ab NAME=VALUE`` then times ``--repeats`` cold and warm runs with that environment variable
set and as many without, alternating (each cold run on its own empty cache, the warm run after
it on the cache it filled), and prints both with their medians: an A/B of a start-up setting
on a shared machine.

``--kernels N`` then runs the command once more cold and warm (each variant), with each
kernel's first call timed (its compilation, or its load from the offline cache, and its first
run) and, within it, Taichi's Python front end (which a warm run pays as a cold one does), and
prints the N slowest: where a start goes. Those runs are not in the figures
above (the timing wrapper is not free).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import checkout  # noqa: E402  (this checkout's bftaichi first on sys.path)


#: Run the command line with the first call of every Taichi kernel timed, and within it
#: Taichi's Python front end (``Kernel.materialize``: the kernel's AST turned into Taichi IR,
#: which every process does, the offline cache only sparing what comes after it); the seconds
#: go, as JSON {"first": {module.kernel: s}, "front": {module.kernel: s}}, to the file named by
#: the first argument.
_FIRST_CALLS = """
import atexit, json, sys, time
import taichi.lang.kernel_impl as ki
first, front, call, materialize = {}, {}, ki.Kernel.__call__, ki.Kernel.materialize
def _name(self):
    return f"{self.func.__module__}.{self.func.__name__}"
def timed(self, *a, **k):
    name = _name(self)
    if name in first:
        return call(self, *a, **k)
    t0 = time.perf_counter()
    try:
        return call(self, *a, **k)
    finally:
        first[name] = time.perf_counter() - t0
def timed_front(self, *a, **k):
    t0 = time.perf_counter()
    try:
        return materialize(self, *a, **k)
    finally:
        name = _name(self)
        front[name] = front.get(name, 0.0) + time.perf_counter() - t0
ki.Kernel.__call__, ki.Kernel.materialize = timed, timed_front
path = sys.argv.pop(1)
atexit.register(lambda: open(path, "w").write(json.dumps({"first": first, "front": front})))
import bftaichi.cli
sys.argv[0] = "bftaichi"
bftaichi.cli.main()
"""


def _first_calls(args: list[str], env: dict) -> tuple[dict, dict]:
    """Each kernel's first-call seconds in a cold run and in the warm run after it, each
    ``{"first": {kernel: s}, "front": {kernel: s}}`` (the front end's part of them)."""
    cache, out = tempfile.mkdtemp(prefix="ti-cache-"), tempfile.mkdtemp(prefix="bftaichi-out-")
    env = dict(env, TI_OFFLINE_CACHE_FILE_PATH=cache)
    found = []
    try:
        for _ in range(2):
            path = os.path.join(out, "first_calls.json")
            cmd = [sys.executable, "-c", _FIRST_CALLS, path, *args, "--out",
                   os.path.join(out, "run"), "--overwrite", "--quiet"]
            subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE)
            with open(path) as f:
                found.append(json.load(f))
    finally:
        shutil.rmtree(cache, ignore_errors=True)
        shutil.rmtree(out, ignore_errors=True)
    return found[0], found[1]


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
                    help="time cold and warm runs with and without this environment variable, "
                         "alternating")
    ap.add_argument("--kernels", type=int, default=0, metavar="N",
                    help="also print the N kernels whose first call takes longest, cold and warm")
    args = ap.parse_args(argv)
    if args.ab is not None and "=" not in args.ab:
        ap.error(f"--ab {args.ab!r}: expected NAME=VALUE")
    exe = [sys.executable, "-m", "bftaichi.cli"]
    base = checkout.child_env()  # the children run this checkout's bftaichi
    if args.ab is not None:
        name, value = args.ab.split("=", 1)
        base.pop(name, None)
        variants = {args.ab: dict(base, **{name: value}), f"{name} unset": base}
    else:
        variants = {"": base}
    times = {label: ([], []) for label in variants}  # label -> (cold, warm)
    for _ in range(args.repeats):
        for label, env in variants.items():  # alternating: the machine's drift hits both
            cache = tempfile.mkdtemp(prefix="ti-cache-")
            out = tempfile.mkdtemp(prefix="bftaichi-out-")
            env = dict(env, TI_OFFLINE_CACHE_FILE_PATH=cache)
            cmd = exe + args.command + ["--out", out, "--overwrite", "--quiet"]
            try:
                times[label][0].append(_time(cmd, env))
                times[label][1].append(_time(cmd, env))
            finally:
                shutil.rmtree(cache, ignore_errors=True)
                shutil.rmtree(out, ignore_errors=True)

    def _all(ts):
        return ", ".join(f"{t:.2f}" for t in ts)

    print(f"command: bftaichi {' '.join(args.command)}")
    cold, warm = times[next(iter(times))] if args.ab is None else times[f"{name} unset"]
    if args.ab is not None:
        print(f"(without {name}:)")
    print(f"cold (empty Taichi cache): {min(cold):.2f} s   (all: {_all(cold)})")
    print(f"warm (offline cache):      {min(warm):.2f} s   (all: {_all(warm)})")
    print(f"JIT overhead saved by the cache: {min(cold) - min(warm):.2f} s")
    if args.ab is not None:
        for label, (c, w) in times.items():
            print(f"cold, {label}: median {statistics.median(c):.2f} s   (all: {_all(c)})")
            print(f"warm, {label}: median {statistics.median(w):.2f} s   (all: {_all(w)})")
    if args.kernels > 0:
        firsts = {label: _first_calls(args.command, env) for label, env in variants.items()}
        for label, (cold_run, warm_run) in firsts.items():
            which = f", {label}" if label else ""
            cold_k, warm_k, front = cold_run["first"], warm_run["first"], warm_run["front"]
            print(f"\nfirst calls{which}: cold {sum(cold_k.values()):.2f} s, warm "
                  f"{sum(warm_k.values()):.2f} s over {len(cold_k)} kernels, of which Taichi's "
                  f"front end {sum(front.values()):.2f} s warm (the rest: loading the cached "
                  f"code and the first run); the slowest:")
            print("| kernel | cold (s) | warm (s) | warm, front end (s) |\n|---|---|---|---|")
            for k in sorted(cold_k, key=cold_k.get, reverse=True)[:args.kernels]:
                print(f"| {k} | {cold_k[k]:.2f} | {warm_k.get(k, float('nan')):.2f} | "
                      f"{front.get(k, float('nan')):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
