"""Run-to-run determinism: the same input twice gives byte-identical mesh.ply, tsdf_mesh.ply and
band.npz (``bftaichi.run`` of the tiny scene, ``bftaichi fuse`` of a synthesised 7scenes folder),
and tools/determinism.py says so.

band.npz is compared byte for byte too: the zip entries :func:`bftaichi.io.write_npz` writes
carry a fixed timestamp (1980-01-01), not the write time, so equal arrays give equal bytes
(checked below on the entries' ``date_time``).
"""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import bftaichi
from bftaichi.cli import main
from conftest import TINY_SCENE_SETS

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ("mesh.ply", "tsdf_mesh.ply", "band.npz")
QUIET = ("run.preview=false", "run.plots=false")


def _assert_identical(a: Path, b: Path) -> None:
    for name in OUTPUTS:
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{name} differs between runs"
    with np.load(a / "band.npz") as za, np.load(b / "band.npz") as zb:
        assert za.files == zb.files and len(za.files) >= 4
        for k in za.files:
            assert np.array_equal(za[k], zb[k]), k
    dates = {i.date_time for i in zipfile.ZipFile(a / "band.npz").infolist()}
    assert dates == {(1980, 1, 1, 0, 0, 0)}  # why the bytes can be equal: no write time inside


def _sets(extra=()) -> list[str]:
    return [arg for s in (*TINY_SCENE_SETS, *extra) for arg in ("--set", s)]


def test_two_runs_of_the_tiny_scene_write_identical_files(tmp_path):
    for k in (1, 2):
        cfg = bftaichi.load_config(None, [*TINY_SCENE_SETS, *QUIET])
        bftaichi.run(cfg, tmp_path / f"run{k}", progress=False)
    _assert_identical(tmp_path / "run1", tmp_path / "run2")


@pytest.fixture(scope="module")
def synth_7scenes(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "tabletop"
    assert main(["synth", "--out", str(out), "-q", *_sets()]) == 0
    return out


def test_two_fuses_of_a_dataset_write_identical_files(tmp_path, synth_7scenes):
    for k in (1, 2):
        args = ["fuse", str(synth_7scenes), "--voxel", "0.03", "--trunc", "0.06",
                "--out", str(tmp_path / f"fuse{k}"), "-q"]
        assert main(args + [a for s in QUIET for a in ("--set", s)]) == 0
    _assert_identical(tmp_path / "fuse1", tmp_path / "fuse2")


def test_determinism_tool_reports_identical_outputs(synth_7scenes):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "determinism.py"), "scenes/default.toml",
         *_sets(("synthetic.n_views=4",)), "--data", str(synth_7scenes), "--voxel", "0.03",
         "--frames", "0:4"],
        capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert sum(ln.split()[:2] in ([n, "identical"] for n in OUTPUTS) for ln in lines) == 6
    assert lines[-1] == "all outputs identical"


def test_determinism_tool_reports_a_difference(tmp_path):
    """The comparison is not vacuous: changed arrays and vertices are reported with their size."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import determinism
    finally:
        sys.path.remove(str(ROOT / "tools"))
    from bftaichi.io import write_mesh_ply, write_npz

    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    for k, dz in ((1, 0.0), (2, 0.25)):
        d = tmp_path / f"r{k}"
        d.mkdir()
        write_mesh_ply(d / "mesh.ply", tri, [[0, 1, 2]])
        write_mesh_ply(d / "tsdf_mesh.ply", tri + [0, 0, dz], [[0, 1, 2]])
        write_npz(d / "band.npz", mean=np.array([1.0, 2.0 + dz]), var=np.ones(2))
    rows = {name: (ok, what) for name, ok, what in determinism.compare_outputs(tmp_path / "r1",
                                                                               tmp_path / "r2")}
    assert rows["mesh.ply"][0] and rows["mesh.ply"][1].startswith("identical")
    assert not rows["tsdf_mesh.ply"][0] and "vertices max |diff| 0.25" in rows["tsdf_mesh.ply"][1]
    assert not rows["band.npz"][0]
    assert "mean max |diff| 0.25" in rows["band.npz"][1] and "var identical" in rows["band.npz"][1]


def test_npz_stores_what_deflates_little_and_reads_back_exactly(tmp_path):
    """write_npz deflates a member only where it pays (ijk-like integers, quantised weights)
    and stores noise-like float fields as they are; np.load reads back every array exactly,
    and the same arrays give the same bytes."""
    from bftaichi.io import write_npz

    rng = np.random.default_rng(0)
    arrays = {"ijk": np.repeat(np.arange(20000, dtype=np.int32), 3).reshape(-1, 3),
              "mean": rng.standard_normal(300000).astype(np.float32),
              "weight": np.round(rng.random(300000) * 4).astype(np.float32),
              "voxel_size": np.float32(0.01)}
    for name in ("a.npz", "b.npz"):
        write_npz(tmp_path / name, **arrays)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with np.load(tmp_path / "a.npz") as back:
        for key, value in arrays.items():
            assert back[key].dtype == np.asarray(value).dtype
            assert np.array_equal(back[key], value)
    kinds = {i.filename: i.compress_type for i in zipfile.ZipFile(tmp_path / "a.npz").infolist()}
    assert kinds["mean.npy"] == zipfile.ZIP_STORED
    assert kinds["ijk.npy"] == kinds["weight.npy"] == zipfile.ZIP_DEFLATED

