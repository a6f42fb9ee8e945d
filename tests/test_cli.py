"""The ``bftaichi`` command line: every command smoke-runs on a tiny scene; user errors give
``error: ...`` on stderr and exit code 2, never a traceback or a half-written run."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bftaichi import __version__
from bftaichi.cli import main
from bftaichi.config import load_config
from bftaichi.io import read_mesh_ply

from conftest import TINY_SCENE_SETS

RUN_FILES = ("tsdf_mesh.ply", "band.npz", "report.json", "config.toml", "mesh.ply", "preview.html")


def sets_args(sets=TINY_SCENE_SETS) -> list[str]:
    return [a for s in sets for a in ("--set", s)]


def call(capsys, *args) -> tuple[int, str, str]:
    """Run ``bftaichi ARGS`` in-process; return (exit code, stdout, stderr)."""
    capsys.readouterr()
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(autouse=True)
def _no_debug(monkeypatch):
    # BFTAICHI_DEBUG=1 re-raises errors with a traceback; these tests check the user-facing path.
    monkeypatch.delenv("BFTAICHI_DEBUG", raising=False)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """`bftaichi run -q` of the tiny tabletop scene; returns its output folder."""
    out = tmp_path_factory.mktemp("run") / "tiny"
    assert main(["run", "--out", str(out), "-q", *sets_args()]) == 0
    return out


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    """`bftaichi synth` of the tiny tabletop scene (7scenes layout + gt_mesh.ply)."""
    out = tmp_path_factory.mktemp("synth") / "tabletop"
    assert main(["synth", "--out", str(out), "-q", *sets_args()]) == 0
    return out


@pytest.fixture(scope="module")
def fused(tmp_path_factory, synth_dir):
    """`bftaichi fuse` of the synthesised frames with the tiny run's voxel and truncation."""
    out = tmp_path_factory.mktemp("fuse") / "fused"
    assert main(["fuse", str(synth_dir), "--voxel", "0.03", "--trunc", "0.06", "--out", str(out),
                 "-q", "--set", "eval.n_samples=5000"]) == 0
    return out


def write_all_invalid_7scenes(folder: Path, n_frames: int = 3) -> Path:
    """A 7scenes sequence whose depth PNGs are all 0 (no measurement anywhere)."""
    folder.mkdir(parents=True)
    (folder / "camera-intrinsics.txt").write_text("52.5 0 31.5\n0 52.5 23.5\n0 0 1\n")
    for i in range(n_frames):
        Image.fromarray(np.zeros((48, 64), np.uint16)).save(folder / f"frame-{i:06d}.depth.png")
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * i, 0.0, -1.0]
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", pose)
    return folder


# --------------------------------------------------------------------------------------------
# run
# --------------------------------------------------------------------------------------------

def test_run_writes_every_output(tiny_run):
    for name in RUN_FILES:
        assert (tiny_run / name).is_file(), name
    # Atomic writes leave no temporary files behind.
    assert sorted(p.name for p in tiny_run.iterdir()) == sorted(RUN_FILES)


def test_run_band_npz_has_the_documented_arrays(tiny_run):
    report = json.loads((tiny_run / "report.json").read_text())
    with np.load(tiny_run / "band.npz") as band:
        assert set(band.files) == {"ijk", "voxel_size", "mean", "var", "cov", "tsdf", "weight",
                                   "observation", "trunc_m", "bootstrap_trunc_m", "sigma_extra_m",
                                   "sigma_corr_m", "origin"}
        assert band["origin"].dtype == np.float64 and not band["origin"].any()  # near the origin
        ijk, tsdf, weight = band["ijk"], band["tsdf"], band["weight"]
        observation = json.loads(str(band["observation"]))
        trunc_m, sigma_extra_m = float(band["trunc_m"]), float(band["sigma_extra_m"])
        mean, var, cov = band["mean"], band["var"], band["cov"]
        voxel_size = band["voxel_size"]
    n = report["counts"]["band_voxels"]
    assert n > 1000
    assert ijk.dtype == np.int32 and ijk.shape == (n, 3)
    for arr in (tsdf, weight, mean, var):
        assert arr.dtype == np.float32 and arr.shape == (n,)
    assert voxel_size.shape == () and float(voxel_size) == pytest.approx(0.03)
    assert len(np.unique(ijk, axis=0)) == n                     # each voxel once
    assert np.all(weight >= 0) and np.all(weight <= 6)          # 0 = dilation, at most 6 frames
    assert np.all(var > 0)
    assert cov.dtype == np.float32 and cov.shape == (n, 3)
    assert np.all(cov ** 2 <= var[:, None] * var.max() * (1 + 1e-6))  # |cov_ij| <= sqrt(var_i var_j)
    # the solve's observation model, for planning and evaluation (tiny run: tau = 6 cm)
    assert observation["stride"] == 1 and observation["count_once"] == "voxel"
    assert trunc_m == pytest.approx(0.06) and sigma_extra_m == report["solver"]["observations"][
        "noise_fit"]["sigma_extra_m"]
    tau_b = report["tsdf"]["bootstrap_trunc_m"]
    assert tau_b == pytest.approx(2.0 * 0.06)                   # alpha * trunc_m
    assert np.all(np.abs(tsdf) <= tau_b * (1 + 1e-6))           # metres, clamped to +-tau_b
    assert tsdf.min() < 0 < tsdf.max()                          # a surface lies in the band


