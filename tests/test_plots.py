"""bftaichi.running.plots: the run's diagnostic PNGs, and the curve data behind them."""

import numpy as np
import pytest

from conftest import TINY_SCENE_SETS

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
ALL_PLOTS = ["precision_recall.png", "fscore.png", "sigma_histogram.png", "calibration.png",
             "pcg_residual.png"]


def _tiny_run(tmp_path_factory, name, extra=()):
    import bftaichi as bf
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    cfg = bf.load_config(None, [*TINY_SCENE_SETS, *extra])
    out = tmp_path_factory.mktemp(name)
    report = bf.run(cfg, out, overwrite=True, progress=False)
    return report, out, load_gt_mesh(cfg, open_frames(cfg))


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    return _tiny_run(tmp_path_factory, "full", ["run.plots=true"])


def test_a_run_writes_its_plots_itself(full_run):
    report, out, _ = full_run
    assert sorted(p.name for p in (out / "plots").iterdir()) == sorted(ALL_PLOTS)
    assert report["seconds"]["plots"] > 0


@pytest.fixture(scope="module")
def full_plots(full_run):
    from bftaichi.running.plots import write_run_plots

    report, out, gt = full_run
    return write_run_plots(report, out, gt=gt)


def _assert_drawn(path):
    from PIL import Image

    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 5000, path
    pixels = np.asarray(Image.open(path).convert("L"), np.float64)
    assert pixels.shape[0] > 300 and pixels.shape[1] > 300
    assert pixels.std() > 10, f"{path.name} looks blank"


def test_full_run_with_ground_truth_writes_all_five(full_run, full_plots):
    _, out, _ = full_run
    assert [p.name for p in full_plots] == ALL_PLOTS
    assert all(p.parent == out / "plots" for p in full_plots)
    for p in full_plots:
        _assert_drawn(p)
    assert not list((out / "plots").glob(".*.tmp"))  # atomic writes leave no temp file


def test_without_ground_truth_only_the_posterior_plots(full_run, full_plots, tmp_path):
    import shutil

    from bftaichi.running.plots import write_run_plots

    report, out, _ = full_run
    copy = tmp_path / "run"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("plots"))
    paths = write_run_plots(report, copy)  # post loaded from band.npz
    assert [p.name for p in paths] == ["sigma_histogram.png", "pcg_residual.png"]
    assert sorted(p.name for p in (copy / "plots").iterdir()) == sorted(p.name for p in paths)


def test_tsdf_only_run_writes_only_the_tsdf_curves(tmp_path_factory):
    from bftaichi.running.plots import write_run_plots

    report, out, gt = _tiny_run(tmp_path_factory, "tsdf_only", ["run.stages=tsdf_only"])
    paths = write_run_plots(report, out, gt=gt)
    assert [p.name for p in paths] == ["precision_recall.png", "fscore.png"]
    for p in paths:
        _assert_drawn(p)
    assert write_run_plots(report, out) == []  # nothing to draw without truth or posterior


def test_curves_are_monotone_and_match_the_report_exactly(full_run):
    from bftaichi.evaluation.metrics import load_mesh, surface_distances, threshold_curves
    from bftaichi.running.plots import curve_thresholds_mm

    report, out, gt = full_run
    ev = report["config"]["eval"]
    thresholds = curve_thresholds_mm(report["tsdf"]["voxel_size_m"], ev["thresholds_mm"])
    assert len(thresholds) >= 40 and np.all(np.diff(thresholds) > 0)
    for name in ("mesh.ply", "tsdf_mesh.ply"):
        d = surface_distances(load_mesh(out / name), gt, ev["n_samples"], ev["seed"])
        c = threshold_curves(*d, thresholds)
        for key in ("precision", "recall", "fscore"):
            assert np.all(np.diff(c[key]) >= 0), (name, key)
            assert 0 <= c[key][0] and c[key][-1] <= 1
        # 50 voxels is far beyond every error of this scene
        assert c["precision"][-1] == 1.0 and c["recall"][-1] == 1.0
        at = {float(t): i for i, t in enumerate(thresholds)}
        m = report["metrics"][name]
        for t_mm in ev["thresholds_mm"]:
            i = at[float(t_mm)]
            for key in ("precision", "recall", "fscore"):
                assert c[key][i] == m[f"{key}@{t_mm:g}mm"], (name, key, t_mm)


def test_threshold_curves_by_hand():
    from bftaichi.running.plots import threshold_curves

    d_pg = np.array([0.001, 0.002, 0.004, 0.010])  # metres
    d_gp = np.array([0.003, 0.003, 0.020, 0.020])
    c = threshold_curves(d_pg, d_gp, [1.0, 3.0, 5.0, 30.0])  # mm; strict "<"
    np.testing.assert_array_equal(c["precision"], [0.0, 0.5, 0.75, 1.0])
    np.testing.assert_array_equal(c["recall"], [0.0, 0.0, 0.5, 1.0])
    np.testing.assert_allclose(c["fscore"], [0.0, 0.0, 0.6, 1.0])


