"""Output folders are never mixed (bftaichi/running/folder.py): the all-or-nothing commit
under kills and injected failures, the writer lock between commands, signals, and writes that
never replace what is not a regular file."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from unittest import mock

import pytest

from bftaichi.cli import main
from bftaichi.running import folder
from bftaichi.running.pipeline import RUN_OUTPUTS
from robustness_cases import sets

PY = sys.executable


def tree(out: Path) -> dict[str, bytes]:
    """Every file below ``out`` (relative path -> bytes), without the commit's own entries."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.relative_to(out).parts[0] not in folder.INTERNAL}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two complete runs of the tiny scene that differ in every file (voxel size, plots)."""
    root = tmp_path_factory.mktemp("runs")
    old, new = root / "old", root / "new"
    assert main(["run", "-q", "--out", str(old), *sets()]) == 0
    assert main(["run", "-q", "--out", str(new), *sets("tsdf.voxel_size_m=0.04",
                                                       "run.plots=true")]) == 0
    assert (new / "plots").is_dir() and not (old / "plots").exists()
    return old, new


# -- the commit, killed at every step ---------------------------------------------------------

_CHILD = textwrap.dedent("""
    import os, shutil, signal, sys
    from pathlib import Path
    from bftaichi.running import folder
    from bftaichi.running.pipeline import RUN_OUTPUTS

    out, src, where, k = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    original, calls = getattr(folder, where), [0]

    def step(*args, **kwargs):
        if where != "_remove" or str(args[0]).endswith(folder.JOURNAL):
            if calls[0] == k:
                os.kill(os.getpid(), signal.SIGKILL)
            calls[0] += 1
        return original(*args, **kwargs)

    setattr(folder, where, step)
    with folder.hold(out):
        staging = folder.Staging(out)
        for p in src.iterdir():
            (shutil.copytree if p.is_dir() else shutil.copy2)(p, staging.dir / p.name)
        staging.commit(remove=RUN_OUTPUTS + ("failed_run.json",))
    print(calls[0])
""")


def _commit_in_child(out: Path, src: Path, where: str, k: int) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-c", _CHILD, str(out), str(src), where, str(k)],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.filterwarnings("ignore:.*broke the stale lock")  # each killed child leaves one
def test_a_commit_killed_at_any_step_leaves_the_old_run_or_the_new_one(runs, tmp_path):
    """SIGKILL before the commit point, at every move of the commit and before the journal is
    removed: a reader then sees exactly the previous run or exactly the new one."""
    old, new = runs
    want_old, want_new = tree(old), tree(new)
    done = _commit_in_child(shutil.copytree(old, tmp_path / "count"), new, "_move", 10 ** 6)
    assert done.returncode == 0, done.stderr
    moves = int(done.stdout)
    assert moves >= len(want_new)  # every new file or folder moved in, the old ones aside
    kill_points = ([("_fsync_dir", 0)] + [("_move", k) for k in range(moves)]
                   + [("_remove", 0)])
    seen = {"old": 0, "new": 0, "mixed": 0}
    for i, (where, k) in enumerate(kill_points):
        out = shutil.copytree(old, tmp_path / f"out{i}")
        killed = _commit_in_child(out, new, where, k)
        assert killed.returncode == -signal.SIGKILL, (where, k, killed.stderr)
        with folder.reading(out):  # completes an interrupted commit first
            now = tree(out)
        seen["old" if now == want_old else "new" if now == want_new else "mixed"] += 1
        assert not (out / folder.JOURNAL).exists()
        from bftaichi.posterior import Posterior

        Posterior.load(out / "band.npz")  # a reader of the API gets a whole band
    print(f"kill points tried: {len(kill_points)}; outcomes {seen}")
    assert seen["mixed"] == 0, seen
    assert seen["old"] == 1 and seen["new"] == len(kill_points) - 1  # the journal decides


@pytest.mark.parametrize("failing_move, err_no", [(0, errno.EPERM), (3, errno.ENOSPC),
                                                (-1, errno.EBUSY)])
