"""kernels.prior.add_prior against a GMRF precision assembled independently as a scipy CSR matrix.

The reference builds Q0 from an explicit edge list (each undirected edge once, found with a dict
of voxel coordinates, not with the band's neighbour table) on a small sphere band, and the
stencil S is compared with it entry by entry; then symmetry, positive definiteness for each
anchor mode, and the membrane's null space (the constant vector). The curvature prior is checked
the same way against ``D^T D`` with D's second differences found by voxel coordinates, and for
the property that makes it the right prior for a signed distance: it does not penalise a field of
unit slope (D x = 0 for affine x), which the membrane does.
"""

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
import taichi as ti
from scipy.sparse.csgraph import connected_components

from kernels.band import build_band
from kernels.stencil import apply_Q, check_far, check_stencil
from kernels.prior import (ANCHOR_MODES, add_curvature_prior, add_prior,
                           laplace_curvature_prior, reweight_curvature_prior)

VOXEL = 0.01
TAU_B = 0.02
LAM, LAM_B = 2.5, 0.7  # 1/m^2 (any positive numbers: the algebra is what is tested)


@pytest.fixture(scope="module")
def band():
    """A small band (~900 voxels) around a sphere of radius 2.5 voxels, cut by the grid's box."""
    r = np.arange(-5, 5)
    ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    sdf = np.linalg.norm((ijk + 0.5) * VOXEL - [0.002, -0.001, 0.003], axis=1) - 0.025
    keep = sdf >= -TAU_B
    ijk, sdf = ijk[keep].astype(np.int32), sdf[keep]
    weight = np.random.default_rng(1).integers(1, 20, len(ijk)).astype(np.float32)
    tsdf = np.clip(sdf, -TAU_B, TAU_B).astype(np.float32)
    out = build_band(ijk, tsdf, weight, TAU_B)
    assert 300 < len(out["ijk"]) < 1000
    return out


def reference_prior(ijk, tsdf, weight, stencil, lam, lam_b, eps, anchors):
    """(Q0 CSR float64, b0 float64) from the math of DESIGN.md 3.4, independent of kernels."""
    n = len(ijk)
    max_sq = {6: 1, 18: 2, 26: 3}[stencil]
    deltas = [d for d in itertools.product((-1, 0, 1), repeat=3)
              if 0 < sum(x * x for x in d) <= max_sq]
    index = {tuple(v): i for i, v in enumerate(ijk.tolist())}
    rows, cols, vals = [], [], []
    boundary = np.zeros(n, bool)
    for i, v in enumerate(ijk.tolist()):
        for d in deltas:
            j = index.get((v[0] + d[0], v[1] + d[1], v[2] + d[2]))
            if j is None:
                boundary[i] = True
            elif d > (0, 0, 0):  # each undirected edge once: lam w (x_i - x_j)^2
                w = lam / sum(x * x for x in d)
                rows += [i, j, i, j]
                cols += [i, j, j, i]
                vals += [w, w, -w, -w]
    if anchors == "boundary":
        a = np.where(boundary, lam_b, 0.0)
    elif anchors == "all":
        a = lam_b * weight.astype(np.float64) / weight.max()
    else:
        a = np.zeros(n)
    Q = sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr() + sp.diags(a + eps)
    return Q.tocsr(), a * tsdf.astype(np.float64)


def stencil_to_csr(S, nbr):
    i, o = np.nonzero(nbr >= 0)
    n = len(nbr)
    return sp.csr_matrix((S[i, o].astype(np.float64), (i, nbr[i, o])), shape=(n, n))


def run_prior(band, stencil, anchors, eps, b0_dtype=np.float32, S=None):
    n = len(band["ijk"])
    S = np.zeros((n, 27), np.float32) if S is None else S
    b0 = np.full(n, np.nan, b0_dtype)  # written, not added: NaN must disappear
    add_prior(S, b0, band["nbr"], band["tsdf"], band["weight"], lam=LAM, lam_b=LAM_B, eps=eps,
              stencil=stencil, anchors=anchors)
    return S, b0


