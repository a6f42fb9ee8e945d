"""The vertex sigma of ``mesh.ply`` (DESIGN.md 3.7): ``sqrt(a_v^T Q^-1 a_v)`` from the probe
estimate of the face-neighbour covariances, against the exact value of a small posterior (a
sphere of radius 0.15 m at 3 cm voxels, ~3k band voxels: a dense inverse of Q), and the
``sigma_pos`` and ``band.npz`` that carry it."""

import numpy as np
import pytest

import bftaichi as bf
from bftaichi.errors import DataError
from bftaichi.io import read_mesh_ply
from bftaichi.posterior import MIN_GRADIENT, Posterior
from bftaichi.stages.surface import (_CORNERS, extract_mesh, sample_field, sample_gradient,
                                     vertex_variance)
from bftaichi.stages.variance import estimate_variance
from conftest import box_data_term, posterior_system, solved, to_csr
from kernels.probes import FACE_PLUS

SPHERE_SETS = (  # a sphere of radius 0.15 m seen from 8 views all around, 3 cm voxels
    "synthetic.mesh=sphere", "synthetic.radius_m=0.15", "synthetic.trajectory=sphere",
    "synthetic.n_views=8", "synthetic.cam_radius_m=0.8", "synthetic.width=80",
    "synthetic.height=60", "synthetic.fx=80", "synthetic.fy=80", "synthetic.cx=39.5",
    "synthetic.cy=29.5", "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06",
    # the probe estimate of Q^-1 alone: local noise adds a b^2 that is fully correlated between
    # neighbours by construction (tests/test_local_noise.py), which would hide the covariances
    "observation.local_noise=false",
    # the linear (Gaussian) curvature prior: conftest.posterior_system rebuilds Q with it; the
    # robust prior, the default, reweights Q at the mean and takes its Hessian for the variance
    "prior.curvature=0.1", "prior.curvature_scale=0",
)


@pytest.fixture(scope="module")
def sphere():
    """The solved sphere, its system, exact Q^-1, mesh and vertex edges."""
    from bftaichi.running.pipeline import open_frames

    cfg = bf.load_config(None, SPHERE_SETS)
    recon, post = solved(cfg, open_frames(cfg))
    band, system = posterior_system(recon)
    assert 2000 < len(band.ijk) < 5000
    C = np.linalg.inv(to_csr(system.S, system.nbr, system.far).toarray())
    verts, faces, edges = extract_mesh(band.ijk, post.mean, band.weight > 0, post.voxel_size,
                                       return_edges=True)
    assert len(verts) > 300
    return dict(cfg=cfg, post=post, band=band, system=system, C=C, verts=verts, edges=edges)


def exact_moments(C, nbr):
    """diag(C) and C with the +x, +y, +z neighbours, (N, 3), 0 where there is none."""
    cov = np.zeros((len(C), 3))
    for e, o in enumerate(FACE_PLUS):
        i = np.flatnonzero(nbr[:, o] >= 0)
        cov[i, e] = C[i, nbr[i, o]]
    return np.diag(C).copy(), cov


def quadratic_form(C, ijk, voxel_size, points):
    """a^T C a with a the trilinear weights of each point over its cell's 8 corners, found by
    a dictionary (independent of surface.py's lookup and of the vertex edges)."""
    index = {tuple(v): k for k, v in enumerate(ijk.tolist())}
    g = points.astype(np.float64) / voxel_size - 0.5
    base = np.floor(g).astype(np.int64)
    f = g - base
    w = np.prod(np.where(_CORNERS[None] == 1, f[:, None], 1 - f[:, None]), axis=2)  # (V, 8)
    idx = np.array([[index.get(tuple(c), -1) for c in (b + _CORNERS).tolist()] for b in base])
    w = np.where(idx >= 0, w, 0.0)
    assert np.all(w.sum(axis=1) > 0.999)  # every corner with weight is in the band
    sub = C[np.maximum(idx, 0)[:, :, None], np.maximum(idx, 0)[:, None, :]]      # (V, 8, 8)
    return np.einsum("vi,vij,vj->v", w, sub, w)


def test_vertex_variance_is_the_quadratic_form_of_the_trilinear_weights(sphere):
    """vertex_variance (edge identification + two-weight formula) equals a^T C a with the
    8 trilinear weights of the vertex position, for the exact C."""
    band, C, edges = sphere["band"], sphere["C"], sphere["edges"]
    var, cov = exact_moments(C, sphere["system"].nbr)
    got = vertex_variance(band.ijk, var, cov, edges)
    grid = edges.axis >= 0
    assert grid.mean() > 0.95 and np.all(np.isfinite(got[grid]))
    assert np.all(np.isnan(got[~grid]))  # cell-centre vertices: left to the caller
    want = quadratic_form(C, band.ijk, sphere["post"].voxel_size, sphere["verts"][grid])
    # float32 vertex positions: t is known to ~1e-6 voxel
    np.testing.assert_allclose(got[grid], want, rtol=1e-4)


