"""Every recorded-data format reads the same synthetic scene back (DESIGN.md section 5).

One small scene (the tabletop, 4 views, 64x48, no noise) is rendered once and written by each test
in each format's own conventions (its depth scale, float16 for CO3D, quaternions and separate
timestamps for TUM, ``seq-01/``-style folders for 7-Scenes, NDC cameras for CO3D, T_C_W for the folder format,
...). Loading any of them must give the rendered depth (within the format's quantisation), poses
and K, and fusing any of them the same mesh as the 7-Scenes copy written by ``bftaichi synth``.
"""

from __future__ import annotations

import gzip
import json
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bftaichi.config import SyntheticConfig, load_config
from bftaichi.formats import FORMATS, CO3DDataset, TUMDataset, detect_format, open_dataset, pytorch3d_to_opencv
from bftaichi.errors import ConfigError, DataError
from bftaichi.stages.integrate import TSDFVolume
from bftaichi.formats.synthetic import SyntheticDataset, write_7scenes

W, H = 64, 48
FX, FY, CX, CY = 52.5, 55.0, 31.2, 23.9  # fx != fy and an off-centre principal point catch swaps
N = 4
VOXEL_M = 0.03
F = np.diag([-1.0, -1.0, 1.0])  # OpenCV <-> PyTorch3D camera axes (x and y flipped)


@pytest.fixture(scope="module")
def scene():
    """(synthetic dataset, K, [(depth_m, T_W_C)] of the 4 views)."""
    cfg = SyntheticConfig(mesh="tabletop", n_views=N, width=W, height=H, fx=FX, fy=FY, cx=CX, cy=CY,
                          noise="none", quantization_m=0.0, cam_radius_m=1.0, cam_height_m=0.8)
    ds = SyntheticDataset(cfg)
    return ds, ds.K, [(f.depth_m, f.T_W_C) for f in ds]


# --------------------------------------------------------------------------------------------
# Writers: one per format, each in that format's own conventions
# --------------------------------------------------------------------------------------------

def _png16(path: Path, depth_m: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.rint(depth_m * scale).astype(np.uint16)).save(path)


def _rows(path: Path, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.17g}" for v in np.ravel(r)) + "\n" for r in rows))


