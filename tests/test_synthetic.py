"""Synthetic scenes: meshes, trajectories, rendering, noise, and the 7-Scenes export."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bftaichi.config import SyntheticConfig
from bftaichi.errors import BftaichiError, DataError
from bftaichi.geometry import intrinsics, look_at
from bftaichi.io import read_mesh_ply
from bftaichi.formats.synthetic import (PRIMITIVES, DepthRenderer, SyntheticDataset, add_noise,
                                intrinsics_of, make_mesh, trajectory, write_7scenes)

DATA = Path(__file__).parents[1] / ".." / "shared" / "data"
BUNNY = DATA / "meshes" / "stanford-bunny.obj"

# An odd-sized image whose principal point is a pixel centre, so one pixel looks down the axis.
W, H, F = 321, 241, 262.5
K_ODD = intrinsics(F, F, 160.0, 120.0)


def _head_on(mesh, distance_m: float, width=W, height=H, K=K_ODD) -> np.ndarray:
    """Depth from a camera on +x at ``distance_m`` from the origin, looking at the origin."""
    return DepthRenderer(mesh).render(K, look_at([distance_m, 0.0, 0.0], [0.0, 0.0, 0.0]),
                                      width, height)


def _plane_cfg(distance_m: float, **kw) -> SyntheticConfig:
    """One head-on view of a box face (half extent 1 m) ``distance_m`` in front of the camera."""
    return SyntheticConfig(mesh="box", radius_m=1.0, trajectory="ring", n_views=1,
                           cam_radius_m=1.0 + distance_m, cam_height_m=0.0, **kw)


def test_sphere_depth_and_silhouette():
    r, D = 0.3, 1.5
    depth = _head_on(make_mesh(SyntheticConfig(mesh="sphere", radius_m=r)), D)
    assert depth.shape == (H, W) and depth.dtype == np.float32
    assert abs(depth[120, 160] - (D - r)) < 1e-4
    # Silhouette of a sphere on the optical axis: a disc of radius f * r / sqrt(D^2 - r^2) pixels.
    disc_area = math.pi * F**2 * r**2 / (D**2 - r**2)
    assert abs((depth > 0).sum() / disc_area - 1.0) < 0.02
    # Off-centre pixels see the sphere surface: back-projected points lie at radius r.
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    p_C = np.stack([(u - 160.0) / F * z, (v - 120.0) / F * z, z], 1)
    p_W = p_C @ look_at([D, 0, 0], [0, 0, 0])[:3, :3].T + [D, 0, 0]
    inner = np.linalg.norm(p_W[:, 1:], axis=1) < 0.9 * r  # away from grazing silhouette rays
    assert np.abs(np.linalg.norm(p_W[inner], axis=1) - r).max() < 1e-4


def test_render_rays_agree_with_solving_for_them():
    """DepthRenderer.render's rays (bftaichi.geometry.pixel_rays): K^-1 [u, v, 1] by the
    diagonal's reciprocals for a pinhole K whose last row is exactly (0, 0, 1), solved
    otherwise (a last row a rounding off): both give the same depth image to float32
    rounding."""
    mesh = make_mesh(SyntheticConfig(mesh="sphere", radius_m=0.3))
    K_off = K_ODD.copy()
    K_off[2, 2] = 1.0 + 1e-13
    fast, solved = _head_on(mesh, 1.5), _head_on(mesh, 1.5, K=K_off)
    assert (fast > 0).sum() > 1000
    np.testing.assert_array_equal(fast > 0, solved > 0)
    np.testing.assert_allclose(fast, solved, rtol=1e-6, atol=0)


def test_box_face_depth_is_constant():
    depth = _head_on(make_mesh(SyntheticConfig(mesh="box", radius_m=0.3)), 1.0)
    face = depth[100:141, 140:181]  # well inside the face's image (|y|, |z| < 0.3 m)
    assert np.all(face > 0)
    assert np.abs(face - 0.7).max() < 1e-5
    assert depth[0, 0] == 0.0  # background is 0


def test_primitives_size_and_centre():
    for name, extents in [("sphere", (0.6, 0.6, 0.6)), ("box", (0.6, 0.6, 0.6)),
                          ("cylinder", (0.6, 0.6, 0.6)), ("torus", (0.8, 0.8, 0.2)),
                          ("bowl", (0.6, 0.6, 0.18))]:
        mesh = make_mesh(SyntheticConfig(mesh=name, radius_m=0.3))
        np.testing.assert_allclose(mesh.extents, extents, atol=2e-3, err_msg=name)
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-3, err_msg=name)
    assert set(PRIMITIVES) == {"sphere", "box", "cylinder", "torus", "bowl", "tabletop",
                               "clutter", "shelf"}


def test_clutter_objects_rest_on_the_table_apart():
    """The cluttered table: a slab and six objects resting on it (lowest point at z = 0), at
    least a centimetre apart, within the table."""
    from scipy.spatial import cKDTree

    mesh = make_mesh(SyntheticConfig(mesh="clutter", radius_m=5.0))  # radius_m must not matter
    parts = mesh.split(only_watertight=False)
    objects = [p for p in parts if p.bounds[0, 2] > -1e-9]
    assert len(parts) == 7 and len(objects) == 6
    for o in objects:
        assert o.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
        assert np.all(np.abs(o.bounds[:, :2]) < 0.25)
    for i, a in enumerate(objects):
        for b in objects[i + 1:]:
            assert cKDTree(a.vertices).query(b.vertices)[0].min() > 0.01


def test_the_shelf_stands_on_the_floor_without_hidden_faces():
    """The shelf stands on z = 0 and its ground truth holds no face on the floor or where two
    panels meet (no view could see them): no triangle centre lies inside another panel."""
    from bftaichi.formats.synthetic import _SHELF_PANELS

    shelf = make_mesh(SyntheticConfig(mesh="shelf", radius_m=5.0))
    assert shelf.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    c = shelf.triangles_center
    assert np.all(c[:, 2] > 1e-6)
    for extents, centre in _SHELF_PANELS:
        lo, hi = np.asarray(centre) - 0.5 * np.asarray(extents), np.asarray(centre) + \
            0.5 * np.asarray(extents)
        assert not np.any(np.all((c > lo + 1e-6) & (c < hi - 1e-6), axis=1))


def test_the_bowl_is_concave_and_closed():
    """Looking straight down into the bowl, the rays meet its floor (not a lid); from the side
    the outer wall hides the inside."""
    bowl = make_mesh(SyntheticConfig(mesh="bowl", radius_m=0.3))
    assert bowl.is_watertight and bowl.volume > 0
    down = DepthRenderer(bowl).render(intrinsics(100.0, 100.0, 31.5, 31.5),
                                      look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0),
                                              up=(0.0, 1.0, 0.0)), 64, 64)
    # centre pixel: the floor, 0.08 R above the base at z = -0.09
    assert down[32, 32] == pytest.approx(1.0 + 0.09 - 0.024, abs=1e-4)


def test_tabletop_parts_separate_and_resting():
    mesh = make_mesh(SyntheticConfig(mesh="tabletop", radius_m=5.0))  # radius_m must not matter
    parts = mesh.split(only_watertight=False)
    assert len(parts) == 5
    slab = max(parts, key=lambda p: p.extents[0] * p.extents[1])
    np.testing.assert_allclose(slab.extents, [1.0, 1.0, 0.04], atol=1e-9)
    assert abs(slab.bounds[1, 2]) < 1e-9  # top face at z = 0
    objects = [p for p in parts if p is not slab]
    for p in objects:
        assert p.bounds[0, 2] >= -1e-9 and p.bounds[0, 2] < 1e-6  # resting on the table top
        assert np.all(np.abs(p.bounds[:, :2]) <= 0.5)  # on the table
    # Disjoint bounding boxes => no two objects interpenetrate (or touch).
    for i in range(len(objects)):
        for j in range(i + 1, len(objects)):
            a, b = objects[i].bounds, objects[j].bounds
            overlap = np.all(a[0] < b[1]) and np.all(b[0] < a[1])
            assert not overlap, (a, b)
    heights = sorted(round(float(p.extents[2]), 3) for p in objects)
    assert heights == [0.06, 0.12, 0.2, 0.2]  # torus, box, sphere, cylinder


def _assert_looks_at(T, target):
    z_axis = T[:3, 2]
    to_target = np.asarray(target) - T[:3, 3]
    np.testing.assert_allclose(z_axis, to_target / np.linalg.norm(to_target), atol=1e-9)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
    assert np.linalg.det(T[:3, :3]) > 0


def test_ring_is_the_papers_controlled_setup():
    cfg = SyntheticConfig(trajectory="ring", n_views=12, cam_radius_m=1.5, cam_height_m=0.6,
                          look_at=[0.1, -0.2, 0.3])
    poses = trajectory(cfg)
    assert poses.shape == (12, 4, 4)
    target = np.array([0.1, -0.2, 0.3])
    rel = poses[:, :3, 3] - target
    np.testing.assert_allclose(np.linalg.norm(rel[:, :2], axis=1), 1.5, atol=1e-12)
    np.testing.assert_allclose(rel[:, 2], 0.6, atol=1e-12)
    az = np.sort(np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2 * np.pi))
    np.testing.assert_allclose(np.diff(az), 2 * np.pi / 12, atol=1e-12)
    for T in poses:
        _assert_looks_at(T, target)
    np.testing.assert_array_equal(trajectory(cfg), poses)  # deterministic
    # An explicit target overrides cfg.look_at.
    _assert_looks_at(trajectory(cfg, target=[0, 0, 0])[3], [0, 0, 0])


def test_sphere_hemisphere_spiral_trajectories():
    target = np.array([0.0, 0.0, 0.2])
    sph = trajectory(SyntheticConfig(trajectory="sphere", n_views=40, cam_radius_m=1.1,
                                     look_at=target.tolist()))
    rel = sph[:, :3, 3] - target
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), 1.1, atol=1e-12)
    assert rel[:, 2].min() < -0.9 and rel[:, 2].max() > 0.9  # covers top and bottom
    assert abs(rel.mean(axis=0)).max() < 0.1  # evenly spread
    for T in sph:
        _assert_looks_at(T, target)

    hemi = trajectory(SyntheticConfig(trajectory="hemisphere", n_views=50, cam_radius_m=1.0,
                                      min_elevation_deg=20.0, look_at=target.tolist()))
    rel = hemi[:, :3, 3] - target
    elevation = np.degrees(np.arcsin(rel[:, 2] / np.linalg.norm(rel, axis=1)))
    assert elevation.min() >= 20.0 and elevation.min() < 25.0 and elevation.max() > 80.0
    for T in hemi:
        _assert_looks_at(T, target)

    spiral = trajectory(SyntheticConfig(trajectory="spiral", n_views=21, cam_radius_m=0.8,
                                        cam_height_m=0.3, cam_height_end_m=0.9, turns=2.0))
    pos = spiral[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(pos[:, :2], axis=1), 0.8, atol=1e-12)
    np.testing.assert_allclose(pos[:, 2], np.linspace(0.3, 0.9, 21), atol=1e-12)
    az = np.unwrap(np.arctan2(pos[:, 1], pos[:, 0]))
    assert abs(az[-1] - az[0] - 2 * 2 * np.pi) < 1e-9
    for T in spiral:
        _assert_looks_at(T, [0, 0, 0])


def test_cameras_are_upright():
    # z-up world: a point above the target must appear above the image centre (smaller v), and
    # the image "down" axis must never point up in the world.
    for name in ("ring", "hemisphere", "spiral"):
        poses = trajectory(SyntheticConfig(trajectory=name, n_views=8))
        assert np.all(poses[:, 2, 1] <= 1e-9), name
        above_C = np.einsum("nji,nj->ni", poses[:, :3, :3], [0, 0, 0.1] - poses[:, :3, 3])
        assert np.all(above_C[:, 1] < 0), name


def test_dataset_frames_follow_config():
    cfg = SyntheticConfig(mesh="sphere", radius_m=0.2, n_views=3, width=64, height=48, fx=50.0,
                          fy=55.0, cx=31.5, cy=23.5, noise="none", quantization_m=0.0)
    ds = SyntheticDataset(cfg)
    assert len(ds) == 3 and ds.image_size == (64, 48)
    np.testing.assert_array_equal(ds.K, intrinsics_of(cfg))
    np.testing.assert_array_equal(ds.K, [[50, 0, 31.5], [0, 55, 23.5], [0, 0, 1]])
    assert ds.name == "synthetic:sphere" and ds.gt_mesh_path is None
    frames = list(ds)
    assert [f.name for f in frames] == ["frame-000000", "frame-000001", "frame-000002"]
    for i, f in enumerate(frames):
        assert f.depth_m.shape == (48, 64) and f.depth_m.dtype == np.float32 and f.rgb is None
        np.testing.assert_array_equal(f.T_W_C, ds.poses[i])
        np.testing.assert_array_equal(f.depth_m, ds.clean_depth(i))  # noise none = clean
    with pytest.raises(IndexError):
        ds[3]
    # Depth limits drop the sphere when it is closer than depth_min_m.
    near = SyntheticDataset(cfg, depth_min_m=2.0)
    assert not np.any(near[0].depth_m > 0)


def _noise_residual(distance_m: float, **kw) -> np.ndarray:
    ds = SyntheticDataset(_plane_cfg(distance_m, quantization_m=0.0, **kw))
    clean = ds.clean_depth(0)
    assert np.allclose(clean[clean > 0], distance_m, atol=1e-6)
    noisy = ds[0].depth_m
    both = (clean > 0) & (noisy > 0)
    assert both.sum() > 40000
    return (noisy - clean)[both].astype(np.float64)


def test_kinect_noise_matches_axial_model():
    a, b, z0 = 0.0012, 0.0019, 0.4
    for z in (1.0, 2.0):
        res = _noise_residual(z, noise="kinect")
        sigma = a + b * (z - z0) ** 2
        assert abs(res.std() / sigma - 1.0) < 0.1, (z, res.std(), sigma)
        assert abs(res.mean()) < 0.1 * sigma


def test_gaussian_noise_std():
    res = _noise_residual(2.0, noise="gaussian", sigma_m=0.005)
    assert abs(res.std() / 0.005 - 1.0) < 0.1
    assert abs(res.mean()) < 5e-4


def test_add_noise_quantisation_dropout_and_misses():
    depth = np.full((200, 300), 1.7, np.float32)
    depth[:, :50] = 0.0  # misses
    cfg = SyntheticConfig(noise="kinect", quantization_m=0.005, dropout=0.3)
    out = add_noise(depth, cfg, np.random.default_rng(1))
    assert out.dtype == np.float32 and out.shape == depth.shape
    assert np.all(out[:, :50] == 0)  # misses stay misses
    valid = out[out > 0].astype(np.float64)
    steps = valid / 0.005
    assert np.abs(steps - np.round(steps)).max() < 1e-3  # multiples of the step
    assert len(np.unique(valid)) > 1  # noise still there
    dropped = 1.0 - (out[:, 50:] > 0).mean()
    assert abs(dropped - 0.3) < 0.02
    # Noisy depth <= 0 becomes 0, never negative.
    big = add_noise(np.full((50, 50), 0.01, np.float32),
                    SyntheticConfig(noise="gaussian", sigma_m=0.05, quantization_m=0.0),
                    np.random.default_rng(0))
    assert big.min() == 0.0 and (big == 0).mean() > 0.3


def test_frames_are_reproducible_and_seeded():
    cfg = SyntheticConfig(mesh="torus", radius_m=0.3, n_views=3, width=80, height=60, fx=70.0,
                          fy=70.0, cx=39.5, cy=29.5, noise="kinect", dropout=0.1, seed=7)
    ds = SyntheticDataset(cfg)
    f2 = ds[2].depth_m
    again = [ds[i].depth_m for i in (1, 0, 2)]
    np.testing.assert_array_equal(again[2], f2)
    np.testing.assert_array_equal(SyntheticDataset(cfg)[2].depth_m, f2)
    assert not np.array_equal(again[0][again[0] > 0][:100], again[1][again[1] > 0][:100])
    cfg8 = dataclasses.replace(cfg, seed=8)
    other = SyntheticDataset(cfg8)[2].depth_m
    assert not np.array_equal(other, f2)
    np.testing.assert_array_equal(SyntheticDataset(cfg8).clean_depth(2), ds.clean_depth(2))


def test_frames_kept_in_memory_are_the_rendered_ones_and_not_aliased():
    """A run reads each frame several times: the kept frame must equal a fresh render, and a
    caller writing into a frame it got must not change what the next caller gets."""
    cfg = SyntheticConfig(mesh="torus", radius_m=0.3, n_views=3, width=80, height=60, fx=70.0,
                          fy=70.0, cx=39.5, cy=29.5, noise="kinect", dropout=0.1, seed=7)
    ds = SyntheticDataset(cfg)
    first = ds[1].depth_m
    first[:] = -1.0  # a caller scribbling on its copy
    np.testing.assert_array_equal(ds[1].depth_m, SyntheticDataset(cfg)[1].depth_m)
    assert (ds[1].depth_m >= 0).all()
    small = SyntheticDataset(cfg)
    small.CACHE_BYTES = 80 * 60 * 4  # room for one frame: the others are rendered every time
    for i in (0, 1, 2, 2, 1):
        np.testing.assert_array_equal(small[i].depth_m, ds[i].depth_m)
    assert list(small._cache) == [0]


def test_write_7scenes_round_trip(tmp_path):
    cfg = SyntheticConfig(mesh="tabletop", n_views=3, width=64, height=48, fx=52.5, fy=52.5,
                          cx=31.5, cy=23.5, noise="gaussian", quantization_m=0.0, dropout=0.05)
    ds = SyntheticDataset(cfg)
    out = write_7scenes(ds, tmp_path / "a" / "scene", progress=True)
    assert out == tmp_path / "a" / "scene"
    K = np.loadtxt(out / "camera-intrinsics.txt")
    np.testing.assert_allclose(K, ds.K, rtol=1e-12)
    for i in range(len(ds)):
        frame = ds[i]
        img = Image.open(out / f"frame-{i:06d}.depth.png")
        assert img.mode == "I;16"
        mm = np.asarray(img)
        assert mm.dtype == np.uint16 and mm.shape == (48, 64)
        np.testing.assert_array_equal(mm > 0, frame.depth_m > 0)
        assert np.abs(mm / 1000.0 - frame.depth_m).max() <= 0.0005 + 1e-7
        pose = np.loadtxt(out / f"frame-{i:06d}.pose.txt")
        np.testing.assert_allclose(pose, ds.poses[i], atol=1e-6)
    v, f, _ = read_mesh_ply(out / "gt_mesh.ply")
    assert len(v) == len(ds.gt_mesh.vertices) and len(f) == len(ds.gt_mesh.faces)
    np.testing.assert_allclose(v, ds.gt_mesh.vertices, atol=1e-6)
    meta = json.loads((out / "scene.json").read_text())
    assert (meta["width"], meta["height"], meta["n_frames"]) == (64, 48, 3)
    assert meta["synthetic"]["mesh"] == "tabletop" and meta["synthetic"]["dropout"] == 0.05
    assert not list(out.glob(".*.tmp"))  # no leftover temp files


def test_write_7scenes_bad_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    ds = SyntheticDataset(SyntheticConfig(mesh="box", n_views=1, width=8, height=6,
                                          cx=3.5, cy=2.5))
    with pytest.raises(BftaichiError, match=re.escape(str(blocker / "sub"))):
        write_7scenes(ds, blocker / "sub")


def test_missing_or_bad_mesh_file(tmp_path):
    missing = tmp_path / "nope.obj"
    with pytest.raises(DataError, match="nope.obj"):
        make_mesh(SyntheticConfig(mesh=str(missing)))
    with pytest.raises(DataError, match="nope.obj"):
        SyntheticDataset(SyntheticConfig(mesh=str(missing)))
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(DataError, match="empty.obj"):
        make_mesh(SyntheticConfig(mesh=str(empty)))
    unknown = tmp_path / "mesh.xyz123"
    unknown.write_text("garbage")
    with pytest.raises(DataError, match="mesh.xyz123"):
        make_mesh(SyntheticConfig(mesh=str(unknown)))


def test_mesh_file_up_scale_centre(tmp_path):
    # A y-up box 0.2 (x) x 0.4 (y) x 0.1 (z), off-centre, written as OBJ.
    import trimesh

    src = trimesh.creation.box(extents=[0.2, 0.4, 0.1])
    src.apply_translation([1.0, 2.0, 3.0])
    path = tmp_path / "box.obj"
    src.export(path)
    mesh = make_mesh(SyntheticConfig(mesh=str(path), mesh_up="y", mesh_scale=2.0,
                                     center_mesh=True))
    np.testing.assert_allclose(mesh.extents, [0.4, 0.2, 0.8], atol=1e-9)  # +y became +z
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    kept = make_mesh(SyntheticConfig(mesh=str(path)))
    np.testing.assert_allclose(kept.bounds.mean(axis=0), [1.0, 2.0, 3.0], atol=1e-9)


@pytest.mark.skipif(not BUNNY.is_file(), reason="shared bunny mesh not available")
def test_bunny_file_renders():
    cfg = SyntheticConfig(mesh=str(BUNNY), mesh_up="y", center_mesh=True, n_views=2,
                          cam_radius_m=0.5, cam_height_m=0.2, noise="none")
    ds = SyntheticDataset(cfg)
    assert len(ds.gt_mesh.faces) > 69000
    np.testing.assert_allclose(ds.gt_mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    assert ds.gt_mesh.extents[2] > 0.15  # the bunny's height (y in the file) is now along z
    d = ds[0].depth_m
    assert 0.3 < d[d > 0].min() and d.max() < 0.7 and (d > 0).sum() > 1000
