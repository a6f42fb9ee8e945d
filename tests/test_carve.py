"""Free space seen by the rays (kernels/carve.py, ``prior.carve``): exact counts, and voxels the
rays passed through are held out of the surface where the data would put one."""

import numpy as np

from conftest import posterior_system, pulled_inside, solved


def _reference_counts(ijk, depth, K, T_W_C, voxel, tau_b):
    """The carve / observe rule of kernels/carve.py in numpy, one voxel at a time in spirit."""
    T_C_W = np.linalg.inv(T_W_C)
    A, c = K @ T_C_W[:3, :3] * voxel, K @ (T_C_W[:3, :3] @ np.full(3, 0.5 * voxel) + T_C_W[:3, 3])
    p = ijk.astype(np.float64) @ A.T + c
    z = p[:, 2]
    h, w = depth.shape
    counts = np.zeros((len(ijk), 2), np.int32)
    for i in range(len(ijk)):
        if z[i] <= 0:
            continue
        uh, vh = p[i, 0] / z[i] + 0.5, p[i, 1] / z[i] + 0.5
        if not (0 <= uh < w and 0 <= vh < h):
            continue
        d = float(depth[int(vh), int(uh)])
        if d > 0 and d - z[i] >= -tau_b:
            counts[i] = (int(d - z[i] >= tau_b), 1)
    return counts


def test_carve_counts_match_the_bootstrap_rule():
    """Per frame, a voxel is observed when it projects onto a valid pixel no farther than
    tau_b behind its depth, and carved when it lies at least tau_b in front of it; the counts
    over frames are exact integers."""
    from kernels.carve import FreeSpaceCounter

    rng = np.random.default_rng(3)
    voxel, tau_b = 0.02, 0.08
    K = np.array([[61.37, 0, 31.71], [0, 60.93, 23.29], [0, 0, 1]])  # no pixel edge on a voxel
    ijk = rng.integers(-40, 40, size=(4000, 3)).astype(np.int32)
    counter = FreeSpaceCounter(ijk, voxel, tau_b)
    expected = np.zeros((len(ijk), 2), np.int32)
    for f in range(3):
        depth = (0.6 + 0.4 * rng.random((48, 64))).astype(np.float32)
        depth[rng.random(depth.shape) < 0.1] = 0.0  # invalid pixels
        T = np.eye(4)
        T[:3, 3] = (0.1031 * f + 0.0047, -0.0513, -1.0071)
        counter.add(depth, K, T)
        expected += _reference_counts(ijk, depth, K, T, voxel, tau_b)
    np.testing.assert_array_equal(counter.carved(), expected[:, 0])
    np.testing.assert_array_equal(counter.observing(), expected[:, 1])
    assert expected[:, 0].sum() > 100 and (expected[:, 1] > expected[:, 0]).sum() > 100


def test_the_groups_out_of_view_are_skipped_without_changing_a_count():
    """A band's rows come block by block; the counter skips the blocks behind the camera or
    outside the image. A camera inside a block-ordered grid, seeing a part of it: the counts
    equal the rule applied to every voxel (numpy, vectorised)."""
    from kernels.carve import FreeSpaceCounter, voxel_groups

    rng = np.random.default_rng(5)
    voxel, tau_b = 0.02, 0.06
    blocks = np.stack(np.meshgrid(*[np.arange(-3, 3)] * 2, np.arange(-1, 2), indexing="ij"),
                      -1).reshape(-1, 3)
    local = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    ijk = (blocks[:, None, :] * 8 + local[None]).reshape(-1, 3).astype(np.int32)
    starts, _ = voxel_groups(ijk)
    assert len(starts) - 1 == len(blocks)  # one group a block
    K = np.array([[61.37, 0, 31.71], [0, 60.93, 23.29], [0, 0, 1]])
    counter = FreeSpaceCounter(ijk, voxel, tau_b)
    expected = np.zeros((len(ijk), 2), np.int64)
    for f in range(4):
        angle = 0.4 * f
        T = np.eye(4)
        T[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                     [-np.sin(angle), 0, np.cos(angle)]]
        T[:3, 3] = (0.013 * f, 0.021, -0.011)
        depth = (0.3 + 0.5 * rng.random((48, 64))).astype(np.float32)
        depth[rng.random(depth.shape) < 0.1] = 0.0
        counter.add(depth, K, T)
        T_C_W = np.linalg.inv(T)
        A = K @ T_C_W[:3, :3] * voxel
        c = K @ (T_C_W[:3, :3] @ np.full(3, 0.5 * voxel) + T_C_W[:3, 3])
        p = ijk.astype(np.float64) @ A.T + c
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uh, vh = p[:, 0] / z + 0.5, p[:, 1] / z + 0.5
        seen = (z > 0) & (uh >= 0) & (uh < 64) & (vh >= 0) & (vh < 48)
        d = np.zeros(len(ijk))
        d[seen] = depth[vh[seen].astype(int), uh[seen].astype(int)]
        observe = seen & (d > 0) & (d - z >= -tau_b)
        expected[:, 1] += observe
        expected[:, 0] += observe & (d - z >= tau_b)
    np.testing.assert_array_equal(counter.observing(), expected[:, 1])
    np.testing.assert_array_equal(counter.carved(), expected[:, 0])
    in_view = (expected[:, 1] > 0).reshape(len(blocks), -1).any(axis=1)
    assert 0 < in_view.sum() < len(blocks) // 2  # most blocks are out of every view


