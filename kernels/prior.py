"""GMRF membrane prior of BayesFusion-SDF (DESIGN.md 3.4), added into the 27-point stencil.

The prior over the band values x (metres) is ``p(x) ∝ exp(-1/2 x^T Q0 x + b0^T x)``, i.e.

    -2 log p(x) = lam * sum_{(i,j) in E} w_ij (x_i - x_j)^2
                + sum_{i in anchors} a_i (x_i - tsdf_i)^2 + eps |x|^2 + const

* E: pairs of band voxels that are neighbours in the chosen stencil (6, 18 or 26 neighbours,
  :func:`kernels.band.stencil_offsets`), each undirected edge once, ``w_ij = 1 / |offset|^2``
  (offset in voxels: 1, 1/2, 1/3 for face, edge, corner neighbours);
* anchors (the paper's ablation, ``anchors=``):

  - ``"boundary"``: the band boundary, voxels with at least one stencil neighbour missing from
    the band (the paper), ``a_i = lam_b``;
  - ``"all"``: every observed voxel, ``a_i = lam_b * weight_i / max(weight)`` (a voxel seen as
    often as the best-seen one is pulled as hard as a boundary anchor, a rarely seen one less);
  - ``"none"``: no anchors; the membrane alone is singular (its null space is the constant
    vector), so ``eps > 0`` or the data term must make Q positive definite.

In stencil form (layout in kernels/stencil.py): ``Q0_ij = -lam w_ij`` at offset o of row i,
``Q0_ii = lam * sum_j w_ij + a_i + eps``, and the anchor part of the right-hand side
``b0_i = a_i tsdf_i``. Since ``w`` of offset o equals that of ``26 - o``, adding Q0 keeps a
symmetric stencil exactly symmetric (the same float32 number is subtracted on both sides).
"""

import numpy as np
import taichi as ti

from .layout import CENTRE, STENCIL, stencil_offsets

ANCHOR_MODES = ("none", "boundary", "all")

_NONE, _BOUNDARY, _ALL = 0, 1, 2  # anchor mode codes passed to the kernel
_MODE_CODE = {"none": _NONE, "boundary": _BOUNDARY, "all": _ALL}


def prior_weights(stencil: int) -> np.ndarray:
    """(27,) float64 membrane weight per stencil offset: ``1 / |offset|^2`` for the offsets of the
    ``stencil`` (6, 18 or 26), 0 for the others and for the centre."""
    offsets, weights = stencil_offsets(stencil)
    w = np.zeros(STENCIL, np.float64)
    w[offsets] = weights
    return w


@ti.kernel
def _add_membrane_prior(S: ti.types.ndarray(dtype=ti.f32, ndim=2),
                        b0: ti.types.ndarray(ndim=1),
                        nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                        tsdf: ti.types.ndarray(dtype=ti.f32, ndim=1),
                        weight: ti.types.ndarray(dtype=ti.f32, ndim=1),
                        w27: ti.types.ndarray(dtype=ti.f64, ndim=1),
                        lam: ti.f64, lam_b: ti.f64, eps: ti.f64, mode: ti.i32,
                        inv_max_weight: ti.f64, b0_dtype: ti.template()):
    """Row i of Q0 into S (added) and b0 (written), for every band voxel i: off-diagonals
    ``S[i, o] -= float32(lam w_o)`` where the neighbour exists; the diagonal sum
    ``lam sum_o w_o + a_i + eps`` accumulated in float64 and added once; ``b0_i = a_i tsdf_i``.
    Deterministic: each row is written by its own thread (gather, no atomics)."""
    for i in range(nbr.shape[0]):
        diag = eps
        boundary = False
        for o in range(27):  # run time, in offset order (the float64 sum's order)
            if o != CENTRE:
                if w27[o] > 0:
                    c = lam * w27[o]  # lam w_ij, the same number for o and 26 - o
                    if nbr[i, o] >= 0:
                        S[i, o] = S[i, o] - ti.cast(c, ti.f32)  # not -=: that is an atomic
                        diag += c
                    else:
                        boundary = True
        anchor = ti.f64(0.0)
        if mode == _BOUNDARY and boundary:
            anchor = lam_b
        elif mode == _ALL:
            anchor = lam_b * ti.cast(weight[i], ti.f64) * inv_max_weight
        S[i, CENTRE] = ti.cast(ti.cast(S[i, CENTRE], ti.f64) + diag + anchor, ti.f32)
        b0[i] = ti.cast(anchor * ti.cast(tsdf[i], ti.f64), b0_dtype)