def test_run_report_has_counts_times_and_metrics(tiny_run):
    report = json.loads((tiny_run / "report.json").read_text())
    c, s = report["counts"], report["seconds"]
    assert c["frames"] == 6 and c["empty_frames"] == 0
    assert 0 < c["pixels_used"] <= 6 * 64 * 48
    assert c["tsdf_mesh_faces"] > 100
    for stage in ("tsdf", "mesh", "metrics", "total"):
        assert s[stage] >= 0
    assert s["total"] >= s["tsdf"] + s["mesh"]
    assert report["has_ground_truth"] is True
    m = report["metrics"]["tsdf_mesh.ply"]
    assert set(m) >= {"chamfer_l2", "accuracy_m", "completeness_m", "fscore@50mm"}
    # Even this coarse run (3 cm voxels, 64x48 pixels) recovers the tabletop to within 5 cm.
    assert m["fscore@50mm"] > 0.9
    assert m["accuracy_m"] < 0.03
    assert m["n_pred_faces"] == c["tsdf_mesh_faces"]


def test_run_mesh_matches_report_and_lies_on_the_table(tiny_run):
    report = json.loads((tiny_run / "report.json").read_text())
    vertices, faces, _ = read_mesh_ply(tiny_run / "tsdf_mesh.ply")
    assert len(vertices) == report["counts"]["tsdf_mesh_vertices"]
    assert len(faces) == report["counts"]["tsdf_mesh_faces"]
    assert faces.min() >= 0 and faces.max() < len(vertices)
    # The tabletop: a 1 x 1 m slab 4 cm thick with its top at z = 0, objects up to 0.2 m tall.
    margin = 2 * 0.03
    assert np.all(np.abs(vertices[:, :2]) <= 0.5 + margin)
    assert vertices[:, 2].min() >= -0.04 - margin and vertices[:, 2].max() <= 0.2 + margin


def test_run_saves_the_resolved_config(tiny_run):
    saved = load_config(tiny_run / "config.toml")
    assert saved == load_config(None, list(TINY_SCENE_SETS))
    report = json.loads((tiny_run / "report.json").read_text())
    assert report["config"] == saved.to_dict()