def test_a_move_that_fails_keeps_the_previous_run_and_records_the_failure(runs, tmp_path,
                                                                          failing_move, err_no):
    """EPERM, ENOSPC or EBUSY on one of the commit's moves (the first, one in the middle, the
    last): every move already made is undone, the previous run stays byte for byte,
    failed_run.json says why, and the command exits 2 naming the file."""
    old, _ = runs
    out = shutil.copytree(old, tmp_path / "out")
    want = tree(out)
    real, calls = folder._move, []

    def count(src, dst):
        calls.append(src)
        return real(src, dst)
    with mock.patch.object(folder, "_move", count):
        assert main(["run", "-q", "--overwrite", "--out", str(out), *sets()]) == 0
    n = len(calls)
    shutil.rmtree(out)
    out = shutil.copytree(old, tmp_path / "out")
    fail_at = failing_move % n
    calls.clear()

    def move(src, dst):
        calls.append(src)
        if len(calls) - 1 == fail_at:
            raise OSError(err_no, os.strerror(err_no), str(src))
        return real(src, dst)
    with mock.patch.object(folder, "_move", move):
        code = main(["run", "-q", "--overwrite", "--out", str(out), *sets()])
    assert code == 2
    now = tree(out)
    failure = json.loads(now.pop("failed_run.json"))
    assert now == want
    assert failure["status"] == "failed" and failure["stage"] == "commit"
    assert os.strerror(err_no) in failure["error"]
    assert not any((out / name).exists() for name in folder.INTERNAL)


def test_an_old_regular_file_named_like_an_output_folder_is_replaced(runs, tmp_path):
    """A regular file ``plots`` where the run writes its plots/ folder (a failure of the old
    one-file-at-a-time commit)."""
    old, _ = runs
    out = shutil.copytree(old, tmp_path / "out")
    (out / "plots").write_text("not a folder")
    assert main(["run", "-q", "--overwrite", "--out", str(out),
                 *sets("run.plots=true")]) == 0
    assert (out / "plots").is_dir() and any((out / "plots").iterdir())


# -- the writer lock --------------------------------------------------------------------------

_HOLDER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from bftaichi.running import folder

    folder.command_line = "bftaichi fuse DATA --out OUT --overwrite"
    with folder.hold(Path(sys.argv[1])):
        print("held", flush=True)
        time.sleep(float(sys.argv[2]))
