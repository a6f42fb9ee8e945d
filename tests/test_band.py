"""kernels.band.build_band on an analytic sphere exported like the bootstrap TSDF.

The scene: a sphere SDF (positive outside) sampled at voxel centres, clamped to +-tau_b and stored
in float32 like ``SparseTSDF.export()``; voxels deeper than tau_b inside are unobserved (absent),
as in a real export, and a cap of the sphere is missing altogether (never seen), so the band's
dilation reaches voxels with no input. References are independent numpy/scipy/dict code.
"""

import itertools

import numpy as np
import pytest
from scipy import ndimage

from kernels.band import MAX_ABS_IJK, MAX_DILATION, build_band
from kernels.layout import stencil_offsets
from kernels.lookup import build_block_table

VOXEL = 0.01  # metres
TAU_B = 0.027  # bootstrap truncation: 2.7 voxels (not a multiple of the voxel size)
CENTRE = np.array([0.031, -0.012, 0.047])
RADIUS = 0.083
HALF = 13  # the grid spans voxels -HALF..HALF-1 on each axis (around the sphere)


def sphere_export(shift=(0, 0, 0), seed=0):
    """Export-like arrays of the sphere: (ijk sorted, tsdf float32 clamped, weight, sdf float64).

    Observed = sdf >= -tau_b (the TSDF observes free space and tau_b behind the surface) and
    x < centre_x + 0.6 r (the cap beyond is missing); weights are random integers 1..9."""
    r = np.arange(-HALF, HALF)
    ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    centres = (ijk + 0.5) * VOXEL
    sdf = np.linalg.norm(centres - CENTRE, axis=1) - RADIUS
    keep = (sdf >= -TAU_B) & (centres[:, 0] < CENTRE[0] + 0.6 * RADIUS)
    ijk, sdf = ijk[keep], sdf[keep]
    weight = np.random.default_rng(seed).integers(1, 10, len(ijk)).astype(np.float32)
    tsdf = np.clip(sdf, -TAU_B, TAU_B).astype(np.float32)
    return (ijk + np.asarray(shift)).astype(np.int32), tsdf, weight, sdf


def dilate_reference(ijk_set: np.ndarray, iterations: int) -> set:
    """26-neighbour dilation of a voxel set, on a dense grid with scipy.ndimage."""
    lo = ijk_set.min(axis=0) - iterations
    shape = ijk_set.max(axis=0) - lo + 1 + iterations
    grid = np.zeros(shape, bool)
    grid[tuple((ijk_set - lo).T)] = True
    if iterations:
        grid = ndimage.binary_dilation(grid, structure=np.ones((3, 3, 3), bool),
                                       iterations=iterations)
    return {tuple(v) for v in (np.argwhere(grid) + lo).tolist()}


def as_set(ijk: np.ndarray) -> set:
    return {tuple(v) for v in ijk.tolist()}


@pytest.fixture(scope="module")
def sphere():
    ijk, tsdf, weight, sdf = sphere_export()
    # precondition: no voxel within 1e-6 m of the truncation, so float32 cannot move it
    assert np.abs(np.abs(sdf) - TAU_B).min() > 1e-6
    return ijk, tsdf, weight, sdf, build_band(ijk, tsdf, weight, TAU_B)


def test_core_is_exactly_the_unclamped_observed_voxels(sphere):
    ijk, tsdf, weight, sdf, band = sphere
    expected = as_set(ijk[np.abs(sdf) < TAU_B])
    assert as_set(band["ijk"][band["core"]]) == expected
    assert 1000 < len(expected) < len(band["ijk"])


@pytest.mark.parametrize("dilation", [0, 1, 2])
def test_band_is_the_core_dilated_by_26_neighbours(sphere, dilation):
    ijk, tsdf, weight, sdf, _ = sphere
    band = build_band(ijk, tsdf, weight, TAU_B, dilation=dilation)
    expected = dilate_reference(ijk[np.abs(sdf) < TAU_B], dilation)
    assert as_set(band["ijk"]) == expected
    assert len(band["ijk"]) == len(expected)  # no duplicates


