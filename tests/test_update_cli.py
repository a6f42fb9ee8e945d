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


def _num(values):
    return " ".join(f"{float(x):.17g}" for x in values)


def _poses(n, seed=0):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = []
    for q in Rotation.random(n, random_state=seed).as_quat():  # x y z w
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        out.append((q, T))
    return out


def test_poses_in_the_tum_and_open3d_log_trajectory_formats(tmp_path):
    """--poses reads the trajectories the loaders read: TUM lines (by frame name, or nearest in
    time for frames named by timestamps) and an Open3D .log (one block per frame)."""
    from bftaichi.errors import DataError
    from bftaichi.running.state import read_poses

    poses = _poses(3)
    names = ["1305031102.175304", "1305031102.211214", "1305031102.243211"]
    # named by the frames' names
    tum = tmp_path / "named.txt"
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{n} {_num(T[:3, 3])} {_num(q)}\n"
        for n, (q, T) in zip(names, poses)))
    got = read_poses(tum, names)
    for n, (_, T) in zip(names, poses):
        assert np.allclose(got[n], T, atol=1e-9)
    # by time: the ground truth runs at its own clock; the third frame has no pose near it
    timed = tmp_path / "groundtruth.txt"
    timed.write_text("".join(
        f"{float(n) + d} {_num(T[:3, 3])} {_num(q)}\n"
        for n, (q, T), d in zip(names, poses, (0.004, -0.01, 0.5))))
    got = read_poses(timed, names)
    assert sorted(got) == names[:2] and np.allclose(got[names[1]], poses[1][1], atol=1e-9)
    with pytest.raises(DataError, match="not named by timestamps"):
        read_poses(timed, ["frame-000000", "frame-000001", "frame-000002"])
    # an Open3D .log
    log = tmp_path / "traj.log"
    log.write_text("".join(f"{i} {i} {i + 1}\n" + "\n".join(_num(r) for r in T)
                           + "\n" for i, (_, T) in enumerate(poses)))
    got = read_poses(log, names)
    for n, (_, T) in zip(names, poses):
        assert np.allclose(got[n], T, atol=1e-12)
    with pytest.raises(DataError, match="3 poses for a run of 2 frames"):
        read_poses(log, names[:2])
