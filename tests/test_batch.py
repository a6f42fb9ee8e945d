"""``bftaichi batch`` on a local Ray cluster of 2 CPUs (issue 20, item 1): each run's outputs
are byte-identical to ``bftaichi run`` of the same scene; a failing run is recorded and does not
stop the others (exit code 1); ``--resume`` skips complete runs; a bad manifest is refused with
a clear message before anything runs."""

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
        f'set = {_toml_list(SETS + ("scene.source=dataset", "scene.data=no/such/folder"))}\n')
    out = root / "out"
    rc = main(["batch", str(manifest), "--out", str(out), "--workers", "2", "-q"])
    return root, manifest, out, rc


def test_batch_runs_equal_local_runs_and_a_failure_is_recorded(batch, tmp_path):
    root, manifest, out, rc = batch
    assert rc == 1  # one run failed
    record = json.loads((out / "batch.json").read_text())
    runs = {r["name"]: r for r in record["runs"]}
    assert [r["name"] for r in record["runs"]] == ["tiny", "tiny-4cm", "missing-data"]
    assert record["counts"]["ok"] == 2 and record["counts"]["failed"] == 1
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


def test_resume_skips_complete_runs(batch):
    root, manifest, out, rc = batch
    stamp = (out / "tiny" / "mesh.ply").stat().st_mtime_ns
    assert main(["batch", str(manifest), "--out", str(out), "--workers", "2", "--resume",
                 "-q"]) == 1  # the failing run is tried again, and fails again
    record = json.loads((out / "batch.json").read_text())
    status = {r["name"]: r["status"] for r in record["runs"]}
    assert status == {"tiny": "skipped", "tiny-4cm": "skipped", "missing-data": "failed"}
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
