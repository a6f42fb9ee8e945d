"""Every tools/ script smoke-runs on a tiny input and prints what the README quotes from it."""

import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TINY_SCENE_SETS

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
SHARED = ROOT.parent / "shared" / "data"


def _run(args, timeout=300):
    proc = subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_results_table_prints_a_markdown_row_per_scene(tmp_path):
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    out = _run([TOOLS / "results_table.py", "scenes/default.toml", *sets,
                "--json", tmp_path / "rows.json"])
    lines = [ln for ln in out.splitlines() if ln.startswith("|")]
    assert lines[0].startswith("| scene |") and len(lines) == 4
    assert lines[2].startswith("| default | 6 | 30 mm | tsdf_mesh.ply |")
    assert lines[3].startswith("| default | 6 | 30 mm | mesh.ply |")
    assert (tmp_path / "rows.json").exists()


def test_bench_render_reports_frame_rate():
    out = _run([TOOLS / "bench_render.py", "--mesh", "sphere", "--frames", "3",
                "--width", "64", "--height", "48"])
    assert "rendered 3 frames of 64x48" in out and "frames/s" in out


def test_bench_startup_reports_cold_and_warm():
    out = _run([TOOLS / "bench_startup.py", "--repeats", "1", "--kernels", "2", "--ab",
                "BFTAICHI_TAICHI_POSITIONS=full", "--", "run", "scenes/default.toml",
                *[a for s in TINY_SCENE_SETS for a in ("--set", s)]])
    assert "cold (empty Taichi cache)" in out and "warm (offline cache)" in out
    assert "cold, BFTAICHI_TAICHI_POSITIONS=full: median" in out
    assert "warm, BFTAICHI_TAICHI_POSITIONS=full: median" in out
    assert "warm, BFTAICHI_TAICHI_POSITIONS unset: median" in out
    # the two slowest first calls of each variant, cold and warm
    assert "first calls, BFTAICHI_TAICHI_POSITIONS unset: cold" in out
    rows = [line for line in out.splitlines() if line.startswith("| kernels.")]
    assert len(rows) == 4, out
    # each row also gives the front end's part of the warm first call: a number, at most it
    for row in rows:
        cold, warm, front = (float(x) for x in row.strip("|").split("|")[1:4])
        assert 0 <= front <= warm + 0.005, row


@pytest.mark.skipif(not (SHARED / "rgbd" / "7scenes-redkitchen").is_dir(),
                    reason="shared redkitchen frames not present")
def test_bench_tsdf_runs_on_a_few_frames():
    out = _run([TOOLS / "bench_tsdf.py", "--frames", "5", "--repeats", "1", "--voxels", "0.04"])
    assert "frames/s" in out


def test_reproduce_paper_prints_the_three_rows(tmp_path):
    out = _run([TOOLS / "reproduce_paper.py", "--set", "synthetic.n_views=4",
                "--markdown", tmp_path / "t.md", "--fig2", tmp_path / "fig2.png",
                "--fig3", tmp_path / "fig3.png", "--fig3-seeds", "1", "--fig3-probes", "4,8"])
    for row in ("TSDF bootstrap", "BayesFusion-SDF, no anchor", "BayesFusion-SDF + anchor",
                "bftaichi default (+ curvature prior)"):
        assert f"| {row} |" in out
    assert (tmp_path / "t.md").read_text().startswith("| method |")
    fig2 = out.split("Fig. 2:")[1].splitlines()
    assert fig2[1].startswith("| method | prior.anchors | P@20 | R@20 | F@20 |")
    rows = {ln.split("|")[2].strip(): [float(c) for c in ln.strip("| ").split("|")[2:]]
            for ln in fig2[3:7]}
    assert list(rows) == ["-", "none", "boundary", "all"]
    for p, r, f in rows.values():  # P, R in [0, 1] and F their harmonic mean (4 decimals)
        assert 0 <= p <= 1 and 0 <= r <= 1 and abs(f - 2 * p * r / (p + r)) < 2e-4
    assert (tmp_path / "fig2.png").stat().st_size > 5000
    fig3 = [ln for ln in out.splitlines() if ln.startswith("| 4 |") or ln.startswith("| 8 |")]
    assert len(fig3) == 2 and all(float(ln.split("|")[2].split()[0]) > 0 for ln in fig3)
    assert (tmp_path / "fig3.png").stat().st_size > 1000


