"""kernels/pcg.py against exact sparse algebra: the stencil Q·x vs a scipy CSR matrix assembled
independently from the same raw terms, PCG vs spsolve, probe variance vs the exact diag(Q^-1).

The test problem is built here with numpy: a spherical-shell band (voxel units), its
neighbour table from a dict (reference), and a posterior precision made of a membrane prior
(lambda / |offset|^2 on the 26-neighbour edges, each edge once), a data term of random
trilinear observations (8 corners of one cell, all in the band, only near the surface, as
observations within +-tau are), and eps * I. The same raw terms go into the 27-point stencil
S (numpy scatter by offset) and, separately, into a CSR matrix (coo triplets).
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from kernels import pcg as kp
from kernels.compact import CompactStencil
from kernels.probes import (box_perturbations, coloring_lattice, perturbation_moments,
                            probe_variance, probe_vectors)
from kernels.stencil import apply_Q, apply_Q_batched, check_stencil
from conftest import box_data_term

ROOT = Path(__file__).resolve().parents[1]

# Offsets written out from the contract: o = (di+1)*9 + (dj+1)*3 + (dk+1).
OFFS = [(di, dj, dk) for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1)]
CORNERS = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])


def shell_band(radius: float, half_width: float):
    """Voxels whose centre (ijk + 0.5) lies within ``half_width`` of a sphere of ``radius``
    (voxel units) about the origin: ijk (N, 3) int32 in lexicographic order, signed distance."""
    m = int(np.ceil(radius + half_width)) + 1
    g = np.arange(-m, m + 1)
    ijk = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    d = np.linalg.norm(ijk + 0.5, axis=1) - radius
    keep = np.abs(d) < half_width
    return ijk[keep].astype(np.int32), d[keep]


def nbr_reference(ijk):
    """Neighbour table from a dict lookup (the reference for the vectorised builders)."""
    index = {v: n for n, v in enumerate(map(tuple, ijk.tolist()))}
    return np.array([[index.get((i + di, j + dj, k + dk), -1) for di, dj, dk in OFFS]
                     for i, j, k in ijk.tolist()], dtype=np.int32)


def posterior(ijk, dist, nbr, lam=1.0, obs_per_voxel=2.0, w_obs=4.0, eps=1e-6, seed=0):
    """Raw prior and data terms -> (S float32 stencil, Q float64 CSR of the same S, h).

    Q is assembled twice from the raw terms: as the stencil (scatter by offset) and as coo
    triplets; the CSR returned is the coo one with its values rounded to float32 (the storage
    precision of S), so both describe the identical matrix."""
    rng = np.random.default_rng(seed)
    n = len(ijk)
    # membrane prior: each undirected edge once (forward offsets o > 13)
    e_i, e_o = np.nonzero(nbr[:, 14:] >= 0)
    e_o += 14
    e_j = nbr[e_i, e_o]
    e_w = lam / np.abs(np.array(OFFS)[e_o]).sum(axis=1)  # 1/|offset|^2 = 1/(number of nonzeros)
    # data: cells (lower corner = a band voxel near the surface) whose 8 corners are in the band
    corner_o = [OFFS.index(tuple(c)) for c in CORNERS]
    cell_ok = (nbr[:, corner_o] >= 0).all(axis=1) & (np.abs(dist) < 1.5)
    cells = np.flatnonzero(cell_ok)
    m = int(obs_per_voxel * len(cells))
    lower = cells[rng.integers(0, len(cells), m)]
    t = rng.random((m, 3))
    a = np.prod(np.where(CORNERS[None], t[:, None], 1 - t[:, None]), axis=2)  # (m, 8) trilinear
    corners = nbr[lower][:, corner_o]  # (m, 8) band indices
    w = w_obs * rng.uniform(0.5, 2.0, m)
    y = rng.normal(0.0, 1.0, m)

    # stencil form: S[i, o] by scatter-add
    S = np.zeros(n * 27)
    np.add.at(S, e_i * 27 + e_o, -e_w)
    np.add.at(S, e_j * 27 + (26 - e_o), -e_w)
    np.add.at(S, e_i * 27 + 13, e_w)
    np.add.at(S, e_j * 27 + 13, e_w)
    d_off = CORNERS[None, :, :] - CORNERS[:, None, :]  # (8, 8, 3) offset from corner a to b
    o_ab = (d_off[..., 0] + 1) * 9 + (d_off[..., 1] + 1) * 3 + (d_off[..., 2] + 1)
    vals = w[:, None, None] * a[:, :, None] * a[:, None, :]
    np.add.at(S, (corners[:, :, None] * 27 + o_ab[None]).ravel(), vals.ravel())
    S = S.reshape(n, 27)
    S[:, 13] += eps
    S = S.astype(np.float32)
    h = np.zeros(n)
    np.add.at(h, corners.ravel(), (w[:, None] * y[:, None] * a).ravel())

    # coo triplets of the same raw terms
    rows = np.concatenate([e_i, e_j, e_i, e_j, np.repeat(corners, 8, axis=1).ravel(),
                           np.arange(n)])
    cols = np.concatenate([e_j, e_i, e_i, e_j, np.tile(corners, (1, 8)).ravel(), np.arange(n)])
    data = np.concatenate([-e_w, -e_w, e_w, e_w, vals.ravel(), np.full(n, eps)])
    Q = sp.coo_matrix((data, (rows, cols)), shape=(n, n)).tocsr()
    Q.sum_duplicates()
    Q.data = Q.data.astype(np.float32).astype(np.float64)
    return S, Q, h


@pytest.fixture(scope="module")
def small():
    """~3k-voxel shell (radius 6, 6 voxels thick) with its exact diag(Q^-1): a dense LAPACK
    inverse (~3x faster here than splu column solves, same result to 1e-15)."""
    ijk, dist = shell_band(6.0, 3.0)
    nbr = nbr_reference(ijk)
    S, Q, h = posterior(ijk, dist, nbr)
    exact = np.diag(np.linalg.inv(Q.toarray()))
    return dict(ijk=ijk, dist=dist, nbr=nbr, S=S, Q=Q, h=h, exact=exact)


@pytest.fixture(scope="module")
def large():
    """~20k-voxel shell (radius 15, 7 voxels thick) for the Q·x comparison."""
    ijk, dist = shell_band(15.0, 3.5)
    nbr = nbr_reference(ijk)
    S, Q, h = posterior(ijk, dist, nbr, seed=1)
    return dict(ijk=ijk, nbr=nbr, S=S, Q=Q)


def rel(a, b):
    return float(np.linalg.norm(np.asarray(a, np.float64) - b) / np.linalg.norm(b))


def median_rel(s, exact):
    return float(np.median(np.abs(s / exact - 1.0)))


# -- Q x ---------------------------------------------------------------------------------------

def test_stencil_matches_csr_assembled_independently(large):
    S, nbr, Q = large["S"], large["nbr"], large["Q"]
    n = len(S)
    assert n > 15000 and (nbr == -1).any()  # a band with boundaries, not a full box
    rng = np.random.default_rng(3)
    x64 = rng.standard_normal(n)
    x32 = x64.astype(np.float32)
    assert rel(apply_Q(S, nbr, x64), Q @ x64) < 1e-5
    out = np.zeros(n, np.float32)
    assert apply_Q(S, nbr, x32, out) is out
    assert rel(out, Q @ x32.astype(np.float64)) < 1e-5
    # batched: 16 vectors in one block, and 20 as two blocks of 10
    for k in (16, 20):
        X = rng.standard_normal((n, k)).astype(np.float32)
        Y = apply_Q_batched(S, nbr, X)
        ref = Q @ X.astype(np.float64)
        assert max(rel(Y[:, c], ref[:, c]) for c in range(k)) < 1e-5
        # the solver's padded layout (zero first row, voxel i in row i+1) gives the same
        Xp = np.concatenate([np.zeros((1, k), np.float32), X])
        Yp = np.full_like(Xp, np.nan)
        apply_Q_batched(S, nbr, Xp, Yp, padded=True)
        assert np.array_equal(Yp[1:], Y) and not Yp[0].any()


def test_compact_columns_are_the_near_offsets_column_by_column():
    """The compact layout's column table: column c's three offsets are (di, dj, -1..1) of
    _COLUMNS[c], and every offset but the centre has its own presence bit."""
    from kernels.compact import _BIT, _COLUMN_OFFSETS, _COLUMNS
    from kernels.layout import CENTRE, stencil_offset

    for (di, dj), offsets in zip(_COLUMNS, _COLUMN_OFFSETS):
        assert [stencil_offset(o) for o in offsets] == [(di, dj, dk) for dk in (-1, 0, 1)]
    bits = [_BIT[o] for o in range(27) if o != CENTRE]
    assert sorted(bits) == list(range(26))


def test_compact_product_matches_csr_on_a_band_with_gaps(large):
    """The solvers' single-vector product (CompactStencil: upper half of S, presence bits,
    SIMD sub-runs) equals the CSR matrix, with the curvature prior's far part, on a band
    with holes punched in it (sub-runs split by gaps, rows summed one at a time)."""
    from kernels.prior import add_curvature_prior
    rng = np.random.default_rng(5)
    ijk, dist = shell_band(15.0, 3.5)
    keep = rng.random(len(ijk)) > 0.03  # scattered holes: gaps inside neighbour columns
    ijk, dist = ijk[keep], dist[keep]
    nbr = nbr_reference(ijk)
    S, _, _ = posterior(ijk, dist, nbr, seed=2)
    S2, nbr2 = add_curvature_prior(S, nbr, lam2=0.5)  # adds its near entries into S
    r, o = np.nonzero(nbr >= 0)
    Q_near = sp.csr_matrix((S[r, o].astype(np.float64), (r, nbr[r, o])), shape=(len(S),) * 2)
    i, a = np.nonzero(nbr2 >= 0)
    Q_far = sp.csr_matrix((S2[i, a].astype(np.float64), (i, nbr2[i, a])), shape=Q_near.shape)
    for far in (None, (S2, nbr2)):
        op = CompactStencil(S, nbr, far)
        assert 0 < op.scalar_rows < len(S) / 4  # both paths (SIMD sub-runs, single rows) run
        assert op.nbytes < 216 * len(S)  # smaller than (S, nbr), even with many gaps
        Qf = Q_near if far is None else Q_near + Q_far
        x64 = rng.standard_normal(len(S))
        assert rel(op.apply(x64), Qf @ x64) < 1e-12
        x32 = x64.astype(np.float32)
        assert rel(op.apply(x32), Qf @ x32.astype(np.float64)) < 1e-5
        assert rel(op.apply(x32), apply_Q(S, nbr, x32, far=far)) < 1e-6
        # padded (the solvers' layout) and deterministic
        xp = np.concatenate([[0.0], x64])
        yp = np.full_like(xp, np.nan)
        op.apply(xp, yp, padded=True)
        assert yp[0] == 0 and np.array_equal(yp[1:], op.apply(x64))
        # a non-finite x gives the exact product's inf/nan pattern (no 0 * inf = nan leak)
        x_inf = x64.copy()
        x_inf[100] = np.inf
        y = op.apply(x_inf)
        np.testing.assert_array_equal(np.isfinite(y),
                                      np.isfinite(apply_Q(S, nbr, x_inf, far=far)))
    with pytest.raises(ValueError, match="shape"):
        op.apply(np.zeros(len(S) + 1))


def test_compact_diagonal_update_equals_a_rebuild(small):
    """The MAP's free-space passes change only Q's diagonal and reuse one layout
    (set_diagonal): the product and the PCG solution are bitwise those of a layout built
    from scratch on the changed stencil."""
    rng = np.random.default_rng(11)
    S, nbr, h = small["S"].copy(), small["nbr"], small["h"]
    op = CompactStencil(S, nbr)
    anchored = rng.random(len(S)) < 0.2
    S[anchored, 13] += 50.0
    op.set_diagonal(S[:, 13])
    fresh = CompactStencil(S, nbr)
    x = rng.standard_normal(len(S))
    assert np.array_equal(op.apply(x), fresh.apply(x))
    x_reuse, info_reuse = kp.pcg(S, nbr, h, tol=1e-8, maxiter=500, compact=op)
    x_fresh, info_fresh = kp.pcg(S, nbr, h, tol=1e-8, maxiter=500)
    assert np.array_equal(x_reuse, x_fresh) and info_reuse == info_fresh
    assert info_fresh["converged"]
    with pytest.raises(ValueError, match="positive"):
        op.set_diagonal(-S[:, 13])


def test_compact_refill_equals_a_rebuild(large):
    """The robust prior's reweighting changes the stencil's values, near and far, not its
    neighbours; the MAP refills one layout (refill): products bitwise those of a fresh
    build, and the exact path (non-finite x) sees the new values too."""
    from kernels.prior import add_curvature_prior
    rng = np.random.default_rng(12)
    S, nbr = large["S"].copy(), large["nbr"]
    S2, nbr2 = add_curvature_prior(S, nbr, lam2=0.5)
    op = CompactStencil(S, nbr, (S2, nbr2))
    S_new, S2_new = S * np.float32(0.7), S2 * np.float32(0.4)  # still symmetric
    S_new[:, 13] += 1.0
    op.refill(S_new, (S2_new, nbr2))
    fresh = CompactStencil(S_new, nbr, (S2_new, nbr2))
    x = rng.standard_normal(len(S))
    assert np.array_equal(op.apply(x), fresh.apply(x))
    assert not np.array_equal(op.apply(x), CompactStencil(S, nbr, (S2, nbr2)).apply(x))
    x[7] = np.inf
    np.testing.assert_array_equal(np.isfinite(op.apply(x)),
                                  np.isfinite(apply_Q(S_new, nbr, x, far=(S2_new, nbr2))))
    with pytest.raises(ValueError, match="far"):
        op.refill(S_new)
    with pytest.raises(ValueError, match="shape"):
        op.refill(S_new[:-1], (S2_new, nbr2))


def test_compact_rows_of_the_product_are_those_of_the_whole_product(large):
    """The MAP's local passes need Q x on a region only (apply_rows): bit for bit the whole
    product's rows there, for regions of single rows, blocks and most of the band, and after
    a diagonal change given for some rows only (set_diagonal(diag, rows))."""
    from kernels.prior import add_curvature_prior
    rng = np.random.default_rng(13)
    S, nbr = large["S"].copy(), large["nbr"]
    S2, nbr2 = add_curvature_prior(S, nbr, lam2=0.5)
    op = CompactStencil(S, nbr, (S2, nbr2))
    x = rng.standard_normal(len(S))
    for rows in (np.array([0]), np.array([len(S) - 1]), np.arange(40, 90),
                 np.flatnonzero(rng.random(len(S)) < 0.6), np.arange(len(S))):
        assert np.array_equal(op.apply_rows(x, rows), op.apply(x)[rows])
    some = np.flatnonzero(rng.random(len(S)) < 0.1)
    S[some, 13] += 7.0
    op.set_diagonal(S[:, 13], some)
    fresh = CompactStencil(S, nbr, (S2, nbr2))
    assert np.array_equal(op.apply(x), fresh.apply(x))
    assert np.array_equal(op.apply_rows(x, some), fresh.apply(x)[some])
    y = rng.standard_normal(len(S))  # the kept vectors hold nothing of the last call
    assert np.array_equal(op.apply_rows(y, np.arange(40, 90)), fresh.apply(y)[40:90])
    op.drop_scratch()
    assert np.array_equal(op.apply_rows(x, some), fresh.apply(x)[some])


def test_principal_submatrix_is_q_on_the_rows(large):
    """The local passes' system: Q's rows and columns of a region, neighbours renumbered
    within it (the numpy gathers' arrays exactly), so that Q_rr x_r = (Q x)[rows] for x zero
    outside the region; the scratch comes back as it went in."""
    from bftaichi.stages.solve import _rings
    from kernels.prior import add_curvature_prior
    from kernels.submatrix import principal_submatrix
    rng = np.random.default_rng(5)
    S, nbr = large["S"], large["nbr"]
    far = add_curvature_prior(S.copy(), nbr, lam2=0.5)
    loc = np.full(len(S) + 1, -1, np.int32)
    for rows in (np.array([7]), _rings(nbr, np.array([100, 2000]), 2),
                 np.flatnonzero(rng.random(len(S)) < 0.3), np.arange(len(S))):
        S_r, nbr_r, far_r = principal_submatrix(S, nbr, far, rows, loc)
        assert (loc == -1).all()
        ref = np.full(len(S) + 1, -1, np.int32)
        ref[rows] = np.arange(len(rows))
        for got, links, (coef, table) in ((nbr_r, S_r, (S, nbr)), (far_r[1], far_r[0], far)):
            want = ref[table[rows]]
            assert np.array_equal(got, want)
            assert np.array_equal(links, np.where(want >= 0, coef[rows], np.float32(0)))
        x = np.zeros(len(S))
        x[rows] = rng.standard_normal(len(rows))
        np.testing.assert_allclose(apply_Q(S_r, nbr_r, x[rows], far=far_r),
                                   apply_Q(S, nbr, x, far=far)[rows], rtol=1e-12, atol=1e-12)


def test_rings_of_a_region_are_the_breadth_first_neighbourhood(large):
    """The local passes' region: every voxel within r 26-neighbour steps of the seeds, once,
    sorted; the scratch comes back as it went in."""
    from bftaichi.stages.solve import _rings
    nbr = large["nbr"]
    seeds = np.array([5, 5, 300, 301])
    mark = np.full(len(nbr), -1, np.int32)
    for r in (0, 1, 3):
        seen, front = set(seeds.tolist()), set(seeds.tolist())
        for _ in range(r):
            front = {int(j) for i in front for j in nbr[i] if j >= 0} - seen
            seen |= front
        region = _rings(nbr, seeds, r, mark)
        assert region.tolist() == sorted(seen)
        assert (mark == -1).all()


def test_bad_stencils_are_rejected(small):
    S, nbr = small["S"], small["nbr"]
    check_stencil(S, nbr)  # the valid one passes
    asym = S.copy()
    i, o = np.argwhere(nbr[:, :13] >= 0)[0]
    asym[i, o] *= 1.5
    with pytest.raises(ValueError, match="not symmetric"):
        kp.pcg(asym, nbr, small["h"])
    neg = S.copy()
    neg[5, 13] = -1.0
    with pytest.raises(ValueError, match="S\\[5, 13\\]"):
        probe_variance(neg, nbr, method="rademacher")
    one_way = nbr.copy()
    i, o = np.argwhere(nbr[:, 14:] >= 0)[0]
    one_way[i, o + 14] = -1  # its neighbour still links back
    with pytest.raises(ValueError, match="nbr is not symmetric"):
        check_stencil(S, one_way)
    out_of_range = nbr.copy()
    out_of_range[0, 0] = len(S)
    with pytest.raises(ValueError, match="outside"):
        check_stencil(S, out_of_range)
    with pytest.raises(ValueError, match=r"\(N, 27\)"):
        apply_Q(S[:, :26], nbr[:, :26], np.zeros(len(S)))
    with pytest.raises(ValueError, match="non-finite"):
        kp.pcg(S, nbr, np.full(len(S), np.nan))


# -- PCG ---------------------------------------------------------------------------------------

def test_pcg_matches_spsolve_and_reports_its_true_residual(small):
    S, nbr, Q, h = small["S"], small["nbr"], small["Q"], small["h"]
    exact = spla.spsolve(Q.tocsc(), h)
    x, info = kp.pcg(S, nbr, h, tol=1e-6)
    assert info["converged"] and info["reason"].startswith("converged")
    assert rel(x, exact) < 1e-4
    recomputed = np.linalg.norm(h - Q @ x) / np.linalg.norm(h)
    assert recomputed <= 1e-6
    assert info["relative_residual"] == pytest.approx(recomputed, rel=1e-6)
    assert info["residual_history"][-1] == info["relative_residual"]
    assert len(info["residual_history"]) == info["iterations"] + 1
    # a warm start near the answer needs fewer iterations (the TSDF warm start of the MAP)
    near = exact + 1e-3 * np.random.default_rng(0).standard_normal(len(h)) * np.abs(exact).mean()
    _, warm = kp.pcg(S, nbr, h, x0=near.astype(np.float32), tol=1e-6)
    assert warm["converged"] and warm["iterations"] < info["iterations"]


def test_pcg_never_reports_success_it_did_not_reach(small):
    S, nbr, Q, h = small["S"], small["nbr"], small["Q"], small["h"]
    x, info = kp.pcg(S, nbr, h, tol=1e-6, maxiter=3)
    assert not info["converged"] and info["iterations"] == 3 and "maxiter" in info["reason"]
    recomputed = np.linalg.norm(h - Q @ x) / np.linalg.norm(h)
    assert recomputed > 1e-6
    assert info["relative_residual"] == pytest.approx(recomputed, rel=1e-6)


def test_pcg_zero_rhs_and_breakdown():
    # 2 voxels (0,0,0), (0,0,1); Q = [[1, 2], [2, 1]] is symmetric with a positive diagonal
    # but indefinite: h = (1, -1) has h^T Q h < 0, so CG breaks down at once.
    nbr = np.full((2, 27), -1, np.int32)
    nbr[0, 13], nbr[1, 13], nbr[0, 14], nbr[1, 12] = 0, 1, 1, 0
    S = np.zeros((2, 27), np.float32)
    S[:, 13] = 1.0
    S[0, 14] = S[1, 12] = 2.0
    x, info = kp.pcg(S, nbr, np.array([1.0, -1.0]))
    assert not info["converged"] and "breakdown" in info["reason"]
    S[0, 14] = S[1, 12] = 0.5  # now positive definite
    x, info = kp.pcg(S, nbr, np.zeros(2), x0=np.ones(2, np.float32))
    assert info["converged"] and info["relative_residual"] == 0.0 and not x.any()


def test_pcg_stops_when_the_precision_is_exhausted(small):
    # float32 vectors cannot reach a 1e-9 residual: the solver must say so and stop early
    S, nbr, Q, h = small["S"], small["nbr"], small["Q"], small["h"]
    B = np.stack([h, -2.0 * h], axis=1)
    X, info = kp.pcg_batched(S, nbr, B, tol=1e-9, maxiter=500, dtype=np.float32)
    assert not info["converged"] and info["n_not_converged"] == 2
    col = info["columns"][0]
    assert "stagnated" in col["reason"] and col["iterations"] < 500 and col["restarts"] >= 2
    recomputed = np.linalg.norm(B - Q @ X.astype(np.float64), axis=0) / np.linalg.norm(B, axis=0)
    assert np.all(recomputed > 1e-9) and np.all(recomputed < 1e-5)


def test_pcg_is_deterministic(small):
    S, nbr, h = small["S"], small["nbr"], small["h"]
    x1, i1 = kp.pcg(S, nbr, h)
    x2, i2 = kp.pcg(S, nbr, h)
    assert np.array_equal(x1, x2) and i1 == i2


# -- probe variance ------------------------------------------------------------------------------

def test_probe_variance_converges_to_the_exact_diagonal(small):
    S, nbr, ijk, exact = small["S"], small["nbr"], small["ijk"], small["exact"]
    errors = {}
    for method in ("rademacher", "coloring"):
        for k in (4, 16, 64):
            s, info = probe_variance(S, nbr, n_probes=k, seed=0, method=method, ijk=ijk)
            assert info["converged"] and info["n_not_converged"] == 0
            assert len(info["iterations"]) == k
            errors[method, k] = median_rel(s, exact)
    for method in ("rademacher", "coloring"):
        assert errors[method, 4] > errors[method, 16] > errors[method, 64], errors
    assert min(errors["rademacher", 16], errors["coloring", 16]) <= 0.10, errors


def test_coloring_probes_separate_neighbours(small):
    ijk, nbr = small["ijk"], small["nbr"]
    for k in (8, 16, 64):
        Z = probe_vectors(len(ijk), k, seed=0, method="coloring", ijk=ijk)
        assert np.all(np.count_nonzero(Z, axis=1) == 1)  # every voxel in exactly one probe
        probe = np.argmax(Z != 0, axis=1)
        # no two of the 27 stencil neighbours share a probe
        has = nbr >= 0
        same = probe[:, None] == probe[np.where(has, nbr, 0)]
        same[:, 13] = False
        assert not (same & has).any()
        assert coloring_lattice(k)[2] >= 4  # same-colour voxels >= 2 voxels apart


def test_probe_variance_is_seeded_and_reports_unconverged_probes(small):
    S, nbr, ijk = small["S"], small["nbr"], small["ijk"]
    for method in ("rademacher", "coloring"):
        a, info_a = probe_variance(S, nbr, n_probes=8, seed=7, method=method, ijk=ijk)
        b, info_b = probe_variance(S, nbr, n_probes=8, seed=7, method=method, ijk=ijk)
        c, _ = probe_variance(S, nbr, n_probes=8, seed=8, method=method, ijk=ijk)
        assert np.array_equal(a, b) and info_a == info_b and not np.array_equal(a, c)
    _, info = probe_variance(S, nbr, n_probes=8, method="rademacher", maxiter=2)
    assert not info["converged"] and info["n_not_converged"] == 8
    assert info["iterations"] == [2] * 8 and min(info["relative_residuals"]) > 1e-4
    with pytest.raises(ValueError, match="ijk"):
        probe_variance(S, nbr, n_probes=8, method="coloring")


# -- perturbation (sandwich) variance --------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny():
    """~500-voxel shell, a data weight on most voxels, and its exact box data term."""
    ijk, dist = shell_band(3.5, 2.0)
    nbr = nbr_reference(ijk)
    W = np.random.default_rng(3).uniform(0.5, 2.0, len(ijk))
    W[np.abs(dist) > 1.2] = 0.0  # voxels far from the surface observe nothing
    return dict(ijk=ijk, nbr=nbr, W=W.astype(np.float32), D=box_data_term(ijk, W))


def test_box_perturbations_have_the_box_data_term_as_covariance(tiny):
    D, errors = tiny["D"], []
    for K in (1500, 6000):
        Z = box_perturbations(tiny["nbr"], tiny["W"], K, seed=1).astype(np.float64)
        C = Z @ Z.T / K
        errors.append((rel(C[D != 0], D[D != 0]), rel(np.diag(C), np.diag(D))))
    # unbiased: the error is sampling error, halving with 4x the draws (measured 0.10 -> 0.049
    # over all entries, 0.031 -> 0.016 on the diagonal)
    assert errors[1][0] < 0.07 and errors[1][1] < 0.025, errors
    assert errors[1][0] < 0.65 * errors[0][0], errors
    assert np.array_equal(Z, box_perturbations(tiny["nbr"], tiny["W"], 6000, seed=1))


def test_perturbation_moments_estimate_the_sandwich(small):
    """diag(Q^-1 D Q^-1) and its face entries against the exact dense product."""
    S, nbr, ijk, Q = small["S"], small["nbr"], small["ijk"], small["Q"].toarray()
    W = np.random.default_rng(5).uniform(0.0, 4.0, len(ijk)).astype(np.float32)
    Qi = np.linalg.inv(Q)
    exact = Qi @ box_data_term(ijk, W) @ Qi
    errors = []
    for k in (4, 16, 64):
        s, cov, info = perturbation_moments(S, nbr, W, n_probes=k, seed=0)
        assert info["converged"] and info["method"] == "perturbation"
        errors.append(median_rel(s, np.diag(exact)))
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.15, errors
    j = nbr[:, 22]  # the +x neighbour
    m = j >= 0
    assert rel(cov[m, 0], exact[np.flatnonzero(m), j[m]]) < 0.3
    again = perturbation_moments(S, nbr, W, n_probes=64, seed=0)
    assert np.array_equal(s, again[0]) and np.array_equal(cov, again[1])


# -- tools/bench_core.py ---------------------------------------------------------------------------

def test_bench_core_runs_and_reports(tmp_path):
    out_json = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_core.py"), "--n", "20000",
                           "--repeats", "1", "--accuracy", "--acc-window", "8", "--json",
                           str(out_json)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for text in ("ns per band voxel", "CSR float32", "PCG MAP", "K=16 batched",
                 "| coloring |"):
        assert text in proc.stdout, text
    rep = json.loads(out_json.read_text())
    assert rep["pcg"]["converged"] and rep["band_voxels"] > 15000
    assert rep["ns_per_voxel"]["stencil_k16"] > 0 and rep["ratio_f32"] > 0


def test_compile_arguments_are_freed_and_later_calls_collect_nothing(monkeypatch):
    """Taichi 1.7 keeps a compiling call's arrays in a reference cycle:
    ``free_compile_arguments`` frees them, and once nothing was compiled since, it runs no
    garbage collection (a solve repeated in one process, a scan step, pays none)."""
    import weakref

    import taichi as ti

    from kernels import stencil

    @ti.kernel
    def fill(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in a:
            a[i] = 1.0

    big = np.zeros(100_000, np.float32)
    alive = weakref.ref(big)
    fill(big)  # compiles: the cycle holds big
    del big
    stencil.free_compile_arguments()
    assert alive() is None
    collections = []
    real = stencil.gc.collect
    monkeypatch.setattr(stencil.gc, "collect", lambda *a: collections.append(1) or real(*a))
    small = np.zeros(10, np.float32)
    fill(small)  # the same specialisation: nothing compiled
    stencil.free_compile_arguments()
    assert collections == [] and small[0] == 1.0

    @ti.kernel
    def fill_twice(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in a:
            a[i] = 2.0

    fill_twice(small)  # a new kernel compiles: the next call collects again
    stencil.free_compile_arguments()
    assert collections == [1]


def test_subruns_split_runs_where_a_column_changes_its_offset():
    """The compact layout's sub-runs against a row-by-row reference: a new one at each run's
    start, at and after a gap row, and where a column takes another offset than at its last
    defined row in the run; each sub-run's offsets are those of its first defining rows."""
    from kernels.subruns import subruns
    rng = np.random.default_rng(3)
    n, n_col = 3000, 5
    cont = rng.random(n) < 0.9
    cont[0] = False
    gap = rng.random(n) < 0.02
    defined = rng.random((n_col, n)) < 0.7
    value = np.where(defined, rng.integers(0, 3, (n_col, n)) * (rng.random((n_col, n)) < 0.05),
                     0).astype(np.int32)
    split = ~cont | gap
    split[1:] |= gap[:-1]
    last = [None] * n_col
    for i in range(n):
        if not cont[i]:
            last = [None] * n_col
        for c in range(n_col):
            if defined[c, i]:
                split[i] |= last[c] is not None and last[c] != value[c, i]
                last[c] = value[c, i]
    start = np.flatnonzero(split)
    ends = np.append(start[1:], n)
    want = np.array([[next((value[c, i] for i in range(a, b) if defined[c, i]), 0)
                      for c in range(n_col)] for a, b in zip(start, ends)])
    got_start, got_length, got = subruns(cont, gap, value, defined)
    assert np.array_equal(got_start, start)
    assert np.array_equal(got_length, ends - start)
    assert np.array_equal(got, want)
    assert (got_length > 1).any() and len(start) > n // 10  # runs of both kinds were tested