def _inv(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R.T, -R.T @ t
    return out


def write_7scenes_seqs(root, K, frames):
    """3DMatch-style: seq-01/ holds views 0-1, seq-02/ views 2-3; intrinsics in the top folder."""
    for k, (depth, T) in enumerate(frames):
        seq = root / f"seq-{k // 2 + 1:02d}"
        _png16(seq / f"frame-{k % 2:06d}.depth.png", depth, 1000.0)
        _rows(seq / f"frame-{k % 2:06d}.pose.txt", T)
    _rows(root / "camera-intrinsics.txt", K)


def tum_stamp(k: int) -> float:
    return 1305031102.0 + 0.1 * k + 0.0333


def write_tum(root, K, frames, skip=()):
    """Depth at tum_stamp(k); its pose 7 ms later, decoy poses 50 ms later (outside the 20 ms
    tolerance, so frames in ``skip``, whose true pose is left out, have none)."""
    gt = []
    lines = ["# depth maps\n# timestamp filename\n"]
    for k, (depth, T) in enumerate(frames):
        t = tum_stamp(k)
        _png16(root / "depth" / f"{t:.6f}.png", depth, 5000.0)
        lines.append(f"{t:.6f} depth/{t:.6f}.png\n")
        s = np.cbrt(np.linalg.det(T[:3, :3]))  # a scaled rotation -> a quaternion of norm s
        q = Rotation.from_matrix(T[:3, :3] / s).as_quat() * s  # x y z w
        if k not in skip:
            gt.append([t + 0.007, *T[:3, 3], *q])
        gt.append([t + 0.05, 9.0, 9.0, 9.0, 0.0, 0.0, 0.0, 1.0])
    (root / "depth.txt").write_text("".join(lines))
    with open(root / "groundtruth.txt", "w") as f:
        f.write("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n")
        f.writelines(" ".join(f"{v:.10f}" for v in row) + "\n" for row in reversed(gt))
    _rows(root / "camera-intrinsics.txt", K)


def write_replica(root, K, frames):
    for k, (depth, _) in enumerate(frames):
        _png16(root / "results" / f"depth{k:06d}.png", depth, 6553.5)
        Image.fromarray(np.full(depth.shape + (3,), 90, np.uint8)).save(root / "results" / f"frame{k:06d}.jpg")
    _rows(root / "traj.txt", [T for _, T in frames])
    h, w = frames[0][0].shape
    cam = {"w": w, "h": h, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "scale": 6553.5}
    (root / "cam_params.json").write_text(json.dumps({"camera": cam}))


def write_scannet(root, K, frames, lost=()):
    for k, (depth, T) in enumerate(frames):
        _png16(root / "depth" / f"{k}.png", depth, 1000.0)
        _rows(root / "pose" / f"{k}.txt", np.full((4, 4), -np.inf) if k in lost else T)
    K4 = np.eye(4)
    K4[:3, :3] = K
    _rows(root / "intrinsic" / "intrinsic_depth.txt", K4)
    K4c = K4.copy()
    K4c[:2] *= 3.0  # the colour camera's: must not be used for depth
    _rows(root / "intrinsic" / "intrinsic_color.txt", K4c)


def opencv_to_ndc(K, T_W_C, size_wh, fmt):
    """CO3D's viewpoint (PyTorch3D NDC camera) of an OpenCV camera: the inverse of the loader's
    conversion, written from PyTorch3D's conventions (X_cam = X_world @ R + T, +X left, +Y up)."""
    half = 0.5 * np.asarray(size_wh, float)
    s = np.full(2, half.min()) if fmt == "ndc_isotropic" else half
    R_C_W = T_W_C[:3, :3].T
    t_C_W = -R_C_W @ T_W_C[:3, 3]
    return {"R": (R_C_W.T @ F).tolist(), "T": (F @ t_C_W).tolist(),
            "focal_length": (np.array([K[0, 0], K[1, 1]]) / s).tolist(),
            "principal_point": ((half - (K[:2, 2] + 0.5)) / s).tolist(), "intrinsics_format": fmt}


CO3D_SCALE_ADJ = 0.25


def write_co3d(root, K, frames, sequence="seq_a", extra=()):
    """A CO3D category folder ``root`` (paths relative to its parent, the CO3D root); frames 0-1
    with ndc_isotropic cameras, 2-3 with ndc_norm_image_bounds."""
    entries = []
    h, w = frames[0][0].shape  # image.size of every frame: a different depth size is an error
    for k, (depth, T) in enumerate(frames):
        rel = f"{root.name}/{sequence}"
        seq = root / sequence
        for sub in ("depths", "depth_masks", "masks", "images"):
            (seq / sub).mkdir(parents=True, exist_ok=True)
        bits = (depth / CO3D_SCALE_ADJ).astype(np.float16).view(np.uint16)
        Image.fromarray(bits).save(seq / "depths" / f"frame{k:06d}.jpg.geometric.png")
        Image.fromarray(np.full(depth.shape, 255, np.uint8)).save(seq / "depth_masks" / f"frame{k:06d}.png")
        fg = np.full(depth.shape, 255, np.uint8)
        fg[:, :10] = 0  # background on the left
        Image.fromarray(fg).save(seq / "masks" / f"frame{k:06d}.png")
        Image.fromarray(np.full(depth.shape + (3,), 50, np.uint8)).save(seq / "images" / f"frame{k:06d}.jpg")
        fmt = "ndc_isotropic" if k < 2 else "ndc_norm_image_bounds"
        entries.append({
            "sequence_name": sequence, "frame_number": 10 * k + 1, "frame_timestamp": 0.1 * k,
            "image": {"path": f"{rel}/images/frame{k:06d}.jpg", "size": [h, w]},
            "depth": {"path": f"{rel}/depths/frame{k:06d}.jpg.geometric.png",
                      "scale_adjustment": CO3D_SCALE_ADJ, "mask_path": f"{rel}/depth_masks/frame{k:06d}.png"},
            "mask": {"path": f"{rel}/masks/frame{k:06d}.png", "mass": float(fg.sum() / 255)},
            "viewpoint": opencv_to_ndc(K, T, (w, h), fmt),
            "meta": {},
        })
    with gzip.open(root / "frame_annotations.jgz", "wt") as f:
        json.dump(entries + list(extra), f)


def write_redwood(root, K, frames):
    blocks = []
    for k, (depth, T) in enumerate(frames):
        _png16(root / "depth" / f"{k:06d}.png", depth, 1000.0)
        (root / "color").mkdir(exist_ok=True)
        Image.fromarray(np.full(depth.shape + (3,), 70, np.uint8)).save(root / "color" / f"{k:06d}.jpg")
        blocks.append(f"{k} {k} {k + 1}\n" + "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in T))
    (root / "trajectory.log").write_text("".join(blocks))
    h, w = frames[0][0].shape
    (root / "camera_intrinsic.json").write_text(json.dumps(
        {"width": w, "height": h, "intrinsic_matrix": K.T.ravel().tolist()}))  # column-major


def write_folder(root, K, frames):
    """PNG millimetres, poses.txt of 3x4 T_W_C rows, intrinsics {fx, fy, cx, cy, width, height}."""
    for k, (depth, _) in enumerate(frames):
        _png16(root / "depth" / f"{k:04d}.png", depth, 1000.0)
    _rows(root / "poses.txt", [T[:3] for _, T in frames])
    h, w = frames[0][0].shape
    (root / "intrinsics.json").write_text(json.dumps(
        {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": w, "height": h}))


def write_folder_tcw(root, K, frames):
    """.npy metres, pose/<stem>.txt 4x4 T_C_W, intrinsics {"K": ...} without the image size."""
    (root / "depth").mkdir(parents=True, exist_ok=True)
    for k, (depth, T) in enumerate(frames):
        np.save(root / "depth" / f"{k}.npy", depth.astype(np.float32))
        _rows(root / "pose" / f"{k}.txt", np.linalg.inv(T))
    (root / "intrinsics.json").write_text(json.dumps({"K": K.tolist()}))


@dataclass
class Spec:
    """How a format's fixture is written and where its files are."""

    write: Callable
    depth_file: Callable[[Path, int], Path]
    pose_ref: Callable[[Path, int], str]  # text naming frame k's pose in error messages
    missing: Callable[[Path], tuple[Path, str]]  # (file to delete, text the error names)
    quantum: Callable[[np.ndarray], np.ndarray]  # largest depth error of the storage, metres
    format: str
    options: dict = field(default_factory=dict)


def _mm(depth):
    return 0.0005 + 1e-6 * depth


SPECS = {
    "7scenes": Spec(
        write_7scenes_seqs,
        lambda r, k: r / f"seq-{k // 2 + 1:02d}" / f"frame-{k % 2:06d}.depth.png",
        lambda r, k: str(r / f"seq-{k // 2 + 1:02d}" / f"frame-{k % 2:06d}.pose.txt"),
        lambda r: (r / "seq-01" / "frame-000001.pose.txt",) * 2,
        _mm, "7scenes"),
    "tum": Spec(
        write_tum,
        lambda r, k: r / "depth" / f"{tum_stamp(k):.6f}.png",
        lambda r, k: f"groundtruth.txt: line {3 + 2 * (N - 1 - k) + 1}",
        lambda r: (r / "depth" / f"{tum_stamp(1):.6f}.png",) * 2,
        lambda d: 0.5 / 5000 + 1e-6 * d, "tum"),
    "replica": Spec(
        write_replica,
        lambda r, k: r / "results" / f"depth{k:06d}.png",
        lambda r, k: f"traj.txt: line {k + 1}",
        lambda r: (r / "traj.txt",) * 2,
        lambda d: 0.5 / 6553.5 + 1e-6 * d, "replica"),
    "scannet": Spec(
        write_scannet,
        lambda r, k: r / "depth" / f"{k}.png",
        lambda r, k: str(r / "pose" / f"{k}.txt"),
        lambda r: (r / "pose" / "1.txt",) * 2,
        _mm, "scannet"),
    "co3d": Spec(
        write_co3d,
        lambda r, k: r / "seq_a" / "depths" / f"frame{k:06d}.jpg.geometric.png",
        lambda r, k: f"frame_annotations.jgz: frame {10 * k + 1}",
        lambda r: (r / "seq_a" / "depths" / "frame000001.jpg.geometric.png",) * 2,
        lambda d: d * 2.0 ** -11 + 1e-6, "co3d"),  # float16: 11 significant bits
    "redwood": Spec(
        write_redwood,
        lambda r, k: r / "depth" / f"{k:06d}.png",
        lambda r, k: f"trajectory.log: lines {5 * k + 1}-{5 * k + 5}",
        lambda r: (r / "trajectory.log", "redwood"),
        _mm, "redwood"),
    "folder": Spec(
        write_folder,
        lambda r, k: r / "depth" / f"{k:04d}.png",
        lambda r, k: f"poses.txt: line {k + 1}",
        lambda r: (r / "poses.txt", "pose file missing for depth frame depth/0000.png"),
        _mm, "folder"),
    "folder_tcw": Spec(
        write_folder_tcw,
        lambda r, k: r / "depth" / f"{k}.npy",
        lambda r, k: str(r / "pose" / f"{k}.txt"),
        lambda r: (r / "pose" / "1.txt",) * 2,
        lambda d: 1e-6 * d, "folder", {"pose_convention": "T_C_W"}),
}


def write(tmp_path, scene, name, frames=None, folder=None, **kw) -> Path:
    _, K, original = scene
    root = tmp_path / (folder or name)
    root.mkdir(parents=True)
    SPECS[name].write(root, K, original if frames is None else frames, **kw)
    return root


def load(root, name, **kw):
    spec = SPECS[name]
    return open_dataset(root, format=spec.format, depth_min_m=0.1, depth_max_m=6.0, **spec.options, **kw)


def fuse(frames) -> np.ndarray:
    """Vertices of the mesh fused from (depth, K, T_W_C) frames."""
    vol = TSDFVolume(VOXEL_M, 3 * VOXEL_M)
    for depth, K, T in frames:
        vol.integrate(depth, K, T)
    return np.asarray(vol.extract_mesh().vertices)


@pytest.fixture(scope="module")
def reference_mesh(scene, tmp_path_factory):
    """The mesh fused from the 7-Scenes copy that ``bftaichi synth`` writes."""
    out = write_7scenes(scene[0], tmp_path_factory.mktemp("ref") / "tabletop")
    return fuse((f.depth_m, f.K, f.T_W_C) for f in open_dataset(out))


# --------------------------------------------------------------------------------------------
# The same world geometry from every format
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(SPECS))
def test_loads_the_rendered_depth_poses_and_K(tmp_path, scene, name):
    _, K, original = scene
    root = write(tmp_path, scene, name)
    assert detect_format(root) == SPECS[name].format
    ds = load(root, name)
    assert type(ds) is FORMATS[SPECS[name].format] and len(ds) == N and ds.skipped == 0
    np.testing.assert_allclose(ds.K, K, rtol=1e-6)
    for k, (depth, T) in enumerate(original):
        f = ds[k]
        np.testing.assert_allclose(f.K, K, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(f.T_W_C, T, atol=1e-6)
        assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (H, W)
        np.testing.assert_array_equal(f.depth_m > 0, depth > 0)
        assert np.all(np.abs(f.depth_m - depth) <= SPECS[name].quantum(depth))
    assert ds.image_size == (W, H)


@pytest.mark.parametrize("name", list(SPECS))
def test_fused_mesh_matches_the_7scenes_one(tmp_path, scene, reference_mesh, name):
    ds = load(write(tmp_path, scene, name), name)
    vertices = fuse((f.depth_m, f.K, f.T_W_C) for f in ds)
    d_ab = cKDTree(reference_mesh).query(vertices)[0]
    d_ba = cKDTree(vertices).query(reference_mesh)[0]
    assert 0.5 * (d_ab.mean() + d_ba.mean()) < 0.25 * VOXEL_M
    assert abs(len(vertices) - len(reference_mesh)) <= 0.02 * len(reference_mesh)


# --------------------------------------------------------------------------------------------
# Errors name the file or frame
# --------------------------------------------------------------------------------------------

def _read_all(root, name):
    return [f.name for f in load(root, name)]


@pytest.mark.parametrize("name", list(SPECS))
def test_missing_file(tmp_path, scene, name):
    root = write(tmp_path, scene, name)
    path, named = SPECS[name].missing(root)
    path.unlink()
    with pytest.raises(DataError, match=re.escape(str(named))):
        _read_all(root, name)


@pytest.mark.parametrize("name", list(SPECS))
def test_non_orthonormal_rotation(tmp_path, scene, name):
    frames = list(scene[2])
    T = frames[1][1].copy()
    T[:3, :3] *= 1.1
    frames[1] = (frames[1][0], T)
    root = write(tmp_path, scene, name, frames)
    ds = load(root, name)
    ds[0]
    with pytest.raises(DataError, match="not (orthonormal|a rotation)") as e:
        ds[1]
    assert SPECS[name].pose_ref(root, 1) in str(e.value)


@pytest.mark.parametrize("name", list(SPECS))
def test_depth_size_differs_from_intrinsics(tmp_path, scene, name):
    frames = list(scene[2])
    frames[1] = (np.full((H // 2, W // 2), 1.5, np.float32), frames[1][1])
    root = write(tmp_path, scene, name, frames)
    ds = load(root, name)
    ds[0]
    with pytest.raises(DataError, match=f"{W // 2}x{H // 2}") as e:
        ds[1]
    assert str(SPECS[name].depth_file(root, 1)) in str(e.value)


@pytest.mark.parametrize("name", ["scannet", "folder_tcw"])
def test_first_frame_size_checked_against_principal_point(tmp_path, scene, name):
    # layouts without the image size: intrinsics for 2x the resolution are caught on frame 0
    frames = list(scene[2])
    frames[0] = (np.full((2 * H, 2 * W), 1.5, np.float32), frames[0][1])
    root = write(tmp_path, scene, name, frames)
    with pytest.raises(DataError, match="principal point") as e:
        load(root, name)[0]
    assert str(SPECS[name].depth_file(root, 0)) in str(e.value)


# --------------------------------------------------------------------------------------------
# Format-specific behaviour
# --------------------------------------------------------------------------------------------

def test_7scenes_sequences_concatenate_and_must_share_intrinsics(tmp_path, scene):
    root = write(tmp_path, scene, "7scenes")
    assert load(root, "7scenes").frame_names == ["seq-01/frame-000000", "seq-01/frame-000001",
                                                 "seq-02/frame-000000", "seq-02/frame-000001"]
    shutil.move(root / "camera-intrinsics.txt", root / "seq-01" / "camera-intrinsics.txt")
    np.testing.assert_allclose(load(root, "7scenes").K, scene[1])  # intrinsics in a sequence
    K2 = scene[1].copy()
    K2[0, 0] += 1
    _rows(root / "seq-02" / "camera-intrinsics.txt", K2)
    with pytest.raises(DataError, match="seq-02"):
        load(root, "7scenes")


def test_tum_frames_without_pose_in_tolerance_are_skipped(tmp_path, scene):
    root = write(tmp_path, scene, "tum", skip=(2,))
    with pytest.warns(UserWarning, match="skipped 1 of 4") as record:
        ds = load(root, "tum")
    assert len(record) == 1 and ds.skipped == 1 and len(ds) == 3
    assert ds.frame_names == [f"{tum_stamp(k):.6f}" for k in (0, 1, 3)]
    np.testing.assert_allclose(ds[2].T_W_C, scene[2][3][1], atol=1e-6)
    # a wider tolerance takes the decoy pose 50 ms away instead
    wide = load(root, "tum", tolerance_s=0.06)
    assert wide.skipped == 0 and len(wide) == 4
    np.testing.assert_allclose(wide[2].T_W_C[:3, 3], [9, 9, 9])


def test_tum_intrinsics_presets(tmp_path, scene):
    root = write(tmp_path, scene, "tum", folder="rgbd_dataset_freiburg3_long_office")
    (root / "camera-intrinsics.txt").unlink()
    ds = load(root, "tum")
    np.testing.assert_allclose(ds.K, [[535.4, 0, 320.1], [0, 539.2, 247.6], [0, 0, 1]])
    assert ds.image_size == (640, 480)
    with pytest.raises(DataError, match="TUM fr3 intrinsics"):
        ds[0]  # the fixture's 64x48 images are not 640x480
    np.testing.assert_allclose(load(root, "tum", intrinsics="fr2").K[0], [520.9, 0, 325.1])
    plain = tmp_path / "recording"
    shutil.copytree(root, plain)
    with pytest.warns(UserWarning, match="Freiburg 1"):
        np.testing.assert_allclose(load(plain, "tum").K[1], [0, 516.5, 255.3])
    with pytest.raises(ConfigError, match="fr4"):
        TUMDataset(root, intrinsics="fr4")


def test_scannet_lost_tracking_frames_are_skipped(tmp_path, scene):
    root = write(tmp_path, scene, "scannet", lost=(2,))
    with pytest.warns(UserWarning, match="skipped 1 of 4") as record:
        ds = load(root, "scannet")
    assert len(record) == 1 and ds.skipped == 1 and ds.frame_names == ["0", "1", "3"]
    np.testing.assert_allclose(ds[2].T_W_C, scene[2][3][1], atol=1e-9)


def test_replica_without_cam_params_uses_nice_slam_camera(tmp_path, scene):
    root = write(tmp_path, scene, "replica")
    rgb = load(root, "replica", load_rgb=True)[0].rgb
    assert rgb.shape == (H, W, 3) and abs(int(rgb.mean()) - 90) <= 3
    (root / "cam_params.json").unlink()
    ds = load(root, "replica")
    np.testing.assert_allclose(ds.K, [[600, 0, 599.5], [0, 600, 339.5], [0, 0, 1]])
    assert ds.image_size == (1200, 680) and ds.depth_scale == 6553.5
    with pytest.raises(DataError, match="1200x680"):
        ds[0]
    assert ds.frame_names[0] == "frame000000"


def test_redwood_colour_and_primesense_default(tmp_path, scene):
    root = write(tmp_path, scene, "redwood")
    rgb = load(root, "redwood", load_rgb=True)[3].rgb
    assert rgb.shape == (H, W, 3) and abs(int(rgb.mean()) - 70) <= 3
    (root / "camera_intrinsic.json").unlink()
    with pytest.warns(UserWarning, match="PrimeSense"):
        ds = load(root, "redwood")
    np.testing.assert_allclose(ds.K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])


@pytest.mark.parametrize("fmt", ["ndc_isotropic", "ndc_norm_image_bounds"])
@pytest.mark.parametrize("size_wh", [(64, 48), (48, 64)])
def test_co3d_camera_projects_world_points_to_the_same_pixel(scene, fmt, size_wh):
    """A world point projected with PyTorch3D's own conventions (row vectors, NDC, +X left, +Y up,
    screen pixel centres at i + 0.5) lands on the pixel the converted OpenCV camera gives."""
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T = rng.normal(size=3) + [0, 0, 4.0]
    f, p = np.array([1.7, 2.1]), np.array([0.08, -0.05])
    K, T_W_C = pytorch3d_to_opencv(R, T, f, p, size_wh, fmt, "test")
    X_cam = rng.normal(size=(50, 3)) * 0.5 + [0, 0, 4.0]  # points in front of the camera
    X_world = (X_cam - T) @ R.T  # inverse of X_cam = X_world @ R + T
    ndc = f * X_cam[:, :2] / X_cam[:, 2:] + p
    half = 0.5 * np.array(size_wh, float)
    s = half.min() if fmt == "ndc_isotropic" else half
    pixel_p3d = half - ndc * s - 0.5  # NDC +x left/+y up -> pixels right/down, centres at integers
    p_C = (_inv(T_W_C) @ np.c_[X_world, np.ones(50)].T)[:3]
    uv = (K @ p_C)[:2] / p_C[2]
    np.testing.assert_allclose(uv.T, pixel_p3d, atol=1e-9)
    assert np.all(p_C[2] > 0)  # OpenCV z forward = PyTorch3D z forward
    # and the fixtures' encoder inverts the loader's conversion
    v = opencv_to_ndc(K, T_W_C, size_wh, fmt)
    K2, T2 = pytorch3d_to_opencv(v["R"], v["T"], v["focal_length"], v["principal_point"], size_wh, fmt, "test")
    np.testing.assert_allclose(K2, K, rtol=1e-12)
    np.testing.assert_allclose(T2, T_W_C, atol=1e-12)


def test_co3d_masks_sequences_and_voxel_suggestion(tmp_path, scene):
    extra = {"sequence_name": "seq_b", "frame_number": 0, "image": {"path": "x.jpg", "size": [H, W]}}
    root = write(tmp_path, scene, "co3d", extra=[extra])
    with pytest.raises(DataError, match="seq_a, seq_b"):
        open_dataset(root)
    ds = open_dataset(root, sequence="seq_a")
    masked = open_dataset(root, sequence="seq_a", use_masks=True)
    d, dm = ds[0].depth_m, masked[0].depth_m
    assert np.any(d[:, :10] > 0) and np.all(dm[:, :10] == 0)
    np.testing.assert_array_equal(dm[:, 10:], d[:, 10:])
    assert ds.frame_names == ["seq_a/1", "seq_a/11", "seq_a/21", "seq_a/31"]
    centres = np.array([T[:3, 3] for _, T in scene[2]])
    extent = np.linalg.norm(centres.max(0) - centres.min(0))
    assert ds.suggested_voxel_m == pytest.approx(extent / 256, rel=1e-9)
    with pytest.raises(DataError, match="seq_c"):
        open_dataset(root, sequence="seq_c")
    with pytest.raises(ConfigError, match="use_masks"):
        open_dataset(write(tmp_path, scene, "folder"), use_masks=True)


def test_co3d_unknown_intrinsics_format_names_the_frame(tmp_path, scene):
    root = write(tmp_path, scene, "co3d")
    with gzip.open(root / "frame_annotations.jgz", "rt") as f:
        entries = json.load(f)
    entries[2]["viewpoint"]["intrinsics_format"] = "screen"
    with gzip.open(root / "frame_annotations.jgz", "wt") as f:
        json.dump(entries, f)
    ds = CO3DDataset(root)
    with pytest.raises(DataError, match="frame 21: intrinsics_format 'screen'"):
        ds[2]


def test_folder_pose_convention_and_depth_scale(tmp_path, scene):
    root = write(tmp_path, scene, "folder_tcw")
    # read as T_W_C, the world-to-camera poses come out inverted
    wrong = open_dataset(root)
    np.testing.assert_allclose(wrong[0].T_W_C, np.linalg.inv(scene[2][0][1]), atol=1e-9)
    halved = load(root, "folder_tcw", depth_scale=2.0)  # .npy divided only when the scale is given
    np.testing.assert_allclose(halved[0].depth_m, scene[2][0][0] / 2, rtol=1e-6)  # all > 0.1 m
    with pytest.raises(ConfigError, match="T_X_Y"):
        open_dataset(root, pose_convention="T_X_Y")
    with pytest.raises(ConfigError, match="folder format"):
        open_dataset(write(tmp_path, scene, "scannet"), pose_convention="T_C_W")
    mm = write(tmp_path, scene, "folder")
    assert open_dataset(mm, depth_scale=0).depth_scale == 1000.0  # 0 = the format's default


def test_config_accepts_depth_scale_and_pose_convention():
    cfg = load_config(None, ["scene.format=folder", "scene.depth_scale=5000.0", "scene.pose_convention=T_C_W"])
    assert cfg.scene.depth_scale == 5000.0 and cfg.scene.pose_convention == "T_C_W"
    assert set(FORMATS) >= {"tum", "replica", "scannet", "co3d", "redwood", "folder"}
    with pytest.raises(ConfigError, match="pose_convention"):
        load_config(None, ["scene.pose_convention=C_W"])
    with pytest.raises(ConfigError, match="folder format only"):
        load_config(None, ["scene.format=tum", "scene.pose_convention=T_C_W"])


def test_ambiguous_and_unknown_folders_list_what_each_format_looks_for(tmp_path, scene):
    root = write(tmp_path, scene, "scannet")
    write_redwood(root, scene[1], scene[2])  # now also a Redwood folder
    with pytest.raises(DataError, match="several dataset layouts") as e:
        detect_format(root)
    msg = str(e.value)
    assert "scannet, redwood" in msg and "groundtruth.txt" in msg and "frame_annotations" in msg
    empty = tmp_path / "empty"
    (empty / "depth").mkdir(parents=True)
    with pytest.raises(DataError, match="no known dataset layout") as e:
        detect_format(empty)
    assert all(name in str(e.value) for name in FORMATS)
