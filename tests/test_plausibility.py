"""Plausibility checks of a run's input (bftaichi.plausibility, issue 17 "silent wrong results").

Each check gets its warning (stderr, also with -q, and report.json ``warnings``) and, with
--strict, its refusal (exit 2, nothing written) on a mutated copy of real or synthetic frames:
transposed depth, an 8-bit depth PNG (or a grey JPEG named .png), inverted poses, a depth scale
off by 10, a GPU backend that falls back to the CPU. None fires on the shipped data: the
redkitchen frames, the synthetic scenes of scenes/*.toml (full size and tiny), and the fixture of
every format in tests/test_datasets_formats.py.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bftaichi.cli import main
from bftaichi.config import load_config
from bftaichi.formats import open_dataset
from bftaichi.formats.base import principal_point_misfit
from bftaichi.plausibility import (GIVEN_CONFLICT, ImplausibleInputError, PlausibilityWarning,
                                   check_inputs, frame_consistency)
from bftaichi.running.pipeline import open_frames
from robustness_cases import TINY, frames_7scenes
from test_datasets_formats import SPECS, load, scene, write  # noqa: F401  (scene: a fixture)

ROOT = Path(__file__).resolve().parents[1]
REDKITCHEN = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"
needs_kitchen = pytest.mark.skipif(not REDKITCHEN.is_dir(),
                                   reason="shared redkitchen frames not present")
QUICK = ("--set", "run.plots=false", "--set", "run.preview=false",
         "--set", "run.stages=tsdf_only")


def _cli(args) -> tuple[int, str]:
    """Exit code and stderr of ``bftaichi ARGS`` run in-process."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, err.getvalue()


def _fuse(data: Path, out: Path, *extra, voxel="0.03") -> list[str]:
    return ["fuse", str(data), "--voxel", voxel, "-q", "--out", str(out), *QUICK, *extra]


def _warns(args, out: Path, code: str) -> dict:
    """Run ``args`` (writing into ``out``): exit 0, the ``code`` warning on stderr and in
    report.json; return the report."""
    rc, err = _cli(args)
    assert rc == 0, err
    assert "warning: " in err and f"[{code}]" in err, err
    report = json.loads((out / "report.json").read_text())
    assert code in [w["code"] for w in report["warnings"]], report["warnings"]
    return report


def _refuses(args, out: Path, code: str) -> str:
    """Run ``args`` with --strict: exit 2, the refusal names ``code``, nothing written."""
    rc, err = _cli([*args, "--strict"])
    assert rc == 2, err
    assert "error: run.strict (--strict) refuses" in err and f"[{code}]" in err, err
    assert not (out / "report.json").exists() and not (out / "tsdf_mesh.ply").exists()
    return err


@pytest.fixture
def tiny(tmp_path) -> Path:
    """A 3-frame 7scenes copy of the tiny tabletop (64x48), without its ground truth (the
    metrics of a mesh fused from broken frames are slow and beside the point)."""
    data = tmp_path / "tiny"
    shutil.copytree(frames_7scenes(tmp_path / "src"), data)
    (data / "gt_mesh.ply").unlink()
    return data


def _kitchen(tmp_path, numbers) -> Path:
    """A 7scenes folder with the redkitchen frames ``numbers`` (depth, pose, intrinsics)."""
    data = tmp_path / "kitchen"
    data.mkdir()
    shutil.copy(REDKITCHEN / "camera-intrinsics.txt", data)
    for k in numbers:
        for suffix in ("depth.png", "pose.txt"):
            shutil.copy(REDKITCHEN / f"frame-{k:06d}.{suffix}", data)
    return data


def _invert_pose_files(data: Path) -> None:
    for p in data.glob("*.pose.txt"):
        np.savetxt(p, np.linalg.inv(np.loadtxt(p)))


# --------------------------------------------------------------------------------------------
# Image size against K
# --------------------------------------------------------------------------------------------

def test_principal_point_rule_is_exact_and_accepts_off_centre_cameras():
    K = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
    assert principal_point_misfit(K, 640, 480) is None
    assert principal_point_misfit(K, 480, 640) == ("transposed", (640, 480))
    assert principal_point_misfit(K, 1280, 960)[0] == "scaled"  # K for half the resolution
    assert principal_point_misfit(K, 320, 240)[0] == "outside"  # K for twice the resolution
    assert principal_point_misfit(K, 480, 480) is None  # square: never "transposed"
    for cx, cy in ((320.0, 420.0), (80.0, 240.0), (600.0, 30.0)):  # far off centre, one axis
        K2 = K.copy()
        K2[0, 2], K2[1, 2] = cx, cy
        assert principal_point_misfit(K2, 640, 480) is None, (cx, cy)
    K3 = K.copy()
    K3[0, 2], K3[1, 2] = 300.0, 270.0  # off centre toward the transposed centre on both axes
    assert principal_point_misfit(K3, 640, 480) is None  # still nearer its own centre
    assert principal_point_misfit(K3, 480, 640)[0] == "transposed"


