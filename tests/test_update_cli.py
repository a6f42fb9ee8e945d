"""``bftaichi update`` (issue 19, item 2): a run that kept its fusion state, given corrected
poses, rewrites outputs byte-identical to fusing the frames at those poses from scratch, and
records the frames that moved; bad input changes nothing."""

import hashlib
import json
import shutil

import numpy as np
import pytest

from bftaichi.cli import main

from conftest import TINY_SCENE_SETS

KEEP = ("--set", "run.keep_state=true", "--set", "run.plots=false", "--set", "run.preview=false",
        "--set", "eval.n_samples=5000")
MOVED = ("frame-000001", "frame-000004")


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _band(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _drift(T, k):
    a = np.deg2rad(1.5 + k)
    D = np.eye(4)
    D[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    D[:3, 3] = [0.02, -0.01 * k, 0.01]
    return D @ T


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The tiny scene's frames (7scenes layout), and a copy whose two frames drifted."""
    root = tmp_path_factory.mktemp("update")
    good = root / "good"
    args = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    assert main(["synth", "--out", str(good), "-q", *args]) == 0
    drifted = root / "drifted"
    shutil.copytree(good, drifted)
    for k, name in enumerate(MOVED):
        f = drifted / f"{name}.pose.txt"
        np.savetxt(f, _drift(np.loadtxt(f), k))
    return root, good, drifted


def _fuse(src, out):
    assert main(["fuse", str(src), "--voxel", "0.03", "--trunc", "0.06", "--out", str(out), "-q",
                 *KEEP]) == 0
    return out


def test_update_equals_fusing_at_the_corrected_poses(data, capsys):
    root, good, drifted = data
    run = _fuse(drifted, root / "run")
    ref = _fuse(good, root / "ref")
    assert _digest(run / "tsdf_mesh.ply") != _digest(ref / "tsdf_mesh.ply")  # the drift shows
    capsys.readouterr()
    assert main(["update", str(run), "--poses", str(good)]) == 0
    out = capsys.readouterr().out
    assert "moved 2 of 6 frames: frame-000001, frame-000004" in out
    for name in ("tsdf_mesh.ply", "mesh.ply"):
        assert _digest(run / name) == _digest(ref / name), name
    for name in ("band.npz", "fusion_state.npz"):
        a, b = _band(run / name), _band(ref / name)
        assert a.keys() == b.keys()
        for key in b:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}:{key}")
    report = json.loads((run / "report.json").read_text())
    assert report["update"]["moved"] == list(MOVED)
    assert report["fusion_state"]["bytes"] == (run / "fusion_state.npz").stat().st_size
    # the same poses again: nothing moves, nothing is rewritten
    stamp = (run / "mesh.ply").stat().st_mtime_ns
    assert main(["update", str(run), "--poses", str(good), "-q"]) == 0
    assert (run / "mesh.ply").stat().st_mtime_ns == stamp


def test_update_takes_a_file_of_named_poses(data):
    root, good, drifted = data
    run = _fuse(drifted, root / "run_file")
    poses = root / "poses.txt"
    poses.write_text("".join(f"{n} " + " ".join(f"{v:.17g}" for v in
                                                   np.loadtxt(good / f"{n}.pose.txt").ravel())
                             + "\n" for n in MOVED))
    assert main(["update", str(run), "--poses", str(poses), "-q"]) == 0
    assert _digest(run / "tsdf_mesh.ply") == _digest(_fuse(good, root / "ref2") / "tsdf_mesh.ply")


def test_bad_updates_are_refused_and_change_nothing(data, capsys, tmp_path):
    root, good, drifted = data
    run = _fuse(drifted, root / "run_bad")
    before = {p.name: _digest(p) for p in run.iterdir() if p.is_file()}
    bad = tmp_path / "bad.txt"
    bad.write_text("frame-000001 1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1\n")
    unknown = tmp_path / "unknown.txt"
    unknown.write_text("nope " + " ".join(map(str, np.eye(4).ravel())) + "\n")
    for poses, message in ((bad, "bad.txt:1"), (unknown, "no frame of the run is named 'nope'"),
                           (tmp_path / "missing", "does not exist")):
        capsys.readouterr()
        assert main(["update", str(run), "--poses", str(poses)]) == 2
        assert message in capsys.readouterr().err
    no_state = _fuse(drifted, root / "no_state")
    (no_state / "fusion_state.npz").unlink()
    capsys.readouterr()
    assert main(["update", str(no_state), "--poses", str(good)]) == 2
    assert "run.keep_state=true" in capsys.readouterr().err
    assert {p.name: _digest(p) for p in run.iterdir() if p.is_file()} == before
