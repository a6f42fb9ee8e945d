"""Matrix-free posterior precision Q·x, preconditioned CG for the MAP SDF and probe variance
(DESIGN.md 3, steps 4-6).

Layout (the band contract shared with band.py / observe.py / prior.py)::

    ijk   (N, 3)  int32    band voxels, band_idx 0..N-1 in lexicographic (i, j, k) order
    nbr   (N, 27) int32    band index of the neighbour at offset o, -1 if not in the band;
                           o = (di+1)*9 + (dj+1)*3 + (dk+1), o = 13 is the voxel itself
    S     (N, 27) float32  Q in stencil form: (Q x)_i = sum_o S[i,o] x[nbr[i,o]] over
                           nbr[i,o] >= 0; symmetric: S[i,o] == S[nbr[i,o], 26-o]; S[i,13] = Q_ii
    far   (S2, nbr2)       optional second-order part: S2 (N, 6) float32 and nbr2 (N, 6)
                           int32, the entries of Q at offsets +-2 along each axis (curvature
                           prior, kernels/prior.py): a = 2 * axis + (0 for -2, 1 for +2),
                           (Q x)_i += sum_a S2[i,a] x[nbr2[i,a]]; symmetric: nbr2[nbr2[i,a],
                           a ^ 1] == i and S2 equal there; nbr2 = -1 (S2 = 0) where unused
    x     (N,)             one vector (float32 or float64)
    X     (N, K)           K vectors side by side ("a block"): row i holds the K values of
                           voxel i, so a neighbour's K values are one contiguous load

Inside the solvers every vector block is *padded*: (N+1, K) with a zero first row and voxel
i in row i+1. A missing neighbour (nbr = -1) then reads row 0, so the stencil loop has no
branch: ``sum_o S[i,o] * X[nbr[i,o] + 1]`` over all 27 offsets (S must be finite also where
nbr = -1; those coefficients multiply zero). Measured 1.35x faster than testing nbr >= 0.

* The stencil kernel (:meth:`_Kernels.apply_dot`) is a gather, one thread per chunk of rows,
  the 27 offsets unrolled (``ti.static``), S and nbr read flat (row i at i*27). It sees a
  block as N+1 vectors of K lanes (``ti.types.vector(K)``), and LLVM turns each neighbour's K
  lanes into SIMD loads and multiply-adds, so a block of K vectors costs little more than
  one vector: S and nbr (216 bytes per voxel, the dominant memory traffic) are read once for
  all K. Blocks wider than :data:`MAX_LANES` run as several blocks (K = 64 compiles in ~10 s
  and runs slower per vector than 16).
* Row sums accumulate in the vectors' dtype: float64 for the MAP solve; float32 for the
  probes (27 terms round to ~1e-6 relative, far below the probe tolerance; a float64
  accumulator halves the SIMD width and ran 2-2.5x slower at K = 16).
* :func:`pcg_batched` is Jacobi-preconditioned conjugate gradients on a block of right-hand
  sides, each column with its own alpha and beta, all advanced by the same kernels per
  iteration. :func:`pcg` (the MAP solve: one float64 column) and :func:`probe_variance`
  (K probes: float32 columns) are its two uses.
* Reductions (dot products, norms) accumulate in float64 over fixed chunks of
  :data:`CHUNK` rows, one thread per chunk summing its rows in order, fused into the kernel
  that produces the vector; the per-chunk partial sums are then added on the host in a fixed
  order (numpy, axis 0). No float atomics anywhere: every result is bitwise reproducible for
  the same inputs, independent of the thread count.

Stopping rule, one residual norm throughout: a column has converged when its true relative
residual ``||b - Q x||_2 / ||b||_2 <= tol``. Each iteration tests the recursively updated
residual r (the same norm, no extra product); when it passes, r is recomputed as b - Q x
and the test repeated on that. The value reported as ``relative_residual`` is exactly this
recomputed norm of the returned x (in float32 blocks it carries float32 rounding, ~1e-7).
If the recursive residual had drifted (it passes, the true one does not), CG restarts from
the true residual (p = M^-1 r); :data:`_STALLS` restarts in a row that do not shrink the true
residual by 10 % end the column as stagnated (tol below what the precision resolves).

Cost (tools/bench_core.py, 500k-voxel sphere band at 1 cm, this 2-core machine shared with
other jobs, so +-30 %): a single vector costs 18-40 ns per voxel against 16-24 ns for scipy's
single-threaded CSR SpMV of the same Q (0.5-1.2x): both read about the same bytes per row (27
float32 + 27 int32 vs ~25 float32 values + 25 int32 column indices) and are memory bound. A
K = 16 block costs 2.7-4.6 ns per voxel and vector (5-7x CSR SpMV, 1.7-3.2x CSR times an
(N, 16) matrix). Per CG iteration on a K = 16 block the two vector updates (x, r and p:
~400 bytes per voxel) take about as long as the product.
"""

import mmap
import time

import numpy as np
import taichi as ti

STENCIL = 27  # offsets {-1, 0, 1}^3
CENTER = 13  # offset of the voxel itself: (0, 0, 0)
FAR = 6  # optional far offsets +-2 along each axis (a = 2 * axis + (0: -2, 1: +2))
CHUNK = 1024  # rows per reduction chunk (fixed: results do not depend on the thread count)
MAX_LANES = 16  # widest compiled vector block (K = 16 probes are one block)
#: Taichi's CPU backend gives each thread one contiguous share of at least this many
#: iterations of a kernel's outer loop (its MakeCPUMultithreadedRangeFor pass), so a loop
#: over the ~500 chunks of a 500k-voxel band ran on one thread. Every parallel loop here
#: runs over max(n_chunks, TASK_MIN * threads) virtual iterations instead (:func:`_spread`).
TASK_MIN = 512

#: (27, 3) int32 offsets (di, dj, dk); row o is offset o = (di+1)*9 + (dj+1)*3 + (dk+1).
OFFSETS = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"),
                   axis=-1).reshape(STENCIL, 3).astype(np.int32)

_RUNNING, _CONVERGED, _BREAKDOWN, _STAGNATED = 0, 1, 2, 3
_STALLS = 2  # restarts in a row without a 10 % smaller true residual: stagnated


# -- kernels ---------------------------------------------------------------------------------

_KERNELS = {}


def _virtual_iterations() -> int:
    """Enough outer-loop iterations for every CPU thread to get a share (:data:`TASK_MIN`);
    read when a kernel is compiled."""
    return TASK_MIN * max(1, int(ti.lang.impl.current_cfg().cpu_max_num_threads))


@ti.func
def _spread(t, n_chunks, n_virtual):
    """First chunk of virtual iteration ``t`` when ``n_chunks`` chunks are dealt out evenly
    over ``n_virtual = max(n_chunks, _virtual_iterations())`` iterations; chunk t itself
    when there are enough chunks (no division)."""
    first = t
    if n_chunks < n_virtual:
        first = t * n_chunks // n_virtual  # < TASK_MIN * threads * n_chunks: no overflow
    return first