_AXIS_STRIDE = (9, 3, 1)  # offset o of (di, dj, dk) is CENTRE + 9 di + 3 dj + dk


@ti.kernel
def _add_curvature_prior(S: ti.types.ndarray(dtype=ti.f32, ndim=2),
                         nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                         S2: ti.types.ndarray(dtype=ti.f32, ndim=2),
                         nbr2: ti.types.ndarray(dtype=ti.i32, ndim=2), c: ti.f64,
                         W: ti.types.ndarray(dtype=ti.f32, ndim=2), weighted: ti.i32):
    """Row i of ``c D^T D`` (second differences along the axes, see :func:`add_curvature_prior`)
    into S (offsets 0 and +-1 along each axis, added) and S2 / nbr2 (offsets +-2, written).

    A second difference ``d_j = x_{j-e} - 2 x_j + x_{j+e}`` exists where voxel j and both of its
    neighbours along axis e are band voxels. Voxel i takes part in three of them per axis:
    centred at i (coefficient -2), at i - e and at i + e (coefficient 1 each), so
    ``(D^T D)_ii = 4 [d_i] + [d_{i-e}] + [d_{i+e}]``, ``(D^T D)_{i,i+e} = -2 ([d_i] + [d_{i+e}])``
    and ``(D^T D)_{i,i+2e} = [d_{i+e}]`` ([.] = 1 if it exists). Each sum is formed in float64
    from the same indicators at both ends of a pair, so S stays exactly symmetric. Deterministic:
    each row is written by its own thread (gather)."""
    for i in range(nbr.shape[0]):
        diag = ti.f64(0.0)
        for ax in ti.static(range(3)):
            om = ti.static(CENTRE - _AXIS_STRIDE[ax])
            op = ti.static(CENTRE + _AXIS_STRIDE[ax])
            m = nbr[i, om]
            p = nbr[i, op]
            mm = -1
            pp = -1
            if m >= 0:
                mm = nbr[m, om]
            if p >= 0:
                pp = nbr[p, op]
            vi = ti.f64(0.0)
            if m >= 0 and p >= 0:
                vi = 1.0 if weighted == 0 else ti.cast(W[i, ax], ti.f64)
            vm = ti.f64(0.0)
            if mm >= 0:
                vm = 1.0 if weighted == 0 else ti.cast(W[m, ax], ti.f64)
            vp = ti.f64(0.0)
            if pp >= 0:
                vp = 1.0 if weighted == 0 else ti.cast(W[p, ax], ti.f64)
            diag += c * (4.0 * vi + vm + vp)
            if m >= 0:
                S[i, om] = ti.cast(ti.cast(S[i, om], ti.f64) - 2.0 * c * (vi + vm), ti.f32)
            if p >= 0:
                S[i, op] = ti.cast(ti.cast(S[i, op], ti.f64) - 2.0 * c * (vi + vp), ti.f32)
            S2[i, 2 * ax] = ti.cast(ti.cast(S2[i, 2 * ax], ti.f64) + c * vm, ti.f32)
            nbr2[i, 2 * ax] = mm
            S2[i, 2 * ax + 1] = ti.cast(ti.cast(S2[i, 2 * ax + 1], ti.f64) + c * vp, ti.f32)
            nbr2[i, 2 * ax + 1] = pp
        S[i, CENTRE] = ti.cast(ti.cast(S[i, CENTRE], ti.f64) + diag, ti.f32)