def test_band_order_is_lexicographic(sphere):
    ijk = sphere[4]["ijk"].astype(np.int64)
    d = np.diff(ijk, axis=0)
    increasing = (d[:, 0] > 0) | ((d[:, 0] == 0)
                                  & ((d[:, 1] > 0) | ((d[:, 1] == 0) & (d[:, 2] > 0))))
    assert increasing.all()


def test_neighbour_table_matches_a_dictionary(sphere):
    band = sphere[4]
    index = {v: n for n, v in enumerate(as_list(band["ijk"]))}
    expected = np.array([[index.get((v[0] + di, v[1] + dj, v[2] + dk), -1)
                          for di, dj, dk in itertools.product((-1, 0, 1), repeat=3)]
                         for v in as_list(band["ijk"])], np.int32)
    np.testing.assert_array_equal(band["nbr"], expected)
    assert (band["nbr"][:, 13] == np.arange(len(band["ijk"]))).all()
    # every core voxel has its full 27-point stencil in the band (the point of the dilation)
    assert (band["nbr"][band["core"]] >= 0).all()


def as_list(ijk):
    return [tuple(v) for v in ijk.tolist()]


def test_neighbour_table_is_symmetric(sphere):
    nbr = sphere[4]["nbr"]
    i, o = np.nonzero(nbr >= 0)
    np.testing.assert_array_equal(nbr[nbr[i, o], 26 - o], i)


def test_values_weights_and_fill(sphere):
    ijk, tsdf, weight, _, band = sphere
    given = {v: (t, w) for v, t, w in zip(as_list(ijk), tsdf.tolist(), weight.tolist())}
    observed = np.array([v in given for v in as_list(band["ijk"])])
    assert 0 < (~observed).sum()  # the missing cap makes the dilation reach unseen voxels
    rows = np.flatnonzero(observed)
    np.testing.assert_array_equal(band["tsdf"][rows],
                                  [given[v][0] for v in as_list(band["ijk"][rows])])
    np.testing.assert_array_equal(band["weight"][rows],
                                  [given[v][1] for v in as_list(band["ijk"][rows])])
    assert (band["weight"][~observed] == 0).all()
    # unobserved voxels: mean tsdf of their observed 26-neighbours (one exists with dilation 1)
    for n in np.flatnonzero(~observed):
        v = tuple(band["ijk"][n])
        vals = [given[u][0] for u in ((v[0] + a, v[1] + b, v[2] + c)
                                      for a, b, c in itertools.product((-1, 0, 1), repeat=3))
                if u in given]
        assert vals
        np.testing.assert_allclose(band["tsdf"][n], np.mean(np.float64(vals)), rtol=1e-6,
                                   atol=1e-9)
    assert (np.abs(band["tsdf"]) <= np.float32(TAU_B)).all()
    np.testing.assert_array_equal(band["x0"], band["tsdf"])
    assert band["x0"] is not band["tsdf"]


def test_block_table_is_the_lookup_of_the_band(sphere):
    band = sphere[4]
    keys, table = build_block_table(band["ijk"])
    np.testing.assert_array_equal(band["block_keys"], keys)
    np.testing.assert_array_equal(band["block_table"], table)
    assert band["block_keys"].dtype == np.int64 and band["block_table"].dtype == np.int32


def test_negative_coordinates_give_the_translated_band(sphere):
    ijk, tsdf, weight, _, band = sphere
    shift = np.array([-53, -27, -1030])  # not multiples of the 8-voxel block
    moved = build_band(ijk + shift.astype(np.int32), tsdf, weight, TAU_B)
    assert (moved["ijk"] < 0).all()
    np.testing.assert_array_equal(moved["ijk"], band["ijk"] + shift)
    for key in ("nbr", "tsdf", "weight", "core", "x0"):
        np.testing.assert_array_equal(moved[key], band[key])


def test_unobserved_input_voxels_are_not_core(sphere):
    ijk, tsdf, weight, sdf, band = sphere
    weight = weight.copy()
    weight[np.argmin(np.abs(sdf))] = 0  # a voxel right on the surface, but weight 0
    out = build_band(ijk, tsdf, weight, TAU_B)
    v = tuple(ijk[np.argmin(np.abs(sdf))])
    n = as_list(out["ijk"]).index(v)  # still in the band (its neighbours are core) ...
    assert not out["core"][n] and out["weight"][n] == 0  # ... but neither core nor weighted