class _Kernels:
    """The 27-point gather kernels for blocks of ``lanes`` vectors of ``dtype`` (compiled on
    first use; Taichi's offline cache keeps them across runs), and the PCG vector updates.

    Arguments: ``S`` and ``nbr`` flattened to (N*27,) (row i at i*27); vectors (N+1, lanes)
    numpy arrays seen as N+1 vectors of ``lanes`` elements, voxel i in row i+1 and row 0
    zero (the pad row: see the module docstring); chunk partial sums (n_chunks, lanes)
    float64; ``dinv`` = 1 / Q_ii (N,) float64. Every loop runs over fixed chunks of
    :data:`CHUNK` rows, one thread per chunk, the chunks dealt out to the threads by
    :func:`_spread`. All kernels are deterministic: every output element is written by one
    thread, sums run in a fixed order, no atomics.

    Code shape matters here (checked in the optimised LLVM IR): with the 27 offsets unrolled
    and the row sums feeding a float64 vector sum, LLVM turns each offset's ``lanes``
    multiply-adds into SIMD instructions; the same row sums only stored (or stored behind a
    select) stayed scalar and ran 2-7x slower at 16 lanes. Hence one stencil kernel,
    :meth:`apply_dot`, for every product, and the residual as apply_dot + subtract. The row
    sum runs in three interleaved partial sums (offsets by column, o // 3 mod 3): one
    27-term chain is latency bound (27 dependent adds per row). The vector updates stay
    scalar (each store reloads the array pointer, which blocks LLVM's SLP vectoriser); they
    stream memory.
    """

    def __init__(self, lanes: int, dtype, far: bool):
        spread = _virtual_iterations()
        V = ti.types.vector(lanes, dtype)
        VD = ti.types.vector(lanes, ti.f64)
        VI = ti.types.vector(lanes, ti.i32)
        flat_s = ti.types.ndarray(dtype=ti.f32, ndim=1)
        flat_n = ti.types.ndarray(dtype=ti.i32, ndim=1)
        vec = ti.types.ndarray(dtype=V, ndim=1)
        part = ti.types.ndarray(dtype=VD, ndim=1)
        diag = ti.types.ndarray(dtype=ti.f64, ndim=1)

        @ti.func
        def q_row(S: ti.template(), nbr: ti.template(), S2: ti.template(),
                  nbr2: ti.template(), X: ti.template(), i: ti.i32):
            """(Q X)_i = sum_o S[i,o] X[nbr[i,o]] (+ the far part): the offsets unrolled, no
            branch (a missing neighbour, index -1, reads the zero pad row), accumulated in
            dtype in three partial sums. Without ``far`` (compile time) S2 and nbr2 are
            never read."""
            acc0, acc1, acc2 = V(0.0), V(0.0), V(0.0)
            base = i * STENCIL
            for o in ti.static(range(STENCIL)):
                term = ti.cast(S[base + o], dtype) * X[nbr[base + o] + 1]
                if ti.static((o // 3) % 3 == 0):
                    acc0 += term
                elif ti.static((o // 3) % 3 == 1):
                    acc1 += term
                else:
                    acc2 += term
            if ti.static(far):
                base2 = i * FAR
                for a in ti.static(range(FAR)):
                    acc0 += ti.cast(S2[base2 + a], dtype) * X[nbr2[base2 + a] + 1]
            return (acc0 + acc1) + acc2

        @ti.kernel
        def apply_dot(S: flat_s, nbr: flat_n, S2: flat_s, nbr2: flat_n, P: vec, AP: vec,
                      pap: part):
            """AP = Q P and the chunk partials of p·Ap (float64; deterministic)."""
            n = P.shape[0] - 1
            n_chunks = pap.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(_spread(t, n_chunks, n_virtual),
                               _spread(t + 1, n_chunks, n_virtual)):
                    s = VD(0.0)
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        ap = q_row(S, nbr, S2, nbr2, P, i)
                        AP[i + 1] = ap
                        s += ti.cast(P[i + 1], ti.f64) * ti.cast(ap, ti.f64)
                    pap[c] = s

        @ti.kernel
        def subtract(B: vec, AX: vec, dinv: diag, mask: VI, R: vec, rr: part, rz: part):
            """r = b - Ax in the lanes where ``mask`` is set (other lanes keep R), and the
            chunk partials of r·r and r·M^-1 r = sum r_i^2 / Q_ii (float64; deterministic)."""
            n = R.shape[0] - 1
            on = mask != 0
            n_chunks = rr.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(_spread(t, n_chunks, n_virtual),
                               _spread(t + 1, n_chunks, n_virtual)):
                    s_rr = VD(0.0)
                    s_rz = VD(0.0)
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        b, ax, r = B[i + 1], AX[i + 1], R[i + 1]  # loads first
                        r = ti.select(on, b - ax, r)
                        R[i + 1] = r
                        r64 = ti.cast(r, ti.f64)
                        s_rr += r64 * r64
                        s_rz += r64 * r64 * dinv[i]
                    rr[c] = s_rr
                    rz[c] = s_rz

        @ti.kernel
        def update_xr(alpha: VD, active: VI, X: vec, R: vec, P: vec, AP: vec, dinv: diag,
                      rr: part, rz: part):
            """x = x + alpha p, r = r - alpha Ap in the active lanes, and the chunk partials
            of r·r and r·M^-1 r (float64; deterministic)."""
            n = X.shape[0] - 1
            a = ti.cast(alpha, dtype)
            on = active != 0
            n_chunks = rr.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(_spread(t, n_chunks, n_virtual),
                               _spread(t + 1, n_chunks, n_virtual)):
                    s_rr = VD(0.0)
                    s_rz = VD(0.0)
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        x, r, p, ap = X[i + 1], R[i + 1], P[i + 1], AP[i + 1]  # loads first
                        x = ti.select(on, x + a * p, x)
                        r = ti.select(on, r - a * ap, r)
                        X[i + 1] = x
                        R[i + 1] = r
                        r64 = ti.cast(r, ti.f64)
                        s_rr += r64 * r64
                        s_rz += r64 * r64 * dinv[i]
                    rr[c] = s_rr
                    rz[c] = s_rz

        @ti.kernel
        def update_p(beta: VD, active: VI, R: vec, dinv: diag, P: vec):
            """p = M^-1 r + beta p in the active lanes (deterministic)."""
            b = ti.cast(beta, dtype)
            on = active != 0
            n = P.shape[0] - 1
            n_chunks = (n + CHUNK - 1) // CHUNK
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(_spread(t, n_chunks, n_virtual),
                               _spread(t + 1, n_chunks, n_virtual)):
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        r, p = R[i + 1], P[i + 1]  # loads first
                        P[i + 1] = ti.select(on, ti.cast(dinv[i], dtype) * r + b * p, p)

        self.apply_dot, self.subtract = apply_dot, subtract
        self.update_xr, self.update_p = update_xr, update_p


def _kernels(lanes: int, dtype, far: bool = False) -> _Kernels:
    key = (lanes, np.dtype(dtype).name, bool(far))
    if key not in _KERNELS:
        _KERNELS[key] = _Kernels(lanes, ti.f64 if np.dtype(dtype) == np.float64 else ti.f32,
                                 bool(far))
    return _KERNELS[key]


# -- the compact layout (single vectors) -----------------------------------------------------

#: Near columns (di, dj) of the compact layout, the voxel's own column (0, 0) excluded.
_COLUMNS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]
_COLUMN_OFFSETS = [[(di + 1) * 9 + (dj + 1) * 3 + dk + 1 for dk in (-1, 0, 1)]
                   for di, dj in _COLUMNS]
_BIT = [o if o < CENTER else o - 1 for o in range(STENCIL)]  # presence bit of offset o
_FAR_BIT = STENCIL - 1  # presence bit of far offset a: _FAR_BIT + a (bits 26..31)
_UPPER = STENCIL - CENTER  # 14 slots: Q_ii and the 13 offsets o > 13 (o - 13)
_R_START, _R_LEN, _R_SIMD, _R_OFF = 0, 1, 2, 3  # columns of the sub-run table
_R_COLS = _R_OFF + len(_COLUMNS) + FAR
_SUBRUNS_PER_CHUNK = 64  # sub-runs per reduction chunk (~1200 rows in a 10-voxel-thick band)
_TAIL = 16  # zero rows after the last voxel (whole-block loads past the end stay in bounds)
_INDEX_MASK = 0x3FFFFFFF  # see _CompactKernels: makes i + r provably non-wrapping for LLVM
_STRIDE_MOD, _STRIDE_REM = 1024, 400  # slot stride = 400 mod 1024 floats (1600 B mod 4 KiB)


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
    :class:`_Kernels`), and only if the scalar rows' code is not in the same loop (it runs
    as a second pass); stores stay scalar. The row sum runs in three partial sums.
    """

    def __init__(self, dtype, far: bool):
        spread = _virtual_iterations()
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
                    if ti.static(o < CENTER):
                        # lower entry: S[i,o] = S[nbr[i,o], 26-o], the neighbour's upper slot;
                        # where the neighbour is missing, row j+t is some other voxel: masked
                        term = vcoef(U, stride, CENTER - o, j + t) * vload(P, j + t)
                        col += ti.select(has(m, _BIT[o]), term, V(0.0))
                    else:
                        # upper entry: own slot, 0 where the neighbour is missing
                        col += vcoef(U, stride, o - CENTER, ep) * vload(P, j + t)
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
            if (m >> _BIT[CENTER - 1]) & 1:  # slot 1: offset 14, of row e-1 / of row e
                acc += ti.cast(U[stride + ep - 1], tdt) * P[ep - 1]
            if (m >> _BIT[CENTER + 1]) & 1:
                acc += ti.cast(U[stride + ep], tdt) * P[ep + 1]
            for c in ti.static(range(len(_COLUMNS))):
                j = ep + off[c]
                for t in ti.static(range(3)):
                    o = ti.static(_COLUMN_OFFSETS[c][t])
                    if (m >> _BIT[o]) & 1:
                        if ti.static(o < CENTER):
                            acc += ti.cast(U[(CENTER - o) * stride + j], tdt) * P[j]
                        else:
                            acc += ti.cast(U[(o - CENTER) * stride + ep], tdt) * P[j]
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
                for c in range(_spread(t, n_chunks, n_virtual),
                               _spread(t + 1, n_chunks, n_virtual)):
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


_NO_FAR = (np.zeros(1, np.float32), np.full(1, -1, np.int32))  # never read (far=False kernels)


def _far_arrays(far, n: int) -> tuple | None:
    """(S2 float32, nbr2 int32) (N, 6), C-contiguous, shapes and dtypes checked; None for
    ``far=None``."""
    if far is None:
        return None
    try:
        S2, nbr2 = far
    except (TypeError, ValueError):
        raise TypeError("far must be None or a pair (S2, nbr2) of (N, 6) arrays") from None
    S2, nbr2 = _numpy(S2, "S2"), _numpy(nbr2, "nbr2")
    if S2.shape != (n, FAR) or nbr2.shape != (n, FAR):
        raise ValueError(f"far (S2, nbr2) must both have shape ({n}, {FAR}), got {S2.shape} "
                         f"and {nbr2.shape}")
    if not np.issubdtype(S2.dtype, np.floating) or not np.issubdtype(nbr2.dtype, np.integer):
        raise TypeError(f"far: S2 must be float and nbr2 integer, got {S2.dtype}, {nbr2.dtype}")
    if nbr2.dtype != np.int32 and nbr2.size and (nbr2.min() < -1 or nbr2.max() >= n):
        raise ValueError(f"nbr2 holds indices outside [-1, {n})")
    return (np.ascontiguousarray(S2, dtype=np.float32),
            np.ascontiguousarray(nbr2, dtype=np.int32))


def _flat_op(S, nbr, far) -> tuple:
    """The kernels' operator arguments (S, nbr, S2, nbr2), flat."""
    S2, nbr2 = _NO_FAR if far is None else (far[0].reshape(-1), far[1].reshape(-1))
    return S.reshape(-1), nbr.reshape(-1), S2, nbr2


@ti.kernel
def _first_asymmetry(S: ti.types.ndarray(dtype=ti.f32, ndim=1),
                     nbr: ti.types.ndarray(dtype=ti.i32, ndim=1), rtol: ti.f64,
                     found: ti.types.ndarray(dtype=ti.i64, ndim=1)):
    """found[0] = the first flat index f = i*27 + o whose link j = nbr[i,o] has no link back
    (nbr[j, 26-o] != i); found[1] = the first f with |S[i,o] - S[j,26-o]| > rtol * max(Q_ii,
    Q_jj). Entries stay as given (N*27) where there is none. nbr must hold indices in
    [-1, N). Integer atomic_min only: deterministic."""
    n = nbr.shape[0] // STENCIL
    for f in range(n * STENCIL):
        i = f // STENCIL
        j = nbr[f]
        if j >= 0:
            back = j * STENCIL + (STENCIL - 1) - (f - i * STENCIL)
            if nbr[back] != i:
                ti.atomic_min(found[0], ti.cast(f, ti.i64))
            elif ti.abs(ti.cast(S[f], ti.f64) - ti.cast(S[back], ti.f64)) > rtol * ti.max(
                    ti.cast(S[i * STENCIL + CENTER], ti.f64),
                    ti.cast(S[j * STENCIL + CENTER], ti.f64)):
                ti.atomic_min(found[1], ti.cast(f, ti.i64))


# -- input checks ----------------------------------------------------------------------------

def _numpy(a, name: str) -> np.ndarray:
    """numpy view of a numpy array or a Taichi ndarray (copied)."""
    if isinstance(a, ti.Ndarray):
        return a.to_numpy()
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy array or a Taichi ndarray, got {type(a).__name__}")
    return a


def _stencil_arrays(S, nbr) -> tuple:
    """(S float32, nbr int32), C-contiguous, with shape and dtype checked (cheap checks only)."""
    S, nbr = _numpy(S, "S"), _numpy(nbr, "nbr")
    if S.ndim != 2 or S.shape[1] != STENCIL or S.shape[0] == 0:
        raise ValueError(f"S must have shape (N, 27) with N >= 1, got {S.shape}")
    if nbr.shape != S.shape:
        raise ValueError(f"nbr must have the shape of S {S.shape}, got {nbr.shape}")
    if not np.issubdtype(S.dtype, np.floating):
        raise TypeError(f"S must be a float array, got {S.dtype}")
    if not np.issubdtype(nbr.dtype, np.integer):
        raise TypeError(f"nbr must be an integer array, got {nbr.dtype}")
    if nbr.dtype != np.int32 and nbr.size and (nbr.min() < -1 or nbr.max() >= S.shape[0]):
        raise ValueError(f"nbr holds indices outside [-1, {S.shape[0]})")
    return np.ascontiguousarray(S, dtype=np.float32), np.ascontiguousarray(nbr, dtype=np.int32)


def check_far(far, S, rtol: float = 1e-5):
    """Validate the far part (S2, nbr2) of a stencil whose near part S (N, 27) is valid;
    return it as C-contiguous float32 / int32 arrays (None for None).

    Checks: shapes (N, 6); S2 finite; ``-1 <= nbr2 < N``; ``nbr2[j, a ^ 1] == i`` for
    ``j = nbr2[i, a] >= 0``; ``|S2[i,a] - S2[j,a^1]| <= rtol * max(S[i,13], S[j,13])``;
    ``S2 == 0`` where ``nbr2 == -1``. Raises ValueError naming the first bad entry."""
    n = S.shape[0]
    far = _far_arrays(far, n)
    if far is None:
        return None
    S2, nbr2 = far
    if not np.isfinite(S2).all():
        raise ValueError(f"S2 has non-finite values (first at band index "
                         f"{int(np.flatnonzero(~np.isfinite(S2).all(axis=1))[0])})")
    if nbr2.size and (nbr2.min() < -1 or nbr2.max() >= n):
        raise ValueError(f"nbr2 holds indices outside [-1, {n})")
    i, a = np.nonzero(nbr2 >= 0)
    j = nbr2[i, a]
    back = nbr2[j, a ^ 1] != i
    if back.any():
        k = int(np.flatnonzero(back)[0])
        raise ValueError(f"nbr2 is not symmetric: nbr2[{i[k]}, {a[k]}] = {j[k]} but "
                         f"nbr2[{j[k]}, {a[k] ^ 1}] = {nbr2[j[k], a[k] ^ 1]}")
    diag = S[:, CENTER].astype(np.float64)
    bad = np.abs(S2[i, a].astype(np.float64) - S2[j, a ^ 1]) > rtol * np.maximum(diag[i],
                                                                                 diag[j])
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(f"S2 is not symmetric: S2[{i[k]}, {a[k]}] = {S2[i[k], a[k]]} but "
                         f"S2[{j[k]}, {a[k] ^ 1}] = {S2[j[k], a[k] ^ 1]}")
    dangling = (nbr2 < 0) & (S2 != 0)
    if dangling.any():
        i0, a0 = (int(v[0]) for v in np.nonzero(dangling))
        raise ValueError(f"S2[{i0}, {a0}] = {S2[i0, a0]} but nbr2[{i0}, {a0}] = -1")
    return S2, nbr2


def check_stencil(S, nbr, rtol: float = 1e-5) -> tuple:
    """Validate a band's stencil; return ``(S, nbr)`` as C-contiguous float32 / int32.

    Checks (each failure raises ValueError naming the first offending band index and
    offset): shapes (N, 27); S finite; ``-1 <= nbr < N``; ``nbr[i, 13] == i``; the neighbour
    table is symmetric (``nbr[nbr[i,o], 26-o] == i``); S is symmetric
    (``|S[i,o] - S[nbr[i,o], 26-o]| <= rtol * max(S[i,13], S[j,13])``, exact for the band
    producers' fixed-point assembly); the diagonal ``S[:, 13]`` is positive. S must be
    finite everywhere, also where ``nbr = -1`` (those coefficients multiply the zero pad row).
    The symmetry checks are one Taichi pass (:func:`_first_asymmetry`); the whole check costs
    about three stencil products.
    """
    S, nbr = _stencil_arrays(S, nbr)
    n = S.shape[0]
    finite = np.isfinite(S).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"S has non-finite values (first at band index {i})")
    low, high = int(nbr.min()), int(nbr.max())
    if low < -1 or high >= n:
        raise ValueError(f"nbr holds indices outside [-1, {n}): min {low}, max {high}")
    self_bad = nbr[:, CENTER] != np.arange(n, dtype=np.int32)
    if self_bad.any():
        i = int(np.flatnonzero(self_bad)[0])
        raise ValueError(f"nbr[{i}, 13] = {nbr[i, CENTER]} must be the voxel itself ({i})")
    diag = S[:, CENTER]
    if not (diag > 0).all():
        i = int(np.flatnonzero(~(diag > 0))[0])
        raise ValueError(f"Q must be positive definite: S[{i}, 13] = Q_ii = {diag[i]} <= 0")
    found = np.full(2, n * STENCIL, np.int64)
    _first_asymmetry(S.reshape(-1), nbr.reshape(-1), float(rtol), found)
    if found[0] < n * STENCIL:
        i, o = divmod(int(found[0]), STENCIL)
        j = int(nbr[i, o])
        raise ValueError(f"nbr is not symmetric: nbr[{i}, {o}] = {j} but "
                         f"nbr[{j}, {STENCIL - 1 - o}] = {nbr[j, STENCIL - 1 - o]}")
    if found[1] < n * STENCIL:
        i, o = divmod(int(found[1]), STENCIL)
        j = int(nbr[i, o])
        raise ValueError(f"S is not symmetric: S[{i}, {o}] = {S[i, o]} but "
                         f"S[{j}, {STENCIL - 1 - o}] = {S[j, STENCIL - 1 - o]}")
    return S, nbr