def test_run_refuses_to_overwrite_unless_asked(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    rc, _, err = call(capsys, "run", "-q", *sets_args())   # default --out: out/<scene name>
    assert rc == 0, err
    out = tmp_path / "out" / "default"
    before = {name: (out / name).read_bytes() for name in RUN_FILES}

    rc, _, err = call(capsys, "run", "-q", *sets_args(TINY_SCENE_SETS + ("synthetic.n_views=4",)))
    assert rc == 2
    assert err.startswith("error:") and "--overwrite" in err and str(Path("out", "default")) in err
    assert {name: (out / name).read_bytes() for name in RUN_FILES} == before   # untouched

    rc, stdout, err = call(capsys, "run", "--overwrite",
                           *sets_args(TINY_SCENE_SETS + ("synthetic.n_views=4",)))
    assert rc == 0, err
    assert json.loads((out / "report.json").read_text())["counts"]["frames"] == 4
    # Without -q a summary is printed: counts, timing, the metrics table, the output folder.
    assert "scene default: 4 frames" in stdout
    assert "fscore@50mm" in stdout and f"outputs in {Path('out') / 'default'}" in stdout


# --------------------------------------------------------------------------------------------
# synth -> fuse -> eval
# --------------------------------------------------------------------------------------------

def test_synth_writes_7scenes_layout_and_ground_truth(synth_dir):
    names = {p.name for p in synth_dir.iterdir()}
    assert {"camera-intrinsics.txt", "gt_mesh.ply"} <= names
    for i in range(6):
        assert f"frame-{i:06d}.depth.png" in names and f"frame-{i:06d}.pose.txt" in names
    assert "frame-000006.depth.png" not in names
    with Image.open(synth_dir / "frame-000000.depth.png") as im:
        depth = np.array(im)
    assert depth.shape == (48, 64) and depth.dtype == np.uint16
    assert np.count_nonzero(depth) > 0.2 * depth.size   # the tabletop fills a third of the view
    K = np.loadtxt(synth_dir / "camera-intrinsics.txt")
    np.testing.assert_allclose(K, [[52.5, 0, 31.5], [0, 52.5, 23.5], [0, 0, 1]])


def test_fuse_finds_ground_truth_and_reports_metrics(fused):
    for name in RUN_FILES:
        assert (fused / name).is_file(), name
    report = json.loads((fused / "report.json").read_text())
    assert report["counts"]["frames"] == 6
    assert report["has_ground_truth"] is True          # gt_mesh.ply found next to the frames
    assert report["metrics"]["tsdf_mesh.ply"]["fscore@50mm"] > 0.9


def test_synth_then_fuse_reproduces_run(tiny_run, fused):
    """The frames `synth` writes (mm PNGs) fuse to the same surface as `run` on the same scene:
    the default scene already quantises depth to millimetres, so only float rounding differs."""
    a = json.loads((tiny_run / "report.json").read_text())
    b = json.loads((fused / "report.json").read_text())
    assert b["counts"]["pixels_used"] == a["counts"]["pixels_used"]
    assert b["counts"]["observed_voxels"] == pytest.approx(a["counts"]["observed_voxels"], rel=0.01)
    ma, mb = a["metrics"]["tsdf_mesh.ply"], b["metrics"]["tsdf_mesh.ply"]
    assert mb["accuracy_m"] == pytest.approx(ma["accuracy_m"], rel=0.05)
    assert mb["completeness_m"] == pytest.approx(ma["completeness_m"], rel=0.05)


def test_eval_prints_a_table(fused, synth_dir, capsys):
    rc, out, err = call(capsys, "eval", fused / "tsdf_mesh.ply", synth_dir / "gt_mesh.ply",
                        "--samples", "5000", "--thresholds", "10,20")
    assert rc == 0, err
    lines = out.splitlines()
    assert "tsdf_mesh.ply" in lines[0]
    labels = [line.split()[0] for line in lines[2:]]
    assert {"accuracy", "completeness", "fscore@10mm", "fscore@20mm"} <= set(labels)
    assert "fscore@5mm" not in labels


def test_eval_json_of_a_mesh_against_itself_is_perfect(synth_dir, capsys):
    gt = synth_dir / "gt_mesh.ply"
    rc, out, err = call(capsys, "eval", gt, gt, "--json", "--samples", "2000")
    assert rc == 0, err
    m = json.loads(out)
    fscores = [v for k, v in m.items() if k.startswith("fscore@")]
    assert len(fscores) == 4 and all(f == 1.0 for f in fscores)
    assert m["chamfer_l2"] == 0.0


def test_eval_json_reproduces_the_runs_metrics(fused, synth_dir, capsys):
    """Same samples and seed as the run: `bftaichi eval` gives the numbers in report.json."""
    rc, out, err = call(capsys, "eval", fused / "tsdf_mesh.ply", synth_dir / "gt_mesh.ply",
                        "--json", "--samples", "5000", "--seed", "0")
    assert rc == 0, err
    m = json.loads(out)
    expected = json.loads((fused / "report.json").read_text())["metrics"]["tsdf_mesh.ply"]
    assert m.keys() == expected.keys()
    for key, value in expected.items():
        assert m[key] == pytest.approx(value, rel=1e-5, abs=1e-9), key


# --------------------------------------------------------------------------------------------
# help and version
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["run", "fuse", "synth", "eval"])
def test_command_help_has_an_example(command, capsys):
    rc, out, _ = call(capsys, command, "--help")
    assert rc == 0
    assert out.startswith(f"Usage: bftaichi {command}")
    assert "Example" in out