@pytest.mark.parametrize("stencil", [6, 18, 26])
@pytest.mark.parametrize("anchors", ANCHOR_MODES)
def test_stencil_equals_reference_csr(band, stencil, anchors):
    eps = 1e-3
    S, b0 = run_prior(band, stencil, anchors, eps)
    Q_ref, b0_ref = reference_prior(band["ijk"], band["tsdf"], band["weight"], stencil, LAM,
                                    LAM_B, eps, anchors)
    Q = stencil_to_csr(S, band["nbr"])
    diff = (Q - Q_ref).tocoo()
    ref_at = np.asarray(Q_ref[diff.row, diff.col]).ravel()
    assert (np.abs(diff.data) <= 1e-6 * np.abs(ref_at)).all()  # entry by entry, same pattern
    assert Q.count_nonzero() == Q_ref.count_nonzero()
    np.testing.assert_allclose(b0, b0_ref, rtol=1e-6, atol=0)
    if anchors != "none":
        assert (b0 != 0).sum() > 10
    # S is exactly symmetric: S[i, o] == S[nbr[i, o], 26 - o]
    i, o = np.nonzero(band["nbr"] >= 0)
    np.testing.assert_array_equal(S[i, o], S[band["nbr"][i, o], 26 - o])


@pytest.mark.parametrize("anchors,eps", [("boundary", 0.0), ("all", 0.0), ("none", 1e-2)])
def test_positive_definite_for_each_anchor_mode(band, anchors, eps):
    S, _ = run_prior(band, 6, anchors, eps)
    eig = np.linalg.eigvalsh(stencil_to_csr(S, band["nbr"]).toarray())
    assert eig[0] > 1e-6 * eig[-1]  # anchors alone (eps = 0) or eps alone make Q0 definite
    if anchors == "none":
        np.testing.assert_allclose(eig[0], eps, rtol=1e-3)  # the constant mode, lifted by eps


@pytest.mark.parametrize("stencil", [6, 26])
def test_membrane_null_space_is_the_constant_vector(band, stencil):
    S, b0 = run_prior(band, stencil, "none", 0.0)
    Q = stencil_to_csr(S, band["nbr"])
    assert connected_components(Q, directed=False)[0] == 1  # precondition: one component
    diag = S[:, 13].astype(np.float64)
    assert np.abs(Q @ np.ones(len(S))).max() <= 1e-6 * diag.max()  # Q0 1 = 0
    eig = np.linalg.eigvalsh(Q.toarray())
    assert abs(eig[0]) <= 1e-5 * eig[-1] and eig[1] > 1e-4 * eig[-1]  # null space: 1-D
    assert (b0 == 0).all()