def _block(a, n: int, name: str, dtype=None) -> np.ndarray:
    """A (n,) or (n, K) float array, C-contiguous, of ``dtype`` (default: float32 stays
    float32, anything else becomes float64); non-finite values rejected."""
    a = _numpy(a, name)
    if a.ndim not in (1, 2) or a.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) or ({n}, K), got {a.shape}")
    if dtype is None:
        dtype = np.float32 if a.dtype == np.float32 else np.float64
    a = np.ascontiguousarray(a, dtype=dtype)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has non-finite values")
    return a


def _column_blocks(k: int) -> list:
    """Split K columns into ceil(K / MAX_LANES) blocks of near-equal width."""
    n_blocks = -(-k // MAX_LANES)
    width = -(-k // n_blocks)
    return [(a, min(a + width, k)) for a in range(0, k, width)]


_HUGE = 2 << 20  # bytes of a transparent huge page (x86-64)


def _zeros(shape, dtype) -> np.ndarray:
    """Zeroed array; from 4 MiB on, 2 MiB-aligned memory advised for transparent huge pages
    (madvise, Linux): the compact product streams ~17 arrays at once, and 4 KiB pages cost it
    TLB misses (measured 5-25 % slower, and more variable). Elsewhere plain np.zeros."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if nbytes < 2 * _HUGE or not hasattr(mmap, "MADV_HUGEPAGE"):
        return np.zeros(shape, dtype)
    buf = mmap.mmap(-1, nbytes + _HUGE)  # anonymous: zero-filled
    raw = np.frombuffer(buf, np.uint8)  # keeps buf alive
    start = (-raw.ctypes.data) % _HUGE
    try:
        buf.madvise(mmap.MADV_HUGEPAGE, start - start % mmap.PAGESIZE,
                    nbytes + start % mmap.PAGESIZE)
    except OSError:  # not supported here: plain pages
        pass
    return raw[start:start + nbytes].view(dtype).reshape(shape)


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
    """The compact layout of a checked stencil (numpy, vectorised over voxels; the loops run
    over the 8 columns and 6 far offsets). See :class:`CompactStencil`."""
    n = S.shape[0]
    rows = np.arange(n, dtype=np.int32)
    present = nbr >= 0
    bits = np.zeros(n, np.uint32)
    for o in range(STENCIL):
        if o != CENTER:
            bits |= present[:, o].astype(np.uint32) << np.uint32(_BIT[o])
    if far is not None:
        for a in range(FAR):
            bits |= (far[1][:, a] >= 0).astype(np.uint32) << np.uint32(_FAR_BIT + a)
    # runs: maximal rows (i, j, k), (i, j, k+1), ... = consecutive band indices
    cont = np.zeros(n, bool)
    cont[1:] = nbr[1:, CENTER - 1] == rows[:-1]
    run_id = np.cumsum(~cont)
    # per row and column: the offset j - e - dk of its present neighbours j (one value unless
    # the column has a gap among the row's 3 neighbours)
    n_col = len(_COLUMNS) + (FAR if far is not None else 0)
    value = np.zeros((n_col, n), np.int32)
    defined = np.zeros((n_col, n), bool)
    gap = np.zeros(n, bool)
    big = np.iinfo(np.int32).max
    for c, offs in enumerate(_COLUMN_OFFSETS):
        J = nbr[:, offs]
        p = J >= 0
        cand = J - rows[:, None] - np.array([-1, 0, 1], np.int32)
        low = np.where(p, cand, big).min(axis=1)
        high = np.where(p, cand, -big).max(axis=1)
        defined[c] = p.any(axis=1)
        gap |= defined[c] & (low != high)
        value[c] = np.where(defined[c], low, 0)
    if far is not None:
        for a in range(FAR):
            c = len(_COLUMNS) + a
            defined[c] = far[1][:, a] >= 0
            value[c] = np.where(defined[c], far[1][:, a] - rows, 0)
    # sub-runs: split runs where a column's offset changes (a gap in a neighbour column) and
    # around rows with a gap inside their own 3 neighbours of a column
    split = ~cont | gap
    split[1:] |= gap[:-1]
    for c in range(n_col):
        last = np.maximum.accumulate(np.where(defined[c], rows, -1))
        prev = np.empty(n, np.int32)
        prev[0], prev[1:] = -1, last[:-1]
        p = np.maximum(prev, 0)
        split |= defined[c] & (prev >= 0) & (run_id[p] == run_id) & (value[c, p] != value[c])
    start = np.flatnonzero(split)
    length = np.diff(np.append(start, n))
    sub_offsets = np.zeros((len(start), n_col), np.int64)
    for c in range(n_col):  # the value of the first row of the sub-run that defines it, or 0
        nxt = np.minimum.accumulate(np.where(defined[c], rows, n)[::-1])[::-1]
        f = nxt[start]
        inside = f < start + length
        sub_offsets[:, c] = np.where(inside, value[c, np.minimum(f, n - 1)], 0)
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
    D = _zeros(size, np.float32)
    U = D[:mbase].reshape(slots, stride)
    U[0, 1:n + 1] = S[:, CENTER]
    U[1:_UPPER, 1:n + 1] = np.where(present[:, CENTER + 1:], S[:, CENTER + 1:], 0).T
    if far is not None:
        U[_UPPER:, 1:n + 1] = np.where(far[1][:, 1::2] >= 0, far[0][:, 1::2], 0).T
    D[mbase:mbase + n].view(np.uint32)[:] = bits
    D[rbase:].view(np.int32)[:] = table.reshape(-1)
    return dict(D=D, stride=int(stride), mbase=int(mbase), rbase=int(rbase),
                n_sub=table.shape[0], n_simd=k, scalar_rows=len(scalar_rows))


class CompactStencil:
    """Q in the compact layout, for fast single-vector products Q·x (float32 or float64).

    Built once from a checked band stencil ``(S, nbr, far)`` (module docstring) by
    vectorised numpy; :func:`pcg` / :func:`pcg_batched` build one per solve of a single
    right-hand side and reuse it every iteration. The layout stores 60 bytes per voxel
    (72 with ``far``) plus the sub-run table (~4 bytes per voxel in a 10-voxel-thick band)
    against the 216 bytes of (S, nbr):

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
        S, nbr = check_stencil(S, nbr) if check else _stencil_arrays(S, nbr)
        far = check_far(far, S) if check else _far_arrays(far, S.shape[0])
        layout = _compact_layout(S, nbr, far)
        self.n = S.shape[0]
        self.far = far is not None
        self._S, self._nbr, self._far_arrays = S, nbr, far  # the exact path (non-finite x)
        self._stride = layout["stride"]
        self._D = layout["D"]
        self._args = (layout["mbase"], layout["rbase"], layout["n_sub"], layout["n_simd"],
                      layout["stride"])
        self.n_subruns = layout["n_sub"]
        self.scalar_rows = layout["scalar_rows"]
        self._n_chunks = max(1, -(-layout["n_simd"] // _SUBRUNS_PER_CHUNK))
        self.nbytes = self._D.nbytes
        self.build_seconds = time.perf_counter() - t0

    def _apply_dot(self, P: np.ndarray, AP: np.ndarray) -> float:
        """AP = Q P for padded (N+1,) float32/float64 vectors (P[0] = 0, written AP[0] = 0);
        returns p·Ap (float64, deterministic). The solvers' product."""
        ker = _compact_kernels(P.dtype, self.far)
        part = np.empty((self._n_chunks, ker.lanes))
        ker.apply_dot(self._D, *self._args, P, AP, part)
        AP[0] = 0
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite P: the caller checks
            return float(part.sum())

    def apply(self, x, out=None, padded: bool = False) -> np.ndarray:
        """``out = Q x`` for one vector; the same arguments and result as :func:`apply_Q`
        (x (N,) or, with ``padded``, (N+1,) with x[0] = 0; float32 or float64; row sums in
        x's dtype). Deterministic. With non-finite values in x the product is recomputed by
        the 27-point gather (a masked-out lane may read a neighbour's inf as 0 * inf)."""
        x = _numpy(x, "x")
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
            xp = _zeros(self.n + 1, dtype)
            xp[1:] = x[1:] if padded else x
        yp = out if direct else _zeros(self.n + 1, dtype)
        if not np.isfinite(self._apply_dot(xp, yp)):
            apply_Q_batched(self._S, self._nbr, xp[:, None], yp[:, None], padded=True,
                            far=self._far_arrays)
        if yp is not out:
            out[:] = yp if padded else yp[1:]
        return out


# -- Q x -------------------------------------------------------------------------------------

def _padded(X: np.ndarray, dtype) -> np.ndarray:
    """(N+1, K) copy of X (N, K) with the zero pad row first."""
    out = _zeros((X.shape[0] + 1, X.shape[1]), dtype)
    out[1:] = X
    return out


def apply_Q(S, nbr, x, out=None, padded: bool = False, far=None) -> np.ndarray:
    """Matrix-free ``out = Q x``: ``out_i = sum_o S[i,o] x[nbr[i,o]]`` over ``nbr[i,o] >= 0``
    (plus ``sum_a S2[i,a] x[nbr2[i,a]]`` with ``far = (S2, nbr2)``).

    Args:
        S: (N, 27) float32 stencil of Q, finite; nbr: (N, 27) int32 neighbour table (module
            docstring). Only shapes and dtypes are checked here (this runs inside loops);
            see :func:`check_stencil` for the full validation.
        x: (N,) float32 or float64; with ``padded``, (N+1,) with x[0] = 0 and voxel i at
            x[i+1] (the solver's layout: no copies).
        out: optional array shaped like x, of x's dtype, written in place.
        far: optional (S2, nbr2) (N, 6), the entries at offsets +-2 (module docstring).
    Returns:
        ``out``, x's dtype; row sums accumulated in x's dtype. Deterministic (a gather).
    """
    x = _numpy(x, "x")
    if x.ndim != 1:
        raise ValueError(f"x must be one vector (1-D), got shape {x.shape}")
    if out is not None and out.shape != x.shape:
        raise ValueError(f"out must have shape {x.shape}, got {out.shape}")
    y = apply_Q_batched(S, nbr, x[:, None], None if out is None else out[:, None], padded, far)
    return y[:, 0] if out is None else out


def apply_Q_batched(S, nbr, X, out=None, padded: bool = False, far=None) -> np.ndarray:
    """``out = Q X`` for a block of K vectors stored side by side, X (N, K).

    The (N, K) layout keeps the K values of one voxel in one contiguous row, so each
    neighbour costs one SIMD load for all K vectors (a (K, N) layout measured ~4x slower per
    vector). K > :data:`MAX_LANES` runs as several blocks.

    Args:
        S, nbr, far: the stencil (see :func:`apply_Q`).
        X: (N, K) float32 or float64; with ``padded``, (N+1, K) with a zero first row and
            voxel i in row i+1 (the solver's layout; with K <= MAX_LANES, C-contiguous
            arrays and ``out`` given, nothing is copied).
        out: optional array shaped like X, of X's dtype, written in place.
    Returns:
        ``out`` (with ``padded``, its first row 0); row sums accumulated in X's dtype.
        Deterministic.
    """
    S, nbr = _stencil_arrays(S, nbr)
    far = _far_arrays(far, S.shape[0])
    op = _flat_op(S, nbr, far)
    X = _numpy(X, "X")
    n = S.shape[0]
    rows = n + 1 if padded else n
    if X.ndim != 2 or X.shape[0] != rows or X.shape[1] == 0:
        raise ValueError(f"X must have shape ({rows}, K) with K >= 1, got {X.shape}")
    if padded and X[0].any():
        raise ValueError("a padded X must have a zero first row")
    dtype = np.float32 if X.dtype == np.float32 else np.float64
    if out is None:
        out = np.empty(X.shape, dtype)
    elif out.shape != X.shape or out.dtype != dtype:
        raise ValueError(f"out must be a {X.shape} {np.dtype(dtype).name} array, got "
                         f"{out.shape} {out.dtype}")
    blocks = _column_blocks(X.shape[1])
    for a, b in blocks:
        if padded and len(blocks) == 1 and X.dtype == dtype and X.flags.c_contiguous \
                and out.flags.c_contiguous:
            Xb, Y = X, out  # the solver's layout already: no copies
        else:
            Xb = (np.ascontiguousarray(X[:, a:b], dtype) if padded
                  else _padded(X[:, a:b], dtype))
            Y = np.empty((n + 1, b - a), dtype)
        partials = np.empty((-(-n // CHUNK), b - a))  # p·Ap, not needed here
        _kernels(b - a, dtype, far is not None).apply_dot(*op, Xb, Y, partials)
        Y[0] = 0
        if Y is not out:
            out[:, a:b] = Y if padded else Y[1:]
    return out


# -- PCG -------------------------------------------------------------------------------------

def _pcg_block(ker: _Kernels, product, B, X, dinv, tol: float, maxiter: int) -> list:
    """Jacobi-PCG on the columns of B from the warm start X, in place; B and X are padded
    (N+1, L) blocks (voxel i in row i+1, row 0 zero); ``product(P, AP)`` writes AP = Q P and
    returns p·Ap per column (float64, deterministic); ``ker`` supplies the vector updates.

    Returns one dict per column: converged, iterations, relative_residual (the true
    ||b - Q x|| / ||b|| of the returned x), residual_history (the relative residual tested
    at each iteration, the last entry being relative_residual), restarts, reason.
    """
    n, lanes = B.shape[0] - 1, B.shape[1]
    n_chunks = -(-n // CHUNK)
    part_a = np.zeros((n_chunks, lanes))
    part_b = np.zeros((n_chunks, lanes))
    R, P, AP = (_zeros(B.shape, B.dtype) for _ in range(3))
    b_norm = np.sqrt(np.einsum("ij,ij->j", B, B, dtype=np.float64))
    zero_rhs = b_norm == 0
    X[:, zero_rhs] = 0  # b = 0: the solution is x = 0
    scale = np.where(zero_rhs, 1.0, b_norm)
    every = np.ones(lanes, np.int32)

    def residual(mask):
        """R = B - Q X in the ``mask`` lanes, chunk partials of r·r and r·M^-1 r (AP is
        scratch)."""
        product(X, AP)
        ker.subtract(B, AP, dinv, mask, R, part_a, part_b)

    # r = b - Q x0 ; relative residual ||r|| / ||b||
    residual(every)
    rr, rz = part_a.sum(axis=0), part_b.sum(axis=0)
    rel = np.sqrt(rr) / scale
    history = [[float(v)] for v in rel]
    status = np.where(rel <= tol, _CONVERGED, _RUNNING)
    iterations = np.zeros(lanes, np.int64)
    restarts = np.zeros(lanes, np.int64)
    stalls = np.zeros(lanes, np.int64)
    last_true = np.full(lanes, np.inf)
    reasons = ["zero right-hand side: x = 0" if z else "" for z in zero_rhs]
    # p = M^-1 r
    ker.update_p(np.zeros(lanes), every, R, dinv, P)
    it = 0
    while it < maxiter and (status == _RUNNING).any():
        it += 1
        active = status == _RUNNING
        # Ap = Q p ; pAp = p·Ap
        pap = product(P, AP)
        broken = active & ~(np.isfinite(pap) & (pap > 0))
        for k in np.flatnonzero(broken):
            reasons[k] = (f"breakdown at iteration {it}: p·Ap = {pap[k]:.3g} (Q is not "
                          f"positive definite, or values overflowed)")
        status[broken] = _BREAKDOWN
        active &= ~broken
        if not active.any():
            break
        # alpha = rz / pAp
        alpha = np.where(active, rz / np.where(active, pap, 1.0), 0.0)
        # x = x + alpha p ; r = r - alpha Ap ; rr = r·r ; rz_new = r·M^-1 r
        ker.update_xr(alpha, active.astype(np.int32), X, R, P, AP, dinv, part_a, part_b)
        rr, rz_new = part_a.sum(axis=0), part_b.sum(axis=0)
        iterations[active] += 1
        rel = np.sqrt(rr) / scale
        for k in np.flatnonzero(active):
            history[k].append(float(rel[k]))
        # converged? test the same norm on the true residual r = b - Q x
        candidates = active & (rel <= tol)
        restart = np.zeros(lanes, bool)
        if candidates.any():
            residual(candidates.astype(np.int32))
            true_rel = np.sqrt(part_a.sum(axis=0)) / scale
            rz_new = np.where(candidates, part_b.sum(axis=0), rz_new)
            for k in np.flatnonzero(candidates):
                history[k][-1] = float(true_rel[k])
            done = candidates & (true_rel <= tol)
            status[done] = _CONVERGED
            restart = candidates & ~done  # recursive residual drifted: restart from the true one
            restarts[restart] += 1
            stalls[restart] = np.where(true_rel >= 0.9 * last_true, stalls + 1, 0)[restart]
            last_true[restart] = true_rel[restart]
            stuck = restart & (stalls >= _STALLS)
            for k in np.flatnonzero(stuck):
                reasons[k] = (f"stagnated at relative residual {true_rel[k]:.3g} > tol = {tol:g}: "
                              f"the true residual stopped decreasing (tol below what the "
                              f"precision of Q and of the vectors resolves)")
            status[stuck] = _STAGNATED
            active &= ~(done | stuck)
        # beta = rz_new / rz (0 on a restart) ; p = M^-1 r + beta p
        beta = np.where(active & ~restart, rz_new / np.where(active, rz, 1.0), 0.0)
        ker.update_p(beta, active.astype(np.int32), R, dinv, P)
        rz = rz_new

    # Columns that stopped without converging: report the true residual of the returned x.
    unfinished = status != _CONVERGED
    if unfinished.any():
        residual(unfinished.astype(np.int32))
        true_rel = np.sqrt(part_a.sum(axis=0)) / scale
        for k in np.flatnonzero(unfinished):
            history[k][-1] = float(true_rel[k])
            if status[k] == _RUNNING:
                reasons[k] = f"not converged after maxiter = {maxiter} iterations"
    for k in np.flatnonzero(status == _CONVERGED):
        if not reasons[k]:
            reasons[k] = f"converged: relative residual <= tol = {tol:g}"
    return [dict(converged=bool(status[k] == _CONVERGED), iterations=int(iterations[k]),
                 relative_residual=history[k][-1], residual_history=history[k],
                 restarts=int(restarts[k]), reason=reasons[k]) for k in range(lanes)]


def _product(ker: _Kernels, op, compact, n: int, lanes: int):
    """``product(P, AP) -> p·Ap`` (lanes,) float64 for :func:`_pcg_block`: the compact
    layout for one column, else the 27-point gather of ``ker``."""
    if compact is not None:
        return lambda P, AP: np.array([compact._apply_dot(P.reshape(-1), AP.reshape(-1))])
    part = np.zeros((-(-n // CHUNK), lanes))

    def gather(P, AP):
        ker.apply_dot(*op, P, AP, part)
        return part.sum(axis=0)
    return gather


def pcg_batched(S, nbr, B, X0=None, tol: float = 1e-6, maxiter: int = 1000,
                dtype=np.float32, check: bool = True, far=None) -> tuple:
    """Solve ``Q X = B`` for K right-hand sides at once (Jacobi-preconditioned CG).

    Every column has its own alpha and beta; all columns advance in the same kernels each
    iteration (one stencil pass per iteration for the whole block), a converged column is
    frozen, and the loop stops when every column has converged, broken down, stagnated or
    reached ``maxiter``. Convergence: ``||b - Q x||_2 / ||b||_2 <= tol`` on the true residual
    (module docstring).

    Args:
        S, nbr: the stencil (module docstring), validated by :func:`check_stencil` unless
            ``check`` is False (the caller already did); far: its optional far part
            (S2, nbr2), validated by :func:`check_far`.
        B: (N, K) right-hand sides.
        X0: (N, K) warm start (default 0).
        tol: relative residual target.
        maxiter: iteration cap per column.
        dtype: vector storage, np.float32 (probes; half the memory traffic) or np.float64.
    Returns:
        ``(X, info)``: X (N, K) of ``dtype``; info = dict(converged: bool (all columns),
        iterations: list[int] per column, relative_residuals: list[float] per column,
        n_not_converged: int, columns: list of per-column dicts as in :func:`pcg`).
        Deterministic.
    """
    S, nbr = check_stencil(S, nbr) if check else _stencil_arrays(S, nbr)
    far = check_far(far, S) if check else _far_arrays(far, S.shape[0])
    op = _flat_op(S, nbr, far)
    n = S.shape[0]
    if np.dtype(dtype) not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if tol <= 0 or maxiter < 0:
        raise ValueError(f"need tol > 0 and maxiter >= 0, got tol={tol}, maxiter={maxiter}")
    B = _block(B, n, "B")
    if B.ndim != 2 or B.shape[1] == 0:
        raise ValueError(f"B must have shape ({n}, K) with K >= 1, got {B.shape}")
    X0 = None if X0 is None else _block(X0, n, "X0")
    if X0 is not None and X0.shape != B.shape:
        raise ValueError(f"X0 must have the shape of B {B.shape}, got {X0.shape}")
    dinv = 1.0 / S[:, CENTER].astype(np.float64)
    X = np.empty(B.shape, dtype)
    # one right-hand side: the compact layout, built once for all iterations
    compact = CompactStencil(S, nbr, far, check=False) if B.shape[1] == 1 else None
    columns = []
    for a, b in _column_blocks(B.shape[1]):
        ker = _kernels(b - a, dtype, far is not None)
        Xb = _zeros((n + 1, b - a), dtype) if X0 is None else _padded(X0[:, a:b], dtype)
        columns += _pcg_block(ker, _product(ker, op, compact, n, b - a),
                              _padded(B[:, a:b], dtype), Xb, dinv, tol, maxiter)
        X[:, a:b] = Xb[1:]
    n_bad = sum(not c["converged"] for c in columns)
    return X, dict(converged=n_bad == 0, iterations=[c["iterations"] for c in columns],
                   relative_residuals=[c["relative_residual"] for c in columns],
                   n_not_converged=n_bad, columns=columns)


def pcg(S, nbr, h, x0=None, tol: float = 1e-6, maxiter: int = 1000, far=None) -> tuple:
    """MAP solve ``Q mu = h`` by Jacobi-preconditioned CG (M = diag Q = S[:, 13]).

    Args:
        S: (N, 27) float32 stencil of the posterior precision; nbr: (N, 27) int32 (module
            docstring); validated by :func:`check_stencil`. far: optional (S2, nbr2) part
            at offsets +-2 (curvature prior), validated by :func:`check_far`.
        h: (N,) right-hand side A^T W y + b0 (float32 or float64).
        x0: (N,) warm start, e.g. the bootstrap TSDF in metres (default 0).
        tol: target of the relative residual ``||h - Q x||_2 / ||h||_2`` (the solution's
            relative error is at most cond(Q) * tol). The default 1e-6 is ~10x the float32
            rounding of the assembled S and h, so tighter targets refine nothing real.
        maxiter: iteration cap.
    Returns:
        ``(x, info)``: x (N,) float64 (the solver works in float64; casting to float32 for
        storage moves each value by at most half an ulp); info = dict(converged,
        iterations, relative_residual, residual_history, restarts, reason).
        ``relative_residual`` is ``||h - Q x|| / ||h||`` of the returned x, recomputed at
        the end; the loop stops on exactly this quantity. ``converged`` is False if maxiter
        was reached, CG broke down (p·Ap <= 0 or non-finite: Q not positive definite) or
        stagnated (restarts no longer reduce the true residual); ``reason`` says which.
        h = 0 returns x = 0 with relative_residual 0.
        Deterministic: the same inputs give bitwise identical x and info.
    """
    S, nbr = check_stencil(S, nbr)
    far = check_far(far, S)
    n = S.shape[0]
    h = _block(h, n, "h", np.float64)
    if h.ndim != 1:
        raise ValueError(f"h must have shape ({n},), got {h.shape}")
    x0 = None if x0 is None else _block(x0, n, "x0", np.float64)
    if x0 is not None and x0.ndim != 1:
        raise ValueError(f"x0 must have shape ({n},), got {x0.shape}")
    X, info = pcg_batched(S, nbr, h[:, None], None if x0 is None else x0[:, None], tol,
                          maxiter, np.float64, check=False, far=far)
    return X[:, 0], info["columns"][0]


# -- probe variance --------------------------------------------------------------------------

_LATTICES = {}


def coloring_lattice(n_colors: int) -> tuple:
    """The lattice colouring with K = ``n_colors`` colours used by the ``coloring`` probes.

    Voxel (i, j, k) gets colour ``(i + a j + b k) mod K``. The voxels of one colour form a
    sublattice of Z^3; (a, b) is chosen by exhaustive search over [0, K)^2 so that its
    shortest vector (the closest two voxels of one colour) is as long as possible, ties
    broken by fewest shortest vectors, then smallest (a, b). For K = 8, 16, 27, 32, 64 the
    closest same-colour voxels are 2.0, 2.45, 3.0, 3.32, 4.24 voxels apart (the cubic
    colouring (i mod p, j mod p, k mod p) reaches p = 2, 2, 3, 3, 4 with K >= p^3 probes).

    Returns ``(a, b, d2)``, d2 the squared length of the shortest same-colour offset.
    """
    k = int(n_colors)
    if k < 1:
        raise ValueError(f"need at least one colour, got {k}")
    if k not in _LATTICES:
        if k == 1:
            _LATTICES[k] = (0, 0, 1)
        else:
            # Minkowski: every index-K sublattice has a vector with |v|_inf <= K^(1/3), so
            # its shortest vector has |v|_2 <= sqrt(3) K^(1/3): the box holds it.
            r = int(np.ceil(np.sqrt(3.0) * k ** (1.0 / 3.0)))
            g = np.arange(-r, r + 1)
            v = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
            v = v[(v != 0).any(axis=1)]
            d2 = (v ** 2).sum(axis=1)
            b = np.arange(k)
            best = None
            for a in range(k):  # candidates (a, 0..K-1) at a time: memory ~ V * K
                same = (v[:, :1] + a * v[:, 1:2] + v[:, 2:] * b) % k == 0  # (V, K)
                shortest = np.where(same, d2[:, None], np.iinfo(np.int64).max).min(axis=0)
                count = (same & (d2[:, None] == shortest)).sum(axis=0)
                j = np.lexsort((b, count, -shortest))[0]
                key = (-int(shortest[j]), int(count[j]))
                if best is None or key < best[0]:
                    best = (key, (a, int(j), int(shortest[j])))
            _LATTICES[k] = best[1]
    return _LATTICES[k]


def probe_vectors(n: int, n_probes: int, seed: int = 0, method: str = "rademacher",
                  ijk=None) -> np.ndarray:
    """The K probe vectors Z (N, K) float32 of :func:`probe_variance`.

    ``rademacher``: independent random signs (+-1), the paper's estimator. The estimate of
    diag(Q^-1)_i then carries the error ``sum_{j != i} Q^-1_ij z_i z_j`` over every voxel j.
    ``coloring``: probe q is the indicator of colour q of :func:`coloring_lattice` (K)
    times random signs, so every voxel is in exactly one probe and the error only sums over
    the voxels of the same colour, all at least sqrt(d2) voxels away, where Q^-1_ij has
    decayed (posterior correlations of neighbouring voxels reach 0.3, two voxels apart 0.07,
    three 0.02 on a fused sphere). Needs ``ijk`` (N, 3).

    Signs come from ``numpy.random.default_rng(seed)``: the same seed gives the same Z.
    """
    if n_probes < 1:
        raise ValueError(f"n_probes must be >= 1, got {n_probes}")
    signs = np.random.default_rng(seed).integers(0, 2, size=(n, n_probes), dtype=np.int8)
    Z = (2 * signs - 1).astype(np.float32)
    if method == "rademacher":
        return Z
    if method != "coloring":
        raise ValueError(f"unknown probe method {method!r}; use 'rademacher' or 'coloring'")
    if ijk is None:
        raise ValueError("method='coloring' needs the band voxels ijk (N, 3)")
    ijk = np.asarray(_numpy(ijk, "ijk"))
    if ijk.shape != (n, 3) or not np.issubdtype(ijk.dtype, np.integer):
        raise ValueError(f"ijk must be an integer array of shape ({n}, 3), got {ijk.shape} "
                         f"{ijk.dtype}")
    a, b, _ = coloring_lattice(n_probes)
    ijk = ijk.astype(np.int64)
    color = (ijk[:, 0] + a * ijk[:, 1] + b * ijk[:, 2]) % n_probes
    Z *= color[:, None] == np.arange(n_probes)[None, :]
    return Z


def probe_variance(S, nbr, n_probes: int = 16, seed: int = 0, method: str = "rademacher",
                   tol: float = 1e-4, maxiter: int = 1000, ijk=None, far=None) -> tuple:
    """Stochastic estimate of the posterior variance ``s ~= diag(Q^-1)`` (DESIGN.md 3.6).

    ``s = sum_k z_k * u_k / sum_k z_k * z_k`` (elementwise) with ``Q u_k = z_k``, the K
    probes z_k from :func:`probe_vectors` (``method`` = ``rademacher`` | ``coloring``; the
    colouring needs ``ijk``), solved as one batched multi-RHS PCG (:func:`pcg_batched`,
    float32 vectors, blocks of up to :data:`MAX_LANES` probes).

    Args:
        S, nbr: the stencil (module docstring), validated by :func:`check_stencil`.
        n_probes: K.
        seed: seed of the probe signs.
        tol: relative residual per probe. 1e-4 keeps the solver's share of the error in s
            near 1e-5 (median), far below the sampling error even at K = 64 (measured on
            tools/bench_core.py's problems: tol 1e-3 / 1e-4 / 1e-6 change s by 1e-4 / 1e-5 /
            1e-7 at 25 % / 35 % more iterations per step).
        maxiter: iteration cap per probe.
        ijk: (N, 3) band voxels (``coloring`` only).
        far: optional (S2, nbr2) part of Q at offsets +-2 (:func:`check_far`).
    Returns:
        ``(s, info)``: s (N,) float32 (m^2 when Q is in 1/m^2); info = dict(method,
        n_probes, lattice ((1, a, b) of the colouring, else None), converged (all probes),
        n_not_converged, iterations (per probe), relative_residuals (per probe),
        n_nonpositive (voxels with s <= 0, possible with few Rademacher probes)).
        Deterministic: the same seed gives bitwise identical s.
    """
    S, nbr = check_stencil(S, nbr)
    far = check_far(far, S)
    n = S.shape[0]
    Z = probe_vectors(n, n_probes, seed, method, ijk)
    U, solve = pcg_batched(S, nbr, Z, None, tol, maxiter, np.float32, check=False, far=far)
    num = np.einsum("ij,ij->i", Z, U, dtype=np.float64)
    den = np.einsum("ij,ij->i", Z, Z, dtype=np.float64)
    s = (num / den).astype(np.float32)
    lattice = None
    if method == "coloring":
        lattice = [1, *coloring_lattice(n_probes)[:2]]
    info = dict(method=method, n_probes=int(n_probes), lattice=lattice,
                converged=solve["converged"], n_not_converged=solve["n_not_converged"],
                iterations=solve["iterations"], relative_residuals=solve["relative_residuals"],
                n_nonpositive=int(np.count_nonzero(~(s > 0))))
    return s, info
