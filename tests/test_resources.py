"""bftaichi.running.resources: the memory estimate scales with the voxel size, the guard names a voxel
size that fits, PeakRSS sees a stage's allocation, and run.memory_fraction / memory_budget_gib are validated."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bftaichi.config import load_config
from bftaichi.errors import BftaichiError, ConfigError
from bftaichi.running.pipeline import open_frames
from bftaichi.running.resources import (BASE_BYTES, GIB, PeakRSS, ResourceError, check_memory,
                                estimate_memory, memory_budget)
from conftest import TINY_SCENE_SETS

ROOT = Path(__file__).resolve().parents[1]


def _tiny(voxel: float = 0.03, *extra):
    cfg = load_config(None, [*TINY_SCENE_SETS, f"tsdf.voxel_size_m={voxel}",
                             f"tsdf.trunc_m={2 * voxel}", *extra])
    return cfg, open_frames(cfg)


def test_estimate_grows_about_4x_when_the_voxel_halves():
    # truncation fixed in voxels: the band and every per-voxel array scale as 1 / voxel^2.
    # "variance - tsdf" removes the run's fixed part (interpreter, Taichi, the minimum pool).
    coarse, fine = (estimate_memory(*_tiny(v)) for v in (0.03, 0.015))
    band = fine["inputs"]["band_voxels"] / coarse["inputs"]["band_voxels"]
    assert 3.0 <= band <= 5.0
    grow = ((fine["stages"]["variance"] - fine["stages"]["tsdf"])
            / (coarse["stages"]["variance"] - coarse["stages"]["tsdf"]))
    assert 3.0 <= grow <= 5.5
    assert fine["peak_bytes"] > coarse["peak_bytes"] > BASE_BYTES
    assert coarse["peak_stage"] in coarse["stages"] and coarse["seconds"] < 5
    assert set(coarse["inputs"]) >= {"blocks", "observed_voxels", "band_voxels"}


def test_tsdf_only_estimates_the_bootstrap_stages_only():
    est = estimate_memory(*_tiny(0.03, "run.stages=tsdf_only"))
    assert set(est["stages"]) == {"tsdf", "export", "mesh"}
    assert est["inputs"]["band_voxels"] == 0


def test_check_memory_names_a_voxel_size_that_fits():
    cfg, frames = _tiny(0.015)
    est = estimate_memory(cfg, frames)
    budget = BASE_BYTES + (est["peak_bytes"] - BASE_BYTES) // 3
    with pytest.raises(ResourceError) as info:
        check_memory(cfg, frames, budget=budget)
    err = info.value
    assert isinstance(err, BftaichiError)
    v = err.voxel_size_m
    assert v is not None and v > 0.015
    assert f"tsdf.voxel_size_m = {v:g} would need" in str(err)
    assert "exceeds the budget" in str(err) and "run.memory_fraction" in str(err)
    # the suggestion fits when estimated on its own
    cfg_fit, _ = _tiny(v)
    cfg_fit.tsdf.trunc_m = cfg.tsdf.trunc_m if cfg.tsdf.trunc_m >= v else v
    assert estimate_memory(cfg_fit, frames)["peak_bytes"] <= budget
    # and a generous budget passes, returning the estimate
    ok = check_memory(cfg, frames, budget=est["peak_bytes"] * 2)
    assert ok["budget_bytes"] == est["peak_bytes"] * 2


def _chunk_fit(voxel):
    """A tiny scene and a budget that a whole-band solve exceeds and a chunked one fits."""
    from bftaichi.running.chunking import chunk_sides
    from bftaichi.running.resources import SceneSample, _model

    cfg, frames = _tiny(voxel)
    whole = estimate_memory(cfg, frames)
    sample = SceneSample(frames, voxel, cfg.scene.depth_max_m)
    chunked = min(_model(sample, voxel, cfg.tsdf.bootstrap_trunc_m, True, (side, 8))["peak_bytes"]
                  for side in chunk_sides(sample, voxel))
    assert chunked < whole["peak_bytes"]
    return cfg, frames, whole, (chunked + whole["peak_bytes"]) // 2


def test_check_memory_chooses_the_largest_chunk_size_that_fits():
    from bftaichi.running.chunking import ChunkingWarning

    cfg, frames, whole, budget = _chunk_fit(0.015)
    with pytest.warns(ChunkingWarning, match="solving in chunks of"):
        est = check_memory(cfg, frames, budget=budget)
    chunk_m = est["chunk_m_chosen"]
    assert est["peak_bytes"] <= budget < est["whole_band_peak_bytes"] == whole["peak_bytes"]
    assert est["inputs"]["chunk_band_voxels"] < est["inputs"]["band_voxels"]
    # the estimate of that chunk size is the one returned; every larger candidate exceeds it
    cfg.run.chunk_m = chunk_m
    assert estimate_memory(cfg, frames)["peak_bytes"] == est["peak_bytes"]
    from bftaichi.running.chunking import chunk_sides
    from bftaichi.running.resources import SceneSample

    sides = chunk_sides(SceneSample(frames, 0.015, cfg.scene.depth_max_m), 0.015)
    larger = [s for s in sides if s * 0.015 > chunk_m + 1e-9]
    for side in larger:
        cfg.run.chunk_m = side * 0.015
        assert estimate_memory(cfg, frames)["peak_bytes"] > budget
    # a user's own chunk size is estimated as chunked, not refused as a whole-band solve
    assert check_memory(cfg, frames, budget=whole["peak_bytes"])["peak_bytes"] < whole["peak_bytes"]


def test_a_run_over_budget_solves_in_chunks_and_says_so(tmp_path, capsys):
    from bftaichi.cli import main

    cfg, frames, whole, budget = _chunk_fit(0.03)
    out = tmp_path / "out"
    sets = [*TINY_SCENE_SETS, "run.plots=false", "run.preview=false",
            f"run.memory_budget_gib={budget / GIB!r}"]
    capsys.readouterr()
    assert main(["run", "--out", str(out), "-q", *[a for s in sets for a in ("--set", s)]]) == 0
    err = capsys.readouterr().err
    assert "warning: estimated peak memory" in err and "solving in chunks of" in err
    import json

    report = json.loads((out / "report.json").read_text())
    chosen = report["memory"]["estimate"]["chunk_m_chosen"]
    assert report["config"]["run"]["chunk_m"] == chosen > 0
    assert report["solver"]["map"]["chunks"]["n"] >= 2
    assert (out / "mesh.ply").is_file()
    # the cost model reads such a report and reproduces the run it came from
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "chunk_cost_model.py"),
                        str(out / "report.json"), "--floor-m2", "100", "--workers", "1", "4"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "predicted: 100 m^2 of floor" in r.stdout and "4 workers" in r.stdout


def test_check_memory_says_when_no_voxel_size_fits():
    cfg, frames = _tiny(0.03)
    with pytest.raises(ResourceError, match="no voxel size up to 1 m fits") as info:
        check_memory(cfg, frames, budget=2 ** 20)  # 1 MiB: less than the interpreter
    assert info.value.voxel_size_m is None


def test_memory_budget_conventions():
    cfg, _ = _tiny(0.03, "run.memory_budget_gib=2")
    assert memory_budget(cfg) == 2 * GIB
    cfg.run.memory_budget_gib = 0.0
    cfg.run.memory_fraction = 0.5
    b = memory_budget(cfg)
    if Path("/proc/meminfo").exists():
        assert 0 < b
        cfg.run.memory_fraction = 1.0
        assert abs(memory_budget(cfg) - 2 * b) <= 2 * 2 ** 20 + 0.01 * b  # RAM moves a little


@pytest.mark.parametrize("key,value", [("memory_fraction", v) for v in
                                       ["0", "-0.5", "1.5", "nan", "inf", "true", "'big'"]]
                         + [("memory_budget_gib", v) for v in ["-1", "nan", "'big'"]])
def test_bad_memory_budget_is_a_config_error(key, value):
    with pytest.raises(ConfigError, match=f"run.{key}"):
        load_config(None, [f"run.{key}={value}"])


@pytest.mark.parametrize("old,new", [("run.memory_budget=2", "run.memory_budget_gib"),
                                     ("synthetic.kinect_a=0.001", "synthetic.depth_a_m"),
                                     ("prior.outer=10", "prior.free")])
def test_a_renamed_key_names_its_successor(old, new):
    with pytest.raises(ConfigError, match=new.replace(".", r"\.")):
        load_config(None, [old])


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_peak_rss_sees_a_stage_allocation():
    rss = PeakRSS()
    assert rss.baseline > 0
    with rss("idle"):
        pass
    with rss("alloc"):
        a = np.ones(200 * 2 ** 20 // 8)  # 200 MiB, touched
        del a
    assert rss.peaks["alloc"] >= rss.baseline + 150 * 2 ** 20
    if rss.reset_works:  # the peak counter was reset at start: the idle stage stays low
        with rss("after"):
            pass
        assert rss.peaks["after"] < rss.peaks["alloc"] - 100 * 2 ** 20
    assert rss.peak == rss.peaks["alloc"]
    assert rss.to_dict()["stages"]["alloc"] == rss.peaks["alloc"]


def test_peak_rss_without_proc_is_none(monkeypatch):
    import bftaichi.running.resources as r

    monkeypatch.setattr(r, "_STATUS", "/nonexistent/status")
    rss = PeakRSS()
    with rss("x"):
        pass
    assert rss.baseline is None and rss.peaks == {"x": None} and rss.peak is None


def test_memory_estimate_tool_runs_on_the_tiny_scene():
    sets = [a for s in TINY_SCENE_SETS if not s.startswith("tsdf.voxel")
            for a in ("--set", s)]
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "memory_estimate.py"), "",
                           "--voxels", "0.03", *sets], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = [ln for ln in proc.stdout.splitlines() if ln.startswith("| default | 30 mm")]
    assert len(row) == 1
    ratio = float(row[0].split("|")[7])
    assert 0.5 <= ratio <= 2.0


def test_the_restated_tsdf_layout_matches_kernels_tsdf():
    import bftaichi.running.resources as r
    import kernels.tsdf as t

    assert (r.BLOCK, r.BLOCK_VOXELS, r.FIRST_POOL_BLOCKS) == (t.BLOCK, t.BLOCK_VOXELS,
                                                               t.FIRST_POOL_BLOCKS)


@pytest.mark.parametrize("span", [3, 40, 1 << 12])  # the last: more than a bitmap holds
def test_distinct_block_keys_are_the_sorted_unique_keys(span):
    # the scene sample counts the distinct blocks its rays meet by a bitmap instead of a sort:
    # the same keys, ascending, for integer or whole-number float coordinates of any sign
    from kernels.layout import block_key_np, distinct_block_keys

    rng = np.random.default_rng(span)
    blocks = rng.integers(-span, span, size=(20_000, 3)) + np.array([-700, 5, 300])
    for b in (blocks, blocks.astype(np.float64), blocks[:1], blocks[:0]):
        np.testing.assert_array_equal(distinct_block_keys(b), np.unique(block_key_np(b)))