def test_prior_adds_to_an_existing_stencil(band):
    nbr = band["nbr"]
    i, o = np.nonzero(nbr >= 0)
    lo, hi = np.minimum(i, nbr[i, o]), np.maximum(i, nbr[i, o])
    S0 = np.zeros(nbr.shape, np.float32)  # a symmetric "data term" already in S
    S0[i, o] = ((lo * 7919 + hi * 104729) % 97).astype(np.float32) / 97
    S, _ = run_prior(band, 18, "boundary", 1e-3, S=S0.copy())
    Q_only, _ = run_prior(band, 18, "boundary", 1e-3)
    np.testing.assert_allclose(S, S0.astype(np.float64) + Q_only, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(S[i, o], S[nbr[i, o], 26 - o])


def test_float64_rhs_and_taichi_ndarrays(band):
    S32, b32 = run_prior(band, 26, "all", 1e-3)
    _, b64 = run_prior(band, 26, "all", 1e-3, b0_dtype=np.float64)
    np.testing.assert_allclose(b64, b32, rtol=1e-6)
    n = len(S32)
    arrays = {}
    for name, dtype, shape in (("S", ti.f32, (n, 27)), ("b0", ti.f64, (n,)),
                               ("nbr", ti.i32, (n, 27)), ("tsdf", ti.f32, (n,)),
                               ("weight", ti.f32, (n,))):
        arrays[name] = ti.ndarray(dtype, shape=shape)
    for name in ("nbr", "tsdf", "weight"):
        arrays[name].from_numpy(band[name])
    add_prior(**arrays, lam=LAM, lam_b=LAM_B, eps=1e-3, stencil=26, anchors="all")
    np.testing.assert_array_equal(arrays["S"].to_numpy(), S32)
    np.testing.assert_allclose(arrays["b0"].to_numpy(), b64, rtol=0)


def test_empty_band_is_a_no_op():
    S, b0 = np.zeros((0, 27), np.float32), np.zeros(0, np.float32)
    out = add_prior(S, b0, np.zeros((0, 27), np.int32), np.zeros(0, np.float32),
                    np.zeros(0, np.float32), lam=1.0, lam_b=1.0, eps=0.0, stencil=6,
                    anchors="boundary")
    assert out is None and S.shape == (0, 27) and b0.shape == (0,)


@pytest.mark.parametrize("bad", ["anchors", "stencil", "lam", "shape", "dtype", "ti_dtype"])
def test_bad_arguments_are_rejected(band, bad):
    n = len(band["ijk"])
    args = dict(S=np.zeros((n, 27), np.float32), b0=np.zeros(n, np.float32), nbr=band["nbr"],
                tsdf=band["tsdf"], weight=band["weight"])
    kw = dict(lam=LAM, lam_b=LAM_B, eps=0.0, stencil=6, anchors="boundary")
    if bad == "anchors":
        kw["anchors"] = "edges"
    elif bad == "stencil":
        kw["stencil"] = 8
    elif bad == "lam":
        kw["lam"] = -1.0
    elif bad == "shape":
        args["b0"] = np.zeros(n + 1, np.float32)
    elif bad == "dtype":
        args["S"] = np.zeros((n, 27), np.float64)
    else:
        args["b0"] = ti.ndarray(ti.i32, shape=(n,))
    with pytest.raises(ValueError):
        add_prior(**args, **kw)


def reference_curvature(ijk, lam2, x=None, c=None, laplace=False, noise=None):
    """lam2 D^T D (CSR float64): one row of D per voxel j and axis e with j - e and j + e in
    the band (found by coordinates), the second difference x_{j-e} - 2 x_j + x_{j+e}. With a
    field ``x`` and a scale ``c``: the robust prior's lam2 D^T diag(w) D at x,
    ``w = 1 / (1 + (D x)^2 / c^2)``; with ``laplace``, ``w`` is the penalty's second derivative
    ``d^2/dd^2 [c^2 log(1 + d^2 / c^2)] / 2``, by central differences, clipped at 0; with a
    per-voxel ``noise`` as well, the closed form ``max(1 - u, 0) / (1 + u)^2`` at ``u = d^2 /
    (c^2 + a)``, ``a`` the variance of ``d`` under independent voxel noise, ``(D o D) noise``."""
    index = {tuple(v): k for k, v in enumerate(ijk.tolist())}
    rows, cols, vals = [], [], []
    r = 0
    for k, v in enumerate(ijk.tolist()):
        for e in np.eye(3, dtype=int).tolist():
            lo = index.get(tuple(np.subtract(v, e)))
            hi = index.get(tuple(np.add(v, e)))
            if lo is not None and hi is not None:
                rows += [r, r, r]
                cols += [lo, k, hi]
                vals += [1.0, -2.0, 1.0]
                r += 1
    D = sp.csr_matrix((vals, (rows, cols)), shape=(r, len(ijk)))
    w = np.ones(r) if x is None else 1.0 / (1.0 + (D @ x) ** 2 / c ** 2)
    if laplace and noise is not None:
        u = (D @ x) ** 2 / (c ** 2 + D.multiply(D) @ noise)
        w = np.maximum(1.0 - u, 0.0) / (1.0 + u) ** 2
    elif laplace:
        d, step = D @ x, 1e-4 * c

        def penalty(t):
            return c ** 2 * np.log1p(t ** 2 / c ** 2)
        w = np.maximum((penalty(d + step) - 2 * penalty(d) + penalty(d - step)) / step ** 2 / 2,
                       0.0)
    return (lam2 * (D.T @ sp.diags(w) @ D)).tocsr()


def curvature_csr(S, nbr, S2, nbr2):
    n = len(nbr)
    i, a = np.nonzero(nbr2 >= 0)
    far = sp.csr_matrix((S2[i, a].astype(np.float64), (i, nbr2[i, a])), shape=(n, n))
    return stencil_to_csr(S, nbr) + far


def test_curvature_prior_equals_reference_csr(band):
    n = len(band["ijk"])
    S = np.zeros((n, 27), np.float32)
    S2, nbr2 = add_curvature_prior(S, band["nbr"], lam2=LAM)
    Q_ref = reference_curvature(band["ijk"], LAM)
    Q = curvature_csr(S, band["nbr"], S2, nbr2)
    diff = abs(Q - Q_ref)
    assert diff.max() <= 1e-6 * abs(Q_ref).max()
    assert Q.count_nonzero() == Q_ref.count_nonzero()
    assert (nbr2 >= 0).sum() > 100  # the band has interior second differences at +-2
    assert (S2[nbr2 < 0] == 0).all()
    # exactly symmetric, in both parts: what check_stencil / check_far verify
    S = S + 1.0 * np.eye(1, 27, 13, dtype=np.float32)  # a positive diagonal, as with data
    check_stencil(S, band["nbr"], rtol=0)
    check_far((S2, nbr2), S, rtol=0)
    i, a = np.nonzero(nbr2 >= 0)
    np.testing.assert_array_equal(S2[i, a], S2[nbr2[i, a], a ^ 1])


def test_curvature_prior_does_not_penalise_a_unit_slope_but_the_membrane_does(band):
    """A signed distance to a plane is affine with unit slope: the curvature prior's energy
    is 0 for it (and for any affine field), the membrane's is not; a bent field costs."""
    n = len(band["ijk"])
    S = np.zeros((n, 27), np.float32)
    far = add_curvature_prior(S, band["nbr"], lam2=LAM)
    x = (band["ijk"] + 0.5) @ np.array([0.6, 0.0, 0.8]) * VOXEL  # plane SDF, |grad| = 1
    qx = apply_Q(S, band["nbr"], x, far=far)
    assert np.abs(qx).max() <= 1e-9 * LAM
    bent = np.linalg.norm((band["ijk"] + 0.5) * VOXEL, axis=1)  # a sphere's SDF + const
    assert bent @ apply_Q(S, band["nbr"], bent, far=far) > 1e-3 * LAM * VOXEL ** 2
    M, _ = run_prior(band, 6, "none", 0.0)
    assert x @ apply_Q(M, band["nbr"], x) > 0.1 * LAM * VOXEL ** 2 * n


def test_curvature_prior_adds_to_an_existing_stencil(band):
    nbr = band["nbr"]
    S0, _ = run_prior(band, 26, "boundary", 1e-3)
    S = S0.copy()
    S2, nbr2 = add_curvature_prior(S, nbr, lam2=LAM)
    Q = curvature_csr(S, nbr, S2, nbr2)
    Q_ref = stencil_to_csr(S0, nbr) + reference_curvature(band["ijk"], LAM)
    assert abs(Q - Q_ref).max() <= 1e-5 * abs(Q_ref).max()


def test_robust_curvature_prior_reweights_to_the_reference_at_the_last_field(band):
    """Each reweighting replaces the weights the stencil holds (it does not stack them): after
    two steps at two fields, S and the far part equal ``lam2 D^T diag(w) D`` with the weights
    of the second field; a crease (second differences >> c) gets a weak prior, a plane the full
    strength."""
    nbr, ijk, c = band["nbr"], band["ijk"], 0.3 * VOXEL
    n = len(ijk)
    S = np.zeros((n, 27), np.float32)
    far = add_curvature_prior(S, nbr, lam2=LAM)
    W = np.ones((n, 3), np.float32)
    sphere = (np.linalg.norm((ijk + 0.5) * VOXEL, axis=1) - 0.025).astype(np.float32)
    crease = (np.abs((ijk[:, 0] + 0.5) * VOXEL) + 0.5 * (ijk[:, 2] + 0.5) * VOXEL
              ).astype(np.float32)  # a V along x: second differences of 1 voxel at x = 0
    reweight_curvature_prior(S, far, nbr, sphere, W, lam2=LAM, scale_m=c)
    reweight_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c)
    Q = curvature_csr(S, nbr, *far)
    Q_ref = reference_curvature(ijk, LAM, crease.astype(np.float64), c)
    assert abs(Q - Q_ref).max() <= 1e-5 * LAM
    check_far(far, S + np.eye(1, 27, 13, dtype=np.float32), rtol=0)
    at_crease = np.abs(ijk[:, 0] + 0.5) < 1
    assert W[at_crease, 0].max() < 0.1 and W[~at_crease].max() > 0.99


