"""The band's stencil form of the posterior precision Q and the matrix-free products Q·x
(DESIGN.md 3, step 4): the contract every producer and solver shares, its checks
(:func:`check_stencil`, :func:`check_far`) and the 27-point gather (:func:`apply_Q`,
:func:`apply_Q_batched`, :class:`GatherKernels`).

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

* The stencil kernel (:meth:`GatherKernels.apply_dot`) is a gather, one thread per chunk of rows,
  the 27 offsets unrolled (``ti.static``), S and nbr read flat (row i at i*27). It sees a
  block as N+1 vectors of K lanes (``ti.types.vector(K)``), and LLVM turns each neighbour's K
  lanes into SIMD loads and multiply-adds, so a block of K vectors costs little more than
  one vector: S and nbr (216 bytes per voxel, the dominant memory traffic) are read once for
  all K. Blocks wider than :data:`MAX_LANES` run as several blocks, one after the other (K =
  64 compiles in ~10 s and runs slower per vector than 16).
* Row sums accumulate in the vectors' dtype: float64 for the MAP solve; float32 for the
  probes (27 terms round to ~1e-6 relative, far below the probe tolerance; a float64
  accumulator halves the SIMD width and ran 2-2.5x slower at K = 16).
* Reductions (dot products, norms) accumulate in float64 over fixed chunks of
  :data:`CHUNK` rows, one thread per chunk summing its rows in order, fused into the kernel
  that produces the vector; the per-chunk partial sums are then added on the host in a fixed
  order (numpy, axis 0). No float atomics anywhere: every result is bitwise reproducible for
  the same inputs, independent of the thread count.
"""

import gc
import mmap

import numpy as np
import taichi as ti

from .layout import CENTRE, FAR, STENCIL

CHUNK = 1024  # rows per reduction chunk (fixed: results do not depend on the thread count)
#: Widest compiled vector block: K = 16 probes are two blocks of 8, solved one after the
#: other. A solve holds five padded (N+1, K) blocks (B, X, R, P, AP), which were the peak
#: memory of a whole run; two blocks of 8 halve that (70 MB less at 2 cm on 500 redkitchen
#: frames, 280 MB at 1 cm) for ~5 % more probe time, and give the same bits: every column
#: has its own CG, and a lane's sums do not depend on the block width.
MAX_LANES = 8
#: Taichi's CPU backend gives each thread one contiguous share of at least this many
#: iterations of a kernel's outer loop (its MakeCPUMultithreadedRangeFor pass), so a loop
#: over the ~500 chunks of a 500k-voxel band ran on one thread. Every parallel loop here
#: runs over max(n_chunks, TASK_MIN * threads) virtual iterations instead (:func:`first_chunk`).
TASK_MIN = 512


# -- kernels ---------------------------------------------------------------------------------

_KERNELS = {}


def virtual_iterations() -> int:
    """Enough outer-loop iterations for every CPU thread to get a share (:data:`TASK_MIN`);
    read when a kernel is compiled."""
    return TASK_MIN * max(1, int(ti.lang.impl.current_cfg().cpu_max_num_threads))


@ti.func
def first_chunk(t, n_chunks, n_virtual):
    """First chunk of virtual iteration ``t`` when ``n_chunks`` chunks are dealt out evenly
    over ``n_virtual = max(n_chunks, virtual_iterations())`` iterations; chunk t itself
    when there are enough chunks (no division)."""
    first = t
    if n_chunks < n_virtual:
        first = t * n_chunks // n_virtual  # < TASK_MIN * threads * n_chunks: no overflow
    return first