@needs_kitchen
def test_transposed_depth_warns_and_strict_refuses(tmp_path):
    """The issue's case: 480x640 depth images with the K of the 640x480 Kinect (the 20 %
    principal-point tolerance used to let them through)."""
    data = _kitchen(tmp_path, (0, 10))
    for p in data.glob("*.depth.png"):
        Image.fromarray(np.ascontiguousarray(np.array(Image.open(p)).T)).save(p)
    args = _fuse(data, tmp_path / "out", voxel="0.05")
    report = _warns(args, tmp_path / "out", "image_size")
    message = next(w["message"] for w in report["warnings"] if w["code"] == "image_size")
    assert "frame-000000.depth.png" in message and "480x640" in message
    assert "transposed" in message
    _refuses(_fuse(data, tmp_path / "strict", voxel="0.05"), tmp_path / "strict", "image_size")


# --------------------------------------------------------------------------------------------
# Depth bit depth and range
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["png8", "grey_jpeg"])
def test_8bit_depth_warns_every_run_and_strict_refuses(tmp_path, tiny, kind):
    for p in tiny.glob("*.depth.png"):
        grey = np.clip(np.array(Image.open(p)) // 8, 0, 255).astype(np.uint8)
        Image.fromarray(grey).save(p, format="PNG" if kind == "png8" else "JPEG")
    out = tmp_path / "out"
    report = _warns(_fuse(tiny, out), out, "depth_8bit")
    assert "frame-000000.depth.png" in report["warnings"][0]["message"]
    # the same warning again in the same process (Python shows a warning once by default)
    _warns(_fuse(tiny, out, "--overwrite"), out, "depth_8bit")
    _refuses(_fuse(tiny, tmp_path / "strict"), tmp_path / "strict", "depth_8bit")


@needs_kitchen
def test_depth_scale_10x_too_large_warns_about_the_range_before_the_run_fails(tmp_path):
    """Depth read at 100 units per metre: 8-35 m instead of 0.8-3.5, beyond depth_max_m = 6.
    Both the range and the consistency checks name the fix; the run then finds no surface."""
    data = _kitchen(tmp_path, range(0, 500, 50))
    args = _fuse(data, tmp_path / "out", "--depth-scale", "100", voxel="0.05")
    rc, err = _cli(args)
    assert "[depth_range]" in err and "--depth-scale 1000" in err, err
    assert "[depth_scale]" in err, err
    assert rc == 2 and "no surface was observed" in err  # warned first, then the known error
    strict = tmp_path / "strict"
    _refuses(_fuse(data, strict, "--depth-scale", "100", voxel="0.05"), strict, "depth_range")


@needs_kitchen
def test_depth_range_check_uses_the_scene_range():
    """scenes/redkitchen.toml keeps 0.3-4 m: depth 10x too small (median 0.18 m) is below it."""
    cfg = load_config(ROOT / "scenes" / "redkitchen.toml",
                      ["scene.depth_scale=10000", "scene.frames=0:500:50"])
    with pytest.warns(PlausibilityWarning) as caught:
        checks = check_inputs(cfg, open_frames(cfg))
    codes = [f.code for f in checks.findings]
    assert codes == ["depth_range", "depth_scale"], codes
    assert checks.measured["depth_range"]["median_m"] < 0.3
    assert len(caught) == 2


# --------------------------------------------------------------------------------------------
# Frame consistency: pose convention and depth scale
# --------------------------------------------------------------------------------------------

def test_inverted_poses_warn_and_strict_refuses(tmp_path, tiny):
    _invert_pose_files(tiny)
    out = tmp_path / "out"
    report = _warns(_fuse(tiny, out), out, "pose_convention")
    c = report["checks"]["consistency"]
    assert c["given"]["conflict"] > 0.5 and c["T_C_W"]["conflict"] < 0.1
    _refuses(_fuse(tiny, tmp_path / "strict"), tmp_path / "strict", "pose_convention")


@needs_kitchen
def test_inverted_poses_of_real_frames_warn(tmp_path):
    data = _kitchen(tmp_path, range(100, 200, 12))
    _invert_pose_files(data)
    out = tmp_path / "out"
    report = _warns(_fuse(data, out, voxel="0.05"), out, "pose_convention")
    assert "invert the pose files" in report["warnings"][0]["message"]


def test_folder_poses_read_with_the_wrong_convention_warn(tmp_path, scene):
    """The folder format says how to fix it: --pose-convention (here: drop it)."""
    root = write(tmp_path, scene, "folder")  # T_W_C files
    cfg = load_config(None, ["scene.source=dataset", f"scene.data={json.dumps(str(root))}",
                             "scene.pose_convention=T_C_W"])
    with pytest.warns(PlausibilityWarning, match="drop --pose-convention T_C_W") as record:
        check_inputs(cfg, open_frames(cfg))
    assert any("drop --pose-convention T_C_W" in str(w.message) for w in record)


def test_depth_scale_10x_too_small_warns_and_strict_refuses(tmp_path, tiny):
    """Depth read at 10000 units per metre (a scene 10x too small): within the depth range,
    so only the frames' consistency shows it."""
    out = tmp_path / "out"
    args = _fuse(tiny, out, "--depth-scale", "10000")
    report = _warns(args, out, "depth_scale")
    assert [w["code"] for w in report["warnings"]] == ["depth_scale"]
    assert "--depth-scale 1000 " in report["warnings"][0]["message"]
    _refuses(_fuse(tiny, tmp_path / "strict", "--depth-scale", "10000"), tmp_path / "strict",
             "depth_scale")


def test_a_single_frame_skips_the_consistency_check(tiny):
    frames = open_dataset(tiny)
    assert frame_consistency([frames[0]]) is None
    assert frame_consistency([frames[0], frames[1]])["pairs"] == 1


# --------------------------------------------------------------------------------------------
# Backend fallback
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("arch", ["cuda", "gpu"])
def test_gpu_fallback_is_recorded_as_cpu_and_warns(tmp_path, arch):
    """This machine has no GPU: Taichi falls back to the CPU; report.json and config.toml say
    so (``gpu`` must not crash on Taichi's OpenGL probe)."""
    out = tmp_path / "out"
    args = ["run", "-q", "--out", str(out), "--arch", arch,
            *[a for s in (*TINY, "run.stages=tsdf_only") for a in ("--set", s)]]
    report = _warns(args, out, "backend_fallback")
    assert report["machine"]["arch"] == "cpu" and report["machine"]["arch_requested"] == arch
    assert report["config"]["run"]["arch"] == "cpu"
    assert tomllib.loads((out / "config.toml").read_text())["run"]["arch"] == "cpu"
    _refuses([*args[:2], "--out", str(tmp_path / "strict"), *args[4:]], tmp_path / "strict",
             "backend_fallback")


# --------------------------------------------------------------------------------------------
# No warning on the shipped data
# --------------------------------------------------------------------------------------------

def _assert_silent(cfg, frames):
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlausibilityWarning)
        checks = check_inputs(cfg, frames)
    assert checks.findings == []
    return checks