def test_laplace_curvature_prior_is_the_penalty_s_curvature_at_the_field(band):
    """After the reweighting, the variance's system holds the robust penalty's second
    derivative at the field (finite differences of ``c^2 log(1 + d^2 / c^2)``, 0 where it is
    concave), not the reweighting's ``1 / (1 + u)``; the weights the reweighting left are
    kept (they give the prior's slope). At a crease (``|d| >> c``) the prior adds nothing."""
    nbr, ijk, c = band["nbr"], band["ijk"], 0.3 * VOXEL
    n = len(ijk)
    crease = (np.abs((ijk[:, 0] + 0.5) * VOXEL) + 0.5 * (ijk[:, 2] + 0.5) * VOXEL
              + 0.002 * np.sin(ijk[:, 1])).astype(np.float32)  # bends of 0 .. ~2 c besides
    S = np.zeros((n, 27), np.float32)
    far = add_curvature_prior(S, nbr, lam2=LAM)
    W = np.ones((n, 3), np.float32)
    reweight_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c)
    W_slope = W.copy()
    W_h = laplace_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c)
    Q = curvature_csr(S, nbr, *far)
    x = crease.astype(np.float64)
    Q_ref = reference_curvature(ijk, LAM, x, c, laplace=True)
    assert abs(Q - Q_ref).max() <= 1e-4 * LAM
    assert abs(Q - reference_curvature(ijk, LAM, x, c)).max() > 0.1 * LAM  # not the slope's
    assert np.array_equal(W, W_slope)
    at_crease = np.abs(ijk[:, 0] + 0.5) < 1
    assert W_h[at_crease, 0].max() == 0 and W_h.min() >= 0
    assert np.all(W_h <= W + 1e-7)  # never stiffer than the reweighting