def test_probe_estimate_of_the_vertex_variance_against_exact(sphere):
    """The default probes (coloring, K = solver.probes = 16) give the vertex variance to a few
    per cent; leaving out the covariances (cov = 0) is several times worse. Measured here
    (seeds 0, 1, 2): median 6.1-6.5 %, p90 23-25 % relative error of the vertex variance, half
    that of sigma (K = 32: median 2.8-3.1 %, p90 11-12 %; cov = 0: median 22-23 %, p90
    48-50 %). This coarse, sparse sphere (3 cm voxels, 8 views of 80x60) is the hard case:
    docs/measurements.md has larger scenes."""
    band, system, edges, C = sphere["band"], sphere["system"], sphere["edges"], sphere["C"]
    var_x, cov_x = exact_moments(C, system.nbr)
    exact = vertex_variance(band.ijk, var_x, cov_x, edges)
    ok = np.isfinite(exact)
    var, cov, stats = estimate_variance(system, sphere["cfg"].solver, band.ijk)
    assert cov.shape == (len(band.ijk), 3) and cov.dtype == np.float32
    assert np.all(cov[system.nbr[:, list(FACE_PLUS)] < 0] == 0)
    rel = np.abs(vertex_variance(band.ijk, var, cov, edges)[ok] / exact[ok] - 1)
    assert np.median(rel) < 0.09 and np.percentile(rel, 90) < 0.32
    no_cov = np.abs(vertex_variance(band.ijk, var, 0 * cov, edges)[ok] / exact[ok] - 1)
    assert np.median(no_cov) > 2 * np.median(rel)  # the covariances matter
    # per neighbour pair (not only through the vertices): the estimate tracks the exact
    pairs = system.nbr[:, list(FACE_PLUS)] >= 0
    r = np.corrcoef(cov[pairs], cov_x[pairs])[0, 1]
    assert r > 0.95


def test_sampled_blend_against_its_exact_value(sphere):
    """``solver.variance = "blend-sampled"``: ``S + (1 - rho) (B - S)`` with
    ``S = Q^-1 D Q^-1`` (D a box data term of weights W, made part of Q), ``B = Q^-1``,
    ``rho = D_ii / Q_ii``, against the dense product. The sandwich is Monte Carlo
    (``perturbation_moments``), so K = 64 here: measured median 1.5 %, p90 16 % relative error
    of the blend (K = 16: 7 %, 34 %), with the data's share ``rho`` 0.08 / 0.32 / 0.90 (5th
    percentile / median / 95th)."""
    from dataclasses import replace

    from kernels.layout import CENTRE

    band, system = sphere["band"], sphere["system"]
    rng = np.random.default_rng(4)
    q0 = system.S[:, CENTRE].astype(np.float64)
    W = (q0 * rng.uniform(0.0, 3.0, len(q0))).astype(np.float32)
    W[rng.random(len(q0)) < 0.2] = 0  # voxels the data do not reach
    D = box_data_term(band.ijk, W)
    S = system.S.astype(np.float64).copy()  # Q + D as a stencil: D lies within the 27 offsets
    rows, offs = np.nonzero(system.nbr >= 0)
    S[rows, offs] += D[rows, system.nbr[rows, offs]]
    assert np.allclose(S.sum(), system.S.sum(dtype=np.float64) + D.sum())
    both = replace(system, S=S.astype(np.float32))
    C = np.linalg.inv(to_csr(both.S, both.nbr, both.far).toarray())
    sandwich, bayes = np.diag(C @ D @ C), np.diag(C)
    D_ii = np.diag(D)
    rho = D_ii / both.S[:, CENTRE]
    exact = sandwich + (1 - rho) * (bayes - sandwich)
    solver = replace(sphere["cfg"].solver, variance="blend-sampled", probes=64)
    var, cov, stats = estimate_variance(both, solver, band.ijk, data=(W, D_ii))
    assert stats["converged"] and "perturbation" in stats
    rel = np.abs(var / exact - 1)
    assert np.median(rel) < 0.04 and np.percentile(rel, 90) < 0.25, np.percentile(rel, [50, 90])
    assert np.all(sandwich <= bayes) and np.all(exact <= bayes)  # D <= Q: the noise's share
    prior_held = rho < 0.1  # there the blend keeps the Bayesian variance
    assert prior_held.sum() > 50
    assert np.median(np.abs(var[prior_held] / bayes[prior_held] - 1)) < 0.1
    pairs = both.nbr[:, list(FACE_PLUS)]
    bound = np.sqrt(var[:, None] * np.where(pairs >= 0, var[np.maximum(pairs, 0)], 0))
    assert np.all(np.abs(cov) <= bound * (1 + 1e-5))


