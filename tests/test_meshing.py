"""Marching cubes over sparse voxels (bftaichi.stages.surface) on analytic fields."""

import numpy as np
import pytest
import trimesh

from bftaichi.errors import BftaichiError
from bftaichi.stages.surface import extract_mesh, sample_field

CENTRE = np.array([0.013, -0.021, 0.007])
RADIUS = 0.3


def voxel_grid(lo, hi):
    """All voxel indices in the box [lo, hi) (int32, (N, 3))."""
    axes = [np.arange(a, b) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.int32)


def centres(ijk, voxel_size):
    return (ijk.astype(np.float64) + 0.5) * voxel_size


def sphere_shell(voxel_size, shell_voxels=3.0, radius=RADIUS, centre=CENTRE):
    """Voxels within ``shell_voxels`` of a sphere, with the exact SDF (positive outside)."""
    n = int(np.ceil((np.abs(centre).max() + radius) / voxel_size)) + 4
    ijk = voxel_grid((-n,) * 3, (n,) * 3)
    sdf = np.linalg.norm(centres(ijk, voxel_size) - centre, axis=1) - radius
    keep = np.abs(sdf) < shell_voxels * voxel_size
    return ijk[keep], sdf[keep].astype(np.float32)


def mesh_of(v, f):
    return trimesh.Trimesh(v, f, process=False)


@pytest.mark.parametrize("voxel_size", [0.01, 0.02, 0.03])
def test_sphere_is_watertight_accurate_and_outward(voxel_size):
    ijk, sdf = sphere_shell(voxel_size)
    v, f = extract_mesh(ijk, sdf, np.ones(len(sdf), bool), voxel_size)
    assert v.dtype == np.float32 and f.dtype == np.int32
    assert v.shape[1] == 3 and f.shape[1] == 3 and len(f) > 100
    mesh = mesh_of(v, f)
    assert mesh.is_watertight and mesh.is_winding_consistent
    # vertices on the true sphere within 0.1 voxel
    radial_err = np.abs(np.linalg.norm(v - CENTRE, axis=1) - RADIUS)
    assert radial_err.max() < 0.1 * voxel_size
    # outward: every face normal points away from the centre, and the enclosed volume is positive
    out = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTRE)
    assert np.all(out > 0)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.02)
    assert len(np.unique(v, axis=0)) == len(v)


def test_normals_point_toward_positive_values():
    """Negating the field (positive inside) flips every face: normals follow increasing values."""
    vs = 0.03
    ijk, sdf = sphere_shell(vs)
    v, f = extract_mesh(ijk, -sdf, np.ones(len(sdf), bool), vs)
    mesh = mesh_of(v, f)
    inward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - CENTRE)
    assert np.all(inward < 0)
    assert mesh.volume < 0


def test_plane_vertices_exact_and_normals_along_gradient():
    vs = 0.02
    n = np.array([0.3, -0.2, 0.9])
    n /= np.linalg.norm(n)
    offset = 0.051
    ijk = voxel_grid((-12, -12, -12), (12, 12, 12))
    x = centres(ijk, vs)
    sdf = x @ n - offset                              # linear: marching cubes is exact on it
    keep = np.abs(sdf) < 3 * vs
    v, f = extract_mesh(ijk[keep], sdf[keep].astype(np.float32), np.ones(keep.sum(), bool), vs)
    assert len(f) > 100
    assert np.abs(v.astype(np.float64) @ n - offset).max() < 1e-5
    mesh = mesh_of(v, f)
    assert np.all(mesh.face_normals @ n > 0.99)
    # the plane clipped to the observed box: the area is close to the box cross-section
    # (bounded below by the inner cell box) and the mesh is one open sheet
    assert mesh.area > 0.3 ** 2
    assert not mesh.is_watertight


def test_level_other_than_zero():
    vs = 0.02
    ijk, sdf = sphere_shell(vs, shell_voxels=5.0)
    v, f = extract_mesh(ijk, sdf, np.ones(len(sdf), bool), vs, level=0.05)
    r = np.linalg.norm(v - CENTRE, axis=1)
    assert np.abs(r - (RADIUS + 0.05)).max() < 0.1 * vs


def test_unobserved_voxel_removes_every_cell_touching_it():
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    observed = np.ones(len(sdf), bool)
    v_full, f_full = extract_mesh(ijk, sdf, observed, vs)
    # a voxel right next to the surface
    u = np.argmin(np.abs(sdf))
    observed[u] = False
    v, f = extract_mesh(ijk, sdf, observed, vs)

    def grid_centroids(vv, ff):
        return vv.astype(np.float64)[ff].mean(axis=1) / vs - 0.5

    # cells having voxel u as a corner fill the open cube (u - 1, u + 1)^3 in grid coordinates;
    # each face lies in its own (closed) cell, so its centroid is never strictly inside that cube
    def in_hole(c):
        return np.all(np.abs(c - ijk[u]) < 1 - 1e-6, axis=1)

    assert in_hole(grid_centroids(v_full, f_full)).sum() >= 4   # the hole region had surface
    assert not in_hole(grid_centroids(v, f)).any()
    # the rest of the surface is untouched
    outside_full = ~np.all(np.abs(grid_centroids(v_full, f_full) - ijk[u]) <= 1 + 1e-6, axis=1)
    outside = ~np.all(np.abs(grid_centroids(v, f) - ijk[u]) <= 1 + 1e-6, axis=1)
    assert outside.sum() == outside_full.sum()
    assert not mesh_of(v, f).is_watertight