def test_laplace_curvature_with_the_noise_allowance(band):
    """With each voxel's variance under the data's noise, a second difference of the field
    counts as a bend only beyond what that noise gives it: the system holds the reference
    ``lam2 D^T diag(w) D`` with ``u = d^2 / (c^2 + a)``; it is nowhere less stiff than the plain
    Laplace curvature, and where the noise is as large as the bends the prior keeps most of its
    strength while a bend far beyond the noise (the crease) is still let go."""
    nbr, ijk, c = band["nbr"], band["ijk"], 0.3 * VOXEL
    n = len(ijk)
    crease = (np.abs((ijk[:, 0] + 0.5) * VOXEL) + 0.5 * (ijk[:, 2] + 0.5) * VOXEL
              + 0.002 * np.sin(ijk[:, 1])).astype(np.float32)
    noise = np.random.default_rng(3).uniform(0, (2 * c) ** 2 / 6, n)  # a up to (2 c)^2

    def hessian(noise):
        S = np.zeros((n, 27), np.float32)
        far = add_curvature_prior(S, nbr, lam2=LAM)
        W = np.ones((n, 3), np.float32)
        reweight_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c)
        exists = W > 0  # the second differences the band holds
        W_h = laplace_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c, noise=noise)
        return curvature_csr(S, nbr, *far), W_h, exists

    Q, W_h, exists = hessian(noise)
    Q_ref = reference_curvature(ijk, LAM, crease.astype(np.float64), c, laplace=True,
                                noise=noise)
    assert abs(Q - Q_ref).max() <= 1e-4 * LAM
    W_plain = hessian(None)[1]
    assert np.all(W_h >= W_plain) and W_h.max() <= 1
    assert (W_h[exists] > W_plain[exists] + 0.05).mean() > 0.1  # noise-level bends: stiffer
    # 1 mm of noise a voxel against the sine's bends of up to 1.8 mm (c = 3 mm) and the crease's
    # 1 cm: the sine's keep at least half the prior, the crease is still let go
    W_mm = hessian(np.full(n, 1e-6))[1]
    smooth = exists & ~(np.abs(ijk[:, 0] + 0.5) < 1)[:, None]
    assert W_plain[smooth].min() < 0.4 and W_mm[smooth].min() > 0.5
    assert W_mm[np.abs(ijk[:, 0] + 0.5) < 1, 0].max() == 0
    with pytest.raises(ValueError, match="noise has"):
        hessian(noise[:-1])


