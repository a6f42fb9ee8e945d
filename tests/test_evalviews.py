"""Held-out-view evaluation (bftaichi/evalviews.py, `bftaichi evalviews`)."""

import json

import numpy as np
import pytest

from bftaichi.cli import main
from bftaichi.evaluation.evalviews import _Scores, split_frames
from conftest import TINY_SCENE_SETS


def test_scores_are_the_exact_statistics():
    rng = np.random.default_rng(0)
    measured = rng.uniform(0.5, 3.0, (40, 50)).astype(np.float32)
    measured[:5] = 0  # invalid measurements
    pred = measured + rng.normal(0, 0.02, measured.shape).astype(np.float32)
    pred[10:15] = 0  # no prediction
    s = _Scores()
    s.add(pred, measured)
    both = (pred > 0) & (measured > 0)
    err = np.abs(pred[both].astype(np.float64) - measured[both])
    out = s.summary()
    assert out["pixels"] == both.sum()
    assert out["completeness"] == pytest.approx(both.sum() / (measured > 0).sum())
    assert out["mean_abs_m"] == pytest.approx(err.mean())
    assert abs(out["median_abs_m"] - np.median(err)) <= 1e-4  # 0.1 mm bins
    assert out["within_2cm"] == pytest.approx(np.mean(err <= 0.02))


def test_split_frames_holds_out_the_others():
    class Seq(list):
        def subset(self, s):
            return Seq(self[s])

    fused, held = split_frames(Seq(range(7)), 2)
    assert list(fused) == [0, 2, 4, 6] and held == [1, 3, 5]
    with pytest.raises(ValueError, match="every"):
        split_frames(Seq(range(7)), 1)


def test_split_frames_in_blocks_keeps_the_held_out_views_away_in_time():
    """block = 3: frames 0-2 and 6-8 fused, 3-5 and 9 held out; every other block by
    default, and block = 1 is the interleaved split."""
    class Seq(list):
        def subset(self, s):
            return Seq(self[s] if isinstance(s, slice) else [self[i] for i in s])

    fused, held = split_frames(Seq(range(10)), 2, block=3)
    assert list(fused) == [0, 1, 2, 6, 7, 8] and held == [3, 4, 5, 9]
    fused, held = split_frames(Seq(range(12)), 3, block=2)
    assert list(fused) == [0, 1, 6, 7] and held == [2, 3, 4, 5, 8, 9, 10, 11]
    assert split_frames(Seq(range(7)), 2, block=1)[1] == split_frames(Seq(range(7)), 2)[1]
    for bad in (0, -1, 2.5):
        with pytest.raises(ValueError, match="block"):
            split_frames(Seq(range(10)), 2, block=bad)
    with pytest.raises(ValueError, match="too few"):
        split_frames(Seq(range(10)), 2, block=10)


def test_dataset_and_synthetic_subsets_take_positions():
    """The frame sources the split views: a list of positions keeps the original indices."""
    import bftaichi as bf
    from bftaichi.running.pipeline import open_frames

    cfg = bf.load_config(None, list(TINY_SCENE_SETS) + ["synthetic.n_views=8"])
    frames = open_frames(cfg)
    fused, held = split_frames(frames, 2, block=2)
    assert held == [2, 3, 6, 7] and len(fused) == 4
    np.testing.assert_array_equal(fused[2].depth_m, frames[4].depth_m)


def test_evalviews_smoke_on_synthesised_frames(tmp_path, capsys):
    data = tmp_path / "data"
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    assert main(["synth", "-q", "--out", str(data), *sets, "--set", "synthetic.n_views=8"]) == 0
    out = tmp_path / "ev"
    assert main(["evalviews", str(data), "--voxel", "0.03", "--out", str(out),
                 "--set", "run.preview=false", "--set", "eval.n_samples=5000"]) == 0
    printed = capsys.readouterr().out
    assert "| bftaichi |" in printed and "| tsdf |" in printed
    r = json.loads((out / "evalviews.json").read_text())
    assert r["fused"] == 4 and r["held_out_evaluated"] == 4
    assert r["every"] == 2 and r["block"] == 1  # the split as asked, recorded
    for m in ("bftaichi", "tsdf"):
        s = r["methods"][m]
        # noisy synthetic frames of the true scene: errors of a few mm, most pixels covered
        assert s["median_abs_m"] < 0.02 and s["completeness"] > 0.8, (m, s)
    # the same pixels for every method: as many, each at most its own
    common = r["methods_common_pixels"]
    assert common["bftaichi"]["pixels"] == common["tsdf"]["pixels"] > 0
    assert all(common[m]["pixels"] <= r["methods"][m]["pixels"] for m in common)
    assert "pixels all predict" in printed
    c = r["calibration"]["coverage_normalised"]
    assert 0 < c[0] <= c[1] <= c[2] <= 1
    # the held-out normalisation uses the extra noise the run fitted to the fused frames
    fit = json.loads((out / "report.json").read_text())["solver"]["observations"]["noise_fit"]
    assert r["calibration"]["sigma_extra_m"] == fit["sigma_extra_m"] >= 0
    assert (out / "mesh.ply").exists() and (out / "tsdf_mesh.ply").exists()
    capsys.readouterr()
    assert main(["evalviews", str(data), "--out", str(tmp_path / "ev1"), "--every", "1"]) == 2
    assert "every = 1" in capsys.readouterr().err