def test_missing_voxel_behaves_like_unobserved():
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    observed = np.ones(len(sdf), bool)
    u = np.argmin(np.abs(sdf))
    observed[u] = False
    v1, f1 = extract_mesh(ijk, sdf, observed, vs)
    drop = np.arange(len(sdf)) != u
    v2, f2 = extract_mesh(ijk[drop], sdf[drop], observed[drop], vs)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)


def test_chunk_seams_are_merged():
    """A sphere spanning 4^3 chunks of 8 cells meshes exactly as in one chunk."""
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    obs = np.ones(len(sdf), bool)
    v_one, f_one = extract_mesh(ijk, sdf, obs, vs)
    v, f = extract_mesh(ijk, sdf, obs, vs, chunk_cells=8)
    span = ijk.max(axis=0) - ijk.min(axis=0)
    assert np.all(span > 3 * 8)                        # really several chunks per axis
    mesh = mesh_of(v, f)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert len(np.unique(v, axis=0)) == len(v)         # no duplicate vertex at a seam
    np.testing.assert_array_equal(v, v_one)            # vertex keys are global
    assert mesh.volume == pytest.approx(mesh_of(v_one, f_one).volume, rel=1e-9)

    def canonical(faces):                              # face set with orientation kept
        rolled = np.stack([np.roll(faces, -k, axis=1) for k in range(3)])
        best = np.argmin(rolled[:, :, 0], axis=0)
        return np.unique(rolled[best, np.arange(len(faces))], axis=0)

    np.testing.assert_array_equal(canonical(f), canonical(f_one))


def test_values_exactly_at_level_stay_watertight_across_seams():
    """A field quantised to half voxels puts many corners exactly on the level: skimage then
    emits several vertices at one corner; they must merge within and across chunks."""
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    sdf = (np.round(sdf / (vs / 2)) * (vs / 2)).astype(np.float32)
    assert (sdf == 0).sum() > 100
    obs = np.ones(len(sdf), bool)
    v1, f1 = extract_mesh(ijk, sdf, obs, vs)
    v3, f3 = extract_mesh(ijk, sdf, obs, vs, chunk_cells=3)
    for v, f in [(v1, f1), (v3, f3)]:
        mesh = mesh_of(v, f)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
        assert len(np.unique(v, axis=0)) == len(v)
    np.testing.assert_array_equal(v1, v3)


def test_shuffled_rows_give_identical_output():
    vs = 0.03
    ijk, sdf = sphere_shell(vs)
    obs = np.ones(len(sdf), bool)
    obs[::17] = False
    perm = np.random.default_rng(1).permutation(len(sdf))
    v1, f1 = extract_mesh(ijk, sdf, obs, vs, chunk_cells=8)
    v2, f2 = extract_mesh(ijk[perm], sdf[perm], obs[perm], vs, chunk_cells=8)
    assert len(f1) > 0
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)


def test_empty_and_unobserved_inputs_return_empty_arrays():
    for ijk, val, obs in [
        (np.zeros((0, 3), np.int32), np.zeros(0, np.float32), np.zeros(0, bool)),
        (voxel_grid((0, 0, 0), (4, 4, 4)), np.linspace(-1, 1, 64, dtype=np.float32),
         np.zeros(64, bool)),
        (voxel_grid((0, 0, 0), (4, 4, 4)), np.ones(64, np.float32), np.ones(64, bool)),  # no crossing
        (voxel_grid((0, 0, 0), (1, 4, 4)), np.linspace(-1, 1, 16, dtype=np.float32),
         np.ones(16, bool)),  # one voxel thick: no cell
    ]:
        v, f = extract_mesh(ijk, val, obs, 0.01)
        assert v.shape == (0, 3) and f.shape == (0, 3)
        assert v.dtype == np.float32 and f.dtype == np.int32


@pytest.mark.parametrize("kwargs, word", [
    (dict(ijk=np.zeros((4, 2), np.int32)), "ijk"),
    (dict(ijk=np.zeros((4, 3), np.float32)), "ijk"),
    (dict(values=np.zeros(3, np.float32)), "values"),
    (dict(observed=np.ones(4, np.int32)), "observed"),
    (dict(observed=np.ones(5, bool)), "observed"),
    (dict(voxel_size=0.0), "voxel_size"),
    (dict(voxel_size=float("nan")), "voxel_size"),
    (dict(values=np.array([0, np.nan, 0, 0], np.float32)), "values"),
    (dict(ijk=np.array([[0, 0, 0], [0, 0, 1], [0, 0, 0], [1, 1, 1]], np.int32)), "more than once"),
    (dict(level=float("inf")), "level"),
    (dict(chunk_cells=0), "chunk_cells"),
])
def test_bad_input_raises_naming_the_argument(kwargs, word):
    args = dict(ijk=np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [1, 1, 1]], np.int32),
                values=np.zeros(4, np.float32), observed=np.ones(4, bool), voxel_size=0.01)
    args.update(kwargs)
    with pytest.raises(BftaichiError, match=word):
        extract_mesh(**args)


