"""bftaichi.running.evalworker: the run's ground-truth evaluation and plots in a worker process
give what the run's own process gives, and a user's script is not run again by it."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from conftest import TINY_SCENE_SETS


@pytest.fixture(scope="module")
def solved():
    """The tiny scene solved in this process: (cfg, gt, post, its mesh, the TSDF mesh), the
    meshes in the grid's local frame, as the pipeline hands them to the evaluation."""
    import bftaichi as bf
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    cfg = bf.load_config(None, list(TINY_SCENE_SETS))
    frames = open_frames(cfg)
    recon = bf.Reconstructor(cfg)
    for i in range(len(frames)):
        f = frames[i]
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    post = recon.solve(frames)
    return (cfg, load_gt_mesh(cfg, frames), post, post.extract_mesh(local=True),
            recon.tsdf_mesh(local=True))


def _measure(evaluation, post, post_mesh, tsdf_mesh, band_first):
    with evaluation:
        evaluation.start(post.origin)
        evaluation.add_tsdf(tsdf_mesh)
        if band_first:
            evaluation.add_band(post)
        evaluation.add_posterior(post, post_mesh)
        return evaluation.results()


def _assert_same(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b)
    else:
        assert a == b or (a != a and b != b)  # NaN == NaN here


@pytest.mark.parametrize("band_first", [True, False])
def test_the_worker_measures_what_the_runs_process_measures(solved, band_first):
    from bftaichi.running.evalworker import EvalWorker
    from bftaichi.running.evaluation import RunEvaluation

    cfg, gt, post, post_mesh, tsdf_mesh = solved
    here = _measure(RunEvaluation(gt, cfg.eval, cfg.tsdf.voxel_size_m), post, post_mesh,
                    tsdf_mesh, band_first)
    there = _measure(EvalWorker(gt, cfg.eval, cfg.tsdf.voxel_size_m), post, post_mesh,
                     tsdf_mesh, band_first)
    assert there["uncertainty"] is not None and there["band_uncertainty"] is not None
    _assert_same(here, there)


def test_the_workers_plots_are_the_plots_of_the_runs_process(tmp_path):
    """A run writes its plots in the worker; write_run_plots in this process, from the same
    folder, ground truth, distances and vertex errors, writes the same bytes."""
    import shutil

    import bftaichi as bf
    from bftaichi.evaluation.metrics import surface_distances, vertex_errors
    from bftaichi.io import read_mesh_ply
    from bftaichi.running.pipeline import load_gt_mesh, open_frames
    from bftaichi.running.plots import PLOTS, write_run_plots

    cfg = bf.load_config(None, [*TINY_SCENE_SETS, "run.plots=true", "run.preview=false"])
    report = bf.run(cfg, tmp_path / "run", progress=False)
    assert not np.any(report["origin_m"])  # the files' frame is the metrics' frame
    gt = load_gt_mesh(cfg, open_frames(cfg))
    copy = tmp_path / "copy"
    shutil.copytree(tmp_path / "run", copy, ignore=shutil.ignore_patterns("plots"))
    # the distances the run measured on its meshes, here from the files (float32 vertices):
    # equal to the run's at the report's precision only, so compare the plots they do not
    # change bit for bit, and the others by their existence
    v, _, _ = read_mesh_ply(copy / "mesh.ply")
    paths = write_run_plots(report, copy, gt=gt, vertex_errors=vertex_errors(v, gt),
                            distances={n: surface_distances(
                                bf.evaluation.metrics.load_mesh(copy / n), gt,
                                cfg.eval.n_samples, cfg.eval.seed)
                                for n in ("mesh.ply", "tsdf_mesh.ply")})
    assert [p.name for p in paths] == [f"{p}.png" for p in PLOTS]
    for name in ("sigma_histogram.png", "pcg_residual.png"):
        assert (copy / "plots" / name).read_bytes() == (tmp_path / "run" / "plots" /
                                                         name).read_bytes(), name
    assert sorted(p.name for p in (tmp_path / "run" / "plots").iterdir()) == sorted(
        p.name for p in paths)


def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """The worker is spawned without the caller's main script: a script that calls bf.run at
    top level (no ``if __name__ == "__main__":``) must not run again inside it."""
    marker = tmp_path / "executions.txt"
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(f"""
        import bftaichi as bf
        with open({str(marker)!r}, "a") as f:
            f.write("ran\\n")
        cfg = bf.load_config(None, {list(TINY_SCENE_SETS) + ["run.plots=true"]!r})
        report = bf.run(cfg, {str(tmp_path / "out")!r}, progress=False)
        print(report["metrics"]["mesh.ply"]["chamfer_l2"])
    """))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert marker.read_text() == "ran\n"
    assert float(proc.stdout.strip().splitlines()[-1]) > 0
    assert (tmp_path / "out" / "plots" / "calibration.png").is_file()


def test_write_run_plots_writes_the_plots_asked_for(tmp_path):
    import bftaichi as bf
    from bftaichi.errors import BftaichiError
    from bftaichi.running.plots import write_run_plots

    cfg = bf.load_config(None, list(TINY_SCENE_SETS))
    report = bf.run(cfg, tmp_path / "run", progress=False)
    paths = write_run_plots(report, tmp_path / "run", which=("pcg_residual",))
    assert [p.name for p in paths] == ["pcg_residual.png"]
    assert [p.name for p in (tmp_path / "run" / "plots").iterdir()] == ["pcg_residual.png"]
    with pytest.raises(BftaichiError, match="no plot histogram"):
        write_run_plots(report, tmp_path / "run", which=("histogram",))