def add_curvature_prior(S, nbr, *, lam2: float, weights=None) -> tuple:
    """Add the second-order (curvature) prior ``lam2 |D x|^2`` to the stencil ``S``; return its
    entries at offsets +-2 as the far part ``(S2, nbr2)`` of Q (kernels/stencil.py). With
    ``weights`` (N, 3) float32, the weights of the second differences centred at each voxel
    along each axis (those :func:`reweight_curvature_prior` leaves in a system), the prior is
    ``lam2 D^T diag(weights) D``.

    D holds one row per band voxel j and axis e whose neighbours ``j +- e`` are both band
    voxels: the second difference ``x_{j-e} - 2 x_j + x_{j+e}``. Unlike the membrane, this
    prior does not penalise the unit slope of a signed distance field (an affine x has
    ``D x = 0``): only bending, i.e. curvature, costs. The prior standard deviation of one
    second difference is ``1 / sqrt(lam2)`` metres.

    Args:
        S: (N, 27) float32 stencil, modified in place (symmetric in, symmetric out).
        nbr: (N, 27) int32 neighbour table (kernels/band.py).
        lam2: strength >= 0, 1/m^2 like Q (chosen by the caller).
    Returns:
        ``(S2, nbr2)``: (N, 6) float32 and int32; column ``a = 2 axis + (0: -2, 1: +2)``;
        ``nbr2 = -1`` and ``S2 = 0`` where that second difference does not exist.

    Raises:
        ValueError: bad shapes, dtypes or lam2.
    """
    if not (isinstance(lam2, (int, float, np.floating, np.integer)) and np.isfinite(lam2)
            and lam2 >= 0):
        raise ValueError(f"prior lam2 must be a finite number >= 0, got {lam2!r}")
    shape = _shape_of(nbr, "nbr")
    n = shape[0] if len(shape) == 2 else -1
    for name, arr in (("S", S), ("nbr", nbr)):
        if _shape_of(arr, name) != (n, 27):
            raise ValueError(f"prior argument {name} must have shape (N, 27), got "
                             f"{_shape_of(arr, name)}")
    _check_dtype(S, "S", (np.float32,))
    _check_dtype(nbr, "nbr", (np.int32,))
    if weights is not None and _shape_of(weights, "weights") != (n, 3):
        raise ValueError(f"prior argument weights must have shape (N, 3), got "
                         f"{_shape_of(weights, 'weights')}")
    S2 = np.zeros((n, 6), np.float32)
    nbr2 = np.full((n, 6), -1, np.int32)
    if n:
        W = S2 if weights is None else np.ascontiguousarray(weights, np.float32)
        _add_curvature_prior(S, nbr, S2, nbr2, float(lam2), W, int(weights is not None))
    return S2, nbr2


@ti.kernel
def _curvature_weights(mean: ti.types.ndarray(dtype=ti.f32, ndim=1),
                       nbr: ti.types.ndarray(dtype=ti.i32, ndim=2),
                       W_old: ti.types.ndarray(dtype=ti.f32, ndim=2),
                       W_new: ti.types.ndarray(dtype=ti.f32, ndim=2),
                       dW: ti.types.ndarray(dtype=ti.f32, ndim=2), inv_c2: ti.f64,
                       laplace: ti.i32, noise: ti.types.ndarray(dtype=ti.f64, ndim=1),
                       allow: ti.i32):
    """The weight of each second difference ``d`` of ``mean`` (centred at voxel i, along each
    axis; 0 where it does not exist), ``u = d^2 / c^2``: the robust weight ``w = 1 / (1 + u)``
    (``laplace`` = 0) or the penalty's curvature ``max(1 - u, 0) / (1 + u)^2`` (``laplace`` =
    1), written to W_new, and its change from W_old to dW. With ``allow`` (and ``laplace``),
    ``u = d^2 / (c^2 + a)``, ``a = noise_(j-e) + 4 noise_j + noise_(j+e)`` the variance the
    voxels' ``noise`` (N,) gives ``d`` (:func:`laplace_curvature_prior`). One thread per voxel
    (gather); W_new may be W_old."""
    for i in range(nbr.shape[0]):
        for ax in ti.static(range(3)):
            m = nbr[i, ti.static(CENTRE - _AXIS_STRIDE[ax])]
            p = nbr[i, ti.static(CENTRE + _AXIS_STRIDE[ax])]
            w = ti.f64(0.0)
            if m >= 0 and p >= 0:
                d = ti.cast(mean[m], ti.f64) - 2.0 * ti.cast(mean[i], ti.f64) + ti.cast(
                    mean[p], ti.f64)
                u = d * d * inv_c2
                if laplace and allow:
                    a = noise[m] + 4.0 * noise[i] + noise[p]
                    u = d * d / (1.0 / inv_c2 + a)
                w = 1.0 / (1.0 + u)
                if laplace:
                    w = ti.max(1.0 - u, 0.0) * w * w
            dW[i, ax] = ti.cast(w - ti.cast(W_old[i, ax], ti.f64), ti.f32)
            W_new[i, ax] = ti.cast(w, ti.f32)