def test_vertex_sigma_accuracy_prints_a_row_per_estimator():
    out = _run([TOOLS / "vertex_sigma_accuracy.py", "--scenes", "sphere-tiny", "--probes", "16",
                "--vertices", "200"])
    rows = [ln.split(" | ") for ln in out.splitlines() if ln.startswith("| sphere-tiny")]
    assert [r[3] for r in rows] == ["interpolated var (exact)", "probes K=16 (cov)",
                                    "probes K=16 (var only, cov=0)"]
    median = {r[3]: float(r[4].rstrip(" %")) for r in rows}
    assert median["probes K=16 (cov)"] < median["probes K=16 (var only, cov=0)"]


def test_evalviews_table_and_gross_errors_on_a_few_real_frames(tmp_path):
    data = SHARED / "rgbd" / "7scenes-redkitchen"
    if not data.exists():
        pytest.skip(f"{data} not found")
    out = _run([TOOLS / "evalviews_table.py", "--frames", "0:6", "--voxels", "0.08",
                "--no-open3d", "--out", tmp_path, "--markdown", tmp_path / "ev.md"])
    rows = [ln for ln in out.splitlines() if ln.startswith("| 8 cm |")]
    assert [r.split("|")[2].strip() for r in rows] == ["bftaichi", "tsdf"]
    nll = rows[0].split("|")[-2].strip()
    assert nll.startswith(("+", "-")) and float(nll) == float(nll)  # the NLL column, finite
    out = _run([TOOLS / "gross_errors.py", tmp_path / "evalviews-8cm", "--frames", "6",
                "--every", "2", "--carve"])
    assert "pixels where all three have depth" in out and "in front of the measured depth" in out
    good = out.split("within 1 cm: ")[1]  # the carve counts of the voxels the good pixels hit
    assert "carved by a median of" in good and "% of those observing it" in good
    # render_compare renders what evalviews scored (frames 1, 3, 5) the way evalviews does for
    # the posterior and the TSDF mesh: the same pixels and mean errors as evalviews.json
    out = _run([TOOLS / "render_compare.py", tmp_path / "evalviews-8cm", "--frames", "6",
                "--every", "2"])
    import json

    scored = json.loads((tmp_path / "evalviews-8cm" / "evalviews.json").read_text())["methods"]
    for row, method in (("posterior, ray cast", "bftaichi"), ("tsdf, tsdf_mesh.ply", "tsdf")):
        line = next(ln for ln in out.splitlines() if ln.startswith(row))
        mean_mm, pixels = line[len(row):].split()[:2]
        assert int(pixels.strip("(").replace(",", "")) == scored[method]["pixels"]
        assert float(mean_mm) == pytest.approx(1000 * scored[method]["mean_abs_m"], abs=0.006)
    assert "mesh.ply:" in out and "tsdf_mesh.ply:" in out


