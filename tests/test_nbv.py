"""Next-best-view planning (bftaichi/nbv.py) and closed-loop scanning (bftaichi/scan.py).

The fast utility is checked against the exact ``diag((Q + A_v^T W_v A_v)^-1)`` of a small
posterior; occlusion and unseen surface are checked on scenes built so the right answer is
known; the CLI commands smoke-run on tiny scenes.
"""

import json

import numpy as np
import pytest
from scipy.stats import spearmanr

from bftaichi import nbv
from bftaichi.cli import main
from bftaichi.config import load_config
from bftaichi.errors import BftaichiError, ConfigError
from bftaichi.posterior import Posterior
from bftaichi.stages.band import Band
from conftest import TINY_SCENE_SETS, posterior_system, solved, to_csr

SPHERE_SETS = (  # a sphere of radius 0.15 m seen from 3 ring views on one side, 3 cm voxels
    "synthetic.mesh=sphere", "synthetic.radius_m=0.15", "synthetic.trajectory=ring",
    "synthetic.n_views=8", "scene.frames=0:3", "synthetic.cam_radius_m=0.8",
    "synthetic.cam_height_m=0.2", "synthetic.width=80", "synthetic.height=60",
    "synthetic.fx=80", "synthetic.fy=80", "synthetic.cx=39.5", "synthetic.cy=29.5",
    "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06", "observation.stride=1",
    # the planner's utility is judged against the exact Gaussian reduction of the same Q: the
    # variance corrections measured after the solve (local_noise) are not part of Q
    "observation.local_noise=false",
    # every pixel on its own: on this tiny scene (80x60, a voxel spans 3.7 pixels) the
    # posterior from 2x2 super-pixels (aggregate=1) is more correlated, and the diagonal-only
    # local update ranks the candidates worse against the exact reduction (Spearman 0.81,
    # 0.95 without super-pixels); measured in issue 16, for the planner issue to take up
    "observation.aggregate=0",
    # the linear (Gaussian) curvature prior: conftest.posterior_system rebuilds Q with it; the
    # robust prior, the default, reweights Q at the mean and takes its Hessian for the variance
    "prior.curvature=0.1", "prior.curvature_scale=0",
)


def solve(cfg):
    from bftaichi.running.pipeline import open_frames

    frames = open_frames(cfg)
    recon, post = solved(cfg, frames)
    return frames, recon, post


@pytest.fixture(scope="module")
def half_sphere():
    cfg = load_config(None, SPHERE_SETS)
    frames, recon, post = solve(cfg)
    return cfg, frames, recon, post


# -- candidates --------------------------------------------------------------------------------

def test_candidates_look_at_the_target_from_the_radius():
    target = np.array([0.1, -0.2, 0.3])
    for poses in (nbv.sphere_candidates(target, 0.7, 48, -20.0, 60.0),
                  nbv.ring_candidates(target, 0.7, 12, height_m=0.2)):
        eyes = poses[:, :3, 3]
        z_axis = poses[:, :3, 2]
        to_target = (target - eyes) / np.linalg.norm(target - eyes, axis=1, keepdims=True)
        np.testing.assert_allclose(np.einsum("ij,ij->i", z_axis, to_target), 1.0, atol=1e-9)
        assert len(np.unique(np.round(eyes, 6), axis=0)) == len(poses)
    sphere = nbv.sphere_candidates(target, 0.7, 48, -20.0, 60.0)
    np.testing.assert_allclose(np.linalg.norm(sphere[:, :3, 3] - target, axis=1), 0.7)
    elevation = np.degrees(np.arcsin((sphere[:, 2, 3] - target[2]) / 0.7))
    assert elevation.min() >= -20.0 and elevation.max() <= 60.0
    assert elevation.min() < 0 < elevation.max()  # spread over the whole band