def test_blend_is_exact_for_independent_voxels_and_scales_the_probes(sphere):
    """``solver.variance = "blend"`` (the default): ``var = B (1 - rho + rho^2)``, the blend
    ``S + (1 - rho) (B - S)`` with ``S_ii = rho_i B_ii``. That ``S`` is exact where the voxels
    are independent (Q diagonal: ``S = d / q^2``), checked here on a diagonal system; on the
    sphere the blend is the probes' variance and covariances scaled by ``F^1/2 . F^1/2``."""
    from dataclasses import replace

    from bftaichi.stages.prior import System
    from kernels.layout import CENTRE

    rng = np.random.default_rng(2)
    n = 500
    d, p = rng.uniform(0, 4, n), rng.uniform(0.1, 2, n)  # data and prior precision per voxel
    S = np.zeros((n, 27), np.float32)
    S[:, CENTRE] = d + p
    nbr = np.full((n, 27), -1, np.int32)
    nbr[:, CENTRE] = np.arange(n)
    ijk = np.stack([np.arange(n) * 3, np.zeros(n, int), np.zeros(n, int)], 1).astype(np.int32)
    diagonal = System(S=S, nbr=nbr, h=np.zeros(n, np.float32), far=None)
    solver = replace(sphere["cfg"].solver, variance="blend")
    var, _, stats = estimate_variance(diagonal, solver, ijk, data=(None, d))
    q = (d + p).astype(np.float32).astype(np.float64)
    sandwich, bayes = d / q ** 2, 1 / q
    exact = sandwich + (p / q) * (bayes - sandwich)
    np.testing.assert_allclose(var, exact, rtol=1e-4)
    assert "local data share" in stats["method"]
    # frames that share their noise (kappa, sharednoise.shared_noise_factor) scale the
    # sandwich, the data's part, and leave the prior's
    kappa = rng.uniform(1, 30, n)
    var, _, _ = estimate_variance(diagonal, solver, ijk, data=(None, d), kappa=kappa)
    np.testing.assert_allclose(var, kappa * sandwich + (p / q) * (bayes - sandwich), rtol=1e-4)

    band, system = sphere["band"], sphere["system"]
    D_ii = system.S[:, CENTRE] * rng.uniform(0, 1, len(band.ijk)).astype(np.float32)
    b_var, b_cov, _ = estimate_variance(system, sphere["cfg"].solver, band.ijk)
    var, cov, _ = estimate_variance(system, solver, band.ijk, data=(None, D_ii))
    rho = D_ii.astype(np.float64) / system.S[:, CENTRE]
    f = 1 - rho + rho ** 2
    np.testing.assert_allclose(var, b_var * f, rtol=1e-5)
    j = system.nbr[:, FACE_PLUS[0]]
    m = j >= 0
    np.testing.assert_allclose(cov[m, 0], b_cov[m, 0] * np.sqrt(f[m] * f[j[m]]), rtol=1e-4,
                               atol=1e-12)
    assert np.all(var <= b_var) and np.all(var >= 0.75 * b_var - 1e-12)  # f in [3/4, 1]


def test_sigma_is_below_the_interpolated_bound_and_sigma_pos_follows_the_gradient(sphere):
    post, verts = sphere["post"], sphere["verts"]
    mesh = post.extract_mesh()
    np.testing.assert_array_equal(mesh.vertices, verts)
    sigma = mesh.vertex_attributes["sigma"].astype(np.float64)
    sigma_pos = mesh.vertex_attributes["sigma_pos"].astype(np.float64)
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0) and np.all(sigma_pos > 0)
    everywhere = np.ones(len(post.ijk), bool)
    bound = np.sqrt(sample_field(post.ijk, post.var, everywhere, post.voxel_size, verts))
    assert np.mean(sigma <= bound * (1 + 1e-4)) > 0.99
    assert np.median(sigma / bound) < 0.95  # strictly below for most: correlations count
    grad = np.linalg.norm(sample_gradient(post.ijk, post.mean, everywhere, post.voxel_size,
                                          verts), axis=1)
    assert 0.7 < np.median(grad) < 1.3  # a posterior SDF has about unit slope
    flat = grad <= 1
    assert flat.any() and np.all(sigma_pos[flat] >= sigma[flat] * (1 - 1e-6))
    g = np.maximum(np.nan_to_num(grad, nan=1.0), MIN_GRADIENT)
    np.testing.assert_allclose(sigma_pos, sigma / g, rtol=1e-5)


