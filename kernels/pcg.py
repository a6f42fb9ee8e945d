"""Jacobi-preconditioned conjugate gradients on the band's stencil (DESIGN.md 3, step 5): the
MAP solve :func:`pcg` and the batched multi-right-hand-side solver :func:`pcg_batched` that the
probe variance (:mod:`kernels.probes`) runs. The stencil contract and the products Q·x are in
:mod:`kernels.stencil` and :mod:`kernels.compact`.

:func:`pcg_batched` is Jacobi-preconditioned conjugate gradients on a block of right-hand
sides, each column with its own alpha and beta, all advanced by the same kernels per
iteration (:class:`kernels.stencil.GatherKernels`). :func:`pcg` (the MAP solve: one float64
column) and :func:`kernels.probes.probe_variance` (K probes: float32 columns) are its two uses.
Reductions are the fixed-chunk float64 sums of :mod:`kernels.stencil`: no float atomics,
every result bitwise reproducible for the same inputs, independent of the thread count.

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

import numpy as np

from .compact import CompactStencil
from .layout import CENTRE
from .stencil import (CHUNK, GatherKernels, as_block, check_far, check_stencil, column_blocks,
                      far_arrays, flat_op, free_compile_arguments, gather_kernels,
                      padded_block, stencil_arrays, zeros_aligned)

_RUNNING, _CONVERGED, _BREAKDOWN, _STAGNATED = 0, 1, 2, 3
_STALLS = 2  # restarts in a row without a 10 % smaller true residual: stagnated
_COMPILED = set()  # kernel sets (id) whose compiling block has run


def _pcg_block(ker: GatherKernels, product, B, X, dinv, tol: float, maxiter: int) -> list:
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
    R, P, AP = (zeros_aligned(B.shape, B.dtype) for _ in range(3))
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


def _product(ker: GatherKernels, op, compact, n: int, lanes: int):
    """``product(P, AP) -> p·Ap`` (lanes,) float64 for :func:`_pcg_block`: the compact
    layout for one column, else the 27-point gather of ``ker``."""
    if compact is not None:
        return lambda P, AP: np.array([compact.apply_dot(P.reshape(-1), AP.reshape(-1))])
    part = np.zeros((-(-n // CHUNK), lanes))

    def gather(P, AP):
        ker.apply_dot(*op, P, AP, part)
        return part.sum(axis=0)
    return gather


def pcg_batched(S, nbr, B, X0=None, tol: float = 1e-6, maxiter: int = 1000,
                dtype=np.float32, check: bool = True, far=None,
                compact: CompactStencil | None = None) -> tuple:
    """Solve ``Q X = B`` for K right-hand sides at once (Jacobi-preconditioned CG).

    Every column has its own alpha and beta; all columns advance in the same kernels each
    iteration (one stencil pass per iteration for the whole block), a converged column is
    frozen, and the loop stops when every column has converged, broken down, stagnated or
    reached ``maxiter``. Convergence: ``||b - Q x||_2 / ||b||_2 <= tol`` on the true residual
    (module docstring).

    Args:
        S, nbr: the stencil (:mod:`kernels.stencil`), validated by :func:`check_stencil` unless
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
    S, nbr = check_stencil(S, nbr) if check else stencil_arrays(S, nbr)
    far = check_far(far, S) if check else far_arrays(far, S.shape[0])
    op = flat_op(S, nbr, far)
    n = S.shape[0]
    if np.dtype(dtype) not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if tol <= 0 or maxiter < 0:
        raise ValueError(f"need tol > 0 and maxiter >= 0, got tol={tol}, maxiter={maxiter}")
    B = as_block(B, n, "B")
    if B.ndim != 2 or B.shape[1] == 0:
        raise ValueError(f"B must have shape ({n}, K) with K >= 1, got {B.shape}")
    X0 = None if X0 is None else as_block(X0, n, "X0")
    if X0 is not None and X0.shape != B.shape:
        raise ValueError(f"X0 must have the shape of B {B.shape}, got {X0.shape}")
    dinv = 1.0 / S[:, CENTRE].astype(np.float64)
    X = np.empty(B.shape, dtype)
    # one right-hand side: the compact layout, built once for all iterations
    if B.shape[1] != 1:
        compact = None
    elif compact is None:
        compact = CompactStencil(S, nbr, far, check=False)
    columns = []
    for a, b in column_blocks(B.shape[1]):
        ker = gather_kernels(b - a, dtype, far is not None)
        Xb = zeros_aligned((n + 1, b - a), dtype) if X0 is None else padded_block(X0[:, a:b], dtype)
        columns += _pcg_block(ker, _product(ker, op, compact, n, b - a),
                              padded_block(B[:, a:b], dtype), Xb, dinv, tol, maxiter)
        X[:, a:b] = Xb[1:]
        if id(ker) not in _COMPILED:  # this block compiled them: free its five vector blocks
            _COMPILED.add(id(ker))
            free_compile_arguments()
    n_bad = sum(not c["converged"] for c in columns)
    return X, dict(converged=n_bad == 0, iterations=[c["iterations"] for c in columns],
                   relative_residuals=[c["relative_residual"] for c in columns],
                   n_not_converged=n_bad, columns=columns)


def pcg(S, nbr, h, x0=None, tol: float = 1e-6, maxiter: int = 1000, far=None,
        compact: CompactStencil | None = None) -> tuple:
    """MAP solve ``Q mu = h`` by Jacobi-preconditioned CG (M = diag Q = S[:, 13]).

    Args:
        S: (N, 27) float32 stencil of the posterior precision; nbr: (N, 27) int32
            (:mod:`kernels.stencil`); validated by :func:`check_stencil`. far: optional
            (S2, nbr2) part at offsets +-2 (curvature prior), validated by :func:`check_far`.
        h: (N,) right-hand side A^T W y + b0 (float32 or float64).
        x0: (N,) warm start, e.g. the bootstrap TSDF in metres (default 0).
        tol: target of the relative residual ``||h - Q x||_2 / ||h||_2`` (the solution's
            relative error is at most cond(Q) * tol). The default 1e-6 is ~10x the float32
            rounding of the assembled S and h, so tighter targets refine nothing real.
        maxiter: iteration cap.
        compact: the :class:`~kernels.compact.CompactStencil` of exactly this (S, nbr, far),
            built (and checked) by the caller, e.g. once for several solves that change only
            the diagonal (:meth:`~kernels.compact.CompactStencil.set_diagonal`); S and nbr are
            then not checked again. Default: built here.
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
    if compact is None:
        S, nbr = check_stencil(S, nbr)
        far = check_far(far, S)
    else:
        S, nbr = stencil_arrays(S, nbr)
        far = far_arrays(far, S.shape[0])
        if compact.n != S.shape[0]:
            raise ValueError(f"compact has {compact.n} rows, S {S.shape[0]}")
    n = S.shape[0]
    h = as_block(h, n, "h", np.float64)
    if h.ndim != 1:
        raise ValueError(f"h must have shape ({n},), got {h.shape}")
    x0 = None if x0 is None else as_block(x0, n, "x0", np.float64)
    if x0 is not None and x0.ndim != 1:
        raise ValueError(f"x0 must have shape ({n},), got {x0.shape}")
    X, info = pcg_batched(S, nbr, h[:, None], None if x0 is None else x0[:, None], tol,
                          maxiter, np.float64, check=False, far=far, compact=compact)
    return X[:, 0], info["columns"][0]