class GatherKernels:
    """The 27-point gather kernels for blocks of ``lanes`` vectors of ``dtype`` (compiled on
    first use; Taichi's offline cache keeps them across runs), and the PCG vector updates.

    Arguments: ``S`` and ``nbr`` flattened to (N*27,) (row i at i*27); vectors (N+1, lanes)
    numpy arrays seen as N+1 vectors of ``lanes`` elements, voxel i in row i+1 and row 0
    zero (the pad row: see the module docstring); chunk partial sums (n_chunks, lanes)
    float64; ``dinv`` = 1 / Q_ii (N,) float64. Every loop runs over fixed chunks of
    :data:`CHUNK` rows, one thread per chunk, the chunks dealt out to the threads by
    :func:`first_chunk`. All kernels are deterministic: every output element is written by one
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
        spread = virtual_iterations()
        V = ti.types.vector(lanes, dtype)
        VD = ti.types.vector(lanes, ti.f64)
        flat_s = ti.types.ndarray(dtype=ti.f32, ndim=1)
        flat_n = ti.types.ndarray(dtype=ti.i32, ndim=1)
        vec = ti.types.ndarray(dtype=V, ndim=1)
        part = ti.types.ndarray(dtype=VD, ndim=1)
        diag = ti.types.ndarray(dtype=ti.f64, ndim=1)
        # per-lane scalars (alpha, beta, the lane masks) as (lanes,) arrays: a vector argument
        # costs Taichi ~60 us of Python a launch, an array ~10 us (kernel launches dominate
        # the solves of small bands)
        coef = ti.types.ndarray(dtype=ti.f64, ndim=1)
        lane_mask = ti.types.ndarray(dtype=ti.i32, ndim=1)

        @ti.func
        def lanes_of(A: ti.template(), T: ti.template()):
            """The (lanes,) array ``A`` as a vector of ``T``."""
            return ti.Vector([ti.cast(A[k], T) for k in ti.static(range(lanes))])

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
                for c in range(first_chunk(t, n_chunks, n_virtual),
                               first_chunk(t + 1, n_chunks, n_virtual)):
                    s = VD(0.0)
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        ap = q_row(S, nbr, S2, nbr2, P, i)
                        AP[i + 1] = ap
                        s += ti.cast(P[i + 1], ti.f64) * ti.cast(ap, ti.f64)
                    pap[c] = s

        @ti.kernel
        def subtract(B: vec, AX: vec, dinv: diag, mask: lane_mask, R: vec, rr: part, rz: part):
            """r = b - Ax in the lanes where ``mask`` is set (other lanes keep R), and the
            chunk partials of r·r and r·M^-1 r = sum r_i^2 / Q_ii (float64; deterministic)."""
            n = R.shape[0] - 1
            on = lanes_of(mask, ti.i32) != 0
            n_chunks = rr.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(first_chunk(t, n_chunks, n_virtual),
                               first_chunk(t + 1, n_chunks, n_virtual)):
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
        def update_xr(alpha: coef, active: lane_mask, X: vec, R: vec, P: vec, AP: vec,
                      dinv: diag, rr: part, rz: part):
            """x = x + alpha p, r = r - alpha Ap in the active lanes, and the chunk partials
            of r·r and r·M^-1 r (float64; deterministic)."""
            n = X.shape[0] - 1
            a = lanes_of(alpha, dtype)
            on = lanes_of(active, ti.i32) != 0
            n_chunks = rr.shape[0]
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(first_chunk(t, n_chunks, n_virtual),
                               first_chunk(t + 1, n_chunks, n_virtual)):
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
        def update_p(beta: coef, active: lane_mask, R: vec, dinv: diag, P: vec):
            """p = M^-1 r + beta p in the active lanes (deterministic)."""
            b = lanes_of(beta, dtype)
            on = lanes_of(active, ti.i32) != 0
            n = P.shape[0] - 1
            n_chunks = (n + CHUNK - 1) // CHUNK
            n_virtual = ti.max(n_chunks, spread)
            for t in range(n_virtual):
                for c in range(first_chunk(t, n_chunks, n_virtual),
                               first_chunk(t + 1, n_chunks, n_virtual)):
                    for i in range(c * CHUNK, ti.min(n, c * CHUNK + CHUNK)):
                        r, p = R[i + 1], P[i + 1]  # loads first
                        P[i + 1] = ti.select(on, ti.cast(dinv[i], dtype) * r + b * p, p)

        self.apply_dot, self.subtract = apply_dot, subtract
        self.update_xr, self.update_p = update_xr, update_p


def gather_kernels(lanes: int, dtype, far: bool = False) -> GatherKernels:
    key = (lanes, np.dtype(dtype).name, bool(far))
    if key not in _KERNELS:
        _KERNELS[key] = GatherKernels(lanes, ti.f64 if np.dtype(dtype) == np.float64 else ti.f32,
                                 bool(far))
    return _KERNELS[key]


_NO_FAR = (np.zeros(1, np.float32), np.full(1, -1, np.int32))  # never read (far=False kernels)


def far_arrays(far, n: int) -> tuple | None:
    """(S2 float32, nbr2 int32) (N, 6), C-contiguous, shapes and dtypes checked; None for
    ``far=None``."""
    if far is None:
        return None
    try:
        S2, nbr2 = far
    except (TypeError, ValueError):
        raise TypeError("far must be None or a pair (S2, nbr2) of (N, 6) arrays") from None
    S2, nbr2 = as_numpy(S2, "S2"), as_numpy(nbr2, "nbr2")
    if S2.shape != (n, FAR) or nbr2.shape != (n, FAR):
        raise ValueError(f"far (S2, nbr2) must both have shape ({n}, {FAR}), got {S2.shape} "
                         f"and {nbr2.shape}")
    if not np.issubdtype(S2.dtype, np.floating) or not np.issubdtype(nbr2.dtype, np.integer):
        raise TypeError(f"far: S2 must be float and nbr2 integer, got {S2.dtype}, {nbr2.dtype}")
    if nbr2.dtype != np.int32 and nbr2.size and (nbr2.min() < -1 or nbr2.max() >= n):
        raise ValueError(f"nbr2 holds indices outside [-1, {n})")
    return (np.ascontiguousarray(S2, dtype=np.float32),
            np.ascontiguousarray(nbr2, dtype=np.int32))


def flat_op(S, nbr, far) -> tuple:
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
                    ti.cast(S[i * STENCIL + CENTRE], ti.f64),
                    ti.cast(S[j * STENCIL + CENTRE], ti.f64)):
                ti.atomic_min(found[1], ti.cast(f, ti.i64))


# -- input checks ----------------------------------------------------------------------------

def as_numpy(a, name: str) -> np.ndarray:
    """numpy view of a numpy array or a Taichi ndarray (copied)."""
    if isinstance(a, ti.Ndarray):
        return a.to_numpy()
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy array or a Taichi ndarray, got {type(a).__name__}")
    return a


def stencil_arrays(S, nbr) -> tuple:
    """(S float32, nbr int32), C-contiguous, with shape and dtype checked (cheap checks only)."""
    S, nbr = as_numpy(S, "S"), as_numpy(nbr, "nbr")
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
    far = far_arrays(far, n)
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
    diag = S[:, CENTRE].astype(np.float64)
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
    S, nbr = stencil_arrays(S, nbr)
    n = S.shape[0]
    finite = np.isfinite(S).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"S has non-finite values (first at band index {i})")
    low, high = int(nbr.min()), int(nbr.max())
    if low < -1 or high >= n:
        raise ValueError(f"nbr holds indices outside [-1, {n}): min {low}, max {high}")
    self_bad = nbr[:, CENTRE] != np.arange(n, dtype=np.int32)
    if self_bad.any():
        i = int(np.flatnonzero(self_bad)[0])
        raise ValueError(f"nbr[{i}, 13] = {nbr[i, CENTRE]} must be the voxel itself ({i})")
    diag = S[:, CENTRE]
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


def as_block(a, n: int, name: str, dtype=None) -> np.ndarray:
    """A (n,) or (n, K) float array, C-contiguous, of ``dtype`` (default: float32 stays
    float32, anything else becomes float64); non-finite values rejected."""
    a = as_numpy(a, name)
    if a.ndim not in (1, 2) or a.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) or ({n}, K), got {a.shape}")
    if dtype is None:
        dtype = np.float32 if a.dtype == np.float32 else np.float64
    a = np.ascontiguousarray(a, dtype=dtype)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has non-finite values")
    return a


def column_blocks(k: int) -> list:
    """Split K columns into ceil(K / MAX_LANES) blocks of near-equal width."""
    n_blocks = -(-k // MAX_LANES)
    width = -(-k // n_blocks)
    return [(a, min(a + width, k)) for a in range(0, k, width)]


_HUGE = 2 << 20  # bytes of a transparent huge page (x86-64)


def free_compile_arguments() -> None:
    """Free the arrays Taichi still holds from kernels' compiling calls.

    Taichi 1.7 keeps the arguments of a kernel's first (compiling) call in a reference cycle
    (an ``ASTTransformerContext`` and the closures of its AST generator), so large arrays
    passed there stay resident until the next garbage collection, which numeric code rarely
    triggers. Measured on redkitchen at 2 cm: the Observer's accumulators were still resident
    at the probe stage, and the probe blocks into the next stage. Costs one ``gc.collect()``
    (0.05-0.06 s, more in a process holding many Python objects); call it where a stage that
    compiled kernels on large arrays ends. It collects only when a kernel was compiled since
    the last collection (:func:`_count_compilations`): a process's later solves compile
    nothing, so nothing of that kind is left to free (a scan step on the cluttered table made
    nine collections, 0.43 s of its 3.4 s solve)."""
    global _collected_at
    if _COMPILATIONS[0] >= 0 and _COMPILATIONS[0] == _collected_at:
        return
    gc.collect()
    _collected_at = _COMPILATIONS[0]


#: Kernel compilations (Taichi front-end materialisations) seen; -1: not counted (another
#: Taichi than 1.7's ``Kernel.materialize``), then every call collects.
_COMPILATIONS = [-1]
_collected_at = None


def _count_compilations() -> None:
    """Count Taichi's kernel compilations, where the reference cycles that
    :func:`free_compile_arguments` frees are made: ``Kernel.materialize`` builds the kernel's
    front end, holding the call's arguments, for a specialisation not compiled yet. Wrapped
    once per process, at import, before any kernel is compiled; left alone where Taichi's
    ``Kernel`` has no ``materialize``/``compiled_kernels`` as in 1.7."""
    from taichi.lang import kernel_impl

    kernel = getattr(kernel_impl, "Kernel", None)
    original = getattr(kernel, "materialize", None)
    if not callable(original) or getattr(original, "_bftaichi_counted", False):
        return

    def materialize(self, key=None, args=None, arg_features=None):
        if key is None or key not in getattr(self, "compiled_kernels", ()):
            _COMPILATIONS[0] += 1
        return original(self, key=key, args=args, arg_features=arg_features)

    materialize._bftaichi_counted = True
    kernel.materialize = materialize
    _COMPILATIONS[0] = 0


_count_compilations()


def zeros_aligned(shape, dtype) -> np.ndarray:
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


# -- Q x -------------------------------------------------------------------------------------

def padded_block(X: np.ndarray, dtype) -> np.ndarray:
    """(N+1, K) copy of X (N, K) with the zero pad row first."""
    out = zeros_aligned((X.shape[0] + 1, X.shape[1]), dtype)
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
    x = as_numpy(x, "x")
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
    S, nbr = stencil_arrays(S, nbr)
    far = far_arrays(far, S.shape[0])
    op = flat_op(S, nbr, far)
    X = as_numpy(X, "X")
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
    blocks = column_blocks(X.shape[1])
    for a, b in blocks:
        if padded and len(blocks) == 1 and X.dtype == dtype and X.flags.c_contiguous \
                and out.flags.c_contiguous:
            Xb, Y = X, out  # the solver's layout already: no copies
        else:
            Xb = (np.ascontiguousarray(X[:, a:b], dtype) if padded
                  else padded_block(X[:, a:b], dtype))
            Y = np.empty((n + 1, b - a), dtype)
        partials = np.empty((-(-n // CHUNK), b - a))  # p·Ap, not needed here
        gather_kernels(b - a, dtype, far is not None).apply_dot(*op, Xb, Y, partials)
        Y[0] = 0
        if Y is not out:
            out[:, a:b] = Y if padded else Y[1:]
    return out
