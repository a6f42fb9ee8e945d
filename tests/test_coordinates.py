"""A map that works anywhere on Earth (issue 17): the grid is built in a local frame near the
first camera (bftaichi.geometry.local_origin) and every output is in world coordinates.

The tiny tabletop (tests/robustness_cases.py ``TINY``) is written to disk by ``bftaichi synth``
and copied with every pose and the ground-truth mesh moved by ``OFFSET`` = (500 km, 5,000 km,
100 m), UTM-like; both folders are fused by ``bftaichi fuse`` (the user's path: files on disk).
At 2.5 cm voxels the block edge is 0.2 m and ``OFFSET`` is a whole number of blocks, so the far
scene's local grid is the near scene's shifted by whole blocks: the two runs see the same voxel
lattice and differ only in float32 rounding (their local coordinates differ by about a metre).

Tolerances, and why: every kernel computes in float32 in its local frame, so values round
differently at the float32 ulp of metre-sized coordinates (6e-8 m), and the PCG solve
(relative residual ~1e-6) carries such differences into the mean: measured vertex
differences up to 1.7e-7 m (mesh.ply) and 7e-8 m (tsdf_mesh.ply), 1.1e-6 m on a 3-view
variant. Asserted: 1e-5 m (a 2500th of a voxel). The world
coordinates themselves are float64 (ulp 1e-9 m at 5,000 km). Metrics sample 20000 points per
surface: a distance rounded across a threshold moves a ratio by 1/20000; asserted within 1e-3
(20 samples), distances within 1e-3 relative.
"""

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bftaichi.cli import main
from bftaichi.errors import DataError
from bftaichi.evaluation.metrics import load_mesh
from bftaichi.io import read_mesh_ply, write_mesh_ply
from bftaichi.posterior import Posterior
from robustness_cases import sets

OFFSET = np.array([500_000.0, 5_000_000.0, 100.0])
VOXEL = 0.025  # block edge 0.2 m: OFFSET / 0.2 is a whole number on every axis
FUSE = ("--voxel", str(VOXEL), "-q", "--set", "run.plots=false", "--set", "run.preview=false",
        "--set", "eval.n_samples=20000")
VERTEX_TOL_M = 1e-5


def _write_pose(path: Path, T: np.ndarray) -> None:
    path.write_text("".join(" ".join(f"{x:.17g}" for x in row) + "\n" for row in T))


def translated_copy(src: Path, dst: Path, offset) -> Path:
    """A copy of the 7scenes folder ``src`` with every pose and the ground truth moved by
    ``offset`` (metres, float64; gt_mesh.ply then holds double coordinates)."""
    shutil.copytree(src, dst)
    for p in sorted(dst.glob("frame-*.pose.txt")):
        T = np.loadtxt(p)
        T[:3, 3] += offset
        _write_pose(p, T)
    gt = load_mesh(src / "gt_mesh.ply")
    write_mesh_ply(dst / "gt_mesh.ply", gt.vertices, gt.faces, origin=np.asarray(offset))
    return dst


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("coordinates")
    near = root / "near"
    # 8 views (TINY has 3): evalviews fuses every other one, and Open3D's mesh needs voxels
    # seen 3 times (its weight threshold; with 3 fused views it has none here)
    assert main(["synth", "--out", str(near), "-q", *sets("synthetic.n_views=8")]) == 0
    far = translated_copy(near, root / "far", OFFSET)
    out = {}
    for name, data in (("near", near), ("far", far)):
        out[name] = root / f"out-{name}"
        assert main(["fuse", str(data), "--out", str(out[name]), *FUSE]) == 0
    report = {k: json.loads((v / "report.json").read_text()) for k, v in out.items()}
    origin = np.array(report["far"]["origin_m"])
    # the far grid is the near one shifted by this many voxels (whole blocks)
    shift = np.round((origin - OFFSET) / VOXEL).astype(np.int64)
    return SimpleNamespace(root=root, near=near, far=far, out=out, report=report,
                           origin=origin, shift=shift)


def _ply_header(path: Path) -> str:
    return path.read_bytes().split(b"end_header")[0].decode("ascii")