def test_rings_of_candidates_at_two_heights():
    """nbv.candidates = rings: the candidates split over the heights (7 = 4 + 3), each ring at
    its height and the radius, looking at the target, alternate rings turned by half a step;
    no heights is an error that names the key."""
    target = np.array([0.1, -0.2, 0.3])
    cfg = load_config(None, ["nbv.candidates=rings", "nbv.heights_m=[0.05, 0.35]",
                             "nbv.n_candidates=7"])
    poses = nbv.make_candidates(cfg, target, 0.8)
    eyes = poses[:, :3, 3]
    np.testing.assert_allclose(eyes[:, 2] - target[2], [0.05] * 4 + [0.35] * 3)
    np.testing.assert_allclose(np.linalg.norm(eyes[:, :2] - target[:2], axis=1), 0.8)
    to_target = (target - eyes) / np.linalg.norm(target - eyes, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ij,ij->i", poses[:, :3, 2], to_target), 1.0,
                               atol=1e-9)
    azimuth = np.degrees(np.arctan2(eyes[:, 1] - target[1], eyes[:, 0] - target[0])) % 360
    np.testing.assert_allclose(azimuth, [0, 90, 180, 270, 60, 180, 300], atol=1e-9)
    with pytest.raises(ConfigError, match="heights_m"):
        load_config(None, ["nbv.candidates=rings"])


def test_poses_file_round_trip_and_errors(tmp_path):
    poses = nbv.sphere_candidates([0, 0, 0], 1.0, 5)
    f = tmp_path / "poses.txt"
    f.write_text("# candidates\n" + "\n".join(" ".join(f"{v:.17g}" for v in T.ravel())
                                            for T in poses))
    np.testing.assert_allclose(nbv.load_poses(f), poses)
    folder = tmp_path / "poses"
    folder.mkdir()
    for k, T in enumerate(poses):
        np.savetxt(folder / f"{k:03d}.txt", T)
    np.testing.assert_allclose(nbv.load_poses(folder), poses)
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(BftaichiError, match=r"bad.txt:1: expected 16 numbers"):
        nbv.load_poses(bad)
    nan = poses[0].ravel().copy()
    nan[3] = np.nan
    bad.write_text(" ".join(f"{v:.17g}" for v in nan))
    with pytest.raises(BftaichiError, match="NaN"):
        nbv.load_poses(bad)
    with pytest.raises(BftaichiError, match="does not exist"):
        nbv.load_poses(tmp_path / "missing.txt")


# -- the utility -------------------------------------------------------------------------------

def test_fast_utility_ranks_like_the_exact_variance_reduction(half_sphere):
    """Local update s' = s / (1 + s d) against diag((Q + dQ)^-1) computed exactly, over
    candidates all around the half-seen sphere (known surface only: coverage=None)."""
    cfg, frames, recon, post = half_sphere
    _, system = posterior_system(recon)
    S, nbr, far = system.S, system.nbr, system.far
    n = len(S)
    assert 300 < n < 4000
    Q = to_csr(S, nbr, far).toarray()
    exact_s = np.diag(np.linalg.inv(Q))
    post.var = exact_s.astype(np.float32)  # isolate the approximation from the probe estimate
    planner = nbv.Planner(post, cfg, frames.K, frames.image_size)
    poses = nbv.sphere_candidates([0, 0, 0], 0.8, 16, -40.0, 60.0)
    fast, exact = [], []
    for T in poses:
        fast.append(planner.utility(T)["known"])
        depth = planner.predict_depth(T)
        planner.observer.reset()
        planner.observer.integrate(depth, planner.K, T, stride=planner.stride)
        S_d, _, _ = planner.observer.finalize()
        # the planner's diagonal-only pass gives bitwise the full data term's diagonal
        np.testing.assert_array_equal(
            planner.observer.information(depth, planner.K, T, stride=planner.stride),
            planner.observer.diagonal())
        s_new = np.diag(np.linalg.inv(Q + to_csr(S_d, nbr).toarray()))
        exact.append(float(np.sum((exact_s - s_new)[planner.omega])))
    fast, exact = np.array(fast), np.array(exact)
    assert exact.max() > 10 * max(exact.min(), 1e-30)  # the candidates do differ
    assert spearmanr(fast, exact).statistic >= 0.85
    # the local update ignores correlations (the exact gain of a voxel is shared with its
    # correlated neighbours, and a view's information couples neighbouring voxels): its
    # factor against the exact reduction differs from candidate to candidate (0.52 to 2.05
    # here since issue 15's noise model, which weights oblique pixels up), but stays within
    # a band and keeps the ranking
    seen = exact > 0
    ratio = fast[seen] / exact[seen]
    assert np.all((ratio >= 0.4) & (ratio <= 2.5)), ratio
    assert np.all(fast[~seen] == 0)