def test_calibration_uses_the_vertices_of_the_report(full_run):
    from bftaichi.evaluation.metrics import vertex_errors
    from bftaichi.io import read_mesh_ply
    from bftaichi.running.plots import coverage_curve

    report, out, gt = full_run
    u = report["uncertainty"]
    v, _, attrs = read_mesh_ply(out / "mesh.ply")
    err, sigma = vertex_errors(v, gt), np.asarray(attrs["sigma"], np.float64)
    assert len(err) == u["n"]
    expected, observed = coverage_curve(err, sigma, np.array([0.0, 1.0, 2.0, 3.0]))
    np.testing.assert_allclose(expected, [0.0, 0.682689, 0.954500, 0.997300], atol=1e-6)
    # mesh.ply holds float32 vertices and sigma: the report was computed from float64 ones
    np.testing.assert_allclose(observed[1:], [u[f"coverage@{k}sigma"] for k in (1, 2, 3)],
                               atol=2e-3)
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(u["rms_error_m"], rel=1e-3)


def test_not_a_run_folder_is_named(full_run, tmp_path):
    from bftaichi.errors import BftaichiError
    from bftaichi.running.plots import write_run_plots

    report, _, _ = full_run
    with pytest.raises(BftaichiError, match="missing mesh.ply, tsdf_mesh.ply: not the folder"):
        write_run_plots(report, tmp_path)
    with pytest.raises(BftaichiError, match="report dict"):
        write_run_plots({"scene": "x"}, tmp_path)


def test_gallery_copies_the_pngs_named_by_scene(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    proc = subprocess.run([sys.executable, str(root / "tools" / "gallery.py"),
                           "scenes/default.toml", *sets, "--set", "nbv.n_candidates=6",
                           "--out", str(tmp_path / "run"), "--docs", str(tmp_path / "docs"),
                           "--no-screenshot"],
                          capture_output=True, text=True, timeout=300, cwd=root)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "docs").iterdir()) == sorted(
        f"default_{name}" for name in ALL_PLOTS)
    assert (tmp_path / "run" / "plots" / "calibration.png").is_file()
    assert "default: run" in proc.stdout and "preview.html" in proc.stdout


def test_the_reports_metrics_are_those_of_its_outputs(full_run):
    """The run measures its meshes beside its stages (bftaichi.running.evaluation): what it
    reports must be what the documented metric functions give for the files it wrote."""
    from bftaichi.evaluation.metrics import (band_uncertainty, load_mesh, metrics_from_distances,
                                             surface_distances, vertex_uncertainty)
    from bftaichi.geometry import mesh_in_local
    from bftaichi.posterior import Posterior

    report, out, gt = full_run
    ev = report["config"]["eval"]
    for name in ("tsdf_mesh.ply", "mesh.ply"):
        mesh = load_mesh(out / name)
        want = metrics_from_distances(
            surface_distances(mesh, gt, int(ev["n_samples"]), int(ev["seed"])),
            ev["thresholds_mm"], len(mesh.faces))
        assert report["metrics"][name] == pytest.approx(want, rel=1e-6), name
    post = Posterior.load(out / "band.npz")
    for got, want in ((report["uncertainty"],
                       vertex_uncertainty(post.extract_mesh(local=True),  # the run's frame
                                          mesh_in_local(gt, post.origin), ev["vertex_sigma"])),
                      (report["band_uncertainty"],
                       band_uncertainty(post, gt, ev["near_voxels"], ev["seed"]))):
        assert got["n"] > 100 and set(got) == set(want)
        for key in want:  # band.npz's sigma differs from the run's by float rounding (~1e-9
            # m), which reorders vertices of nearly equal errors: the rank statistics move a bit
            ranked = key in ("spearman", "ause", "sparsification", "top10_ratio")
            assert np.allclose(got[key], want[key], rtol=1e-2 if ranked else 1e-5,
                               atol=1e-9), key


def test_a_large_ground_truth_waits_for_the_posterior_with_the_same_report(
        full_run, tmp_path_factory, monkeypatch):
    """The band's signed distance of a ground truth too large to prepare beside the posterior
    (bftaichi.running.evaluation.AHEAD_SAMPLES) is prepared after it: the same numbers."""
    import bftaichi.running.evaluation as evaluation

    monkeypatch.setattr(evaluation, "AHEAD_SAMPLES", 0)
    report, _, _ = _tiny_run(tmp_path_factory, "late")
    for part in ("metrics", "uncertainty", "band_uncertainty"):
        assert report[part] == full_run[0][part], part