def test_a_scene_near_the_origin_keeps_the_world_grid(scenes):
    r = scenes.report["near"]
    assert r["origin_m"] == [0.0, 0.0, 0.0]
    with np.load(scenes.out["near"] / "band.npz") as z:
        assert z["origin"].dtype == np.float64 and not z["origin"].any()
    for name in ("mesh.ply", "tsdf_mesh.ply"):
        assert "property float x" in _ply_header(scenes.out["near"] / name)
        assert read_mesh_ply(scenes.out["near"] / name)[0].dtype == np.float32
    assert Posterior.load(scenes.out["near"] / "band.npz").origin.tolist() == [0.0, 0.0, 0.0]


def test_a_far_scene_gets_a_block_aligned_origin_next_to_its_first_camera(scenes):
    origin = scenes.origin
    camera = np.loadtxt(scenes.far / "frame-000000.pose.txt")[:3, 3]
    block = 8 * VOXEL
    assert np.all(np.abs(origin - camera) <= block / 2 + 1e-6)
    assert np.allclose(origin / block, np.round(origin / block), rtol=0, atol=1e-6)
    assert np.any(scenes.shift != 0)  # the local frames really differ (by whole blocks)
    with np.load(scenes.out["far"] / "band.npz") as z:
        np.testing.assert_array_equal(z["origin"], origin)
    assert scenes.report["far"]["counts"]["out_of_range_samples"] == 0
    for name in ("mesh.ply", "tsdf_mesh.ply"):
        header = _ply_header(scenes.out["far"] / name)
        assert "property double x" in header and "property double z" in header


@pytest.mark.parametrize("name", ["tsdf_mesh.ply", "mesh.ply"])
def test_the_far_mesh_is_the_near_mesh_moved_by_the_offset(scenes, name):
    v_near, f_near, a_near = read_mesh_ply(scenes.out["near"] / name)
    v_far, f_far, a_far = read_mesh_ply(scenes.out["far"] / name)
    assert v_far.dtype == np.float64 and len(v_near) > 1000
    assert len(v_far) == len(v_near)
    np.testing.assert_array_equal(f_far, f_near)
    # the far file holds world coordinates: UTM-sized, and the near mesh plus the offset
    assert np.all(v_far[:, 1] > 4.99e6)
    assert np.abs((v_far - OFFSET) - v_near).max() < VERTEX_TOL_M
    if name == "mesh.ply":
        # sigma as well (sigma_pos is not compared: the gradient it divides by is that of the
        # trilinear mean in the vertex's cell, and a vertex lies on a cell face, where that
        # gradient jumps; float rounding of its position picks the side)
        np.testing.assert_allclose(a_far["sigma"], a_near["sigma"], rtol=1e-3, atol=0)


def test_metrics_against_the_far_ground_truth_equal_the_near_ones(scenes):
    near, far = scenes.report["near"], scenes.report["far"]
    assert set(far["metrics"]) == {"tsdf_mesh.ply", "mesh.ply"}
    for mesh, m in near["metrics"].items():
        for key, value in m.items():
            got = far["metrics"][mesh][key]
            if key.startswith(("precision@", "recall@", "fscore@")):
                assert abs(got - value) <= 1e-3, (mesh, key, got, value)
            else:  # chamfer, accuracy, completeness (metres), face counts: the means agree to
                # 1e-5 m (test_posterior_load_gives_world_coordinates), which moves distances of
                # ~1.6 cm by ~1e-3 and their squares (chamfer) by ~2e-3
                assert got == pytest.approx(value, rel=2e-3), (mesh, key)
    for part in ("uncertainty", "band_uncertainty"):
        for key in ("n", "rms_error_m", "mean_error_m", "median_sigma_m", "coverage@1sigma",
                    "coverage@2sigma", "coverage@3sigma", "nll_vs_constant", "ause"):
            assert far[part][key] == pytest.approx(near[part][key], rel=1e-3, abs=1e-6), (part, key)