def box_sdf(p, lo, hi):
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def analytic_posterior(voxel, parts):
    """A Posterior whose mean is the exact SDF of a union of boxes, ``parts`` = [(lo, hi,
    variance)], every voxel observed; a voxel's variance is that of the nearest box."""
    lo = np.min([p[0] for p in parts], axis=0) - 4 * voxel
    hi = np.max([p[1] for p in parts], axis=0) + 4 * voxel
    g = [np.arange(np.floor(a / voxel), np.ceil(b / voxel)) for a, b in zip(lo, hi)]
    ijk = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3).astype(np.int32)
    x = (ijk + 0.5) * voxel
    d = np.stack([box_sdf(x, np.asarray(a), np.asarray(b)) for a, b, _ in parts])
    sdf, nearest = d.min(axis=0), d.argmin(axis=0)
    keep = np.abs(sdf) < 3 * voxel
    var = np.array([p[2] for p in parts])[nearest]
    n = int(keep.sum())
    band = Band.from_voxels(ijk[keep], sdf[keep], np.ones(n, np.float32))
    return Posterior(band=band, voxel_size=voxel, mean=sdf[keep].astype(np.float32),
                     var=var[keep].astype(np.float32))


def test_an_occluded_view_scores_lower():
    """An uncertain patch (variance 1e-4 m^2) under a well-known blocker (1e-7): the view from
    straight above sees only the blocker; a view from the side, as far from the patch, sees the
    patch. If rays did not stop at the first surface, the first would score the patch too."""
    voxel = 0.02
    patch = (np.array([-0.2, -0.2, -0.04]), np.array([0.2, 0.2, 0.0]), 1e-4)
    blocker = (np.array([-0.16, -0.16, 0.46]), np.array([0.16, 0.16, 0.5]), 1e-7)
    post = analytic_posterior(voxel, [patch, blocker])
    cfg = load_config(None, ["tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04",
                             "observation.stride=1"])
    K = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])
    planner = nbv.Planner(post, cfg, K, (80, 60))
    from bftaichi.geometry import look_at

    above = look_at([0, 0, 1.0], [0, 0, 0], up=(0, 1, 0))
    side = look_at([0.8, 0, 0.6], [0, 0, 0])
    u_above, u_side = planner.utility(above), planner.utility(side)
    assert u_above["hit_fraction"] > 0.05 and u_side["hit_fraction"] > 0.05  # both see surface
    assert u_side["utility"] > 10 * u_above["utility"]
    # the blocker really hides the patch: the depth from above stops at z = 0.5
    depth = planner.predict_depth(above)
    assert np.median(depth[depth > 0]) == pytest.approx(0.5, abs=voxel)


def test_a_seen_voxel_never_scores_above_an_unseen_one():
    """The planner scores an unseen voxel at s0, the variance of an SDF known only to lie
    within the bootstrap truncation. A seen voxel whose variance is larger (the prior's bias,
    an offset in the variance, reached centimetres on a few voxels of a sparse scan and
    decided the ranking) is scored at s0: no view gains more from it than from unseen space."""
    voxel = 0.02
    patch = (np.array([-0.2, -0.2, -0.04]), np.array([0.2, 0.2, 0.0]), 1.0)  # sigma 1 m
    post = analytic_posterior(voxel, [patch])
    cfg = load_config(None, ["tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04",
                             "observation.stride=1"])
    K = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])
    planner = nbv.Planner(post, cfg, K, (80, 60))
    from bftaichi.geometry import look_at

    u = planner.utility(look_at([0, 0, 1.0], [0, 0, 0], up=(0, 1, 0)))
    assert u["known"] > 0
    assert planner.s_omega.max() <= planner.s0
    assert u["known"] <= planner.omega.sum() * planner.s0