def test_band_npz_round_trip_keeps_cov_and_an_old_band_still_loads(sphere, tmp_path):
    post = sphere["post"]
    out = post.save(tmp_path / "new")
    back = Posterior.load(out / "band.npz")
    np.testing.assert_array_equal(back.cov, post.cov)
    v, _, extra = read_mesh_ply(out / "mesh.ply")
    assert list(extra) == ["sigma", "sigma_pos"]
    np.testing.assert_array_equal(extra["sigma"], back.extract_mesh().vertex_attributes["sigma"])
    # a band.npz of an older version: no cov; sigma falls back to the interpolated bound
    arrays = post.band_arrays()
    del arrays["cov"]
    np.savez(tmp_path / "old.npz", **arrays)
    old = Posterior.load(tmp_path / "old.npz")
    assert old.cov is None
    mesh = old.extract_mesh()
    bound = np.sqrt(sample_field(old.ijk, old.var, np.ones(len(old.ijk), bool),
                                 old.voxel_size, mesh.vertices))
    np.testing.assert_allclose(mesh.vertex_attributes["sigma"], bound, rtol=1e-6)
    assert np.median(extra["sigma"] / bound) < 0.95  # the new sigma differs from the fallback
    arrays["cov"] = np.zeros((3, 3), np.float32)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(DataError, match="cov"):
        Posterior.load(tmp_path / "bad.npz")


def test_prior_bias_estimates_the_maps_bias(sphere):
    """``solver.prior_bias``: on data the model itself generates from a known field (``h = D
    x + b0``, no noise; ``x`` the sphere's signed distance), the MAP sits ``mu - x = -Q^-1 (P
    x - b0)`` from the truth, the prior's pull on the curved surface. The estimate from the
    mean alone, ``-Q^-1 (P mu - b0)`` (:func:`~bftaichi.stages.solve.prior_bias`), is that
    solve to its tolerance, and on the voxels around the surface points the way the actual
    bias does (measured: cosine 0.96, relative error 38 %; no estimate, 0, is 100 % off),
    with less of its size (70 %: the mean is smoother than the truth, so ``P mu`` is smaller
    than ``P x``)."""
    from bftaichi.stages.prior import prior_terms
    from bftaichi.stages.solve import prior_bias

    band, system, post, cfg, C = (sphere[k] for k in ("band", "system", "post", "cfg", "C"))
    vs = cfg.tsdf.voxel_size_m
    x = np.linalg.norm(post.origin + (band.ijk + 0.5) * vs, axis=1) - 0.15
    P = np.zeros_like(system.S)
    b0, far = prior_terms(P, band, cfg.prior, cfg.band.stencil, vs)
    Pm = to_csr(P, band.nbr, far)
    D = to_csr(system.S, system.nbr, system.far) - Pm
    mu = C @ (D @ x + b0)
    actual = mu - x
    est, stats = prior_bias(system, band, cfg.prior, cfg.band.stencil, vs, mu, cfg.solver)
    assert stats["converged"] and stats["iterations"] > 0
    exact = -C @ (Pm @ mu - b0)
    assert np.linalg.norm(est - exact) <= 1e-2 * np.linalg.norm(exact)
    near = np.abs(x) < vs
    assert np.linalg.norm(actual[near]) > 1e-4 * vs * np.sqrt(near.sum())  # a bias to find
    rel = np.linalg.norm(est[near] - actual[near]) / np.linalg.norm(actual[near])
    cos = est[near] @ actual[near] / np.linalg.norm(est[near]) / np.linalg.norm(actual[near])
    ratio = np.linalg.norm(est[near]) / np.linalg.norm(actual[near])
    assert cos > 0.9 and rel < 0.5 and 0.5 < ratio <= 1.0, (cos, rel, ratio)


def test_bias_solve_on_the_maps_layout_equals_a_fresh_one(sphere):
    """``prior_bias`` solves on the compact layout ``solve_map`` leaves (``System.compact``,
    its free-space anchors taken out again) instead of building one: the same bits as a
    layout built from the system afresh, after a MAP that did anchor voxels."""
    import dataclasses

    from bftaichi.stages.solve import prior_bias, solve_map

    band, system, cfg = (sphere[k] for k in ("band", "system", "cfg"))
    vs = cfg.tsdf.voxel_size_m
    run = dataclasses.replace(system, S=system.S.copy(), h=system.h.copy(), compact=None)
    mean, stats = solve_map(run, band.tsdf.astype(np.float64), cfg.solver, band,
                            trunc_m=cfg.tsdf.trunc_m, voxel_size_m=vs, free=cfg.prior.free,
                            bootstrap_trunc_m=cfg.tsdf.bootstrap_trunc_m)
    assert stats["free_space"]["anchored"] > 0 and run.compact is not None
    fresh = dataclasses.replace(run, compact=None)
    reused, _ = prior_bias(run, band, cfg.prior, cfg.band.stencil, vs, mean, cfg.solver)
    assert run.compact is None  # let go after the solve
    built, _ = prior_bias(fresh, band, cfg.prior, cfg.band.stencil, vs, mean, cfg.solver)
    assert reused.tobytes() == built.tobytes()