def test_posterior_load_gives_world_coordinates(scenes):
    near = Posterior.load(scenes.out["near"] / "band.npz")
    far = Posterior.load(scenes.out["far"] / "band.npz")
    np.testing.assert_array_equal(far.origin, scenes.origin)
    # the grids: the same voxels, shifted by whole blocks; world centres agree
    np.testing.assert_array_equal(far.ijk + scenes.shift, near.ijk)
    centres_far = far.origin + (far.ijk + 0.5) * far.voxel_size
    assert np.abs(centres_far - OFFSET - (near.ijk + 0.5) * near.voxel_size).max() < 1e-6
    np.testing.assert_allclose(far.mean, near.mean, rtol=0, atol=1e-5)
    # extract_mesh(): world float64, what mesh.ply holds (up to band.npz's float32 voxel_size,
    # 0.025 -> 0.02500000037: a float32 ulp of the local vertices); local=True: the local frame
    world = far.extract_mesh()
    assert world.vertices.dtype == np.float64
    v_file, _, _ = read_mesh_ply(scenes.out["far"] / "mesh.ply")
    assert np.abs(world.vertices - v_file).max() < 1e-6
    local = far.extract_mesh(local=True)
    assert np.abs(local.vertices).max() < 10.0
    np.testing.assert_array_equal(far.origin + local.vertices, world.vertices)
    assert np.abs(world.vertices - OFFSET - near.extract_mesh().vertices).max() < VERTEX_TOL_M


