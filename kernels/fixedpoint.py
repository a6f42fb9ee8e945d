"""Fixed-point accumulation: the data term's sums in int64, exact and order-independent.

A contribution ``x`` is added as ``round(x * scale)`` (:func:`fixed_point`), each CPU thread
into its own copy (*part*) of the accumulators, without atomics; integer addition is
associative, so the sums are bitwise the same whatever the thread schedule, and a frame's
contribution can be subtracted exactly. The adds test nothing: :func:`growth_bound` bounds
what one frame can add to an entry, and the caller counts the entries beyond SATURATION
(:func:`count_saturated`) before the bounds summed since the last count pass GROWTH_LIMIT, so
no entry wraps around unseen (:mod:`kernels.observe`, "Saturation").
"""

import math
import os

import numpy as np
import taichi as ti

FRACTION_BITS = 32  # one maximal-weight contribution = 2^32 fixed-point units
SATURATION = 1 << 60  # |entry| beyond this at a check is counted as saturated
GROWTH_LIMIT = 1 << 62  # most an entry may grow between two checks (2^60 + 2^62 < 2^63)
MAX_PARTS = 4  # accumulator copies (one per thread): their sum stays below 2^63


def accumulator_parts() -> int:
    """Copies of the accumulators: one per CPU thread of the Taichi runtime (of the machine,
    before Taichi is initialised), at most MAX_PARTS (their integer sum cannot overflow)."""
    from taichi.lang import impl

    threads = 0
    if impl.get_runtime().prog is not None:  # before ti.init: as many as the CPU has
        threads = int(getattr(impl.current_cfg(), "cpu_max_num_threads", 0) or 0)
    return max(1, min(MAX_PARTS, threads or os.cpu_count() or 1))


def growth_bound(shape, fx: float, fy: float, cx: float, cy: float, spacing_m: float,
                 share: float, m: int, mf: int) -> float:
    """Most one frame of ``shape`` (H, W) can move an accumulator entry of
    :mod:`kernels.observe`, in units: ``mf + m + 1`` samples a pixel (``spacing_m`` apart),
    each carrying at most ``w_max / min(1, share)`` (a super-pixel of k^2 pixels counts k^2),
    and ``|y| <= max(m, mf) spacing |K^-1 (u, v, 1)|`` metres (intrinsics fx, fy, cx, cy)."""
    ray = max(math.hypot((u - cx) / fx, (v - cy) / fy, 1.0)
              for u in (0, shape[1]) for v in (0, shape[0]))
    y_max = max(m, mf) * spacing_m * ray
    return (float(shape[0] * shape[1]) * (m + mf + 1) * 2.0 ** FRACTION_BITS
            * max(1.0, y_max) / min(1.0, share))


@ti.func
def fixed_point(x: ti.f64) -> ti.i64:
    """round(x) half away from zero, as int64 (no libm call)."""
    return ti.cast(x + ti.select(x >= 0, 0.5, -0.5), ti.i64)


@ti.func
def part_sum(acc: ti.template(), i: ti.i32, c: ti.i32) -> ti.i64:
    """Entry ``(i, c)`` summed over the accumulator's parts (integers: exact), unrolled over
    at most :data:`MAX_PARTS`: LLVM vectorised a run-time loop here into ~13k lines of IR, code
    even a warm run generates on the first call (:func:`finalize_stencil`'s first call 0.47 ->
    0.12 s warm, 0.84 -> 0.22 s cold; ``python tools/bench_startup.py --kernels 25``)."""
    total = ti.i64(0)
    for p in ti.static(range(MAX_PARTS)):
        if p < acc.shape[0]:
            total += acc[p, i, c]
    return total


@ti.func
def saturated_entries(acc: ti.template(), i: ti.i32) -> ti.i64:
    """How many of voxel ``i``'s accumulator entries ``acc[p, i, :]`` (every part p) are
    beyond SATURATION."""
    n = ti.i64(0)
    for p in range(acc.shape[0]):
        for c in range(acc.shape[2]):
            n += ti.cast(ti.abs(acc[p, i, c]) > ti.i64(SATURATION), ti.i64)
    return n


@ti.kernel
def count_saturated(acc: ti.types.ndarray(dtype=ti.i64, ndim=3),
                    saturated: ti.types.ndarray(dtype=ti.i64, ndim=1)):
    """``saturated[0] +=`` the entries of ``acc`` (parts, N, columns) beyond SATURATION
    (integer atomics)."""
    for i in range(acc.shape[1]):
        n = saturated_entries(acc, i)
        if n > 0:
            ti.atomic_add(saturated[0], n)


def saturated_count(acc: np.ndarray) -> int:
    """How many entries of the accumulator ``acc`` (parts, N, columns) are beyond
    SATURATION: one kernel pass."""
    found = np.zeros(1, np.int64)
    count_saturated(acc, found)
    return int(found[0])
