"""The public Python API (bftaichi.Reconstructor, Posterior, nbv.rank) and its runnable example."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bftaichi as bf
from conftest import TINY_SCENE_SETS

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny():
    from bftaichi.formats.synthetic import SyntheticDataset

    cfg = bf.load_config(None, TINY_SCENE_SETS)
    return cfg, SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)


def test_the_api_gives_what_the_pipeline_gives(tiny, tmp_path):
    cfg, frames = tiny
    recon = bf.Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    post = recon.solve()
    assert isinstance(post, bf.Posterior) and post.solver["converged"]
    report = bf.run(cfg, tmp_path / "run", progress=False)
    band = np.load(tmp_path / "run" / "band.npz")
    np.testing.assert_array_equal(post.ijk, band["ijk"])
    np.testing.assert_array_equal(post.mean, band["mean"])  # bitwise: the same computation
    np.testing.assert_array_equal(post.var, band["var"])
    assert report["counts"]["band_voxels"] == len(post.ijk)
    mesh = post.extract_mesh()
    assert len(mesh.faces) == report["counts"]["mesh_faces"]
    assert (mesh.vertex_attributes["sigma"] > 0).all()
    assert (mesh.vertex_attributes["sigma_pos"] > 0).all()
    # save / load round trip of the DESIGN.md files
    out = recon.save(tmp_path / "api")
    assert {p.name for p in out.iterdir()} == {"mesh.ply", "tsdf_mesh.ply", "band.npz"}
    again = bf.Posterior.load(out / "band.npz")
    np.testing.assert_array_equal(again.mean, post.mean)
    # ranking: best first, every candidate scored
    poses = bf.nbv.candidates_around(post, n=6)
    ranked = bf.nbv.rank(post, poses, recon.K, recon.image_size, cfg, frames=recon.frames)
    assert [r["rank"] for r in ranked] == list(range(6))
    assert ranked[0]["utility"] >= ranked[-1]["utility"] and ranked[0]["utility"] > 0


def test_solve_again_after_more_frames_warm_starts(tiny):
    cfg, frames = tiny
    recon = bf.Reconstructor(cfg)
    for f in list(frames)[:3]:
        recon.integrate(f.depth_m, f.K, f.T_W_C)
    first = recon.solve(variance=False)
    for f in list(frames)[3:]:
        recon.integrate(f.depth_m, f.K, f.T_W_C)
    second = recon.solve(variance=False)
    assert len(second.ijk) > len(first.ijk) and second.solver["converged"]


def test_api_errors_name_the_frame(tiny):
    cfg, frames = tiny
    recon = bf.Reconstructor(cfg)
    f = frames[0]
    with pytest.raises(bf.NoSurfaceError):
        recon.solve()
    bad = f.T_W_C.copy()
    bad[0, 0] = np.nan
    with pytest.raises(bf.BftaichiError, match="cam7.*NaN"):
        recon.integrate(f.depth_m, f.K, bad, name="cam7")
    with pytest.raises(bf.BftaichiError, match="frame-0.*\\(H, W\\)"):
        recon.integrate(f.depth_m[None], f.K, f.T_W_C)
    with pytest.raises(bf.BftaichiError, match="focal"):
        recon.integrate(f.depth_m, np.diag([0.0, 1.0, 1.0]), f.T_W_C)


def test_public_api_listing():
    assert {"Reconstructor", "Posterior", "nbv", "Config", "open_dataset", "run",
            "init"} <= set(bf.__all__)
    assert all(hasattr(bf, name) for name in bf.__all__)


def test_the_readme_example_runs(tmp_path):
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "reconstruct.py"), *sets,
                           "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "next-best view: candidate" in proc.stdout
    assert {p.name for p in (tmp_path / "out").iterdir()} == {"mesh.ply", "tsdf_mesh.ply",
                                                               "band.npz"}


def test_the_slam_example_runs_and_its_update_equals_re_fusing():
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "slam_integration.py"),
                           *sets, "--drifted", "2"], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "update_poses moved 2 frames" in proc.stdout
    assert "equals re-fusing all 6 frames bitwise: True" in proc.stdout
    assert "posterior after the update equals the re-fused one's bitwise: True" in proc.stdout


def test_robust_curvature_prior_tends_to_the_gaussian_one_and_changes_the_mean(tiny):
    """``prior.curvature_scale``: with a huge scale every weight is ~1 and the reweighted MAP is
    the Gaussian prior's (to the solver's tolerance); at 0.25 voxel it lets go where the field
    bends, and the mean moves (without the free-space constraint, which is an active set)."""
    import dataclasses

    cfg, frames = tiny

    def mean_with(scale):
        # free = 0: the free-space active set gets more passes with each reweighting
        prior = dataclasses.replace(cfg.prior, curvature=0.5, curvature_scale=scale, free=0.0)
        recon = bf.Reconstructor(dataclasses.replace(cfg, prior=prior))
        for f in frames:
            recon.integrate(f.depth_m, f.K, f.T_W_C)
        post = recon.solve(variance=False)
        assert post.solver["converged"]
        return post.mean, post.solver["iterations"]

    gauss, it_gauss = mean_with(0.0)
    near, it_near = mean_with(100.0)
    robust, _ = mean_with(0.25)
    vs = cfg.tsdf.voxel_size_m
    assert it_near > it_gauss  # the reweighted solves ran
    # where the mesh is (4 voxels of 15,524 far from it differed by up to 0.016 voxel, 4 % of
    # their sigma, after the reweighting's float32 round-off)
    surface = np.abs(gauss) < 2 * vs
    assert np.abs(near - gauss)[surface].max() < 0.01 * vs
    assert np.abs(robust - gauss).max() > 0.05 * vs