def test_dilation_two_fills_from_the_previous_round(sphere):
    ijk, tsdf, weight, _, _ = sphere
    band = build_band(ijk, tsdf, weight, TAU_B, dilation=2)
    assert (band["nbr"][band["core"]] >= 0).all()
    unobserved = band["weight"] == 0
    assert unobserved.sum() > 0
    assert (np.abs(band["tsdf"][unobserved]) <= np.float32(TAU_B)).all()


@pytest.mark.parametrize("case", ["empty", "all_clamped"])
def test_empty_band(case):
    if case == "empty":
        ijk = np.zeros((0, 3), np.int32)
        tsdf, weight = np.zeros(0, np.float32), np.zeros(0, np.float32)
    else:
        ijk = np.array([[0, 0, 0], [0, 0, 1]], np.int32)
        tsdf = np.full(2, TAU_B, np.float32)  # clamped: seen, but not near a surface
        weight = np.ones(2, np.float32)
    band = build_band(ijk, tsdf, weight, TAU_B)
    shapes = {"ijk": (0, 3), "nbr": (0, 27), "block_keys": (0,), "block_table": (0, 512),
              "tsdf": (0,), "weight": (0,), "core": (0,), "x0": (0,)}
    assert {k: v.shape for k, v in band.items()} == shapes
    assert band["nbr"].dtype == np.int32 and band["core"].dtype == bool


def test_single_voxel_band_is_a_3x3x3_cube():
    band = build_band(np.array([[-1, 7, 8]], np.int32), np.array([0.001], np.float32),
                      np.array([2.0], np.float32), TAU_B)
    cube = {(-1 + a, 7 + b, 8 + c) for a, b, c in itertools.product((-1, 0, 1), repeat=3)}
    assert as_set(band["ijk"]) == cube
    assert band["core"].sum() == 1
    np.testing.assert_allclose(band["tsdf"], 0.001, rtol=1e-6)  # fill = the one neighbour


@pytest.mark.parametrize("bad", ["unsorted", "duplicate", "shape", "nan", "tau", "dilation",
                                 "range"])
def test_bad_input_is_rejected(sphere, bad):
    ijk, tsdf, weight = sphere[0].copy(), sphere[1].copy(), sphere[2].copy()
    tau, dilation = TAU_B, 1
    if bad == "unsorted":
        ijk[[3, 4]] = ijk[[4, 3]]
    elif bad == "duplicate":
        ijk[4] = ijk[3]
    elif bad == "shape":
        tsdf = tsdf[:-1]
    elif bad == "nan":
        tsdf[10] = np.nan
    elif bad == "tau":
        tau = 0.0
    elif bad == "range":
        ijk[-1, 0] = MAX_ABS_IJK + 1  # still sorted: only the range is wrong
    else:
        dilation = MAX_DILATION + 1
    with pytest.raises(ValueError):
        build_band(ijk, tsdf, weight, tau, dilation=dilation)


def test_stencil_offsets():
    for kind, face_edge_corner in ((6, (6, 0, 0)), (18, (6, 12, 0)), (26, (6, 12, 8))):
        offsets, weights = stencil_offsets(kind)
        assert len(offsets) == kind and 13 not in offsets
        assert sorted(26 - o for o in offsets) == offsets  # closed under OPPOSITE
        d = np.array([(o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1) for o in offsets])
        sq = (d ** 2).sum(1)
        assert tuple((sq == s).sum() for s in (1, 2, 3)) == face_edge_corner
        np.testing.assert_allclose(weights, 1.0 / sq)
    with pytest.raises(ValueError):
        stencil_offsets(8)


def test_the_kernels_offset_of_is_the_layouts_stencil_offset():
    """kernels.funcs.offset_of (a run-time offset inside a kernel) gives the (di, dj, dk) of
    kernels.layout.stencil_offset for all 27 offsets."""
    import taichi as ti

    from kernels.funcs import offset_of
    from kernels.layout import OFFSETS

    @ti.kernel
    def table(out: ti.types.ndarray(dtype=ti.i32, ndim=2)):
        for o in range(out.shape[0]):
            d = offset_of(o)
            for c in ti.static(range(3)):
                out[o, c] = d[c]

    out = np.zeros((27, 3), np.int32)
    table(out)
    np.testing.assert_array_equal(out, OFFSETS)
