"""The probabilistic stage end to end: outputs, known answers, determinism, calibration sanity."""

import json

import numpy as np
import pytest
import trimesh

import bftaichi as bf
from bftaichi.io import read_mesh_ply
from conftest import TINY_SCENE_SETS


def _sphere_cfg(voxel: float, extra=()):
    """Noiseless sphere r = 0.3 m seen from a Fibonacci sphere of 16 views, 96x72 pixels."""
    return bf.load_config(None, [
        "synthetic.mesh=sphere", "synthetic.radius_m=0.3", "synthetic.trajectory=sphere",
        "synthetic.n_views=16", "synthetic.cam_radius_m=1.0", "synthetic.noise=none",
        "synthetic.quantization_m=0.0", "synthetic.width=96", "synthetic.height=72",
        "synthetic.fx=78.75", "synthetic.fy=78.75", "synthetic.cx=47.5", "synthetic.cy=35.5",
        f"tsdf.voxel_size_m={voxel}", f"tsdf.trunc_m={2 * voxel}", "eval.n_samples=20000",
        "observation.stride=1", *extra])


def _plane_file(tmp_path):
    """A 1.6 x 1.6 m square tilted 20 degrees about x, as a mesh file."""
    plane = trimesh.creation.box(extents=[1.6, 1.6, 1e-6])
    plane = trimesh.Trimesh(plane.vertices, plane.faces[plane.face_normals[:, 2] > 0.5])
    plane = plane.subdivide().subdivide()
    plane.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), [1, 0, 0]))
    path = tmp_path / "plane.ply"
    plane.export(path)
    return path, plane


def _rms_sphere(vertices):
    return float(np.sqrt(np.mean((np.linalg.norm(vertices, axis=1) - 0.3) ** 2)))


@pytest.mark.parametrize("voxel", [0.02, 0.03])
def test_noiseless_sphere_posterior_at_least_as_accurate_as_tsdf(tmp_path, voxel):
    report = bf.run(_sphere_cfg(voxel), tmp_path / "out", progress=False)
    assert report["solver"]["map"]["converged"]
    v_tsdf, _, _ = read_mesh_ply(tmp_path / "out" / "tsdf_mesh.ply")
    v_post, f_post, extra = read_mesh_ply(tmp_path / "out" / "mesh.ply")
    assert len(f_post) > 1000
    assert _rms_sphere(v_post) <= _rms_sphere(v_tsdf) * 1.02
    assert report["metrics"]["mesh.ply"]["chamfer_l2"] <= report["metrics"]["tsdf_mesh.ply"][
        "chamfer_l2"] * 1.05
    assert np.all(np.isfinite(extra["sigma"])) and np.all(extra["sigma"] > 0)


def test_noiseless_plane_posterior_at_least_as_accurate_as_tsdf(tmp_path):
    path, plane = _plane_file(tmp_path)
    cfg = bf.load_config(None, [
        f"synthetic.mesh={path}", "synthetic.trajectory=hemisphere", "synthetic.n_views=8",
        "synthetic.min_elevation_deg=50", "synthetic.cam_radius_m=1.2", "synthetic.noise=none",
        "synthetic.quantization_m=0.0", "synthetic.width=96", "synthetic.height=72",
        "synthetic.fx=78.75", "synthetic.fy=78.75", "synthetic.cx=47.5", "synthetic.cy=35.5",
        "tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04", "eval.n_samples=20000",
        "observation.stride=1"])
    bf.run(cfg, tmp_path / "out", progress=False)
    n = plane.face_normals[0]
    p0 = plane.vertices[0]

    def rms(vertices):
        return float(np.sqrt(np.mean(((vertices - p0) @ n) ** 2)))

    v_tsdf, _, _ = read_mesh_ply(tmp_path / "out" / "tsdf_mesh.ply")
    v_post, _, _ = read_mesh_ply(tmp_path / "out" / "mesh.ply")
    assert rms(v_post) <= rms(v_tsdf) * 1.02 + 1e-4


