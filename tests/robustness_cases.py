"""The bad-input catalogue of docs/robustness.md: each case builds its input in a folder, runs
one ``bftaichi`` command in-process and says what the user must see (exit code and a regular
expression the message must match). tests/test_robustness.py runs every case;
tools/robustness_catalogue.py runs them and writes the table with the messages users get.
"""

from __future__ import annotations

import contextlib
import errno
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

TINY = ("synthetic.width=64", "synthetic.height=48", "synthetic.fx=52.5", "synthetic.fy=52.5",
        "synthetic.cx=31.5", "synthetic.cy=23.5", "synthetic.n_views=3",
        "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06", "eval.n_samples=3000",
        "run.plots=false", "run.preview=false")


def sets(*extra) -> list[str]:
    return [a for s in (*TINY, *extra) for a in ("--set", s)]


def frames_7scenes(root: Path) -> Path:
    """A valid 3-frame 7scenes folder of the tiny tabletop (written once per root)."""
    from bftaichi.config import load_config
    from bftaichi.formats.synthetic import SyntheticDataset, write_7scenes

    data = root / "frames"
    if not data.exists():
        cfg = load_config(None, TINY)
        write_7scenes(SyntheticDataset(cfg.synthetic), data)
    return data


def copy_frames(root: Path, name: str) -> Path:
    import shutil

    dst = root / name
    shutil.copytree(frames_7scenes(root), dst)
    return dst


def fuse(data: Path, root: Path, *extra: str) -> list[str]:
    return ["fuse", str(data), "--voxel", "0.03", "-q", "--out", str(root / "out"),
            "--set", "run.plots=false", "--set", "run.preview=false", *extra]


def _png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path)


# -- builders: root folder -> argv ------------------------------------------------------------

def missing_depth(root):
    """The depth file is listed but gone: a dangling link (deleted behind the loader's back)."""
    d = copy_frames(root, "missing")
    (d / "frame-000001.depth.png").unlink()
    (d / "frame-000001.depth.png").symlink_to(d / "gone.png")
    return fuse(d, root)


def missing_pose(root):
    d = copy_frames(root, "nopose")
    (d / "frame-000001.pose.txt").unlink()
    return fuse(d, root)


def corrupt_png(root):
    d = copy_frames(root, "corrupt")
    p = d / "frame-000001.depth.png"
    p.write_bytes(p.read_bytes()[:200])  # truncated
    return fuse(d, root)


def depth_wrong_dtype(root):
    """A float32 image (a TIFF saved under the .png name: what a float depth exporter writes)."""
    from PIL import Image

    d = copy_frames(root, "dtype")
    Image.fromarray(np.ones((48, 64), np.float32)).save(d / "frame-000001.depth.png",
                                                        format="TIFF")
    return fuse(d, root)


def depth_rgb(root):
    d = copy_frames(root, "rgb")
    _png(d / "frame-000001.depth.png", np.zeros((48, 64, 3), np.uint8))
    return fuse(d, root)


def depth_size(root):
    """Every depth image is 32x24 but K is for 64x48 (principal point 31.5, 23.5)."""
    d = copy_frames(root, "size")
    for p in d.glob("*.depth.png"):
        _png(p, np.full((24, 32), 1000, np.uint16))
    return fuse(d, root)


def depth_size_between_frames(root):
    d = copy_frames(root, "size2")
    _png(d / "frame-000001.depth.png", np.full((24, 32), 1000, np.uint16))
    return fuse(d, root)


def k_focal(root):
    d = copy_frames(root, "focal")
    (d / "camera-intrinsics.txt").write_text("0 0 31.5\n0 52.5 23.5\n0 0 1\n")
    return fuse(d, root)


def _pose(root, name, edit):
    d = copy_frames(root, name)
    p = d / "frame-000001.pose.txt"
    T = np.loadtxt(p)
    edit(T)
    np.savetxt(p, T)
    return fuse(d, root)


def pose_nan(root):
    return _pose(root, "nan", lambda T: T.__setitem__((0, 3), np.nan))


def pose_inf(root):
    return _pose(root, "inf", lambda T: T.__setitem__((1, 1), np.inf))


def pose_not_rigid(root):
    return _pose(root, "rigid", lambda T: T.__setitem__((0, 0), 2.0))


def pose_last_row(root):
    return _pose(root, "lastrow", lambda T: T.__setitem__((3, 0), 0.5))


def all_invalid(root):
    d = copy_frames(root, "invalid")
    for p in d.glob("*.depth.png"):
        _png(p, np.zeros((48, 64), np.uint16))
    return fuse(d, root)


