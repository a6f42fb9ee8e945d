"""``bftaichi batch`` on a local Ray cluster of 2 CPUs (issue 20, item 1): each run's outputs
are byte-identical to ``bftaichi run`` of the same scene; a failing run is recorded and does not
stop the others (exit code 1); ``--resume`` skips complete runs; a bad manifest is refused with
a clear message before anything runs; a chunked run sends its chunks to Ray as tasks, with the
bytes of a local chunked run; a run whose worker process dies is retried once, then reported."""

import hashlib
import json
from pathlib import Path

import pytest

from bftaichi.cli import main

from conftest import TINY_SCENE_SETS

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "default.toml"
QUIET = ("run.plots=false", "run.preview=false")
SETS = TINY_SCENE_SETS + QUIET
CHUNKED = SETS + ("run.chunk_m=0.24",)

pytest.importorskip("ray", reason="the distributed extra: pip install '.[distributed]'")


def _toml_list(items):
    return "[" + ", ".join(json.dumps(s) for s in items) + "]"


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """A manifest of two good runs and one whose data is missing, run once with 2 workers."""
    root = tmp_path_factory.mktemp("batch")
    manifest = root / "runs.toml"
    manifest.write_text(
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "tiny"\nset = {_toml_list(SETS)}\n\n'
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "tiny-4cm"\n'
        f'set = {_toml_list(SETS + ("tsdf.voxel_size_m=0.04", "tsdf.trunc_m=0.08"))}\n\n'
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "missing-data"\n'
        f'set = {_toml_list(SETS + ("scene.source=dataset", "scene.data=no/such/folder"))}\n\n'
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "tiny-chunked"\n'
        f'set = {_toml_list(CHUNKED)}\n')
    out = root / "out"
    rc = main(["batch", str(manifest), "--out", str(out), "--workers", "2", "-q"])
    return root, manifest, out, rc


def test_batch_runs_equal_local_runs_and_a_failure_is_recorded(batch, tmp_path):
    root, manifest, out, rc = batch
    assert rc == 1  # one run failed
    record = json.loads((out / "batch.json").read_text())
    runs = {r["name"]: r for r in record["runs"]}
    assert [r["name"] for r in record["runs"]] == ["tiny", "tiny-4cm", "missing-data",
                                                   "tiny-chunked"]
    assert record["counts"]["ok"] == 3 and record["counts"]["failed"] == 1
    assert runs["tiny"]["status"] == "ok" and runs["tiny"]["seconds"] > 0
    assert runs["tiny"]["peak_bytes"] > 0 and ":" in runs["tiny"]["worker"]
    assert runs["missing-data"]["status"] == "failed"
    assert "no/such/folder" in runs["missing-data"]["error"]
    assert not (out / "missing-data" / "mesh.ply").exists()
    local = tmp_path / "local"
    assert main(["run", str(SCENE), "--out", str(local), "-q",
                 *[a for s in SETS for a in ("--set", s)]]) == 0
    for name in ("mesh.ply", "tsdf_mesh.ply", "band.npz"):
        assert _digest(out / "tiny" / name) == _digest(local / name), name
    assert _digest(out / "tiny-4cm" / "mesh.ply") != _digest(local / "mesh.ply")


def test_a_chunked_run_solves_its_chunks_as_ray_tasks_with_the_bytes_of_a_local_one(batch,
                                                                                    tmp_path):
    root, manifest, out, rc = batch
    runs = {r["name"]: r for r in json.loads((out / "batch.json").read_text())["runs"]}
    report = json.loads((out / "tiny-chunked" / "report.json").read_text())
    chunks = report["solver"]["map"]["chunks"]
    assert chunks["n"] >= 2
    # the run's own worker waits in ray.get: its chunks ran in other worker processes
    assert all(c["worker"] != runs["tiny-chunked"]["worker"] for c in chunks["per_chunk"])
    local = tmp_path / "local"
    assert main(["run", str(SCENE), "--out", str(local), "-q",
                 *[a for s in CHUNKED for a in ("--set", s)]]) == 0
    for name in ("mesh.ply", "band.npz"):
        assert _digest(out / "tiny-chunked" / name) == _digest(local / name), name


def test_a_run_whose_worker_dies_is_retried_once_then_reported(tmp_path, monkeypatch):
    from bftaichi.running import batch as batch_module

    attempts = tmp_path / "attempts"
    attempts.mkdir()
    real = batch_module.run_one  # by reference: the worker imports the real one

    def dying(name, scene, sets, out_root, cwd):  # a local function: pickled by value
        import os
        import uuid

        if name == "dies":
            (attempts / uuid.uuid4().hex).touch()
            os._exit(1)  # the worker process dies, as under the OOM killer
        return real(name, scene, sets, out_root, cwd)

    monkeypatch.setattr(batch_module, "run_one", dying)
    manifest = tmp_path / "runs.toml"
    manifest.write_text(
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "dies"\nset = {_toml_list(SETS)}\n\n'
        f'[[run]]\nscene = {json.dumps(str(SCENE))}\nname = "lives"\nset = {_toml_list(SETS)}\n')
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out), "--workers", "2", "-q"]) == 1
    runs = {r["name"]: r for r in json.loads((out / "batch.json").read_text())["runs"]}
    assert runs["lives"]["status"] == "ok" and (out / "lives" / "mesh.ply").is_file()
    assert runs["dies"]["status"] == "failed"
    assert "worker process died, retried once" in runs["dies"]["error"]
    assert len(list(attempts.iterdir())) == 2  # the first try and one retry


def test_resume_skips_complete_runs(batch):
    root, manifest, out, rc = batch
    stamp = (out / "tiny" / "mesh.ply").stat().st_mtime_ns
    assert main(["batch", str(manifest), "--out", str(out), "--workers", "2", "--resume",
                 "-q"]) == 1  # the failing run is tried again, and fails again
    record = json.loads((out / "batch.json").read_text())
    status = {r["name"]: r["status"] for r in record["runs"]}
    assert status == {"tiny": "skipped", "tiny-4cm": "skipped", "missing-data": "failed",
                      "tiny-chunked": "skipped"}
    assert (out / "tiny" / "mesh.ply").stat().st_mtime_ns == stamp


@pytest.mark.parametrize("body, message", [
    ('[[run]]\nscene = "{scene}"\nvoxel = 1\n', "unknown key 'voxel'; known: name, scene, set"),
    ('[[run]]\nscene = "nope.toml"\n', "nope.toml does not exist"),
    ('[[run]]\nscene = "{scene}"\nname = "a"\n[[run]]\nscene = "{scene}"\nname = "a"\n',
     "[[run]] 2: duplicate name 'a'"),
    ('[[runs]]\nscene = "{scene}"\n', "unknown top-level key 'runs'"),
    ('[[run]]\nscene = "{scene}"\nset = "tsdf.voxel_size_m=0.01"\n', "set must be a list"),
])
def test_a_bad_manifest_is_refused_before_anything_runs(tmp_path, capsys, body, message):
    manifest = tmp_path / "bad.toml"
    manifest.write_text(body.format(scene=SCENE))
    capsys.readouterr()
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), "-q"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