def test_full_run_writes_the_documented_outputs(tmp_path):
    cfg = bf.load_config(None, list(TINY_SCENE_SETS))
    report = bf.run(cfg, tmp_path, progress=False)
    band = np.load(tmp_path / "band.npz")
    n = len(band["ijk"])
    assert n == report["counts"]["band_voxels"] > 0
    for key in ("mean", "var", "tsdf", "weight"):  # and cov (N, 3), below
        assert band[key].shape == (n,) and band[key].dtype == np.float32, key
    assert np.all(band["var"] > 0)
    v, f, extra = read_mesh_ply(tmp_path / "mesh.ply")
    assert list(extra) == ["sigma", "sigma_pos"] and len(extra["sigma"]) == len(v) and len(f) > 0
    assert band["cov"].shape == (n, 3) and band["cov"].dtype == np.float32
    saved = json.loads((tmp_path / "report.json").read_text())
    assert set(saved["metrics"]) == {"tsdf_mesh.ply", "mesh.ply"}
    assert saved["solver"]["map"]["converged"] is True
    assert saved["solver"]["variance"]["n_probes"] == cfg.solver.probes
    u = saved["uncertainty"]  # the vertex sigma judged against the exact vertex errors
    assert u["n"] > 50 and 0 <= u["coverage@1sigma"] <= u["coverage@2sigma"] <= 1
    assert u["median_sigma_m"] == pytest.approx(float(np.median(extra["sigma"])), rel=1e-5)


def test_eval_vertex_sigma_chooses_the_judged_property(tmp_path):
    cfg = bf.load_config(None, [*TINY_SCENE_SETS, "eval.vertex_sigma=sigma_pos"])
    u = bf.run(cfg, tmp_path, progress=False)["uncertainty"]
    _, _, extra = read_mesh_ply(tmp_path / "mesh.ply")
    assert u["median_sigma_m"] == pytest.approx(float(np.median(extra["sigma_pos"])), rel=1e-5)
    assert u["median_sigma_m"] != pytest.approx(float(np.median(extra["sigma"])), rel=1e-3)
    with pytest.raises(bf.ConfigError, match="eval.vertex_sigma"):
        bf.load_config(None, ["eval.vertex_sigma=position"])


def test_tsdf_only_stage_skips_the_posterior(tmp_path):
    cfg = bf.load_config(None, [*TINY_SCENE_SETS, "run.stages=tsdf_only"])
    report = bf.run(cfg, tmp_path, progress=False)
    assert not (tmp_path / "mesh.ply").exists()
    assert "posterior" not in report["stages_run"] and report["solver"] is None
    assert set(np.load(tmp_path / "band.npz").files) == {"ijk", "voxel_size", "tsdf", "weight",
                                                         "origin"}


def test_same_seed_gives_identical_band_arrays(tmp_path):
    cfg = bf.load_config(None, list(TINY_SCENE_SETS))
    bf.run(cfg, tmp_path / "a", progress=False)
    bf.run(cfg, tmp_path / "b", progress=False)
    a, b = np.load(tmp_path / "a" / "band.npz"), np.load(tmp_path / "b" / "band.npz")
    for key in a.files:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert (tmp_path / "a" / "mesh.ply").read_bytes() == (tmp_path / "b" / "mesh.ply").read_bytes()