def test_carved_voxels_are_lifted_out_of_the_surface():
    """Voxels in front of the surface that the averaged TSDF does not call free (``tsdf <=
    tau``), pulled toward "inside" (as the samples behind a thin part pull them) below half a
    voxel, end in front of the surface once the rays carved them, and stay bent otherwise."""
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.prior import System
    from bftaichi.stages.solve import solve_map
    from test_posterior import _sphere_cfg

    cfg = _sphere_cfg(0.03, ["observation.fit_noise=false", "observation.aggregate=0"])
    recon, post = solved(cfg, open_frames(cfg), variance=False)
    band, system = posterior_system(recon)
    S, nbr, far = system.S.copy(), system.nbr, system.far
    vs, tau = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m
    near_free = np.flatnonzero(band.observed & (band.tsdf <= tau) & (post.mean > vs))
    assert len(near_free) > 100
    pulled = near_free[:: len(near_free) // 24][:24]
    h, bent = pulled_inside(S, nbr, far, post.mean, pulled, tau, vs)
    hit = pulled[bent[pulled] < 0.5 * vs]  # the inequality broken
    assert len(hit) >= 8
    cfg.solver.tol = 1e-8
    carved = np.zeros(len(band), bool)
    carved[hit] = True
    runs = {}
    for name, mask in (("plain", None), ("carved", carved)):
        runs[name], info = solve_map(System(S=S.copy(), nbr=nbr, h=h.copy(), far=far), bent,
                                     cfg.solver, band, trunc_m=tau, voxel_size_m=vs,
                                     bootstrap_trunc_m=cfg.tsdf.bootstrap_trunc_m,
                                     free=1000.0, carved=mask)
        assert info["converged"]
    assert info["free_space"]["carved_voxels"] == len(hit)
    np.testing.assert_allclose(runs["plain"][hit], bent[hit], atol=0.05 * vs)
    # a soft inequality (the anchors' strength is that of the pull): in front, no surface
    assert (runs["carved"][hit] > 0).all()


def test_a_closed_convex_object_is_carved_nowhere_on_its_surface():
    """On a sphere every ray that reaches a voxel near the surface ends on that surface: the
    default carve rule holds no voxel the surface passes through, and the posterior equals the
    one without it."""
    from bftaichi.running.pipeline import open_frames
    from test_posterior import _sphere_cfg

    cfg = _sphere_cfg(0.03, ["observation.fit_noise=false"])
    off = _sphere_cfg(0.03, ["observation.fit_noise=false", "prior.carve=0"])
    _, post = solved(cfg, open_frames(cfg), variance=False)
    _, post_off = solved(off, open_frames(off), variance=False)
    assert "carved_voxels" in post.solver["free_space"]  # the count ran (0 on the sphere)
    np.testing.assert_allclose(post.mean, post_off.mean, atol=1e-3 * cfg.tsdf.voxel_size_m)


def test_free_space_anchors_do_not_push_a_perfectly_seen_surface():
    """A 0.1 m sphere seen with perfect depth by 60 views from a ring above it (oblique rays,
    whose projective distances overstate the true one beside the surface): the free-space
    constraint must hold the surface where the data put it. The SDF of the voxels within a
    voxel of the true surface is nearly as close to the exact signed distance as without the
    constraint: anchors at the TSDF's projective value made it 1.43x worse; today's anchors
    give 1.03x with the Gaussian curvature prior and 1.10x with the robust one (the default),
    which resists the kinks the anchors leave less."""
    import bftaichi as bf
    from bftaichi.running.pipeline import open_frames

    base = ["synthetic.mesh=sphere", "synthetic.radius_m=0.1", "synthetic.trajectory=ring",
            "synthetic.look_at=[0.0, 0.0, 0.0]", "synthetic.n_views=60",
            "synthetic.cam_radius_m=0.6", "synthetic.cam_height_m=0.3", "synthetic.width=320",
            "synthetic.height=240", "synthetic.fx=262.5", "synthetic.fy=262.5",
            "synthetic.cx=159.5", "synthetic.cy=119.5", "synthetic.noise=none",
            "synthetic.quantization_m=0", "synthetic.dropout=0", "tsdf.voxel_size_m=0.003",
            "tsdf.trunc_m=0.006"]
    rms = {}
    for name, extra in (("constrained", []), ("free", ["prior.free=0", "prior.carve=0"])):
        cfg = bf.load_config(None, base + extra)
        _, post = solved(cfg, open_frames(cfg), variance=False)
        h = post.voxel_size
        sdf = np.linalg.norm(post.origin + (post.ijk + 0.5) * h, axis=1) - 0.1
        near = (np.abs(sdf) < h) & (post.weight > 0)
        rms[name] = float(np.sqrt(np.mean((post.mean[near] - sdf[near]) ** 2)))
        if name == "constrained":
            assert post.solver["free_space"]["anchored"] > 0  # the constraint did act
    assert rms["free"] < 0.3 * h  # a surface the data pin down
    assert rms["constrained"] <= 1.2 * rms["free"], rms


def test_anchor_target_runs_from_the_bound_to_the_projective_value():
    """A free-space anchor pulls to half a voxel where the TSDF barely calls the voxel free
    (``tsdf <= tau``), to the TSDF's own value where every frame saw it beyond the truncation
    (``tau_b``), and in between never below the bound nor above the TSDF, rising with it."""
    from bftaichi.stages.solve import anchor_target

    h, tau, tau_b = 0.01, 0.02, 0.04
    tsdf = np.linspace(-tau_b, tau_b, 801).astype(np.float32)
    t = anchor_target(tsdf, tau, tau_b, h)
    assert t.dtype == np.float32 and t.shape == tsdf.shape
    np.testing.assert_allclose(t[tsdf <= tau], 0.5 * h, rtol=1e-6)
    assert abs(t[-1] - tau_b) < 1e-7
    assert (t >= 0.5 * h - 1e-7).all() and (t <= np.maximum(tsdf, 0.5 * h) + 1e-7).all()
    assert (np.diff(t) >= -1e-7).all()