""")


def _holder(out: Path, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen([PY, "-c", _HOLDER, str(out), str(seconds)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held", proc.stderr.read()
    return proc


def test_a_second_writer_is_refused_with_the_holder_named(runs, tmp_path, capsys):
    """While another process holds the folder (here: what `fuse --overwrite` holds), `nbv`
    and a second `run --overwrite` exit 2 naming its pid and command, and change nothing."""
    old, _ = runs
    out = shutil.copytree(old, tmp_path / "out")
    want = tree(out)
    proc = _holder(out, 60)
    try:
        for argv in (["nbv", str(out), "-q"],
                     ["run", "-q", "--overwrite", "--out", str(out), *sets()]):
            capsys.readouterr()
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert re.search(rf"in use by pid {proc.pid} .*bftaichi fuse DATA --out OUT "
                             r"--overwrite.*started", err), err
        assert tree(out) == want
    finally:
        proc.kill()
        proc.wait()


def test_two_concurrent_runs_into_one_folder(runs, tmp_path):
    """Two `run --overwrite` processes started together: one writes the folder, the other is
    refused at once with the first one named; the folder holds one whole run."""
    old, new = runs
    out = shutil.copytree(old, tmp_path / "out")
    argv = [PY, "-m", "bftaichi.cli", "run", "-q", "--overwrite", "--out", str(out), *sets()]
    procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    refused = next(err for code, err in results if code == 2)
    winner = next(p for p, (code, _) in zip(procs, results) if code == 0)
    assert f"in use by pid {winner.pid}" in refused, refused
    assert json.loads((out / "report.json").read_text())["status"] == "complete"
    assert not (out / "failed_run.json").exists()


def test_a_lock_left_by_a_killed_process_is_broken(runs, tmp_path, capsys):
    old, _ = runs
    out = shutil.copytree(old, tmp_path / "out")
    proc = _holder(out, 60)
    proc.kill()
    proc.wait()
    assert (out / folder.LOCK).exists()  # what a killed writer leaves
    capsys.readouterr()
    assert main(["run", "-q", "--overwrite", "--out", str(out), *sets()]) == 0
    assert re.search(rf"warning: .*broke the stale lock of pid {proc.pid} .*no longer runs",
                     capsys.readouterr().err)
    assert not (out / folder.LOCK).exists()  # a clean release removes it


def test_the_lock_is_reentrant_within_a_process_but_not_across_opens(tmp_path):
    with folder.hold(tmp_path):
        with folder.hold(tmp_path):  # evalviews holds it and runs `run`, which holds it
            pass
        assert (tmp_path / folder.LOCK).exists()
    assert not (tmp_path / folder.LOCK).exists()


# -- signals and stdout -----------------------------------------------------------------------

@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_end_a_run_like_ctrl_c(tmp_path, sig):
    """What `timeout`, systemd or `docker stop` send: exit 128+n, the interruption recorded,
    the staging removed."""
    out = tmp_path / "out"
    proc = subprocess.Popen([PY, "-m", "bftaichi.cli", "run", "-q", "--out", str(out),
                             "--set", "run.plots=false"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (out / folder.STAGING).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    name = signal.Signals(sig).name
    assert proc.returncode == 128 + sig and f"interrupted by {name}" in err, err
    assert [p.name for p in out.iterdir()] == ["report.json"]
    r = json.loads((out / "report.json").read_text())
    assert r["status"] == "interrupted" and name in r["error"]


def test_quiet_prints_nothing_on_stdout_and_needs_no_stdout(tmp_path):
    """-q: not even Taichi's start-up line; an unwritable stdout (/dev/full) does not matter."""
    argv = [PY, "-m", "bftaichi.cli", "run", "-q", "--out", str(tmp_path / "out"), *sets()]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout == "", (done.stdout, done.stderr)
    with open("/dev/full", "w") as full:
        done = subprocess.run(argv + ["--overwrite"], stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=300)
    assert done.returncode == 0, done.stderr


# -- writes never replace what is not a regular file ------------------------------------------

def test_view_html_refuses_devices_fifos_and_folders_and_writes_through_links(runs, tmp_path,
                                                                               capsys):
    old, _ = runs
    fifo = tmp_path / "fifo.html"
    os.mkfifo(fifo)
    for target, kind in ((Path("/dev/null"), "a device"), (fifo, "a FIFO"),
                         (tmp_path, "a folder")):
        capsys.readouterr()
        assert main(["view", str(old), "--html", str(target)]) == 2
        err = capsys.readouterr().err  # click itself refuses a folder for --html
        assert f"cannot write {target}: it is {kind}" in err or "is a directory" in err, err
    assert fifo.exists() and not fifo.is_file() and Path("/dev/null").is_char_device()
    real = tmp_path / "pages" / "real.html"
    real.parent.mkdir()
    link = tmp_path / "link.html"
    link.symlink_to(real)
    assert main(["view", str(old), "--html", str(link)]) == 0
    assert link.is_symlink() and real.read_text().startswith("<!DOCTYPE html>")


def test_a_file_system_without_locks_warns_and_still_writes(runs, tmp_path, capsys):
    """Some network file systems refuse flock (ENOLCK): the run goes on, with a warning."""
    import fcntl

    old, _ = runs
    out = shutil.copytree(old, tmp_path / "out")

    def flock(fd, op):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))
    capsys.readouterr()
    with mock.patch.object(fcntl, "flock", flock):
        assert main(["run", "-q", "--overwrite", "--out", str(out), *sets()]) == 0
    assert "does not support locks" in capsys.readouterr().err
    assert json.loads((out / "report.json").read_text())["status"] == "complete"