def test_noise_fit_finds_the_noise_the_depth_model_misses(tmp_path):
    """ObservationConfig.fit_noise: Gaussian depth noise of 1 cm and 4 mm (the Kinect model says
    ~1.9 mm at 1 m, so the extra noise is ~9.8 and ~3.5 mm) is found; noise the model does
    describe leaves well under a millimetre. The 2 cm bootstrap's own error (which is the same
    in every frame that sees a point) is not taken for frame noise: fitted to the residuals
    themselves, it read as ~2.9 mm on the Kinect case. Nor does the voxel size change the
    fit: pairs are kept only where their frames agree within 3 sigma of the pair's model
    (fitted noise included) or 2 voxels, and the fit models that cut (measured here: 9.6 mm
    at 1 cm and at 2 cm; with a cut of 2 voxels alone, 8.9 mm at 1 cm, where it fell at 1.4
    sigma of the 1 cm noise's pairs; without modelling the cut 7.7 mm). The noise is
    independent per pixel, so little of it is taken for the part a frame's neighbouring
    pixels share: 2.4 mm of the 9.6 and none of the 4.1 mm (5.5 and 1.2 mm while two pixels
    paired with one pixel of the other frame counted, its noise then read as shared)."""
    fits = {}
    for name, voxel, extra in (
            ("kinect", 0.02, ["synthetic.noise=kinect"]),
            ("gauss", 0.02, ["synthetic.noise=gaussian", "synthetic.sigma_m=0.01"]),
            ("gauss_1cm", 0.01, ["synthetic.noise=gaussian", "synthetic.sigma_m=0.01"]),
            ("gauss4", 0.02, ["synthetic.noise=gaussian", "synthetic.sigma_m=0.004"])):
        cfg = _sphere_cfg(voxel, extra + ["run.plots=false", "eval.n_samples=2000",
                                          "observation.fit_noise=true"])
        report = bf.run(cfg, tmp_path / name, progress=False)
        fits[name] = report["solver"]["observations"]["noise_fit"]
    # pairs of head-on pixels (within 37 deg) of 16 frames seeing one point
    assert fits["gauss"]["pixels"] > 200 and fits["gauss"]["frames"] == 16
    assert 0.008 < fits["gauss"]["sigma_extra_m"] < 0.012
    assert 0.008 < fits["gauss_1cm"]["sigma_extra_m"] < 0.012
    assert fits["gauss_1cm"]["sigma_extra_m"] == pytest.approx(fits["gauss"]["sigma_extra_m"],
                                                               rel=0.03)
    assert 0.0025 < fits["gauss4"]["sigma_extra_m"] < 0.0045
    assert fits["kinect"]["sigma_extra_m"] < 0.0012
    assert fits["gauss"]["sigma_corr_m"] < 0.35 * fits["gauss"]["sigma_extra_m"]
    assert fits["gauss4"]["sigma_corr_m"] < 0.15 * fits["gauss4"]["sigma_extra_m"]
    off = bf.run(_sphere_cfg(0.02, ["synthetic.noise=gaussian", "synthetic.sigma_m=0.01",
                                    "run.plots=false", "eval.n_samples=2000",
                                    "observation.fit_noise=false"]),
                 tmp_path / "off", progress=False)
    assert off["solver"]["observations"]["noise_fit"]["sigma_extra_m"] == 0.0