def voxel_zero(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.voxel_size_m=0")]


def voxel_negative(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.voxel_size_m=-0.01")]


def voxel_absurd(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.voxel_size_m=50")]


def trunc_small(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.trunc_m=0.001")]


def alpha_range(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.alpha=5")]


def seed_negative(root):
    """A key that used to fail only in the metrics, after the whole run."""
    return ["run", "-q", "--out", str(root / "out"), *sets("eval.seed=-1")]


def probes_zero(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("solver.probes=0")]


def unknown_key(root):
    return ["run", "-q", "--out", str(root / "out"), *sets("tsdf.voxel_sise_m=0.02")]


def syntax_error(root):
    scene = root / "broken.toml"
    scene.write_text("[tsdf]\nvoxel_size_m = = 0.02\n")
    return ["run", str(scene), "-q", "--out", str(root / "out")]


def unwritable_out(root):
    blocker = root / "a-file"
    blocker.write_text("not a folder")
    return ["run", "-q", "--out", str(blocker / "out"), *sets()]


def existing_run(root):
    out = root / "out"
    out.mkdir()
    (out / "report.json").write_text("{}")
    return ["run", "-q", "--out", str(out), *sets()]


def disk_full(root):
    """Writing runs out of space: fsync fails with ENOSPC (patched in :func:`run_case`)."""
    return ["run", "-q", "--out", str(root / "out"), *sets()]


def ctrl_c(root):
    """Ctrl-C during the posterior (KeyboardInterrupt injected in :func:`run_case`)."""
    return ["run", "-q", "--out", str(root / "out"), *sets()]


def not_converged_strict(root):
    return ["run", "-q", "--strict", "--out", str(root / "out"), *sets("solver.maxiter=2")]


def focal_in_wrong_unit(root):
    """fx = fy = 1 for a 64x48 image (a focal length in metres or normalised): a 176 degree
    field of view. It once made the memory estimate run for minutes."""
    d = copy_frames(root, "focal1")
    (d / "camera-intrinsics.txt").write_text("1 0 31.5\n0 1 23.5\n0 0 1\n")
    return fuse(d, root)


def folder_in_use(root):
    """Another command holds the output folder (its writer lock is taken in :func:`run_case`)."""
    return ["run", "-q", "--overwrite", "--out", str(root / "out"), *sets()]


def html_into_device(root):
    (root / "out").mkdir()
    return ["view", str(root / "out"), "--html", "/dev/null"]


def commit_not_permitted(root):
    """Moving the finished outputs into the folder fails (EPERM, injected in :func:`run_case`)."""
    return ["run", "-q", "--out", str(root / "out"), *sets()]


def _frames_without_truth(root, name):
    """A copy of the tiny frames without gt_mesh.ply (metrics of a mesh fused from broken frames
    are slow and beside the point)."""
    d = copy_frames(root, name)
    (d / "gt_mesh.ply").unlink(missing_ok=True)
    return d


def depth_8bit(root, *strict):
    """Depth saved as an 8-bit PNG (a grey image): values 0-255 read as millimetres."""
    d = _frames_without_truth(root, "depth8")
    for p in d.glob("*.depth.png"):
        from PIL import Image

        _png(p, np.clip(np.asarray(Image.open(p)) // 8, 0, 255).astype(np.uint8))
    return fuse(d, root, *strict)


def depth_8bit_strict(root):
    return depth_8bit(root, "--strict")


def depth_transposed(root):
    """Every depth image transposed (48x64) with the K of the 64x48 camera."""
    from PIL import Image

    d = _frames_without_truth(root, "transposed")
    for p in d.glob("*.depth.png"):
        _png(p, np.ascontiguousarray(np.asarray(Image.open(p)).T))
    return fuse(d, root)


def poses_inverted(root):
    """Every pose file holds T_C_W (world-to-camera) instead of T_W_C."""
    d = _frames_without_truth(root, "inverted")
    for p in d.glob("*.pose.txt"):
        np.savetxt(p, np.linalg.inv(np.loadtxt(p)))
    return fuse(d, root)


def depth_scale_10x(root):
    """Depth read at 10000 units per metre instead of 1000: a scene 10x too small."""
    return fuse(_frames_without_truth(root, "scale10"), root, "--depth-scale", "10000")


def gpu_fallback(root):
    return ["run", "-q", "--arch", "cuda", "--out", str(root / "out"), *sets()]


def scene_beyond_the_map(root):
    """One camera 1 km from the others: the scene does not fit the TSDF's 8192 voxels a side."""
    d = _frames_without_truth(root, "far")
    p = d / "frame-000001.pose.txt"
    T = np.loadtxt(p)
    T[0, 3] += 1000.0
    np.savetxt(p, T)
    return fuse(d, root)


def _run_then(root, damage, argv_after):
    """A complete tiny run in ``root/run``, then ``damage(run folder)``; return ``argv_after``."""
    from bftaichi.cli import main

    run = root / "run"
    assert main(["run", "-q", "--out", str(run), *sets()]) == 0
    damage(run)
    return [a.replace("RUN", str(run)) for a in argv_after]


def truncate(path: Path, keep: float = 0.5) -> None:
    path.write_bytes(path.read_bytes()[:int(path.stat().st_size * keep)])


def band_truncated(root):
    return _run_then(root, lambda run: truncate(run / "band.npz"), ["nbv", "RUN", "-q"])


def mesh_face_out_of_range(root):
    def damage(run):
        from bftaichi.io import read_mesh_ply, write_mesh_ply

        v, f, extra = read_mesh_ply(run / "mesh.ply")
        f[0, 0] = len(v) + 7
        write_mesh_ply(run / "mesh.ply", v, f, vertex_attrs=extra)
    return _run_then(root, damage, ["view", "RUN", "--html", str(root / "page.html")])


def report_not_json(root):
    return _run_then(root, lambda run: truncate(run / "report.json", 0.3),
                     ["view", "RUN", "--html", str(root / "page.html")])


def config_bad_value(root):
    def damage(run):
        p = run / "config.toml"
        p.write_text(p.read_text().replace("probes = ", "probes = -", 1))
    return _run_then(root, damage, ["nbv", "RUN", "-q"])


def user_ply_garbage(root):
    (root / "gt.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
                                  b"property float x\nend_header\n" + bytes(range(7)))
    d = frames_7scenes(root)
    return ["eval", str(d / "gt_mesh.ply"), str(root / "gt.ply")]


@dataclass
class Case:
    name: str
    build: Callable
    code: int
    message: str  # regular expression the stderr must match
    test: str = "tests/test_robustness.py::test_catalogue_case"
    inject: str = ""  # "enospc" | "sigint": a failure simulated in run_case


CASES = [
    Case("missing / unreadable depth file", missing_depth, 2, r"frame-000001\.depth\.png.*not found"),
    Case("missing pose file", missing_pose, 2, r"frame-000001\.pose\.txt"),
    Case("truncated / corrupt PNG", corrupt_png, 2, r"frame-000001\.depth\.png.*corrupt or truncated"),
    Case("depth of the wrong dtype", depth_wrong_dtype, 2, r"frame-000001\.depth\.png"),
    Case("3-channel depth", depth_rgb, 2, r"frame-000001\.depth\.png.*(single-channel|channel)"),
    Case("depth size differs from K", depth_size, 2, r"(principal point|intrinsics).*32x24|32x24.*(principal point|intrinsics)"),
    Case("depth size differs between frames", depth_size_between_frames, 2, r"frame-000001.*32x24.*64x48"),
    Case("K with zero focal length", k_focal, 2, r"camera-intrinsics\.txt.*focal"),
    Case("pose with NaN", pose_nan, 2, r"frame-000001\.pose\.txt.*NaN"),
    Case("pose with inf", pose_inf, 2, r"frame-000001\.pose\.txt.*(NaN or inf|inf)"),
    Case("pose not orthonormal", pose_not_rigid, 2, r"frame-000001\.pose\.txt.*not orthonormal"),
    Case("pose last row not 0 0 0 1", pose_last_row, 2, r"frame-000001\.pose\.txt.*last row"),
    Case("all frames invalid (no depth)", all_invalid, 2, r"no surface was observed.*No mesh was written"),
    Case("voxel size 0", voxel_zero, 2, r"tsdf\.voxel_size_m"),
    Case("voxel size negative", voxel_negative, 2, r"tsdf\.voxel_size_m"),
    Case("voxel size absurd (50 m)", voxel_absurd, 2, r"tsdf\.voxel_size_m"),
    Case("truncation below one voxel", trunc_small, 2, r"tsdf\.trunc_m"),
    Case("alpha outside [1, 3]", alpha_range, 2, r"tsdf\.alpha"),
    Case("probes < 1", probes_zero, 2, r"solver\.probes"),
    Case("a negative seed (eval.seed = -1)", seed_negative, 2, r"eval\.seed = -1 is out of range"),
    Case("unknown scene key", unknown_key, 2, r"voxel_sise_m.*did you mean.*voxel_size_m"),
    Case("scene file with a syntax error", syntax_error, 2, r"broken\.toml"),
    Case("output folder cannot be written", unwritable_out, 2, r"a-file"),
    Case("output folder already holds a run", existing_run, 2, r"already holds a run.*--overwrite"),
    Case("disk full while writing", disk_full, 2, r"cannot write .*No space left on device", inject="enospc"),
    Case("Ctrl-C mid-run", ctrl_c, 130, r"interrupted", inject="sigint"),
    Case("MAP not converged with --strict", not_converged_strict, 2, r"did not converge.*strict"),
    Case("focal length in the wrong unit (fx = fy = 1)", focal_in_wrong_unit, 2, r"frame-000000.*176\.\d degree field of view"),
    Case("output folder in use by another command", folder_in_use, 2, r"out is in use by pid \d+ .*bftaichi fuse", inject="locked"),
    Case("view --html into a device (/dev/null)", html_into_device, 2, r"cannot write /dev/null: it is a device"),
    Case("SIGTERM mid-run (timeout, systemd, docker stop)", ctrl_c, 143, r"interrupted by SIGTERM", inject="sigterm"),
    Case("moving the outputs in is not permitted", commit_not_permitted, 2, r"cannot replace the outputs .*Operation not permitted.*previous outputs are kept", inject="eperm"),
    Case("8-bit depth PNG (a grey image)", depth_8bit, 0, r"warning: .*frame-000000\.depth\.png.*\[depth_8bit\]"),
    Case("8-bit depth PNG with --strict", depth_8bit_strict, 2, r"frame-000000\.depth\.png.*\[depth_8bit\]"),
    Case("depth transposed against K (48x64 with the K of 64x48)", depth_transposed, 0, r"warning: .*48x64.*transposed.*\[image_size\]"),
    Case("poses given as T_C_W instead of T_W_C", poses_inverted, 0, r"warning: .*T_C_W.*\[pose_convention\]"),
    Case("depth scale off by 10 (scene 10x too small)", depth_scale_10x, 0, r"warning: .*--depth-scale 1000 .*\[depth_scale\]"),
    Case("GPU backend requested, none available", gpu_fallback, 0, r"warning: .*cuda.*cpu.*\[backend_fallback\]"),
    Case("scene larger than the TSDF map (a camera 1 km away)", scene_beyond_the_map, 2, r"frame-000001: .*8192 voxels.*spans 1001\.\d m along x: it does not fit"),
    Case("band.npz truncated, read by `nbv`", band_truncated, 2, r"band\.npz"),
    Case("mesh.ply with a face index out of range, read by `view`", mesh_face_out_of_range, 2, r"mesh\.ply.*(face|index)"),
    Case("report.json truncated, read by `view`", report_not_json, 2, r"report\.json"),
    Case("config.toml of a run with a bad value, read by `nbv`", config_bad_value, 2, r"solver\.probes.*config\.toml"),
    Case("a user PLY of garbage as `eval` ground truth", user_ply_garbage, 2, r"gt\.ply"),
]


def run_case(case: Case, root: Path) -> tuple[int, str]:
    """Build and run one case in ``root``; return (exit code, stderr text)."""
    import contextlib
    import io
    import os
    from unittest import mock

    from bftaichi.cli import main

    argv = case.build(root)
    err = io.StringIO()
    patches = []
    if case.inject == "enospc":
        def fsync(fd):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        patches.append(mock.patch("bftaichi.io.os.fsync", fsync))
    elif case.inject in ("sigint", "sigterm"):
        import signal

        from bftaichi.running.signals import Terminated

        def interrupted(*args, **kwargs):
            raise KeyboardInterrupt if case.inject == "sigint" else Terminated(signal.SIGTERM)
        patches.append(mock.patch("bftaichi.reconstructor.Reconstructor.solve", interrupted))
    elif case.inject == "eperm":
        def move(src, dst):
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(src))
        patches.append(mock.patch("bftaichi.running.folder._move", move))
    elif case.inject == "locked":
        patches.append(_held_by_another_command(root / "out"))
    with contextlib.ExitStack() as stack:
        for p in patches:
            stack.enter_context(p)
        stack.enter_context(contextlib.redirect_stderr(err))
        code = main(argv)
    return code, err.getvalue().strip()


@contextlib.contextmanager
def _held_by_another_command(out: Path):
    """The writer lock of ``out`` taken as `bftaichi fuse` takes it (another open of the lock
    file conflicts even within this process)."""
    import fcntl
    import json
    import os

    from bftaichi.running import folder

    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / folder.LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, json.dumps({"pid": os.getpid(), "host": "this-host", "started": "now",
                                 "command": "bftaichi fuse DATA --out OUT"}).encode())
        yield
    finally:
        os.close(fd)