def test_weighted_curvature_prior_is_the_one_the_reweighting_left(band):
    """``add_curvature_prior(..., weights=W)`` builds the prior with the weights a system was
    left with after reweighting (what ``solver.prior_bias`` rebuilds the prior from): the same
    Q as the reference ``lam2 D^T diag(w) D``, and not the all-one prior."""
    nbr, ijk, c = band["nbr"], band["ijk"], 0.3 * VOXEL
    n = len(ijk)
    crease = (np.abs((ijk[:, 0] + 0.5) * VOXEL) + 0.5 * (ijk[:, 2] + 0.5) * VOXEL
              ).astype(np.float32)
    S = np.zeros((n, 27), np.float32)
    far = add_curvature_prior(S, nbr, lam2=LAM)
    W = np.ones((n, 3), np.float32)
    reweight_curvature_prior(S, far, nbr, crease, W, lam2=LAM, scale_m=c)
    unit_S = np.zeros((n, 27), np.float32)
    unit = curvature_csr(unit_S, nbr, *add_curvature_prior(unit_S, nbr, lam2=LAM))
    fresh = np.zeros((n, 27), np.float32)
    far_fresh = add_curvature_prior(fresh, nbr, lam2=LAM, weights=W)
    Q, Q_fresh = curvature_csr(S, nbr, *far), curvature_csr(fresh, nbr, *far_fresh)
    Q_ref = reference_curvature(ijk, LAM, crease.astype(np.float64), c)
    assert abs(Q_fresh - Q_ref).max() <= 1e-5 * LAM
    assert abs(Q_fresh - Q).max() <= 1e-5 * LAM
    assert abs(unit - Q_ref).max() > 0.5 * LAM  # the weights matter at the crease


@pytest.mark.parametrize("bad", ["lam2", "shape", "dtype"])
def test_curvature_prior_rejects_bad_arguments(band, bad):
    n = len(band["ijk"])
    S, nbr, lam2 = np.zeros((n, 27), np.float32), band["nbr"], 1.0
    if bad == "lam2":
        lam2 = float("nan")
    elif bad == "shape":
        S = np.zeros((n, 26), np.float32)
    else:
        S = np.zeros((n, 27), np.float64)
    with pytest.raises(ValueError):
        add_curvature_prior(S, nbr, lam2=lam2)
