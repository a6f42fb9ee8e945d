"""Dataset loaders: 7scenes and bfsdf layouts, format detection, invalid depth, validation errors."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bftaichi.formats import (
    FORMATS,
    BFSDFDataset,
    Dataset,
    SevenScenesDataset,
    detect_format,
    open_dataset,
)
from bftaichi.errors import DataError
from bftaichi.geometry import look_at

W, H = 8, 6
N_FRAMES = 3
FX, FY, CX, CY = 7.0, 6.5, 3.5, 2.5
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _depth_mm(i: int) -> np.ndarray:
    """Frame i's raw depth in millimetres: a ramp 1000 + 10*i + pixel number (all valid)."""
    return (1000 + 10 * i + np.arange(W * H).reshape(H, W)).astype(np.uint16)


def _pose(i: int) -> np.ndarray:
    return look_at([1.0 + 0.1 * i, -0.5, 0.8], [0.0, 0.0, 0.0])


def _write_pose(path: Path, T: np.ndarray) -> None:
    np.savetxt(path, T)


def _write_png(path: Path, a: np.ndarray) -> None:
    Image.fromarray(a).save(path)


def make_7scenes(root: Path, n: int = N_FRAMES, intrinsics: bool = True, color: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        _write_png(root / f"frame-{i:06d}.depth.png", _depth_mm(i))
        _write_pose(root / f"frame-{i:06d}.pose.txt", _pose(i))
        if color:
            rgb = np.full((H, W, 3), (10 * i, 100, 200), np.uint8)
            Image.fromarray(rgb).save(root / f"frame-{i:06d}.color.jpg", quality=100)
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    return root


def make_bfsdf(root: Path, n: int = N_FRAMES, color: bool = False) -> Path:
    for sub in ("depth", "pose", "intrinsic", "color"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        _write_png(root / "depth" / f"{i:06d}.png", _depth_mm(i))
        _write_pose(root / "pose" / f"{i:06d}.txt", _pose(i))
        if color:
            _write_png(root / "color" / f"{i:06d}.png", np.full((H, W, 3), (10 * i, 100, 200), np.uint8))
    (root / "intrinsic" / "intrinsic.txt").write_text(f"{W} {H}\n{FX} {FY} {CX} {CY}\n")
    return root


def _corrupt(path: Path, mode: str) -> None:
    if mode == "garbage":
        path.write_bytes(b"this is not a png at all" * 10)
    else:  # truncated: a valid header, half of the data
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])


K_EXPECTED = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]])


# --------------------------------------------------------------------------------------------
# Loading the two layouts
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
def test_frames_load_in_metres_with_pose_and_K(tmp_path, fmt):
    root = make_7scenes(tmp_path / "seq") if fmt == "7scenes" else make_bfsdf(tmp_path / "seq")
    ds = open_dataset(root)
    assert ds.format == fmt and isinstance(ds, FORMATS[fmt])
    assert len(ds) == N_FRAMES and ds.name == "seq" and ds.path == root
    np.testing.assert_allclose(ds.K, K_EXPECTED)
    assert ds.K.dtype == np.float64 and ds.gt_mesh_path is None and ds.load_rgb is False
    frames = list(ds)
    expected_names = ([f"frame-{i:06d}" for i in range(N_FRAMES)] if fmt == "7scenes"
                      else [f"{i:06d}" for i in range(N_FRAMES)])
    assert [f.name for f in frames] == expected_names
    for i, f in enumerate(frames):
        assert f.index == i
        assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (H, W)
        np.testing.assert_allclose(f.depth_m, _depth_mm(i) / 1000.0, rtol=1e-6)
        np.testing.assert_allclose(f.T_W_C, _pose(i), atol=1e-12)
        np.testing.assert_allclose(f.K, K_EXPECTED)
        assert f.rgb is None
    assert ds.image_size == (W, H)
    # negative indices count from the end; out of range is an IndexError
    assert ds[-1].index == N_FRAMES - 1
    with pytest.raises(IndexError):
        ds[N_FRAMES]
    with pytest.raises(IndexError):
        ds[-N_FRAMES - 1]