def test_a_view_of_unseen_surface_beats_re_observing_a_seen_side(half_sphere):
    cfg, frames, _, post = half_sphere
    lo, hi = nbv.region_of_interest(post.ijk, post.voxel_size, 1.5, [0, 0, 0])
    coverage = nbv.coverage_grid(cfg, lo, hi, post.voxel_size)
    for f in frames:
        coverage.mark(f.depth_m, f.K, f.T_W_C, stride=1)
    planner = nbv.Planner(post, cfg, frames.K, frames.image_size, coverage)
    seen_eyes = frames.poses[:, :3, 3]
    from bftaichi.geometry import look_at

    mean_dir = seen_eyes.mean(axis=0)
    same = look_at(mean_dir / np.linalg.norm(mean_dir) * 0.8, [0, 0, 0])
    opposite = look_at(-mean_dir / np.linalg.norm(mean_dir) * 0.8, [0, 0, 0])
    u_same, u_opp = planner.utility(same), planner.utility(opposite)
    assert u_same["known"] > 0 and u_same["hit_fraction"] > u_opp["hit_fraction"]
    assert u_opp["frontier_cells"] > 5 * max(u_same["frontier_cells"], 1)
    assert u_opp["utility"] > u_same["utility"]
    assert planner.rho > 0 and planner.s0 > np.median(post.var[planner.omega])  # unseen: vaguer


def test_rank_screens_at_twice_the_stride_and_scores_the_best_again(half_sphere):
    """nbv.rerank = k: every candidate scored at twice the stride, the k best of that screen
    scored again at the full stride and ranked first by it; rerank = 0 (or k >= n) is the
    full-stride ranking itself."""
    from dataclasses import replace

    cfg, frames, _, post = half_sphere
    lo, hi = nbv.region_of_interest(post.ijk, post.voxel_size, 1.5, [0, 0, 0])
    coverage = nbv.coverage_grid(cfg, lo, hi, post.voxel_size)
    for f in frames:
        coverage.mark(f.depth_m, f.K, f.T_W_C, stride=1)
    poses = nbv.sphere_candidates([0, 0, 0], 0.8, 12, -40.0, 60.0)

    def ranking(k):
        c = replace(cfg, nbv=replace(cfg.nbv, rerank=k))
        return nbv.Planner(post, c, frames.K, frames.image_size, coverage).rank(poses)

    full = ranking(0)
    assert [r["stride"] for r in full] == [1] * len(poses)
    assert [r["index"] for r in ranking(len(poses))] == [r["index"] for r in full]
    planner = nbv.Planner(post, cfg, frames.K, frames.image_size, coverage)
    screen = {i: planner.utility(T, 2)["utility"] for i, T in enumerate(poses)}
    best4 = sorted(screen, key=lambda i: (-screen[i], i))[:4]
    ranked = ranking(4)
    assert sorted(r["index"] for r in ranked) == list(range(len(poses)))
    head, tail = ranked[:4], ranked[4:]
    assert sorted(r["index"] for r in head) == sorted(best4)
    exact = {r["index"]: r["utility"] for r in full}
    assert all(r["stride"] == 1 and r["utility"] == exact[r["index"]] for r in head)
    assert [r["utility"] for r in head] == sorted((r["utility"] for r in head), reverse=True)
    assert all(r["stride"] == 2 and r["utility"] == screen[r["index"]] for r in tail)
    assert [r["rank"] for r in ranked] == list(range(len(poses)))


# -- commands ----------------------------------------------------------------------------------