def reweight_curvature_prior(S, far, nbr, mean, W, *, lam2: float, scale_m: float) -> None:
    """One iteratively reweighted step of the robust curvature prior
    ``lam2 c^2 sum log(1 + d^2 / c^2)`` (a Cauchy / Lorentzian penalty of each second difference
    ``d`` of :func:`add_curvature_prior`, scale ``c = scale_m``): its weights at ``mean``,
    ``w = 1 / (1 + d^2 / c^2)``, replace the weights ``W`` (N, 3) float32 the stencil holds
    (all ones after :func:`add_curvature_prior`), in ``S`` and the far part ``far = (S2, nbr2)``,
    in place. Where the field bends by much more than ``c`` (creases, thin parts) the prior lets
    go; where it is smooth it keeps the full strength ``lam2``."""
    _replace_curvature_weights(S, far, nbr, mean, W, W, lam2, scale_m, laplace=0)


def laplace_curvature_prior(S, far, nbr, mean, W, *, lam2: float, scale_m: float,
                            noise: np.ndarray | None = None) -> np.ndarray:
    """The robust curvature prior's Laplace approximation at ``mean`` (its MAP): the stencil
    ``S`` and far part ``far``, which hold ``lam2 D^T diag(W) D`` (``W``: the reweighting's
    weights, left unchanged), get the penalty's own curvature instead, in place::

        d^2/dd^2 [c^2 log(1 + d^2 / c^2)] / 2 = (1 - u) / (1 + u)^2,   u = d^2 / c^2,

    taken as 0 where it is negative (``|d| > c``: the penalty is concave there and adds no
    precision). The reweighting's ``1 / (1 + u)`` is the slope's ratio ``rho'(d) / 2 d``, which
    gives the MAP, not the posterior's spread around it: at a crease or a thin part it keeps
    charging a bend the prior no longer resists, and the variance came out too small there
    (docs/measurements.md, "The robust prior's variance from its Hessian").

    ``noise`` (N,) float64, m^2: each voxel's variance under the data's noise alone (the
    MAP's, :func:`bftaichi.stages.solve.solve_map`). A second difference of the MAP then
    counts as a bend only beyond what that noise gives it: ``u = d^2 / (c^2 + a)``, ``a =
    noise_(j-e) + 4 noise_j + noise_(j+e)`` (the voxels taken as independent). Without it the
    noisy second differences of a sparse capture's mean reach ``c``, where the Hessian lets go
    of bends that are not there, and sigma came out too wide (docs/measurements.md, "The
    MAP's noise in the robust prior's Hessian"). Returns the (N, 3) float32 weights now
    in ``S``."""
    W_h = np.empty_like(W)
    _replace_curvature_weights(S, far, nbr, mean, W, W_h, lam2, scale_m, laplace=1,
                               noise=noise)
    return W_h


def _replace_curvature_weights(S, far, nbr, mean, W_old, W_new, lam2, scale_m, *, laplace,
                               noise=None):
    """``S`` and ``far`` (holding ``lam2 D^T diag(W_old) D``) get the weights of
    :func:`_curvature_weights` at ``mean`` instead (written to ``W_new``, which may be
    ``W_old``): one pass for the weights, one adding ``lam2 D^T diag(W_new - W_old) D``."""
    S2, nbr2 = far
    dW = np.empty_like(W_old)
    if noise is not None and len(noise) != len(mean):
        raise ValueError(f"noise has {len(noise)} voxels, the mean {len(mean)}")
    allow = noise is not None
    noise = (np.ascontiguousarray(noise, np.float64) if allow else np.zeros(1, np.float64))
    _curvature_weights(np.ascontiguousarray(mean, np.float32), nbr, W_old, W_new, dW,
                       1.0 / float(scale_m) ** 2, laplace, noise, int(allow))
    _add_curvature_prior(S, nbr, S2, nbr2, float(lam2), dW, 1)


def _shape_of(arr, name: str) -> tuple:
    if not hasattr(arr, "shape"):
        raise ValueError(f"prior argument {name} must be a numpy array or Taichi ndarray, "
                         f"got {type(arr).__name__}")
    return tuple(arr.shape)


_TI_DTYPES = {np.dtype(np.float32): ti.f32, np.dtype(np.float64): ti.f64,
              np.dtype(np.int32): ti.i32}