def test_depth_scale_override(tmp_path):
    ds = open_dataset(make_bfsdf(tmp_path / "seq"), depth_scale=5000.0, depth_min_m=0.0)
    np.testing.assert_allclose(ds[0].depth_m, _depth_mm(0) / 5000.0, rtol=1e-6)


@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
def test_rgb_loaded_only_when_asked(tmp_path, fmt):
    maker = make_7scenes if fmt == "7scenes" else make_bfsdf
    root = maker(tmp_path / "seq", color=True)
    assert open_dataset(root)[1].rgb is None
    rgb = open_dataset(root, load_rgb=True)[1].rgb
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8
    np.testing.assert_allclose(rgb[..., 1].astype(float), 100, atol=3)  # jpeg is lossy
    assert abs(int(rgb[..., 0].mean()) - 10) <= 3


def test_frames_sorted_by_number_not_listing_order(tmp_path):
    root = tmp_path / "seq"
    root.mkdir()
    for number in (10, 2, 7):
        _write_png(root / f"frame-{number:06d}.depth.png", _depth_mm(number))
        _write_pose(root / f"frame-{number:06d}.pose.txt", _pose(0))
    np.savetxt(root / "camera-intrinsics.txt", K_EXPECTED)
    ds = open_dataset(root)
    assert ds.frame_names == ["frame-000002", "frame-000007", "frame-000010"]
    np.testing.assert_allclose(ds[2].depth_m, _depth_mm(10) / 1000.0, rtol=1e-6)


def test_bfsdf_unpadded_stems_sort_numerically(tmp_path):
    root = make_bfsdf(tmp_path / "seq", n=0)
    for number in (10, 9, 1):
        _write_png(root / "depth" / f"{number}.png", _depth_mm(number))
        _write_pose(root / "pose" / f"{number}.txt", _pose(0))
    assert open_dataset(root).frame_names == ["1", "9", "10"]


def test_gt_mesh_path_found(tmp_path):
    root = make_bfsdf(tmp_path / "seq")
    (root / "gt_mesh.ply").write_bytes(b"ply\n")
    assert open_dataset(root).gt_mesh_path == root / "gt_mesh.ply"