def test_top_level_help_lists_every_command(capsys):
    rc, out, _ = call(capsys, "--help")
    assert rc == 0
    for command in ("run", "fuse", "synth", "eval"):
        assert f"  {command} " in out


def test_version(capsys):
    rc, out, _ = call(capsys, "--version")
    assert rc == 0 and __version__ in out


# --------------------------------------------------------------------------------------------
# user errors: exit 2, "error: ..." naming the culprit, no traceback, no run written
# --------------------------------------------------------------------------------------------

def _error_cases(tmp_path: Path) -> dict[str, tuple[list, str]]:
    """name -> (arguments, text the message must contain)."""
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    invalid = write_all_invalid_7scenes(tmp_path / "dark_seq")
    gt = tmp_path / "gt.ply"
    return {
        "missing scene file": (["run", tmp_path / "missing.toml"], "missing.toml"),
        "unknown --set key": (["run", "--set", "tsdf.voxel_sise_m=0.02"], "voxel_sise_m"),
        "bad --set value": (["run", "--set", "tsdf.alpha=7"], "tsdf.alpha"),
        "missing dataset": (["fuse", tmp_path / "no_such_data"], "no_such_data"),
        "all-invalid depth": (["fuse", invalid, "--voxel", "0.03"], str(invalid)),
        "--trunc 0": (["fuse", invalid, "--voxel", "0.03", "--trunc", "0"], "tsdf.trunc_m"),
        "out inside a file": (["run", "--out", a_file / "sub", *sets_args()], str(a_file)),
        "missing gt for fuse": (["fuse", invalid, "--gt", gt], str(gt)),
    }


@pytest.mark.parametrize("case", ["missing scene file", "unknown --set key", "bad --set value",
                                  "missing dataset", "all-invalid depth", "--trunc 0",
                                  "out inside a file", "missing gt for fuse"])
def test_user_error_exits_2_with_a_message(case, tmp_path, capsys):
    args, named = _error_cases(tmp_path)[case]
    has_out = "--out" in args
    out_dir = tmp_path / "out"
    rc, stdout, err = call(capsys, *args, *([] if has_out else ["--out", out_dir]))
    assert rc == 2
    assert err.startswith("error: ")
    assert named in err
    assert "Traceback" not in err + stdout
    assert not list(tmp_path.rglob("tsdf_mesh.ply")) and not list(tmp_path.rglob("mesh.ply"))
    for report in tmp_path.rglob("report.json"):  # only the record of the failure, if any
        assert json.loads(report.read_text())["status"] == "failed", report


