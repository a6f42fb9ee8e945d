"""The compact layout of the stencil, for fast single-vector products Q·x
(:class:`CompactStencil`; the stencil contract is in :mod:`kernels.stencil`).

Deterministic: every row is written by one thread, sums run in a fixed order, no atomics.
"""

import time

import numpy as np
import taichi as ti

from .layout import CENTRE, FAR, STENCIL
from .stencil import (apply_Q_batched, as_numpy, check_far, check_stencil, far_arrays,
                      first_chunk, stencil_arrays, virtual_iterations, zeros_aligned)
from .subruns import subruns

_KERNELS = {}

# -- the compact layout (single vectors) -----------------------------------------------------

#: Near columns (di, dj) of the compact layout, the voxel's own column (0, 0) excluded.
_COLUMNS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]


@ti.pyfunc
def _column_offset(c, t):
    """Stencil offset of voxel ``t`` (``dk = t - 1``) of near column ``c`` (``_COLUMNS[c]``:
    the 3 x 3 columns in order, the centre's, k = 4, skipped); a kernel may pass run-time
    values."""
    k = c if c < 4 else c + 1
    return (k // 3) * 9 + (k % 3) * 3 + t


@ti.pyfunc
def _bit(o):
    """Presence bit of stencil offset ``o`` (the offsets in order, the centre skipped)."""
    return o if o < CENTRE else o - 1


_COLUMN_OFFSETS = [[_column_offset(c, t) for t in range(3)] for c in range(len(_COLUMNS))]
_BIT = [_bit(o) for o in range(STENCIL)]
_FAR_BIT = STENCIL - 1  # presence bit of far offset a: _FAR_BIT + a (bits 26..31)
_UPPER = STENCIL - CENTRE  # 14 slots: Q_ii and the 13 offsets o > 13 (o - 13)
_R_START, _R_LEN, _R_SIMD, _R_OFF = 0, 1, 2, 3  # columns of the sub-run table
_R_COLS = _R_OFF + len(_COLUMNS) + FAR
_SUBRUNS_PER_CHUNK = 64  # sub-runs per reduction chunk (~1200 rows in a 10-voxel-thick band)
_TAIL = 16  # zero rows after the last voxel (whole-block loads past the end stay in bounds)
_INDEX_MASK = 0x3FFFFFFF  # see _CompactKernels: makes i + r provably non-wrapping for LLVM
_STRIDE_MOD, _STRIDE_REM = 1024, 400  # slot stride = 400 mod 1024 floats (1600 B mod 4 KiB)

_NDA = ti.types.ndarray
_BIG = np.iinfo(np.int32).max
_N_NEAR = len(_COLUMNS)


@ti.kernel
def _row_columns(nbr: _NDA(dtype=ti.i32, ndim=2), nbr2: _NDA(dtype=ti.i32, ndim=2),
                 has_far: ti.i32, bits: _NDA(dtype=ti.u32, ndim=1),
                 value: _NDA(dtype=ti.i32, ndim=2), defined: _NDA(dtype=ti.i8, ndim=2),
                 gap: _NDA(dtype=ti.i8, ndim=1)):
    """Per row i (one thread each): the presence bits; per near column c the offset
    ``j - i - dk`` of its present neighbours j (the smallest; ``gap`` where they differ) and
    whether it has one; per far offset a (``has_far``) its ``j - i``. See _compact_layout."""
    for i in range(nbr.shape[0]):
        # run-time loops over the offsets (integers: the same values as unrolled, for a
        # fraction of the code every process's first call builds)
        b = ti.u32(0)
        for o in range(STENCIL):
            if o != CENTRE:
                b |= ti.cast(nbr[i, o] >= 0, ti.u32) << ti.cast(_bit(o), ti.u32)
        g = 0
        for c in range(_N_NEAR):
            low, high, any_ = _BIG, -_BIG, 0
            for t in range(3):
                j = nbr[i, _column_offset(c, t)]
                if j >= 0:
                    cand = j - i - (t - 1)
                    low, high, any_ = ti.min(low, cand), ti.max(high, cand), 1
            defined[c, i] = ti.cast(any_, ti.i8)
            value[c, i] = low if any_ else 0
            if any_ and low != high:
                g = 1
        if has_far:
            for a in ti.static(range(FAR)):
                j = nbr2[i, a]
                b |= ti.cast(j >= 0, ti.u32) << ti.static(_FAR_BIT + a)
                defined[_N_NEAR + a, i] = ti.cast(j >= 0, ti.i8)
                value[_N_NEAR + a, i] = j - i if j >= 0 else 0
        bits[i] = b
        gap[i] = ti.cast(g, ti.i8)


@ti.kernel
def _fill_slots(S: _NDA(dtype=ti.f32, ndim=2), nbr: _NDA(dtype=ti.i32, ndim=2),
                S2: _NDA(dtype=ti.f32, ndim=2), nbr2: _NDA(dtype=ti.i32, ndim=2),
                has_far: ti.i32, U: _NDA(dtype=ti.f32, ndim=2)):
    """The coefficient slots of the compact layout, voxel i in column i + 1 (one thread per
    row): slot 0 ``Q_ii``, slots 1..13 the offsets 14..26 (0 where the neighbour is absent),
    with ``has_far`` slots 14..16 the far offsets +2 along i, j, k."""
    for i in range(S.shape[0]):
        U[0, i + 1] = S[i, CENTRE]
        for o in ti.static(range(1, _UPPER)):
            U[o, i + 1] = S[i, CENTRE + o] if nbr[i, CENTRE + o] >= 0 else 0.0
        if has_far:
            for a in ti.static(range(FAR // 2)):
                U[_UPPER + a, i + 1] = S2[i, 2 * a + 1] if nbr2[i, 2 * a + 1] >= 0 else 0.0


def _compact_lanes(dtype) -> int:
    """SIMD rows per block: 4, float32 or float64 (a float64 AVX2 register; 8 float32 rows
    measured slower: sub-runs of ~19 voxels leave 19 % of 8-row lanes idle, and the wider
    block spilled more registers)."""
    return 4


class _CompactKernels:
    """The single-vector product Q·x on the compact layout (:class:`CompactStencil`), SIMD
    across rows: a block of ``lanes`` consecutive rows of one sub-run shares the column
    offsets, so each of the 27 (+6 far) terms is one contiguous vector load of x, one of the
    coefficients and a multiply-add, for all ``lanes`` rows at once.

    Arguments: ``U`` the layout (:func:`_compact_layout`: coefficient slot s of voxel i at
    s*stride + i + 1, presence bits of voxel i at mbase + i, sub-run table row q at
    rbase + q*_R_COLS, the int32 words stored bit for bit; one array, as each array
    argument costs ~30 us per launch), ``n_sub`` sub-runs of which the first ``n_simd`` are
    SIMD,
    P and AP padded (N+1,) vectors of ``dtype``, ``pap`` chunk partials of p·Ap
    (n_chunks, lanes) float64. Deterministic: every row is written by one thread, sums run
    in a fixed order, no atomics.

    Code shape (checked in the optimised LLVM IR): Taichi indexes arrays with int32
    arithmetic that LLVM cannot prove free of wrap-around, so ``A[i + r]`` for r = 0..7 were
    eight unrelated loads; masking the block base with ``& 0x3FFFFFFF`` (a no-op for valid
    indices) lets it prove ``i + r`` consecutive and merge them into one vector load. The
    loads only become SIMD when the row sums feed a per-lane float64 sum (p·Ap, as in
    :class:`GatherKernels`), and only if the scalar rows' code is not in the same loop (it runs
    as a second pass); stores stay scalar. The row sum runs in three partial sums.
    """

    def __init__(self, dtype, far: bool):
        spread = virtual_iterations()
        lanes = _compact_lanes(dtype)
        tdt = ti.f64 if np.dtype(dtype) == np.float64 else ti.f32
        V = ti.types.vector(lanes, tdt)
        VD = ti.types.vector(lanes, ti.f64)
        mi = ti.i64 if tdt == ti.f64 else ti.i32  # mask lanes as wide as the data lanes
        pre = 32 if tdt == ti.f64 else 0  # int64 lanes: bit b moved to b + 32

        @ti.func
        def vload(A: ti.template(), i):
            """A[i .. i+lanes-1] as one vector (``i`` masked: see the class docstring)."""
            b = i & _INDEX_MASK
            return ti.Vector([A[b + r] for r in ti.static(range(lanes))], dt=tdt)

        @ti.func
        def vcoef(U: ti.template(), stride, slot: ti.template(), i):
            """Coefficient slot ``slot`` of padded rows i .. i+lanes-1, as dtype."""
            b = (slot * stride + i) & _INDEX_MASK
            return ti.Vector([ti.cast(U[b + r], tdt) for r in ti.static(range(lanes))])

        @ti.func
        def rw(U: ti.template(), rbase, q, col: ti.template()):
            """Sub-run table entry (q, col), int32 stored bit for bit in U."""
            return ti.bit_cast(U[rbase + q * _R_COLS + col], ti.i32)

        @ti.func
        def has(m, bit: ti.template()):
            """Per lane: presence bit ``bit`` is set (moved to the sign bit; int64 lanes hold
            the bits 32 higher)."""
            return (m << (31 - bit)) < 0

        @ti.func
        def block(U: ti.template(), mbase, P: ti.template(), stride, e, off,
                  off2):
            """(Q P) of the rows e .. e+lanes-1 (unpadded) of one sub-run with column
            offsets ``off`` (near) and ``off2`` (far)."""
            ep = e + 1  # padded index of row e
            mb = (mbase + e) & _INDEX_MASK
            m = ti.Vector([ti.cast(ti.bit_cast(U[mb + r], ti.i32), mi)
                           for r in ti.static(range(lanes))]) << pre
            # diagonal and the own column (0, 0, -+1): rows e-1 and e+1. A missing (0,0,-1)
            # neighbour means row e-1 is not (i, j, k-1), so its slot (0,0,+1) is 0.
            a0 = vcoef(U, stride, 0, ep) * vload(P, ep)
            a0 += vcoef(U, stride, 1, ep - 1) * vload(P, ep - 1)  # slot 1: offset 14
            a0 += vcoef(U, stride, 1, ep) * vload(P, ep + 1)
            a1, a2 = V(0.0), V(0.0)
            for c in ti.static(range(len(_COLUMNS))):
                j = ep + off[c] - 1  # padded index of the column's (dk = -1) voxel
                col = V(0.0)
                for t in ti.static(range(3)):
                    o = ti.static(_COLUMN_OFFSETS[c][t])
                    if ti.static(o < CENTRE):
                        # lower entry: S[i,o] = S[nbr[i,o], 26-o], the neighbour's upper slot;
                        # where the neighbour is missing, row j+t is some other voxel: masked
                        term = vcoef(U, stride, CENTRE - o, j + t) * vload(P, j + t)
                        col += ti.select(has(m, _BIT[o]), term, V(0.0))
                    else:
                        # upper entry: own slot, 0 where the neighbour is missing
                        col += vcoef(U, stride, o - CENTRE, ep) * vload(P, j + t)
                if ti.static(c % 3 == 0):
                    a1 += col
                elif ti.static(c % 3 == 1):
                    a2 += col
                else:
                    a0 += col
            if ti.static(far):
                for a in ti.static(range(FAR)):
                    j = ep + off2[a]
                    if ti.static(a % 2 == 0):  # -2 along an axis: the neighbour's slot a+1
                        term = vcoef(U, stride, _UPPER + a // 2, j) * vload(P, j)
                        a2 += ti.select(has(m, _FAR_BIT + a), term, V(0.0))
                    else:
                        a2 += vcoef(U, stride, _UPPER + a // 2, ep) * vload(P, j)
            return (a0 + a1) + a2

        @ti.func
        def row(U: ti.template(), mbase, P: ti.template(), stride, e, off, off2):
            """(Q P)_e of one row, scalar, for the few rows the blocks cannot take (index
            range, or a column with a gap): ``off`` = first present neighbour of each
            column minus e, the others follow in k order."""
            ep = e + 1
            m = ti.bit_cast(U[mbase + e], ti.i32)
            acc = ti.cast(U[ep], tdt) * P[ep]
            if (m >> _BIT[CENTRE - 1]) & 1:  # slot 1: offset 14, of row e-1 / of row e
                acc += ti.cast(U[stride + ep - 1], tdt) * P[ep - 1]
            if (m >> _BIT[CENTRE + 1]) & 1:
                acc += ti.cast(U[stride + ep], tdt) * P[ep + 1]
            for c in ti.static(range(len(_COLUMNS))):
                j = ep + off[c]
                for t in ti.static(range(3)):
                    o = ti.static(_COLUMN_OFFSETS[c][t])
                    if (m >> _BIT[o]) & 1:
                        if ti.static(o < CENTRE):
                            acc += ti.cast(U[(CENTRE - o) * stride + j], tdt) * P[j]
                        else:
                            acc += ti.cast(U[(o - CENTRE) * stride + ep], tdt) * P[j]
                        j += 1
            if ti.static(far):
                for a in ti.static(range(FAR)):
                    if (m >> (_FAR_BIT + a)) & 1:
                        j = ep + off2[a]
                        if ti.static(a % 2 == 0):
                            acc += ti.cast(U[(_UPPER + a // 2) * stride + j], tdt) * P[j]
                        else:
                            acc += ti.cast(U[(_UPPER + a // 2) * stride + ep], tdt) * P[j]
            return acc

        @ti.kernel
        def apply_dot(U: ti.types.ndarray(dtype=ti.f32, ndim=1),
                      mbase: ti.i32, rbase: ti.i32, n_sub: ti.i32, n_simd: ti.i32, stride: ti.i32,
                      P: ti.types.ndarray(dtype=tdt, ndim=1),
                      AP: ti.types.ndarray(dtype=tdt, ndim=1),
                      pap: ti.types.ndarray(dtype=VD, ndim=1)):
            """AP = Q P over the sub-runs, and the chunk partials of p·Ap per lane. Two
            passes: the SIMD sub-runs R[:n_simd] in parallel, then the scalar rows
            R[n_simd:] on one thread, added to pap[0][0] in order (their code in the same
            loop stopped LLVM from vectorising the blocks at full width; a second parallel
            loop costs a ~120 us thread-pool round trip)."""
            n_chunks = pap.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(first_chunk(t, n_chunks, n_virtual),
                               first_chunk(t + 1, n_chunks, n_virtual)):
                    s = VD(0.0)
                    for q in range(c * _SUBRUNS_PER_CHUNK,
                                   ti.min(n_simd, c * _SUBRUNS_PER_CHUNK + _SUBRUNS_PER_CHUNK)):
                        start, length = rw(U, rbase, q, _R_START), rw(U, rbase, q, _R_LEN)
                        off = ti.Vector([rw(U, rbase, q, _R_OFF + h) for h in ti.static(range(8))])
                        off2 = ti.Vector([0] * FAR)
                        if ti.static(far):
                            off2 = ti.Vector([rw(U, rbase, q, _R_OFF + 8 + a)
                                              for a in ti.static(range(FAR))])
                        for k in range((length + lanes - 1) // lanes):
                            e = start + k * lanes
                            ap = block(U, mbase, P, stride, e, off, off2)
                            for r in ti.static(range(lanes)):
                                if k * lanes + r < length:
                                    AP[e + 1 + r] = ap[r]
                            valid = ti.Vector([k * lanes + r < length
                                               for r in ti.static(range(lanes))], dt=ti.i32)
                            s += ti.select(valid != 0, ti.cast(vload(P, e + 1), ti.f64)
                                           * ti.cast(ap, ti.f64), VD(0.0))
                    pap[c] = s
            ti.loop_config(serialize=True)
            for q in range(n_simd, n_sub):
                e = rw(U, rbase, q, _R_START)
                off = ti.Vector([rw(U, rbase, q, _R_OFF + h) for h in ti.static(range(8))])
                off2 = ti.Vector([0] * FAR)
                if ti.static(far):
                    off2 = ti.Vector([rw(U, rbase, q, _R_OFF + 8 + a) for a in ti.static(range(FAR))])
                ap = row(U, mbase, P, stride, e, off, off2)
                AP[e + 1] = ap
                pap[0][0] += ti.cast(P[e + 1], ti.f64) * ti.cast(ap, ti.f64)

        self.lanes = lanes
        self.apply_dot = apply_dot


def _compact_kernels(dtype, far: bool) -> _CompactKernels:
    key = ("compact", np.dtype(dtype).name, bool(far))
    if key not in _KERNELS:
        _KERNELS[key] = _CompactKernels(dtype, bool(far))
    return _KERNELS[key]


def _first_offsets(nbr, far, rows) -> np.ndarray:
    """(len(rows), n_col) offsets of the scalar rows: per column the first present
    neighbour's index minus the row (0 if none), per far offset its index minus the row."""
    J = nbr[rows][:, np.array(_COLUMN_OFFSETS)].astype(np.int64)  # (m, 8, 3)
    p = J >= 0
    f = np.take_along_axis(J, np.argmax(p, axis=2)[..., None], axis=2)[..., 0]
    out = np.where(p.any(axis=2), f - rows[:, None], 0)
    if far is not None:
        J2 = far[1][rows].astype(np.int64)
        out = np.concatenate([out, np.where(J2 >= 0, J2 - rows[:, None], 0)], axis=1)
    return out


def _compact_layout(S, nbr, far) -> dict:
    """The compact layout of a checked stencil: the per-row columns and the coefficient slots
    by two Taichi passes over the rows (:func:`_row_columns`, :func:`_fill_slots`), the
    sub-runs by two more over runs and sub-runs (:func:`kernels.subruns.subruns`). See
    :class:`CompactStencil`."""
    n = S.shape[0]
    rows = np.arange(n, dtype=np.int32)
    # per row: presence bits, per column its neighbours' offset (one Taichi pass over nbr)
    n_col = len(_COLUMNS) + (FAR if far is not None else 0)
    bits = np.zeros(n, np.uint32)
    value = np.zeros((n_col, n), np.int32)
    defined = np.zeros((n_col, n), np.int8)
    gap = np.zeros(n, np.int8)
    nbr2 = far[1] if far is not None else np.full((1, FAR), -1, np.int32)
    if n:
        _row_columns(nbr, nbr2, int(far is not None), bits, value, defined, gap)
    defined, gap = defined.view(bool), gap.view(bool)
    # runs: maximal rows (i, j, k), (i, j, k+1), ... = consecutive band indices; sub-runs:
    # split where a column's offset changes (a gap in a neighbour column) and around rows
    # with a gap inside their own 3 neighbours of a column (kernels.subruns)
    cont = np.zeros(n, bool)
    cont[1:] = nbr[1:, CENTRE - 1] == rows[:-1]
    start, length, sub_offsets = subruns(cont, gap, value, defined)
    # SIMD sub-runs: every padded index a whole block touches lies in [0, N] (blocks of the
    # widest lane count, so one layout serves float32 and float64)
    lanes = _compact_lanes(np.float32)
    last_row = start + -(-length // lanes) * lanes - 1
    near = sub_offsets[:, :len(_COLUMNS)]
    lo = np.minimum((start[:, None] + near).min(axis=1), start)
    hi = np.maximum((last_row[:, None] + near + 2).max(axis=1), last_row + 2)
    if far is not None:
        lo = np.minimum(lo, (start[:, None] + 1 + sub_offsets[:, len(_COLUMNS):]).min(axis=1))
        hi = np.maximum(hi, (last_row[:, None] + 1 + sub_offsets[:, len(_COLUMNS):]).max(axis=1))
    simd = (lo >= 0) & (hi <= n) & ~np.logical_or.reduceat(gap, start)
    scalar_rows = np.flatnonzero(~np.repeat(simd, length))
    table = np.zeros((int(simd.sum()) + len(scalar_rows), _R_COLS), np.int64)
    k = int(simd.sum())
    table[:k, _R_START], table[:k, _R_LEN], table[:k, _R_SIMD] = start[simd], length[simd], 1
    table[:k, _R_OFF:_R_OFF + n_col] = sub_offsets[simd]
    table[k:, _R_START], table[k:, _R_LEN] = scalar_rows, 1
    table[k:, _R_OFF:_R_OFF + n_col] = _first_offsets(nbr, far, scalar_rows)
    # one float32 array: coefficient slots (0 = Q_ii, 1..13 = offsets 14..26, 14..16 = far
    # +2 along i, j, k), then the presence bits and the sub-run table as int32 bit patterns
    slots = _UPPER + (FAR // 2 if far is not None else 0)
    stride = n + 1 + _TAIL
    stride += (_STRIDE_REM - stride) % _STRIDE_MOD
    mbase = slots * stride
    rbase = mbase + n + _TAIL
    size = rbase + table.size
    if size > _INDEX_MASK:
        raise ValueError(f"band too large for the compact layout ({n} voxels; needs "
                         f"{size} < 2^30 words)")
    D = zeros_aligned(size, np.float32)
    if n:
        S2 = far[0] if far is not None else np.zeros((1, FAR), np.float32)
        _fill_slots(S, nbr, S2, nbr2, int(far is not None), D[:mbase].reshape(slots, stride))
    D[mbase:mbase + n].view(np.uint32)[:] = bits
    D[rbase:].view(np.int32)[:] = table.reshape(-1)
    return dict(D=D, stride=int(stride), mbase=int(mbase), rbase=int(rbase),
                n_sub=table.shape[0], n_simd=k, scalar_rows=len(scalar_rows))


class CompactStencil:
    """Q in the compact layout, for fast single-vector products Q·x (float32 or float64).

    Built once from a checked band stencil ``(S, nbr, far)`` (:mod:`kernels.stencil`) by
    Taichi passes and numpy (:func:`_compact_layout`); :func:`pcg` / :func:`pcg_batched`
    build one per solve of a single right-hand side and reuse it every iteration. The
    layout stores 60 bytes per voxel (72 with ``far``) plus the sub-run table (~4 bytes per
    voxel in a 10-voxel-thick band) against the 216 bytes of (S, nbr):

    * ``U``: Q_ii and the 13 *upper* offsets o > 13 (14 float32 slots, +3 for the far
      offsets +2), structure of arrays (slot s of every voxel contiguous, voxel i at
      position i+1 like the padded vectors), zero where the neighbour is missing. A lower
      entry is read from the neighbour's row: S[i,o] = S[nbr[i,o], 26-o] (o < 13; the
      symmetry that :func:`check_stencil` verifies to ``rtol``). Voxels in lexicographic
      order put the lower neighbours' rows (one slab back) in the cache already.
    * ``M``: one int32 of presence bits per voxel (26 near offsets, 6 far).
    * sub-runs: maximal runs of consecutive voxels (i, j, k), (i, j, k+1), ... along k
      (consecutive band indices), split where a neighbour column has a gap. In a sub-run the
      neighbour at (di, dj, dk) of voxel e is band index ``e + off[di, dj] + dk`` for one
      offset per column (9 int32 per ~19 voxels in a 10-voxel-thick band), so a block of 4
      consecutive rows (float32 or float64) reads each term as one contiguous vector:
      SIMD across rows (:class:`_CompactKernels`), one thread per chunk of 64 sub-runs.

    Rows a block cannot take (a gap inside a column's 3 neighbours, or within a block of the
    band's ends) are summed one at a time. The product equals the 27-point gather of
    :func:`apply_Q` with each symmetric pair taken from its upper entry (summed in a
    different order: ~1e-7 relative in float32, ~1e-16 in float64).

    Attributes: ``n`` voxels, ``far`` (bool), ``nbytes`` of the layout, ``build_seconds``,
    ``n_subruns``, ``scalar_rows``.
    """

    def __init__(self, S, nbr, far=None, check: bool = True):
        t0 = time.perf_counter()
        S, nbr = check_stencil(S, nbr) if check else stencil_arrays(S, nbr)
        far = check_far(far, S) if check else far_arrays(far, S.shape[0])
        layout = _compact_layout(S, nbr, far)
        self.n = S.shape[0]
        self.far = far is not None
        self._S, self._nbr, self._far_arrays = S, nbr, far  # the exact path (non-finite x)
        self._stride = layout["stride"]
        self._slots = layout["mbase"] // layout["stride"]
        self._D = layout["D"]
        self._args = (layout["mbase"], layout["rbase"], layout["n_sub"], layout["n_simd"],
                      layout["stride"])
        self.n_subruns = layout["n_sub"]
        self.scalar_rows = layout["scalar_rows"]
        self._n_chunks = max(1, -(-layout["n_simd"] // _SUBRUNS_PER_CHUNK))
        self.nbytes = self._D.nbytes
        self._run_of_row = None  # the sub-run of each row (apply_rows), built on first use
        self._rows_buffers = None  # apply_rows' padded vectors, made on first use
        self.build_seconds = time.perf_counter() - t0

    def set_diagonal(self, diag: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Replace Q_ii by ``diag`` (N,) (float32; the off-diagonal entries are kept): the
        layout of Q + D for a diagonal change D, e.g. the MAP's free-space passes, without a
        rebuild (the stencil the products fall back to for non-finite x gets it too). With
        ``rows`` (band indices) only those entries are taken from ``diag``: the others have
        not changed since the last call."""
        diag = np.asarray(diag, np.float32)
        if diag.shape != (self.n,):
            raise ValueError(f"diag must have shape ({self.n},), got {diag.shape}")
        rows = slice(None) if rows is None else np.asarray(rows, np.int64)
        new = diag[rows]
        if not (np.isfinite(new).all() and (new > 0).all()):
            raise ValueError("diag must be finite and positive")
        self._D[1:self.n + 1][rows] = new  # slot 0 of U, voxel i at position i + 1
        if not np.shares_memory(self._S, diag):
            self._S[rows, CENTRE] = new  # the exact path's copy

    def refill(self, S, far=None) -> None:
        """Take every coefficient from ``(S, far)``: a stencil with the neighbour tables the
        layout was built on and new values (e.g. the robust prior's reweighting,
        :func:`kernels.prior.reweight_curvature_prior`), without recomputing the runs. The
        layout then equals a fresh build's on ``(S, nbr, far)``, slot for slot."""
        S, _ = stencil_arrays(S, self._nbr)
        if S.shape[0] != self.n:
            raise ValueError(f"S must have shape ({self.n}, {STENCIL}), got {S.shape}")
        far = far_arrays(far, self.n)
        if (far is None) != (not self.far):
            raise ValueError("far must be given exactly when the layout was built with it")
        self._S = S  # the exact path (non-finite x)
        if far is not None:
            self._far_arrays = (far[0], self._far_arrays[1])
        S2, nbr2 = self._far_arrays if far is not None else (
            np.zeros((1, FAR), np.float32), np.full((1, FAR), -1, np.int32))
        _fill_slots(S, self._nbr, S2, nbr2, int(far is not None),
                    self._D[:self._args[0]].reshape(self._slots, self._stride))

    def apply_dot(self, P: np.ndarray, AP: np.ndarray) -> float:
        """AP = Q P for padded (N+1,) float32/float64 vectors (P[0] = 0, written AP[0] = 0);
        returns p·Ap (float64, deterministic). The solvers' product."""
        ker = _compact_kernels(P.dtype, self.far)
        part = np.empty((self._n_chunks, ker.lanes))
        ker.apply_dot(self._D, *self._args, P, AP, part)
        AP[0] = 0
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite P: the caller checks
            return float(part.sum())

    def apply_rows(self, x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """``(Q x)[rows]`` for an (N,) float64 ``x`` and band indices ``rows``, bit for bit
        :meth:`apply`'s values there, at the cost of the sub-runs that hold ``rows`` rather
        than of the band (the MAP's local passes): :meth:`apply_dot`'s kernel on a table of
        those sub-runs, kept after the layout's own (the first call makes room for it, and
        for two padded vectors kept until :meth:`drop_scratch`)."""
        x = np.asarray(x, np.float64)
        if x.shape != (self.n,):
            raise ValueError(f"x must have shape ({self.n},), got {x.shape}")
        mbase, rbase, n_sub, n_simd, stride = self._args
        if self._run_of_row is None:  # the sub-run of every row; room for a selection
            if self._D.size + n_sub * _R_COLS > _INDEX_MASK:
                return self.apply(x)[rows]
            size = self._D.size
            D = zeros_aligned(size + (size - rbase), np.float32)
            D[:size] = self._D
            self._D = D
            table = D[rbase:size].view(np.int32).reshape(n_sub, _R_COLS)
            start, length = table[:, _R_START].astype(np.int64), table[:, _R_LEN].astype(np.int64)
            first = np.cumsum(length) - length  # sub-run q's first position in the repeat
            run_of = np.full(self.n, -1, np.int32)
            run_of[np.repeat(start - first, length) + np.arange(int(length.sum()))] = \
                np.repeat(np.arange(n_sub, dtype=np.int32), length)
            if (run_of < 0).any():
                raise RuntimeError("CompactStencil: the sub-runs do not cover every row")
            self._run_of_row = run_of
        runs = np.unique(self._run_of_row[np.asarray(rows, np.int64)])  # SIMD ones first
        sel_base = rbase + n_sub * _R_COLS
        table = self._D[rbase:sel_base].view(np.int32).reshape(n_sub, _R_COLS)
        self._D[sel_base:sel_base + len(runs) * _R_COLS].view(np.int32)[:] = \
            table[runs].reshape(-1)
        n_simd_sel = int(np.searchsorted(runs, n_simd))
        if self._rows_buffers is None:  # padded x and Q x, kept: the local passes call this
            self._rows_buffers = (zeros_aligned(self.n + 1, np.float64),  # tens of times
                                  np.empty(self.n + 1, np.float64))  # (only rows are read)
        xp, yp = self._rows_buffers
        xp[1:] = x
        ker = _compact_kernels(np.float64, self.far)
        part = np.empty((max(1, -(-n_simd_sel // _SUBRUNS_PER_CHUNK)), ker.lanes))
        if len(runs):
            ker.apply_dot(self._D, mbase, sel_base, len(runs), n_simd_sel, stride, xp, yp, part)
        return yp[1:][rows]

    def drop_scratch(self) -> None:
        """Free the padded vectors :meth:`apply_rows` keeps between calls."""
        self._rows_buffers = None

    def apply(self, x, out=None, padded: bool = False) -> np.ndarray:
        """``out = Q x`` for one vector; the same arguments and result as :func:`apply_Q`
        (x (N,) or, with ``padded``, (N+1,) with x[0] = 0; float32 or float64; row sums in
        x's dtype). Deterministic. With non-finite values in x the product is recomputed by
        the 27-point gather (a masked-out lane may read a neighbour's inf as 0 * inf)."""
        x = as_numpy(x, "x")
        rows = self.n + 1 if padded else self.n
        if x.ndim != 1 or x.shape[0] != rows:
            raise ValueError(f"x must have shape ({rows},), got {x.shape}")
        if padded and x[0] != 0:
            raise ValueError("a padded x must have x[0] = 0")
        dtype = np.float32 if x.dtype == np.float32 else np.float64
        if out is None:
            out = np.empty(rows, dtype)
        elif out.shape != x.shape or out.dtype != dtype:
            raise ValueError(f"out must be a {x.shape} {np.dtype(dtype).name} array, got "
                             f"{out.shape} {out.dtype}")
        direct = padded and x.dtype == dtype and x.flags.c_contiguous and out.flags.c_contiguous
        if direct:
            xp = x
        else:
            xp = zeros_aligned(self.n + 1, dtype)
            xp[1:] = x[1:] if padded else x
        yp = out if direct else zeros_aligned(self.n + 1, dtype)
        if not np.isfinite(self.apply_dot(xp, yp)):
            apply_Q_batched(self._S, self._nbr, xp[:, None], yp[:, None], padded=True,
                            far=self._far_arrays)
        if yp is not out:
            out[:] = yp if padded else yp[1:]
        return out