def test_7scenes_without_intrinsics_warns_and_uses_published_K(tmp_path):
    root = tmp_path / "seq"
    root.mkdir()
    _write_png(root / "frame-000000.depth.png", np.full((480, 640), 1500, np.uint16))
    _write_pose(root / "frame-000000.pose.txt", np.eye(4))
    with pytest.warns(UserWarning, match="published 7-Scenes intrinsics"):
        ds = open_dataset(root)
    np.testing.assert_allclose(ds.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    assert ds[0].depth_m.shape == (480, 640)
    # the published K is for 640x480: a differently sized sequence must not silently use it
    small = make_7scenes(tmp_path / "small", intrinsics=False)
    with pytest.warns(UserWarning):
        ds_small = open_dataset(small)
    with pytest.raises(DataError, match="frame-000000.depth.png"):
        ds_small[0]


# --------------------------------------------------------------------------------------------
# Laziness, slicing
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_corrupt_frame_only_breaks_itself(tmp_path, fmt, damage):
    if fmt == "7scenes":
        root = make_7scenes(tmp_path / "seq")
        bad = root / "frame-000002.depth.png"
    else:
        root = make_bfsdf(tmp_path / "seq")
        bad = root / "depth" / "000002.png"
    _corrupt(bad, damage)
    ds = open_dataset(root)  # opening reads no depth image
    assert len(ds) == N_FRAMES
    np.testing.assert_allclose(ds[0].depth_m, _depth_mm(0) / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(ds[1].depth_m, _depth_mm(1) / 1000.0, rtol=1e-6)
    with pytest.raises(DataError, match=re.escape(str(bad))):
        ds[2]


def test_frames_slice_and_subset_keep_original_indices(tmp_path):
    root = make_7scenes(tmp_path / "seq", n=7)
    ds = open_dataset(root, frames=slice(1, None, 2))
    assert len(ds) == 3 and ds.indices == [1, 3, 5]
    f = ds[1]
    assert f.index == 3 and f.name == "frame-000003"
    np.testing.assert_allclose(f.depth_m, _depth_mm(3) / 1000.0, rtol=1e-6)
    sub = ds.subset(slice(1, None))  # a view of a view still reports original indices
    assert [fr.index for fr in sub] == [3, 5]
    picked = open_dataset(root).subset([0, 1, 4])  # positions: evalviews' blocks
    assert picked.indices == [0, 1, 4] and [fr.index for fr in picked.subset([2])] == [4]
    with pytest.raises(TypeError, match="slice or a list"):
        ds.subset(1)
    assert [fr.index for fr in open_dataset(root)[::-3]] == [6, 3, 0]
    assert len(open_dataset(root)) == 7  # the parent is not changed by subsetting
    with pytest.raises(DataError, match="selects none"):
        open_dataset(root, frames=slice(10, 20))


# --------------------------------------------------------------------------------------------
# Format detection
# --------------------------------------------------------------------------------------------

def test_detect_format_picks_each_layout(tmp_path):
    assert detect_format(make_7scenes(tmp_path / "a")) == "7scenes"
    assert detect_format(make_bfsdf(tmp_path / "b")) == "bfsdf"
    assert set(FORMATS) >= {"7scenes", "bfsdf"}
    assert all(issubclass(cls, Dataset) and cls.format == name for name, cls in FORMATS.items())


def test_unknown_folder_names_formats_and_content(tmp_path):
    root = tmp_path / "mystery"
    root.mkdir()
    (root / "image_0001.jpg").write_bytes(b"x")
    (root / "calib").mkdir()
    with pytest.raises(DataError) as e:
        open_dataset(root)
    msg = str(e.value)
    assert "7scenes" in msg and "bfsdf" in msg and "image_0001.jpg" in msg and "calib/" in msg


def test_missing_folder_and_empty_dataset(tmp_path):
    with pytest.raises(DataError, match="does-not-exist"):
        open_dataset(tmp_path / "does-not-exist")
    root = make_bfsdf(tmp_path / "empty", n=0)
    with pytest.raises(DataError, match="no frames"):
        open_dataset(root)
    with pytest.raises(DataError, match="no frames"):
        SevenScenesDataset(tmp_path / "empty")


# --------------------------------------------------------------------------------------------
# Invalid depth
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
def test_invalid_depth_becomes_zero(tmp_path, fmt):
    root = make_7scenes(tmp_path / "seq", n=1) if fmt == "7scenes" else make_bfsdf(tmp_path / "seq", n=1)
    raw = np.full((H, W), 2000, np.uint16)
    raw[0, 0] = 0          # no measurement
    raw[0, 1] = 65535      # 7-Scenes "invalid" code (65.5 m: out of range for bfsdf too)
    raw[0, 2] = 50         # 0.05 m < depth_min
    raw[0, 3] = 7000       # 7 m > depth_max
    raw[0, 4] = 500        # exactly depth_min: kept
    depth_path = root / "frame-000000.depth.png" if fmt == "7scenes" else root / "depth" / "000000.png"
    _write_png(depth_path, raw)
    d = open_dataset(root, depth_min_m=0.5, depth_max_m=6.0)[0].depth_m
    np.testing.assert_array_equal(d[0, :4], 0.0)
    assert d[0, 4] == pytest.approx(0.5)
    assert np.all(d[1:] == np.float32(2.0))
    assert np.count_nonzero(d == 0) == 4


def test_65535_invalid_even_with_huge_depth_max(tmp_path):
    root = make_7scenes(tmp_path / "seq", n=1)
    raw = np.full((H, W), 2000, np.uint16)
    raw[2, 3] = 65535
    _write_png(root / "frame-000000.depth.png", raw)
    d = open_dataset(root, depth_max_m=100.0)[0].depth_m
    assert d[2, 3] == 0 and np.count_nonzero(d == 0) == 1


def test_8bit_depth_accepted(tmp_path):
    root = make_bfsdf(tmp_path / "seq", n=1)
    _write_png(root / "depth" / "000000.png", np.full((H, W), 200, np.uint8))
    d = open_dataset(root, depth_scale=100.0)[0].depth_m
    np.testing.assert_allclose(d, 2.0)


def test_32bit_integer_depth_checked_by_range(tmp_path):
    # Pillow reads 32-bit integer images as mode "I"; a TIFF under a .png name is opened by content.
    root = make_bfsdf(tmp_path / "seq", n=2)
    ok = np.full((H, W), 1500, np.int32)
    Image.fromarray(ok).save(root / "depth" / "000000.png", format="TIFF")
    assert Image.open(root / "depth" / "000000.png").mode == "I"
    ds = open_dataset(root)
    np.testing.assert_allclose(ds[0].depth_m, 1.5)
    bad = np.full((H, W), 70000, np.int32)
    Image.fromarray(bad).save(root / "depth" / "000001.png", format="TIFF")
    with pytest.raises(DataError, match="000001.png"):
        ds[1]


# --------------------------------------------------------------------------------------------
# Validation errors name the file
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
def test_missing_pose_file(tmp_path, fmt):
    if fmt == "7scenes":
        root = make_7scenes(tmp_path / "seq")
        pose = root / "frame-000001.pose.txt"
    else:
        root = make_bfsdf(tmp_path / "seq")
        pose = root / "pose" / "000001.txt"
    pose.unlink()
    with pytest.raises(DataError, match=re.escape(str(pose))):
        open_dataset(root, format=fmt)


@pytest.mark.parametrize("image", ["rgb", "float"])
def test_depth_not_single_channel_integer(tmp_path, image):
    root = make_bfsdf(tmp_path / "seq")
    bad = root / "depth" / "000001.png"
    if image == "rgb":
        _write_png(bad, np.zeros((H, W, 3), np.uint8))
        match = "3-channel"
    else:
        Image.fromarray(np.ones((H, W), np.float32)).save(bad, format="TIFF")
        match = "single-channel 16-bit or 8-bit"
    ds = open_dataset(root)
    with pytest.raises(DataError, match=match) as e:
        ds[1]
    assert str(bad) in str(e.value)


def test_bfsdf_depth_size_must_match_intrinsics(tmp_path):
    root = make_bfsdf(tmp_path / "seq")
    bad = root / "depth" / "000000.png"  # the first frame: the intrinsics, not frame 0, set the size
    _write_png(bad, np.full((H, W + 1), 1000, np.uint16))
    ds = open_dataset(root)
    with pytest.raises(DataError, match="intrinsic.txt") as e:
        ds[0]
    assert str(bad) in str(e.value) and f"{W + 1}x{H}" in str(e.value)
    assert ds[1].depth_m.shape == (H, W)


def test_7scenes_depth_size_must_match_first_frame(tmp_path):
    root = make_7scenes(tmp_path / "seq")
    bad = root / "frame-000002.depth.png"
    _write_png(bad, np.full((H + 2, W), 1000, np.uint16))
    ds = open_dataset(root)
    ds[0]
    with pytest.raises(DataError, match=re.escape(str(bad))):
        ds[2]


@pytest.mark.parametrize("problem", ["nan", "inf", "scaled", "last_row", "reflection", "15_values", "word"])
@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf"])
def test_bad_pose_names_pose_file(tmp_path, fmt, problem):
    if fmt == "7scenes":
        root = make_7scenes(tmp_path / "seq")
        pose = root / "frame-000001.pose.txt"
    else:
        root = make_bfsdf(tmp_path / "seq")
        pose = root / "pose" / "000001.txt"
    T = _pose(1)
    if problem == "nan":
        T[0, 3] = np.nan
    elif problem == "inf":
        T[1, 1] = np.inf
    elif problem == "scaled":
        T[:3, :3] *= 1.1
    elif problem == "last_row":
        T[3] = [0, 0, 1, 1]
    elif problem == "reflection":
        T[:3, 0] *= -1
    if problem == "15_values":
        pose.write_text(" ".join(str(v) for v in T.ravel()[:15]))
    elif problem == "word":
        pose.write_text(" ".join(str(v) for v in T.ravel()[:15]) + " one")
    else:
        _write_pose(pose, T)
    ds = open_dataset(root)
    ds[0]  # other frames are unaffected
    with pytest.raises(DataError, match=re.escape(str(pose))):
        ds[1]


@pytest.mark.parametrize("content", [
    "7 0 3.5\n0 6.5 2.5\n0 0 1\n0\n",      # 10 values
    "-7 0 3.5\n0 6.5 2.5\n0 0 1\n",        # negative focal length (check_K)
    "7 0 3.5\n0 6.5 2.5\n0 0 nan\n",       # NaN
    "7 0 3.5\n0 6.5 2.5\n0 0 x\n",         # not a number
])
def test_7scenes_bad_intrinsics(tmp_path, content):
    root = make_7scenes(tmp_path / "seq")
    k_path = root / "camera-intrinsics.txt"
    k_path.write_text(content)
    with pytest.raises(DataError, match=re.escape(str(k_path))):
        open_dataset(root)


@pytest.mark.parametrize("content", [
    f"{W} {H}\n{FX} {FY} {CX}\n",            # 3 parameters
    f"{W}\n{FX} {FY} {CX} {CY}\n",           # size without height
    f"{W} {H} {FX} {FY} {CX} {CY}\n",        # one line
    f"{W} {H}\n0 {FY} {CX} {CY}\n",          # zero focal length (check_K)
    f"{W}.5 {H}\n{FX} {FY} {CX} {CY}\n",     # fractional width
    f"{W} {H}\n{FX} {FY} {CX} cy\n",         # not a number
])
def test_bfsdf_bad_intrinsics(tmp_path, content):
    root = make_bfsdf(tmp_path / "seq")
    k_path = root / "intrinsic" / "intrinsic.txt"
    k_path.write_text(content)
    with pytest.raises(DataError, match=re.escape(str(k_path))):
        BFSDFDataset(root)


def test_unknown_format_name_is_rejected(tmp_path):
    root = make_bfsdf(tmp_path / "seq")
    with pytest.raises(ValueError, match="bfsdf"):
        open_dataset(root, format="kitti")


# --------------------------------------------------------------------------------------------
# Real data
# --------------------------------------------------------------------------------------------

REDKITCHEN = SHARED_DATA / "rgbd" / "7scenes-redkitchen"


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason="shared 7-Scenes redkitchen data not present")
def test_real_7scenes_redkitchen():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the folder has camera-intrinsics.txt: no fallback warning
        ds = open_dataset(REDKITCHEN)
    assert ds.format == "7scenes" and len(ds) == 500
    assert ds.K[0, 0] == pytest.approx(585.0) and ds.K[1, 1] == pytest.approx(585.0)
    f0 = ds[0]
    assert f0.depth_m.shape == (480, 640) and ds.image_size == (640, 480)
    invalid = np.mean(f0.depth_m == 0)
    assert 0.05 < invalid < 0.25
    valid = f0.depth_m[f0.depth_m > 0]
    assert 0.3 < valid.min() and valid.max() < 4.5  # README: valid depth about 0.8-3.5 m
    last = ds[-1]
    assert last.index == 499 and last.name == "frame-000499"
    np.testing.assert_allclose(last.T_W_C[3], [0, 0, 0, 1])
