#!/usr/bin/env python
"""Where a command's kernel time goes: run a ``bftaichi`` command with Taichi's kernel profiler
on and print, per kernel, its total time, its share of all kernel time and how many of its
offloaded loops ran.

The profiler times each launch on the device (here the CPU threads), so the figures are kernel
time only: no Python, no frame reading, no Taichi front end. Kernels Taichi splits into several
offloaded loops (``name_c.._kernel_N_range_for``) are summed under their name, and so are
kernels of one name in different modules. The profiler adds a little time to every launch: use
it to see shares, not for benchmarks::

    python tools/kernel_profile.py fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out out/k2
    python tools/kernel_profile.py run --out out/default --overwrite --top 15

``--loops NAME`` also lists kernel NAME's offloaded tasks one by one (Taichi numbers them
``0, 1, ...`` in code order: each top-level loop, a static unroll giving each copy its own,
and the serial code between them), with their seconds and runs: which loop of a kernel the
time is in::

    python tools/kernel_profile.py --loops superpixels fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --frames 0:500:5 --out out/k2
"""

from __future__ import annotations

import re
import sys
from collections import defaultdict

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def _option(argv: list, flag: str, default=None):
    """The value after ``flag`` in ``argv`` (both removed), or ``default`` without it: this
    tool's own options, taken before the rest goes to ``bftaichi``."""
    if flag not in argv:
        return default
    i = argv.index(flag)
    if i + 1 == len(argv):
        raise SystemExit(f"kernel_profile.py: {flag} needs a value")
    value = argv[i + 1]
    del argv[i:i + 2]
    return value


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = int(_option(argv, "--top", 25))
    loops = _option(argv, "--loops")
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    import taichi as ti

    init = ti.init

    def profiled_init(*args, **kwargs):
        kwargs["kernel_profiler"] = True
        return init(*args, **kwargs)

    ti.init = profiled_init
    import bftaichi.cli

    code = bftaichi.cli.main(argv)
    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    profiler = get_default_kernel_profiler()
    profiler._update_records()  # Taichi 1.7: the backend's records into _traced_records
    totals, calls = defaultdict(float), defaultdict(int)
    per_loop, loop_calls = defaultdict(float), defaultdict(int)
    for rec in profiler._traced_records:
        # Taichi names an offloaded task <kernel>_c<id>_<instance>_kernel_<task>_<kind>
        m = re.match(r"(.*?)_c\d+_\d+_kernel_(\d+)_", rec.name)
        name = m.group(1) if m else rec.name
        totals[name] += rec.kernel_time / 1000.0  # ms -> s
        calls[name] += 1
        if m and name == loops:
            per_loop[int(m.group(2))] += rec.kernel_time / 1000.0
            loop_calls[int(m.group(2))] += 1
    total = sum(totals.values())
    print(f"kernel time {total:.2f} s in {len(totals)} kernels ({sum(calls.values())} offloaded loops run)")
    print(f"{'kernel':40s} {'seconds':>9s} {'share':>7s} {'loops run':>10s}")
    for name, sec in sorted(totals.items(), key=lambda kv: -kv[1])[:top]:
        print(f"{name:40s} {sec:9.3f} {100 * sec / max(total, 1e-12):6.1f}% {calls[name]:10d}")
    if loops is not None:
        print(f"\nthe offloaded tasks of {loops} (in code order):")
        print(f"{'task':>6s} {'seconds':>9s} {'runs':>10s}")
        for loop in sorted(per_loop):
            print(f"{loop:6d} {per_loop[loop]:9.3f} {loop_calls[loop]:10d}")
    return code


if __name__ == "__main__":
    sys.exit(main())