@needs_kitchen
def test_no_warning_on_the_redkitchen_frames(tmp_path):
    out = tmp_path / "out"
    rc, err = _cli(_fuse(REDKITCHEN, out, "--frames", "0:500:50", voxel="0.05"))
    assert rc == 0 and "warning" not in err, err
    report = json.loads((out / "report.json").read_text())
    assert report["warnings"] == [] and report["machine"]["arch"] == "cpu"
    # all 500 frames with the scene file's range; the margins of the consistency check
    cfg = load_config(ROOT / "scenes" / "redkitchen.toml")
    c = _assert_silent(cfg, open_frames(cfg)).measured["consistency"]
    assert c["pairs"] >= 10
    assert c["given"]["conflict"] < GIVEN_CONFLICT / 3 < GIVEN_CONFLICT < c["T_C_W"]["conflict"]
    assert c["given"]["agree"] > c["depth_x10"]["agree"] + 0.1


@pytest.mark.parametrize("path", sorted((ROOT / "scenes").glob("*.toml")), ids=lambda p: p.stem)
def test_no_warning_on_the_shipped_synthetic_scenes(path):
    if load_config(path).scene.source != "synthetic":
        pytest.skip("a recorded dataset (test_no_warning_on_the_redkitchen_frames)")
    for sets in ([], list(TINY)):
        cfg = load_config(path, sets)
        _assert_silent(cfg, open_frames(cfg))


@pytest.mark.parametrize("name", list(SPECS))
def test_no_warning_on_any_format_fixture(tmp_path, scene, name):
    root = write(tmp_path, scene, name)
    ds = load(root, name)
    cfg = load_config(None, ["scene.source=dataset", f"scene.data={json.dumps(str(root))}"])
    checks = _assert_silent(cfg, ds)
    assert checks.measured["consistency"]["pairs"] >= 3  # the check ran on overlapping frames


def test_strict_error_lists_every_finding(tiny):
    """8-bit depth in centimetres (read right with depth_scale 100), inverted poses and a GPU
    fallback: one refusal names all three."""
    for p in tiny.glob("*.depth.png"):
        cm = np.array(Image.open(p)) // 10
        assert cm.max() <= 255
        Image.fromarray(cm.astype(np.uint8)).save(p)
    _invert_pose_files(tiny)
    cfg = load_config(None, ["scene.source=dataset", f"scene.data={json.dumps(str(tiny))}",
                             "scene.depth_scale=100", "run.arch=cuda", "run.strict=true"])
    with pytest.raises(ImplausibleInputError) as e:
        check_inputs(cfg, open_frames(cfg))
    codes = [line.rsplit("[", 1)[1].rstrip("]") for line in str(e.value).splitlines()
             if line.startswith("  - ")]
    assert codes == ["backend_fallback", "depth_8bit", "pose_convention"], str(e.value)
