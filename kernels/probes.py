"""Probe estimate of the posterior variance ``s ~= diag(Q^-1)`` (DESIGN.md 3, step 6) and of the
covariances of face neighbours (step 7's vertex sigma): probe
vectors (Rademacher or lattice colouring) solved as one batched PCG
(:func:`kernels.pcg.pcg_batched`).

Deterministic: the same seed gives bitwise identical results.
"""

import numpy as np
import taichi as ti

from .funcs import corner
from .layout import stencil_offset
from .pcg import pcg_batched
from .stencil import as_numpy, check_far, check_stencil, far_arrays, stencil_arrays

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


def probe_vectors(n: int, n_probes: int, seed: int = 0, *, method: str,
                  ijk=None) -> np.ndarray:
    """The K probe vectors Z (N, K) float32 of :func:`probe_variance`.

    ``method`` (keyword, no default: the caller chooses) is one of:
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
    ijk = np.asarray(as_numpy(ijk, "ijk"))
    if ijk.shape != (n, 3) or not np.issubdtype(ijk.dtype, np.integer):
        raise ValueError(f"ijk must be an integer array of shape ({n}, 3), got {ijk.shape} "
                         f"{ijk.dtype}")
    a, b, _ = coloring_lattice(n_probes)
    ijk = ijk.astype(np.int64)
    color = (ijk[:, 0] + a * ijk[:, 1] + b * ijk[:, 2]) % n_probes
    Z *= color[:, None] == np.arange(n_probes)[None, :]
    return Z


#: Stencil offsets of the face neighbours +x, +y, +z (:data:`kernels.layout.OFFSETS`), the
#: columns of the neighbour covariance :func:`probe_variance` returns.
FACE_PLUS = (22, 16, 14)

#: Default relative residual of the probe solves (``solver.probe_tol``; docs/measurements.md).
PROBE_TOL = 1e-2


def probe_variance(S, nbr, n_probes: int = 16, seed: int = 0, *, method: str,
                   tol: float = PROBE_TOL, maxiter: int = 1000, ijk=None, far=None) -> tuple:
    """``(s, info)`` of :func:`probe_moments` (the same arguments), without the covariances."""
    s, _, info = probe_moments(S, nbr, n_probes, seed, method=method, tol=tol, maxiter=maxiter,
                               ijk=ijk, far=far)
    return s, info


def probe_moments(S, nbr, n_probes: int = 16, seed: int = 0, *, method: str,
                  tol: float = PROBE_TOL, maxiter: int = 1000, ijk=None, far=None,
                  check: bool = True) -> tuple:
    """Stochastic estimate of the posterior variance ``s ~= diag(Q^-1)`` (DESIGN.md 3.6) and
    of each voxel's covariance with its +x, +y, +z neighbours (DESIGN.md 3.7: the variance
    of the SDF interpolated on a grid edge needs them).

    ``s = sum_k z_k * u_k / sum_k z_k * z_k`` (elementwise) with ``Q u_k = z_k``, the K
    probes z_k from :func:`probe_vectors` (``method`` = ``rademacher`` | ``coloring``, no
    default: the caller chooses; the colouring needs ``ijk``), solved as one batched multi-RHS
    PCG (:func:`pcg_batched`, float32 vectors, blocks of up to
    :data:`kernels.stencil.MAX_LANES` probes). The same solutions give the covariances
    (:func:`probe_covariance`).

    Args:
        S, nbr: the stencil (:mod:`kernels.stencil`), validated by :func:`check_stencil`.
        n_probes: K.
        seed: seed of the probe signs.
        tol: relative residual per probe (default :data:`PROBE_TOL`, 1e-2). The solver's
            share of the error in s stays far below the sampling error (~6 % per voxel at
            K = 16): on 500 real frames at 2 cm sigma moves by 2.7e-4 of itself (median),
            3.9e-3 at the 99th percentile, between 1e-3 and 1e-2, for 523 -> 324 iterations
            (tools/bench_core.py's problems: tol 1e-3 / 1e-4 / 1e-6 change s by 1e-4 / 1e-5 /
            1e-7; docs/measurements.md, "The probes' tolerance, again").
        maxiter: iteration cap per probe.
        ijk: (N, 3) band voxels (``coloring`` only).
        far: optional (S2, nbr2) part of Q at offsets +-2 (:func:`check_far`).
        check: validate S, nbr and far (:func:`check_stencil`, :func:`check_far`); False for
            a stencil its producer guarantees (the pipeline's, from
            :func:`bftaichi.stages.prior.add_prior`), which saves about three stencil
            products and ~240 bytes per voxel of temporaries.
    Returns:
        ``(s, cov, info)``: s (N,) float32 (m^2 when Q is in 1/m^2); cov (N, 3) float32, the
        covariance of voxel i with its neighbour at +x, +y, +z (:data:`FACE_PLUS`), 0 where
        that neighbour is not in the band; info = dict(method, n_probes, lattice ((1, a, b)
        of the colouring, else None), converged (all probes), n_not_converged, iterations
        (per probe), relative_residuals (per probe), n_nonpositive (voxels with s <= 0,
        possible with few Rademacher probes)).
        Deterministic: the same seed gives bitwise identical s and cov.
    """
    S, nbr = check_stencil(S, nbr) if check else stencil_arrays(S, nbr)
    far = check_far(far, S) if check else far_arrays(far, S.shape[0])
    n = S.shape[0]
    Z = probe_vectors(n, n_probes, seed, method=method, ijk=ijk)
    U, solve = pcg_batched(S, nbr, Z, None, tol, maxiter, np.float32, check=False, far=far)
    num = np.einsum("ij,ij->i", Z, U, dtype=np.float64)
    den = np.einsum("ij,ij->i", Z, Z, dtype=np.float64)
    s = (num / den).astype(np.float32)
    cov = probe_covariance(Z, U, nbr, den)
    lattice = None
    if method == "coloring":
        lattice = [1, *coloring_lattice(n_probes)[:2]]
    info = dict(method=method, n_probes=int(n_probes), lattice=lattice,
                converged=solve["converged"], n_not_converged=solve["n_not_converged"],
                iterations=solve["iterations"], relative_residuals=solve["relative_residuals"],
                n_nonpositive=int(np.count_nonzero(~(s > 0))))
    return s, cov, info


def probe_covariance(Z: np.ndarray, U: np.ndarray, nbr: np.ndarray, den: np.ndarray
                     ) -> np.ndarray:
    """(N, 3) float32 ``Cov(i, j) ~= (Q^-1)_ij`` for j the +x, +y, +z neighbour of i, from the
    probes Z (N, K) and their solutions ``U = Q^-1 Z``; ``den`` (N,) = ``sum_k Z_ik^2``.

    ``sum_k Z_ik U_jk = (Q^-1)_ji sum_k Z_ik^2 + sum_k sum_{l != i} (Q^-1)_jl Z_ik Z_lk``:
    the estimate from i's probes, ``sum_k Z_ik U_jk / sum_k Z_ik^2``, errs by the covariances
    of j with the voxels that share i's probes (with colouring: i's colour, the nearest of them
    ``sqrt(d2) - 1`` voxels from j, so closer than they are to i for the diagonal). The
    estimate from j's probes errs over j's colour instead; the two errors are independent
    (different signs), so their mean halves the error variance. 0 where j is not in the band.
    """
    cov = np.zeros((len(Z), 3), np.float32)
    if len(Z):
        _covariance(np.ascontiguousarray(Z, np.float32), np.ascontiguousarray(U, np.float32),
                    np.ascontiguousarray(nbr, np.int32), np.ascontiguousarray(den, np.float64),
                    cov)
    return cov


@ti.kernel
def _covariance(Z: ti.types.ndarray(dtype=ti.f32, ndim=2),
                U: ti.types.ndarray(dtype=ti.f32, ndim=2),
                nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                den: ti.types.ndarray(dtype=ti.f64, ndim=1),
                cov: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """:func:`probe_covariance`, one thread per voxel i (float64 sums over the probes in
    order; each entry written by one thread)."""
    for i in range(Z.shape[0]):
        for e in ti.static(range(3)):
            j = nbr[i, ti.static(FACE_PLUS[e])]
            if j >= 0:
                from_i, from_j = ti.f64(0.0), ti.f64(0.0)
                for k in range(Z.shape[1]):
                    from_i += ti.cast(Z[i, k], ti.f64) * ti.cast(U[j, k], ti.f64)
                    from_j += ti.cast(Z[j, k], ti.f64) * ti.cast(U[i, k], ti.f64)
                cov[i, e] = ti.cast(0.5 * (from_i / den[i] + from_j / den[j]), ti.f32)


def perturbation_moments(S, nbr, W, n_probes: int = 16, seed: int = 0, *, tol: float = PROBE_TOL,
                         maxiter: int = 1000, far=None) -> tuple:
    """Monte Carlo estimate of the diagonal and face covariances of ``Q^-1 D Q^-1``: the
    covariance of the MAP's error under the measurement noise alone (the *sandwich*), where
    the data term ``D`` is taken as ``sum_i W_i E_i[a a^T]``: each voxel i's data weight
    ``W_i`` spread over its own box (``|x - x_i| <= h/2`` per axis), ``a(x)`` the trilinear
    weights of the cell holding x, and ``E_i`` the average over that box.

    Each of the K right-hand sides is one draw ``z = sum_i sqrt(W_i) xi_i a(x_i)``, with
    ``x_i`` uniform in voxel i's box and ``xi_i = +-1``, so that ``E[z z^T]`` is that ``D``
    exactly; ``X = Q^-1 Z`` (one batched PCG), and ``mean_k X_ik X_jk`` estimates
    ``(Q^-1 D Q^-1)_ij``. A point whose cell has a corner outside the band is dropped, as the
    observation pass drops such samples. The draws come from
    ``numpy.random.default_rng(seed)``, and :func:`_box_perturbation` gathers them (each entry
    of Z summed by one thread in a fixed order), so the same seed gives the same bytes.
    Unbiased, and Monte Carlo: one voxel's error falls as ``1/sqrt(K)`` (on the test sphere of
    tests/test_vertex_sigma.py, median 26 % at K = 16, 14 % at 64, 7 % at 256; the colouring
    of the ``coloring`` probes does not carry over, as the draws' points vary, not only their
    signs: coloured, 55 % at any K).

    Args:
        S, nbr, far: the system ``Q`` (as :func:`probe_moments`; not checked: the pipeline's).
        W: (N,) the data weight of each voxel, 1/m^2 (the data term's row sums).
        n_probes, seed, tol, maxiter: as :func:`probe_moments`.
    Returns:
        ``(s, cov, info)`` as :func:`probe_moments`; ``info["method"]`` is ``"perturbation"``.
    """
    S, nbr = stencil_arrays(S, nbr)
    far = far_arrays(far, S.shape[0])
    n = S.shape[0]
    W = np.ascontiguousarray(W, np.float32)
    if W.shape != (n,):
        raise ValueError(f"W must have shape ({n},), got {W.shape}")
    Z = box_perturbations(nbr, W, n_probes, seed)
    X, solve = pcg_batched(S, nbr, Z, None, tol, maxiter, np.float32, check=False, far=far)
    s = np.einsum("ij,ij->i", X, X, dtype=np.float64) / n_probes
    cov = probe_covariance(X, X, nbr, np.full(n, float(n_probes)))
    info = dict(method="perturbation", n_probes=int(n_probes), lattice=None,
                converged=solve["converged"], n_not_converged=solve["n_not_converged"],
                iterations=solve["iterations"], relative_residuals=solve["relative_residuals"],
                n_nonpositive=int(np.count_nonzero(~(s > 0))))
    return s.astype(np.float32), cov, info


def box_perturbations(nbr, W, n_probes: int, seed: int = 0) -> np.ndarray:
    """(N, K) float32: the K right-hand sides ``z`` of :func:`perturbation_moments`: each
    voxel draws a point in its box and a sign for every probe (``default_rng(seed)``)."""
    nbr = np.ascontiguousarray(nbr, np.int32)
    n = nbr.shape[0]
    Z = np.zeros((n, n_probes), np.float32)
    if n == 0:
        return Z
    ok = np.zeros(n, np.int8)
    _cell_complete(nbr, ok)
    rng = np.random.default_rng(seed)
    root_w = np.sqrt(np.maximum(np.asarray(W, np.float64), 0))
    for k in range(n_probes):  # one column per draw: the loop is over probes, not voxels
        t = rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
        amp = root_w * (2 * rng.integers(0, 2, n) - 1)
        _box_perturbation(nbr, ok, t, amp.astype(np.float32), k, Z)
    return Z


#: Stencil offset of cell corner c (:func:`kernels.funcs.corner`) from the cell's base voxel.
_CORNER_OFFSET = [[stencil_offset(o) for o in range(27)].index(corner(c)) for c in range(8)]


@ti.func
def _offset_index(d0, d1, d2):
    """Stencil offset number of (d0, d1, d2) in {-1, 0, 1}^3, the inverse of
    :func:`kernels.layout.stencil_offset`."""
    return (d0 + 1) * 9 + (d1 + 1) * 3 + (d2 + 1)


@ti.kernel
def _cell_complete(nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                   ok: ti.types.ndarray(dtype=ti.i8, ndim=1)):
    """ok[b] = 1 where the cell based at voxel b (b + {0, 1}^3) lies wholly in the band."""
    for b in range(nbr.shape[0]):
        good = 1
        for c in ti.static(range(8)):
            if nbr[b, ti.static(_CORNER_OFFSET[c])] < 0:
                good = 0
        ok[b] = ti.cast(good, ti.i8)


@ti.kernel
def _box_perturbation(nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                      ok: ti.types.ndarray(dtype=ti.i8, ndim=1),
                      t: ti.types.ndarray(dtype=ti.f32, ndim=2),
                      amp: ti.types.ndarray(dtype=ti.f32, ndim=1), col: ti.i32,
                      Z: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """``Z[j, col] = sum_i amp_i a_j(x_i)``, ``x_i = x_i + t_i h``: a gather over the 27
    voxels i around j (the only ones whose point can lie in a cell with corner j), so each
    entry is summed by one thread in a fixed order."""
    for j in range(nbr.shape[0]):
        z = ti.f32(0.0)
        for o in ti.static(range(27)):
            i = nbr[j, o]
            if i >= 0 and amp[i] != 0.0:
                d = ti.static(stencil_offset(o))  # x_i - x_j, voxels
                a = ti.f32(1.0)
                inside = True
                sh = ti.Vector([0, 0, 0])
                for e in ti.static(range(3)):
                    if t[i, e] < 0.0:
                        sh[e] = 1  # the cell holding x_i is based at x_i - sh
                    c = sh[e] - d[e]  # j's corner of that cell, along axis e
                    f = t[i, e] + ti.cast(sh[e], ti.f32)  # x_i's fraction in the cell
                    if c == 0:
                        a *= 1.0 - f
                    elif c == 1:
                        a *= f
                    else:
                        inside = False
                if inside:
                    b = nbr[i, _offset_index(-sh[0], -sh[1], -sh[2])]
                    if b >= 0:
                        if ok[b] != 0:
                            z += amp[i] * a
        Z[j, col] = z