def _free_voxels_pulled_inside(strength: float):
    """The sphere's posterior with a pull of ``strength`` per voxel^2 to ``-tau`` on 12 of the
    voxels its TSDF saw as free (straddling samples), and the free-space constraint's solve of
    it (``prior.free`` = 1000), as a namespace: ``band``, ``post``, ``free``, ``hit``, the bent
    MAP ``bent`` the solve started from, ``S0, h0`` (the bent system) and ``S, h`` (as the
    solve left them), ``fixed``, ``info``, ``vs``, ``tau``."""
    from types import SimpleNamespace

    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.prior import System
    from bftaichi.stages.solve import solve_map
    from conftest import posterior_system, pulled_inside, solved

    # the linear (Gaussian) curvature prior, which conftest.posterior_system rebuilds
    cfg = _sphere_cfg(0.03, ["prior.free=0", "observation.fit_noise=false",
                             "observation.aggregate=0", "prior.curvature=0.1",
                             "prior.curvature_scale=0"])
    recon, post = solved(cfg, open_frames(cfg), variance=False)
    band, system = posterior_system(recon)
    S, nbr, far = system.S.copy(), system.nbr, system.far
    vs, tau = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m
    free = np.flatnonzero(band.observed & (band.tsdf > tau))
    hit = free[:: len(free) // 12][:12]
    h, bent = pulled_inside(S, nbr, far, post.mean, hit, tau, vs, strength=strength)
    cfg.solver.tol = 1e-8
    S0, h0 = S.copy(), h.copy()
    fixed, info = solve_map(System(S=S, nbr=nbr, h=h, far=far), bent, cfg.solver, band,
                            trunc_m=tau, voxel_size_m=vs, free=1000.0,
                            bootstrap_trunc_m=cfg.tsdf.bootstrap_trunc_m)
    return SimpleNamespace(band=band, post=post, free=free, hit=hit, bent=bent, S0=S0, h0=h0,
                           S=S, h=h, fixed=fixed, info=info, vs=vs, tau=tau)


def test_free_space_constraint_lifts_voxels_the_bootstrap_saw_as_free():
    """PriorConfig.free: data that drags voxels the TSDF saw as free below zero (as samples
    straddling an occlusion edge do) is overruled there, and only there."""
    run = _free_voxels_pulled_inside(1000.0)
    band, post, free, hit, bent, fixed, info, vs = (run.band, run.post, run.free, run.hit,
                                                    run.bent, run.fixed, run.info, run.vs)
    # every pixel on its own (observation.aggregate=0); even so 4 of the 7071 free voxels,
    # out at the band's edge and seen by one frame, end below half a voxel without the
    # constraint (the constraint anchors them too, so the comparison far from the bent
    # voxels leaves them out)
    low = free[post.mean[free] <= 0.5 * vs]
    assert len(free) > 50 and len(low) <= 0.001 * len(free)  # consistent so far
    assert (band.weight[low] <= 1).all()
    assert (bent[hit] < 0).sum() >= 6  # false surfaces in free space
    stats = info["free_space"]
    assert info["converged"] and stats["passes"] >= 1 and stats["settled"]
    assert stats["anchored"] >= (bent[hit] < 0.5 * vs).sum()
    assert (fixed[hit] > 0).all()
    assert (fixed[free] >= 0.5 * vs - 1e-4).sum() >= 0.98 * len(free)
    # far from them (more than 4 voxels) the field is the unbent one
    moved = np.concatenate([hit, low])  # the bent voxels, and the few the constraint anchors
    d = np.abs(band.ijk[:, None, :] - band.ijk[moved][None]).max(-1).min(1)
    away = d > 4
    np.testing.assert_allclose(fixed[away], post.mean[away], atol=0.05 * vs)


def test_free_space_anchors_outweighed_by_the_data_still_settle_in_a_few_passes():
    """A pull 100x the anchors' strength (``prior.free``) on free voxels: raising an anchor's
    target alone moves its voxel by ~1 % of the raise a pass, and 64 passes left surfaces in
    free space; the anchors that need a second raise stiffen, and the set settles."""
    from bftaichi.stages.solve import STIFFEN

    run = _free_voxels_pulled_inside(100 * 1000.0)
    assert (run.bent[run.hit] < -0.5 * run.tau).sum() >= 6  # deep false surfaces in free space
    stats = run.info["free_space"]
    assert run.info["converged"] and stats["settled"] and stats["passes"] <= 32, stats
    assert (run.fixed[run.hit] > 0).all()
    # the anchors are taken out again: the system is the data's and the prior's
    np.testing.assert_allclose(run.S, run.S0, rtol=1e-6 * STIFFEN, atol=0)
    np.testing.assert_allclose(run.h, run.h0, rtol=0, atol=1e-4 * np.abs(run.h0).max())


def test_free_space_passes_solved_locally_settle_where_whole_solves_settle(monkeypatch):
    """solve_map's passes after the robust prior's reweighting solve only around their new
    anchors (LOCAL_RINGS rings), then the settled mean is solved whole and checked again:
    the same anchors and, to the solver's tolerance, the same mean as passes that each solve
    the whole band (LOCAL_SHARE = 0), with part of the work on small regions."""
    import bftaichi.stages.solve as solve_mod
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.prior import System
    from conftest import posterior_system, pulled_inside, solved

    cfg = _sphere_cfg(0.03, ["prior.free=0", "observation.fit_noise=false",
                             "observation.aggregate=0", "prior.curvature=0.1",
                             "prior.curvature_scale=0"])
    recon, post = solved(cfg, open_frames(cfg), variance=False)
    band, system = posterior_system(recon)
    vs, tau = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m
    S0 = system.S.copy()
    free = np.flatnonzero(band.observed & (band.tsdf > tau))
    hit = free[:: len(free) // 12][:12]
    h0, bent = pulled_inside(S0, system.nbr, system.far, post.mean, hit, tau, vs)
    cfg.solver.tol = 1e-8

    def run(share):
        monkeypatch.setattr(solve_mod, "LOCAL_SHARE", share)
        return solve_mod.solve_map(System(S=S0.copy(), nbr=system.nbr, h=h0.copy(),
                                          far=system.far), bent, cfg.solver, band,
                                   trunc_m=tau, voxel_size_m=vs, free=1000.0,
                                   bootstrap_trunc_m=cfg.tsdf.bootstrap_trunc_m)

    local, info_l = run(solve_mod.LOCAL_SHARE)
    whole, info_w = run(0.0)
    assert info_l["local_solves"] > 0 and info_w["local_solves"] == 0
    assert info_l["solves"] < info_w["solves"]
    for info in (info_l, info_w):
        assert info["converged"] and info["free_space"]["settled"]
    assert info_l["free_space"]["anchored"] == info_w["free_space"]["anchored"]
    assert np.abs(local - whole).max() < 1e-3 * vs


def test_noise_fit_pairs_limited_to_nearly_the_same_point():
    """estimate_extra_noise(max_offset_px=...): only the pairs whose point projects within that
    many pixels of the paired pixel's centre count; a limit no offset reaches (half the cast
    stride's diagonal) keeps every pair, a tight one fewer."""
    from bftaichi.frame import local_frames
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import estimate_extra_noise

    cfg = _sphere_cfg(0.02, ["synthetic.noise=gaussian", "synthetic.sigma_m=0.004"])
    recon = bf.Reconstructor(cfg)
    for f in open_frames(cfg):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)

    def fit(offset, stride=1):
        return estimate_extra_noise(frames, band, cfg.observation, cfg.tsdf.voxel_size_m,
                                    cfg.tsdf.bootstrap_trunc_m, (0.1, 10.0), stride=stride,
                                    max_offset_px=offset)

    every = fit(None)
    assert fit(0.75) == every  # the nearest pixel's centre is at most 0.71 px away
    tight = fit(0.25)
    assert 0 < tight["pixels"] < 0.6 * every["pixels"]
    # the 4 mm of noise is found from the nearly coincident pairs too
    assert 0.0025 < tight["sigma_extra_m"] < 0.0045


def test_noise_allowance_narrows_sigma_and_leaves_the_mean():
    """``prior.noise_allowance`` changes only the robust prior's Hessian, which the variance
    reads: the mean (so the mesh) is bitwise the one without it, and on a sparse capture (a
    pixel spanning more than a voxel, where the mean's second differences are noisiest) sigma
    near the surface is narrower, since bends no larger than the data's noise no longer let
    the prior go."""
    from bftaichi.running.pipeline import open_frames
    from conftest import solved

    sparse = ("synthetic.width=32", "synthetic.height=24", "synthetic.fx=26.25",
              "synthetic.fy=26.25", "synthetic.cx=15.5", "synthetic.cy=11.5")
    runs = {}
    for on in (False, True):
        cfg = bf.load_config(None, [*TINY_SCENE_SETS, *sparse,
                                    f"prior.noise_allowance={str(on).lower()}"])
        runs[on] = solved(cfg, open_frames(cfg))[1]
    off, on = runs[False], runs[True]
    assert np.array_equal(off.mean, on.mean)
    near = np.abs(on.mean) < cfg.tsdf.voxel_size_m
    assert np.median(np.sqrt(on.var[near] / off.var[near])) < 0.98