def test_nan_values_of_unobserved_voxels_are_ignored():
    vs = 0.03
    ijk, sdf = sphere_shell(vs)
    obs = np.ones(len(sdf), bool)
    obs[::5] = False
    sdf_nan = sdf.copy()
    sdf_nan[~obs] = np.nan
    v1, f1 = extract_mesh(ijk, sdf, obs, vs)
    v2, f2 = extract_mesh(ijk, sdf_nan, obs, vs)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)


# ---------------------------------------------------------------- sample_field

def test_sample_field_reproduces_linear_function():
    vs = 0.025
    ijk = voxel_grid((-5, -3, 2), (6, 7, 9))
    coef = np.array([0.7, -1.3, 2.1])

    def lin(x):
        return x @ coef + 0.4

    val = lin(centres(ijk, vs)).astype(np.float32)
    rng = np.random.default_rng(0)
    # points strictly inside the box of voxel centres: all 8 neighbours exist
    lo = (ijk.min(0) + 0.5) * vs
    hi = (ijk.max(0) + 0.5) * vs
    pts = rng.uniform(lo, hi, size=(2000, 3))
    out = sample_field(ijk, val, np.ones(len(val), bool), vs, pts)
    assert out.dtype == np.float32 and out.shape == (2000,)
    np.testing.assert_allclose(out, lin(pts), atol=1e-5)
    # voxel centres give the voxel values, including those on the border of the set
    out_c = sample_field(ijk, val, np.ones(len(val), bool), vs, centres(ijk, vs))
    np.testing.assert_allclose(out_c, val, atol=1e-5)


def test_sample_field_nan_outside_or_unobserved():
    vs = 0.1
    ijk = voxel_grid((0, 0, 0), (3, 3, 3))
    val = np.arange(27, dtype=np.float32)
    obs = np.ones(27, bool)
    obs[np.flatnonzero(np.all(ijk == [1, 1, 1], axis=1))] = False
    pts = np.array([
        [0.1, 0.1, 0.1],          # cell (0,0,0): uses voxel (1,1,1) -> NaN
        [0.22, 0.22, 0.22],       # cell (1,1,1): uses voxel (1,1,1) -> NaN
        [-0.01, 0.1, 0.1],        # left of the first voxel centres -> NaN
        [0.27, 0.25, 0.05],       # x beyond the last voxel centre -> NaN
    ])
    out = sample_field(ijk, val, obs, vs, pts)
    assert np.all(np.isnan(out))
    obs[:] = True
    out = sample_field(ijk, val, obs, vs, pts[:2])
    assert np.all(np.isfinite(out))


def test_sample_field_at_mesh_vertices_gives_level():
    """Mesh vertices of an observed band all get a value, and the SDF there is the level."""
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    obs = np.ones(len(sdf), bool)
    v, f = extract_mesh(ijk, sdf, obs, vs)
    out = sample_field(ijk, sdf, obs, vs, v)
    assert np.all(np.isfinite(out))
    assert np.abs(out).max() < 0.01 * vs


def test_sample_field_columns_are_each_columns_own():
    """(N, C) values (colour) give, column by column, bitwise what each column gives alone,
    NaN where a corner is unobserved, and the voxels may come in any order."""
    vs = 0.02
    ijk, sdf = sphere_shell(vs)
    rng = np.random.default_rng(3)
    rgb = rng.uniform(0, 255, (len(ijk), 3)).astype(np.float32)
    obs = rng.random(len(ijk)) > 0.02
    v, _ = extract_mesh(ijk, sdf, np.ones(len(sdf), bool), vs)
    perm = rng.permutation(len(ijk))
    out = sample_field(ijk[perm], rgb[perm], obs[perm], vs, v)
    assert out.shape == (len(v), 3) and out.dtype == np.float32
    alone = np.stack([sample_field(ijk, rgb[:, c], obs, vs, v) for c in range(3)], axis=1)
    assert np.isnan(alone).any() and np.isfinite(alone).any()
    np.testing.assert_array_equal(out, alone)
    with pytest.raises(BftaichiError, match="values must have shape"):
        sample_field(ijk, rgb[:, :, None], obs, vs, v)


def test_sample_field_bad_points():
    ijk = voxel_grid((0, 0, 0), (2, 2, 2))
    val = np.zeros(8, np.float32)
    obs = np.ones(8, bool)
    with pytest.raises(BftaichiError, match="points"):
        sample_field(ijk, val, obs, 0.1, np.zeros((4, 2)))
    with pytest.raises(BftaichiError, match="points"):
        sample_field(ijk, val, obs, 0.1, np.array([[np.nan, 0, 0]]))
    assert sample_field(ijk, val, obs, 0.1, np.zeros((0, 3))).shape == (0,)