def test_a_band_without_origin_loads_in_the_world_frame(scenes, tmp_path):
    with np.load(scenes.out["near"] / "band.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "origin"}
    np.savez(tmp_path / "band.npz", **arrays)  # a band.npz of an older version
    old = Posterior.load(tmp_path / "band.npz")
    assert old.origin.dtype == np.float64 and old.origin.tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_array_equal(old.extract_mesh().vertices,
                                  old.extract_mesh(local=True).vertices)


def _ranking(out: Path) -> dict:
    r = json.loads((out / "nbv.json").read_text())
    return {c["index"]: c for c in r["candidates"]}


def test_nbv_candidates_are_world_poses_and_rank_as_near_the_origin(scenes, tmp_path):
    for name in ("near", "far"):
        assert main(["nbv", str(scenes.out[name]), "--n", "8", "-q"]) == 0
    near, far = _ranking(scenes.out["near"]), _ranking(scenes.out["far"])
    assert len(near) == len(far) == 8
    for i, c in near.items():
        T_near, T_far = np.array(c["pose"]), np.array(far[i]["pose"])
        assert np.abs(T_far[:3, 3] - OFFSET - T_near[:3, 3]).max() < 1e-6  # world poses
        np.testing.assert_allclose(T_far[:3, :3], T_near[:3, :3], atol=1e-9)
        assert far[i]["utility"] == pytest.approx(c["utility"], rel=1e-3)
        assert far[i]["frontier_cells"] == c["frontier_cells"]
    assert [far[i]["rank"] for i in sorted(far)] == [near[i]["rank"] for i in sorted(near)]
    # `--poses FILE` in world coordinates: the near candidates moved by the offset
    poses = np.stack([np.array(near[i]["pose"]) for i in sorted(near)])
    poses[:, :3, 3] += OFFSET
    path = tmp_path / "poses.txt"
    path.write_text("".join(" ".join(f"{x:.17g}" for x in T.ravel()) + "\n" for T in poses))
    assert main(["nbv", str(scenes.out["far"]), "--poses", str(path), "-q"]) == 0
    from_file = _ranking(scenes.out["far"])
    for i in sorted(near):
        assert from_file[i]["utility"] == pytest.approx(near[i]["utility"], rel=1e-3)


def test_evalviews_of_the_far_scene_equals_the_near_one(scenes):
    result = {}
    for name in ("near", "far"):
        out = scenes.root / f"ev-{name}"
        assert main(["evalviews", str(getattr(scenes, name)), "--voxel", str(VOXEL), "-q",
                     "--out", str(out), "--set", "run.preview=false",
                     "--set", "run.plots=false", "--set", "eval.n_samples=5000"]) == 0
        result[name] = json.loads((out / "evalviews.json").read_text())
    near, far = result["near"], result["far"]
    assert near["held_out_evaluated"] == far["held_out_evaluated"] == 4
    assert set(far["methods"]) == set(near["methods"]) >= {"bftaichi", "tsdf"}
    for method, s in near["methods"].items():
        assert s["pixels"] > 100, method
        # Open3D integrates in float32 in its own grid: on these 64x48 frames only ~200 pixels
        # see voxels at its weight threshold (3 views), and a few flip with the frame's rounding
        tol = dict(rel=0.05, abs=5e-3) if method == "open3d" else dict(rel=1e-3, abs=2e-3)
        for key, value in s.items():
            assert far["methods"][method][key] == pytest.approx(value, **tol), (method, key)
    np.testing.assert_allclose(far["calibration"]["coverage_normalised"],
                               near["calibration"]["coverage_normalised"], atol=2e-3)


class _Scene:
    """A stand-in meshcat visualizer: records the geometry sent to each path."""

    def __init__(self, sent=None, path=""):
        self.sent, self.path = ({} if sent is None else sent), path

    def __getitem__(self, key):
        return _Scene(self.sent, f"{self.path}/{key}")

    def set_object(self, geometry, material=None):
        self.sent[self.path] = geometry

    def set_property(self, *args):
        pass

    def set_transform(self, *args):
        pass


def test_the_preview_shows_the_local_frame(scenes):
    from bftaichi.running.viz import build_scene

    sent = {}
    for name in ("near", "far"):
        sent[name] = _Scene()
        build_scene(sent[name], scenes.out[name])
    shift_m = scenes.origin - OFFSET  # far local = near - shift_m
    for path in ("/bftaichi/mesh", "/bftaichi/tsdf_mesh"):
        v_near = np.asarray(sent["near"].sent[path].vertices, np.float64)
        v_far = np.asarray(sent["far"].sent[path].vertices, np.float64)
        assert np.abs(v_far).max() < 10.0  # float32-friendly: not UTM coordinates
        assert np.abs(v_far + shift_m - v_near).max() < VERTEX_TOL_M
    cams_near = sent["near"].sent["/bftaichi/cameras"].geometry.position  # (3, 16 n) float32
    cams_far = sent["far"].sent["/bftaichi/cameras"].geometry.position
    assert np.abs(cams_far + shift_m[:, None] - cams_near).max() < 1e-4


def test_a_scene_larger_than_the_map_is_refused_with_its_extent(scenes, tmp_path, capsys):
    """The last frame 1 km away: at 2.5 cm voxels the map holds 204.8 m per axis."""
    data = translated_copy(scenes.near, tmp_path / "long", np.zeros(3))
    last = sorted(data.glob("frame-*.pose.txt"))[-1]
    T = np.loadtxt(last)
    T[0, 3] += 1000.0
    _write_pose(last, T)
    capsys.readouterr()
    assert main(["fuse", str(data), "--out", str(tmp_path / "out"), *FUSE]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err
    assert "204.8 m per axis" in err and "does not fit" in err
    extent = float(err.split("spans ")[1].split(" m along x")[0])
    assert 999.0 < extent < 1003.0
    assert "voxel of at least 0.12" in err and "split the scene" in err
    assert "T_C_W" not in err


def test_a_few_samples_outside_the_map_are_counted_many_refused(scenes):
    """The 1 % rule of bftaichi.stages.integrate.MAX_OUTSIDE, on frame 0 of the near scene with
    some pixels' depth set to 300 m (the map reaches 102.4 m from the origin per axis, and a
    ray 300 m long gets at least 173 m from its camera along some axis)."""
    from bftaichi import TSDFVolume
    from bftaichi.formats import open_dataset

    frame = open_dataset(scenes.near)[0]
    valid = np.flatnonzero(frame.depth_m > 0)
    assert len(valid) > 500

    def volume():
        return TSDFVolume(VOXEL, 4 * VOXEL, depth_max_m=400.0)

    def far_pixels(n):
        depth = frame.depth_m.copy()
        depth.flat[valid[:n]] = 300.0
        return depth

    vol = volume()
    assert vol.integrate(far_pixels(int(0.005 * len(valid))), frame.K, frame.T_W_C) > 0
    assert vol.stats()["out_of_range_samples"] > 0  # counted, not fatal
    with pytest.raises(DataError, match=r"frame-x: \d+% of its valid pixels see surface outside"):
        volume().integrate(far_pixels(int(0.05 * len(valid))), frame.K, frame.T_W_C,
                           name="frame-x")
    # A frame 150 m away from the first: the scene would fit in the map's 204.8 m, but not
    # around the first camera, which is the grid's centre.
    vol = volume()
    vol.integrate(frame.depth_m, frame.K, frame.T_W_C)
    moved = frame.T_W_C.copy()
    moved[0, 3] += 150.0
    with pytest.raises(DataError, match="which would fit") as e:
        vol.integrate(frame.depth_m, frame.K, moved, name="frame-y")
    assert "centred on the world origin" in str(e.value) and "start the sequence" in str(e.value)