def test_synth_into_a_file_exits_2(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    rc, _, err = call(capsys, "synth", "--out", a_file / "seq", "-q", *sets_args())
    assert rc == 2 and err.startswith("error: ") and str(a_file) in err


@pytest.mark.parametrize("args, named", [
    (["--samples", "0"], "eval.n_samples"),
    (["--thresholds", "5,x"], "--thresholds"),
])
def test_eval_bad_option_exits_2(args, named, synth_dir, capsys):
    gt = synth_dir / "gt_mesh.ply"
    rc, _, err = call(capsys, "eval", gt, gt, *args)
    assert rc == 2 and err.startswith("error: ") and named in err


def test_eval_missing_mesh_exits_2(tmp_path, synth_dir, capsys):
    rc, _, err = call(capsys, "eval", tmp_path / "pred.ply", synth_dir / "gt_mesh.ply")
    assert rc == 2 and err.startswith("error: ") and str(tmp_path / "pred.ply") in err


def test_unknown_command_is_a_usage_error(capsys):
    rc, _, err = call(capsys, "fusee")
    assert rc == 2 and "No such command" in err


def test_two_runs_write_byte_identical_outputs(tiny_run, tmp_path, capsys):
    """Same inputs and seed -> the same bytes (integration has no float atomics)."""
    rc, _, err = call(capsys, "run", "-q", "--out", str(tmp_path / "again"), *sets_args())
    assert rc == 0, err
    for name in ("band.npz", "tsdf_mesh.ply"):
        assert (tmp_path / "again" / name).read_bytes() == (tiny_run / name).read_bytes(), name


def test_run_summary_compact_verbose_and_quiet(tmp_path, capsys):
    assert main(["run", "--out", str(tmp_path / "a"), *sets_args(), "--set",
                 "run.preview=false"]) == 0
    compact = capsys.readouterr().out
    assert "fscore@" in compact and "precision@" not in compact
    fit = json.loads((tmp_path / "a" / "report.json").read_text())["solver"]["observations"][
        "noise_fit"]
    assert ("noise fit:" in compact) == (fit["sigma_extra_m"] > 0)  # said where it counts
    assert "share it" not in compact  # synthetic poses: no pose error shared in time
    assert "seconds per stage" not in compact and "preview.html" not in compact
    assert main(["run", "-v", "--out", str(tmp_path / "b"), *sets_args()]) == 0
    verbose = capsys.readouterr().out
    assert "precision@" in verbose and "seconds per stage" in verbose
    assert "posterior seconds" in verbose and "preview.html" in verbose
    assert main(["run", "-q", "--out", str(tmp_path / "c"), *sets_args()]) == 0
    assert capsys.readouterr().out == ""


REDKITCHEN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason="shared redkitchen frames not present")
def test_fuse_rgb_colours_both_meshes(tmp_path):
    import plyfile

    out = tmp_path / "rgb"
    assert main(["fuse", str(REDKITCHEN), "--voxel", "0.08", "--frames", "0:4", "--rgb", "-q",
                 "--out", str(out), "--set", "run.plots=false", "--set", "run.preview=false"]) == 0
    for name in ("mesh.ply", "tsdf_mesh.ply"):
        v = plyfile.PlyData.read(out / name)["vertex"]
        rgb = np.stack([np.asarray(v[c]) for c in ("red", "green", "blue")], axis=1)
        assert len(rgb) > 100 and rgb.std(axis=0).min() > 5, name  # real colours, not a fill
    names = plyfile.PlyData.read(out / "mesh.ply")["vertex"].data.dtype.names
    assert "sigma" in names and "sigma_pos" in names


def test_the_command_line_fills_taichis_offline_cache(tmp_path):
    """A second ``bftaichi`` command starts from the kernels the first compiled: the process
    writes Taichi's offline cache as it exits (the CLI freezes its imports' objects for the
    run's garbage collections, and must unfreeze them at exit, or Taichi's program is never
    freed and nothing is written: every run then compiled every kernel again)."""
    import os
    import subprocess
    import sys

    cache = tmp_path / "ti-cache"
    cache.mkdir()
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache))
    cmd = [sys.executable, "-m", "bftaichi.cli", "run", "--out", str(tmp_path / "out"), "-q",
           "--set", "run.stages=tsdf_only", "--set", "run.plots=false", *sets_args()]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert sum(1 for p in cache.rglob("*") if p.is_file()) > 0


def test_the_command_keeps_its_exit_code_and_output_through_the_quick_exit(tmp_path):
    """The console script ends with os._exit (bftaichi.process.quick_exit): its exit code, a
    refusal's message on stderr and the results on stdout must survive it, piped."""
    import subprocess
    import sys

    missing = tmp_path / "missing.toml"
    done = subprocess.run([sys.executable, "-m", "bftaichi.cli", "run", str(missing), "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert "error:" in done.stderr and "missing.toml" in done.stderr
    assert not (tmp_path / "out").exists()
    done = subprocess.run([sys.executable, "-m", "bftaichi.cli", "--help"], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and "Quick start" in done.stdout


def test_a_profiled_command_still_writes_its_profile(tmp_path):
    """The quick exit steps aside under a profiler: ``python -m cProfile -o F -m bftaichi.cli``
    must leave its profile F (os._exit would drop it)."""
    import subprocess
    import sys

    prof = tmp_path / "cli.prof"
    done = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(prof), "-m",
                           "bftaichi.cli", "--help"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert prof.is_file() and prof.stat().st_size > 0