def _check_dtype(arr, name: str, allowed: tuple) -> None:
    """The dtype of ``arr`` (numpy array or Taichi ndarray) is one of the ``allowed`` numpy
    dtypes; numpy arrays must also be C-contiguous (the kernel writes in place)."""
    allowed = tuple(np.dtype(a) for a in allowed)
    if isinstance(arr, np.ndarray):
        ok = arr.dtype in allowed
        if ok and not arr.flags.c_contiguous:
            raise ValueError(f"prior argument {name} must be C-contiguous")
    else:
        ok = getattr(arr, "dtype", None) in [_TI_DTYPES[a] for a in allowed]
    if not ok:
        raise ValueError(f"prior argument {name} must have dtype "
                         f"{' or '.join(str(a) for a in allowed)}, got {arr.dtype}")


def _rhs_dtype(b0):
    """Taichi dtype of the right-hand side array (float32 or float64)."""
    if isinstance(b0, np.ndarray):
        return ti.f64 if b0.dtype == np.float64 else ti.f32
    return b0.dtype


def _to_numpy(arr) -> np.ndarray:
    return arr.to_numpy() if hasattr(arr, "to_numpy") else np.asarray(arr)


def add_prior(S, b0, nbr, tsdf, weight, *, lam: float, lam_b: float, eps: float,
              stencil: int, anchors: str) -> None:
    """Add the membrane prior Q0 into the stencil ``S`` and write its right-hand side ``b0``.

    Args:
        S: (N, 27) float32 stencil of Q, modified in place (``S += Q0``); symmetric in,
            symmetric out.
        b0: (N,) float32 or float64, overwritten with the anchor term ``a_i tsdf_i``
            (1/m units times metres; add it to ``A^T W y`` to get h).
        nbr: (N, 27) int32 neighbour table of the band (kernels/band.py).
        tsdf: (N,) float32 bootstrap values, metres (the anchors' targets).
        weight: (N,) float32 bootstrap weights (used by ``anchors="all"``).
        lam: membrane strength lambda >= 0, 1/m^2 like Q (no default: chosen by the caller).
        lam_b: anchor strength lambda_b >= 0, 1/m^2.
        eps: added to every diagonal entry, >= 0, 1/m^2.
        stencil: 6, 18 or 26 neighbours (no default: the caller's configuration chooses; 6 is
            the cheapest to assemble, 18 and 26 smooth more isotropically).
        anchors: ``"boundary"`` (the paper's full model), ``"all"`` or ``"none"`` (module
            docstring); no default.
    S, b0, nbr, tsdf, weight are numpy arrays or Taichi ndarrays (any N, no recompilation).

    Raises:
        ValueError: bad stencil, anchor mode, parameters, shapes or dtypes.

    Deterministic (one thread per row, no atomics).
    """
    if anchors not in ANCHOR_MODES:
        raise ValueError(f"prior anchors must be one of {', '.join(ANCHOR_MODES)}, "
                         f"got {anchors!r}")
    w27 = prior_weights(stencil)
    for name, value in (("lam", lam), ("lam_b", lam_b), ("eps", eps)):
        if not (isinstance(value, (int, float, np.floating, np.integer))
                and np.isfinite(value) and value >= 0):
            raise ValueError(f"prior {name} must be a finite number >= 0, got {value!r}")
    n = _shape_of(nbr, "nbr")[0] if len(_shape_of(nbr, "nbr")) == 2 else -1
    expected = {"S": (n, 27), "b0": (n,), "nbr": (n, 27), "tsdf": (n,), "weight": (n,)}
    arrays = {"S": S, "b0": b0, "nbr": nbr, "tsdf": tsdf, "weight": weight}
    for name, arr in arrays.items():
        if _shape_of(arr, name) != expected[name]:
            raise ValueError(f"prior argument {name} must have shape (N, 27) / (N,) with N = "
                             f"{n} band voxels: expected {expected[name]}, got "
                             f"{_shape_of(arr, name)}")
    _check_dtype(S, "S", (np.float32,))
    _check_dtype(b0, "b0", (np.float32, np.float64))
    _check_dtype(nbr, "nbr", (np.int32,))
    _check_dtype(tsdf, "tsdf", (np.float32,))
    _check_dtype(weight, "weight", (np.float32,))
    if n == 0:
        return
    inv_max_weight = 0.0
    if anchors == "all":
        max_weight = float(_to_numpy(weight).max())
        inv_max_weight = 1.0 / max_weight if max_weight > 0 else 0.0
    _add_membrane_prior(S, b0, nbr, tsdf, weight, w27, float(lam), float(lam_b), float(eps),
                        _MODE_CODE[anchors], inv_max_weight, _rhs_dtype(b0))