def test_kernel_profile_shares_the_kernel_time_of_a_run(tmp_path):
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    out = _run([TOOLS / "kernel_profile.py", "--loops", "_integrate_frame", "run", "--out",
                tmp_path / "run", *sets, "--top", "40"])
    assert (tmp_path / "run" / "mesh.ply").exists()  # the command itself ran
    lines = out[out.index("kernel time "):out.index("\nthe offloaded tasks")].splitlines()
    total = float(lines[0].split()[2])
    rows = {r.split()[0]: (float(r.split()[1]), float(r.split()[2].rstrip("%")))
            for r in lines[2:] if r.strip()}
    assert {"_integrate_frame", "observe_frame", "apply_dot"} <= set(rows)
    # every kernel is listed (--top 40), each rounded to 1 ms and 0.1 %
    assert total > 0
    assert sum(sec for sec, _ in rows.values()) == pytest.approx(total, abs=0.01 + 5e-4 * len(rows))
    assert sum(share for _, share in rows.values()) == pytest.approx(100, abs=0.05 * len(rows))
    # --loops: the TSDF kernel's offloaded tasks, which add up to its row
    tasks = out.split("the offloaded tasks of _integrate_frame (in code order):")[1].splitlines()
    seconds = [float(r.split()[1]) for r in tasks[2:] if r.strip()]
    assert len(seconds) >= 2
    assert sum(seconds) == pytest.approx(rows["_integrate_frame"][0], abs=0.001 * (len(seconds) + 1))


def test_sigma_breakdown_compares_bulk_and_mean_square():
    out = _run([TOOLS / "sigma_breakdown.py", "homer", "few_views",
                "--set", "synthetic.n_views=4"])
    assert "homer/few_views:" in out and "fitted noise" in out
    cover = out.split("within 1 / 2 / 3 sigma: ")[1].split(" %")[0]
    c1, c2, c3 = (float(x) for x in cover.split(" / "))
    assert 0 < c1 <= c2 <= c3 <= 100


def test_thin_parts_finds_a_sheet_thinner_than_the_radius():
    """sigma_breakdown.thin_parts: a 2 mm thick slab is thin within 3 mm of its faces, a 10 cm
    sphere is not anywhere."""
    import numpy as np
    import trimesh

    sys.path.insert(0, str(TOOLS))
    from sigma_breakdown import thin_parts

    slab = trimesh.creation.box((0.1, 0.1, 0.002))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    on_slab = np.array([[0.0, 0.0, 0.001], [0.03, -0.02, -0.001]])
    assert thin_parts(on_slab, slab, 0.003, n_samples=50_000).all()
    assert not thin_parts(ball.vertices[:50], ball, 0.003, n_samples=50_000).any()