def test_run_with_nbv_and_the_nbv_command(tmp_path, capsys):
    out = tmp_path / "run"
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    assert main(["run", "-q", "--out", str(out), *sets, "--set", "nbv.enabled=true",
                 "--set", "nbv.n_candidates=8"]) == 0
    ranked = json.loads((out / "nbv.json").read_text())["candidates"]
    report = json.loads((out / "report.json").read_text())
    assert [c["rank"] for c in ranked] == list(range(8))
    u = [c["utility"] for c in ranked]
    assert u == sorted(u, reverse=True) and u[0] > 0
    assert report["nbv"]["best"]["index"] == ranked[0]["index"]
    assert np.asarray(ranked[0]["pose"]).shape == (4, 4)
    # the command on the same outputs, with other candidates
    capsys.readouterr()
    assert main(["nbv", str(out), "--n", "6", "--candidates", "ring", "--top", "2"]) == 0
    printed = capsys.readouterr().out
    assert "rank" in printed and "nbv.json" in printed
    again = json.loads((out / "nbv.json").read_text())
    assert len(again["candidates"]) == 6
    assert json.loads((out / "report.json").read_text())["nbv"]["n_candidates"] == 6


def test_nbv_command_errors(tmp_path, capsys):
    assert main(["nbv", str(tmp_path / "nothing")]) == 2
    assert "config.toml" in capsys.readouterr().err
    assert main(["run", "-q", "--out", str(tmp_path / "t"), "--set", "run.stages=tsdf_only",
                 "--set", "nbv.enabled=true"]) == 2
    assert "run.stages" in capsys.readouterr().err


def test_scan_smoke_runs_every_policy(tmp_path, capsys):
    out = tmp_path / "scan"
    sets = [a for s in SPHERE_SETS if not s.startswith("scene.frames") for a in ("--set", s)]
    assert main(["scan", "-q", "--out", str(out), "--steps", "2", "--candidates", "8",
                 *sets, "--set", "nbv.random_seeds=2", "--set", "eval.n_samples=3000",
                 "--set", "nbv.initial_seeds=2"]) == 0
    report = json.loads((out / "scan.json").read_text())
    assert (out / "scan.png").stat().st_size > 1000
    assert set(report["policies"]) == {"bayes", "coverage", "frontier", "entropy", "farthest",
                                       "random"}
    draws = report["initial_draws"]
    assert len(draws) == 2 and draws[0] == report["initial_views"] and draws[0] != draws[1]
    for policy, res in report["policies"].items():
        views = [s["views"] for s in res["steps"]]
        assert views == [2, 3, 4], policy
        for run in res["runs"]:
            assert run["views"][:2] == draws[run["initial_draw"]]
            assert len(set(run["views"])) == 4  # never the same view twice
            for step in run["steps"]:  # surface coverage: recall at 2 mm <= 5 mm <= 10 mm
                assert 0 <= step["recall@2mm"] <= step["recall@5mm"] <= step["recall@10mm"] <= 1
                assert ("calibration" in step) == (policy == "bayes")
        s = res["summary"]
        assert 0 <= s["auc_f10"] <= 1 and 0 <= s["auc_recall5"] <= 1
        runs = len(res["runs"])
        assert s["n_runs"] == runs == (4 if policy == "random" else 2)
        r5 = [np.mean([(a + b) / 2 for a, b in zip(c[:-1], c[1:])]) for c in
              ([st["recall@5mm"] for st in run["steps"]] for run in res["runs"])]
        assert s["auc_recall5"] == pytest.approx(np.mean(r5))  # unit views: mean of trapezoids
        assert s["std"]["auc_recall5"] == pytest.approx(np.std(r5))
        assert 0 <= s["reached"]["views_to_recall5_0.95"] <= 1
    cal = report["policies"]["bayes"]["runs"][0]["steps"][-1]["calibration"]
    assert 0 <= cal["coverage@1sigma"] <= cal["coverage@2sigma"] <= cal["coverage@3sigma"] <= 1
    # more views never make the bayes scan's completeness much worse
    comp = [s["completeness_mm"] for s in report["policies"]["bayes"]["steps"]]
    assert comp[-1] <= comp[0] * 1.05
    assert main(["scan", "-q", "--out", str(out), *sets]) == 2  # refuses to overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["scan", "-q", "--out", str(tmp_path / "x"), "--policies", "greedy"]) == 2
