"""The sub-runs of the compact stencil layout (:class:`kernels.compact.CompactStencil`).

A run is a maximal stretch of consecutive band rows (i, j, k), (i, j, k+1), ...; a sub-run is
a piece of a run along which every neighbour column keeps its offset, so that a block of its
rows reads each stencil term as one contiguous vector. Both passes below are parallel over
runs or sub-runs, each thread scanning its own rows in order (integers only: the same result
whatever the schedule). They replace two numpy scans of the whole band per column (prefix
maxima and minima of the rows defining it), which with the numpy around them cost the MAP's
local passes more than their solves (docs/measurements.md, "The MAP's local passes without
their Python overhead").
"""

import numpy as np
import taichi as ti

_NDA = ti.types.ndarray


@ti.kernel
def _split(first: _NDA(dtype=ti.i32, ndim=1), value: _NDA(dtype=ti.i32, ndim=2),
           defined: _NDA(dtype=ti.i8, ndim=2), split: _NDA(dtype=ti.i8, ndim=1)):
    """Within each run ``[first[r], first[r + 1])`` (one thread each): mark a row where a
    column it defines takes another offset than at the column's last defined row before it
    in the run."""
    for r in range(first.shape[0] - 1):
        for c in range(value.shape[0]):
            last, seen = 0, 0
            for i in range(first[r], first[r + 1]):
                if defined[c, i]:
                    if seen and value[c, i] != last:
                        split[i] = ti.i8(1)
                    last, seen = value[c, i], 1


@ti.kernel
def _offsets(start: _NDA(dtype=ti.i32, ndim=1), value: _NDA(dtype=ti.i32, ndim=2),
             defined: _NDA(dtype=ti.i8, ndim=2), out: _NDA(dtype=ti.i64, ndim=2)):
    """Per sub-run ``[start[q], start[q + 1])`` (one thread each) and column: the offset at
    its first row that defines the column, 0 where none does."""
    for q in range(start.shape[0] - 1):
        for c in range(value.shape[0]):
            v = 0
            for i in range(start[q], start[q + 1]):
                if defined[c, i]:
                    v = value[c, i]
                    break
            out[q, c] = v


def subruns(cont: np.ndarray, gap: np.ndarray, value: np.ndarray,
            defined: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sub-runs of ``n`` rows: ``(start, length, offsets)``, their first rows (ascending),
    lengths and (n_sub, n_col) int64 per-column offsets (that of the sub-run's first row
    defining the column, else 0).

    ``cont`` (n,) bool: row i continues row i - 1 (its -k neighbour); ``gap`` (n,) bool: a
    row whose own 3 neighbours of a column disagree (a sub-run of its own, and it ends the
    one before it); ``value``, ``defined`` (n_col, n) int32 / bool: each column's offset at
    each row and whether the row has it."""
    n = len(cont)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, len(value)), np.int64)
    split = ~cont | gap
    split[1:] |= gap[:-1]
    split = split.view(np.int8)
    flag = defined.view(np.int8)
    first = np.append(np.flatnonzero(~cont), n).astype(np.int32)  # n < 2^30 (the layout's)
    _split(first, value, flag, split)
    start = np.append(np.flatnonzero(split), n).astype(np.int32)
    offsets = np.empty((len(start) - 1, len(value)), np.int64)
    _offsets(start, value, flag, offsets)
    return start[:-1].astype(np.int64), np.diff(start).astype(np.int64), offsets