def test_sigma_breakdown_takes_a_synthetic_scene_file():
    out = _run([TOOLS / "sigma_breakdown.py", "scenes/seed_sphere.toml",
                "--set", "synthetic.n_views=4"])
    assert "scenes/seed_sphere.toml:" in out and "smooth interior" in out
    proc = subprocess.run([sys.executable, str(TOOLS / "sigma_breakdown.py"),
                           "scenes/seed_sphere.toml", "few_views"], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and "takes no condition" in proc.stderr


def test_suite_diff_shows_what_moved_and_the_targets_of_both(tmp_path):
    """Two suite runs that differ in one case's 1-sigma coverage: the summary lines count the
    target each run meets, and only that case is listed, old -> new, with its misses."""
    import json

    row = {"cd_tsdf": 2e-5, "cd_post": 1.4e-5, "f_mm": 1.0, "f_tsdf": 0.6, "f_post": 0.7,
           "coverage@1sigma": 0.70, "coverage@2sigma": 0.95, "coverage@3sigma": 0.99,
           "nll_vs_constant": -0.5, "ause": 3e-4, "spearman": 0.4}
    old = {"homer/few_views": dict(row), "suzanne/few_views": dict(row)}
    new = {"homer/few_views": dict(row), "suzanne/few_views": {**row, "coverage@1sigma": 0.82}}
    for name, rows in (("old.json", old), ("new.json", new)):
        (tmp_path / name).write_text(json.dumps({"sets": [], "rows": rows}))
    out = _run([TOOLS / "suite_diff.py", tmp_path / "old.json", tmp_path / "new.json"])
    assert "before (no overrides): targets met: cov1 2/2" in out
    assert "after (no overrides): targets met: cov1 1/2" in out
    listed = [ln for ln in out.splitlines() if ln.startswith("| ") and "/" in ln.split("|")[1]]
    assert len(listed) == 1 and listed[0].startswith("| suzanne/few_views |")
    assert "70 / 95 / 99.0 -> 82 / 95 / 99.0" in listed[0] and "| - -> cov1 |" in listed[0]
    assert ("over the 2 cases of both: mean NLL - const -0.500 -> -0.500; AUSE new / old "
            "1.000" in out)
    same = _run([TOOLS / "suite_diff.py", tmp_path / "old.json", tmp_path / "old.json"])
    assert "no case moved" in same
    # the CD on the surface the frames saw: a run from before the split has none (no move);
    # between two runs with it, a change is listed
    seen = {n: {**r, "seen_share": 0.9, "cd_seen_tsdf": 1e-5, "cd_seen_post": 6e-6}
            for n, r in old.items()}
    moved = {**seen, "homer/few_views": {**seen["homer/few_views"], "cd_seen_post": 9e-6}}
    for name, rows in (("seen.json", seen), ("moved.json", moved)):
        (tmp_path / name).write_text(json.dumps({"sets": [], "rows": rows}))
    assert "no case moved" in _run([TOOLS / "suite_diff.py", tmp_path / "old.json",
                                    tmp_path / "seen.json"])
    out = _run([TOOLS / "suite_diff.py", tmp_path / "seen.json", tmp_path / "moved.json"])
    listed = [ln for ln in out.splitlines() if ln.startswith("| ") and "/" in ln.split("|")[1]]
    assert len(listed) == 1 and "| 0.600 -> 0.900 |" in listed[0]
    assert "on the surface the frames saw: CD <= TSDF on 2/2" in out


def test_bench_pose_update_checks_exactness_on_real_frames():
    data = SHARED / "rgbd" / "7scenes-redkitchen"
    if not data.exists():
        pytest.skip(f"{data} not found")
    out = _run([TOOLS / "bench_pose_update.py", "--frames", "8", "--moved", "2", "--voxel",
                "0.08", "--repeats", "1"])
    # the updated TSDF equals re-fusing every frame at its corrected pose, bit for bit
    assert "2 poses: updated TSDF bitwise equal to the re-fused one: True" in out
    assert "2 poses, the solve after the update: band" in out
    assert "posterior: max |mean difference| 0.00e+00 voxel" in out  # the solve after it too
    assert len([ln for ln in out.splitlines() if "-> ratio" in ln]) == 2  # TSDF only, + solve


def test_alternate_runs_a_command_in_each_checkout_in_turn(tmp_path):
    """Two directories whose command prints a different figure: each round runs both in turn,
    in its own directory, and the table holds each one's values and the ratio of medians; a
    run that prints no figure stops the series with a non-zero exit naming its directory."""
    a, b = tmp_path / "a", tmp_path / "b"
    for d, ms in ((a, "20.0"), (b, "15.0")):
        d.mkdir()
        (d / "figure.txt").write_text(ms)
    command = [sys.executable, "-c",
               "print(f'defaults: rays {open(\"figure.txt\").read()} ms per frame')"]
    out = _run([TOOLS / "alternate.py", a, b, "--rounds", "3", "--", *command])
    order = [ln.split(", ")[1].split(":")[0] for ln in out.splitlines() if ln.startswith("round")]
    assert order == [str(a), str(b)] * 3
    assert f"| {a} | 20.00 | 20.00 | 20.00 | 1.000 | 20 20 20 |" in out
    assert f"| {b} | 15.00 | 15.00 | 15.00 | 0.750 | 15 15 15 |" in out
    (b / "figure.txt").write_text("no figure")
    proc = subprocess.run([sys.executable, TOOLS / "alternate.py", a, b, "--", *command],
                          capture_output=True, text=True, cwd=ROOT)  # the dirs end at --
    assert proc.returncode == 1 and str(b) in proc.stderr and "no match" in proc.stderr
