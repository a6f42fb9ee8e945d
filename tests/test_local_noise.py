"""observation.local_noise: the posterior variance judged against the data around each voxel
(bftaichi.stages.misfit.local_misfit). Where the frames agree with each other the correction
is small; where they disagree (here: misregistered frames) sigma grows with the disagreement,
so it still covers the error; the mean is never touched."""

import numpy as np
import pytest

import bftaichi as bf
from bftaichi.running.pipeline import open_frames
from conftest import solved

SHIFT_M = 0.006


def _sphere_cfg(extra=()):
    """A 0.15 m sphere, 12 views on a ring, Kinect noise, 5 mm voxels. The per-frame noise
    fit is off: it would absorb the misregistration before the solve (what it is for), and
    these tests are about what local_noise finds after it."""
    return bf.load_config(None, [
        "synthetic.mesh=sphere", "synthetic.radius_m=0.15", "synthetic.trajectory=ring",
        "synthetic.n_views=12", "synthetic.cam_radius_m=0.7", "synthetic.cam_height_m=0.3",
        "synthetic.width=120", "synthetic.height=90", "synthetic.fx=105", "synthetic.fy=105",
        "synthetic.cx=59.5", "synthetic.cy=44.5", "tsdf.voxel_size_m=0.005",
        "tsdf.trunc_m=0.01", "observation.fit_noise=false", *extra])


def _shifted(frames):
    """Every other frame's pose moved SHIFT_M along the camera's x axis: a misregistration."""
    out = []
    for i, f in enumerate(frames):
        T = np.array(f.T_W_C, np.float64)
        if i % 2:
            T[:3, 3] += SHIFT_M * T[:3, 0]
        out.append(type(f)(index=f.index, name=f.name, depth_m=f.depth_m, K=f.K, T_W_C=T,
                           rgb=None))
    return out


@pytest.fixture(scope="module")
def runs():
    """Posteriors of the clean and the misregistered frames, with and without local_noise."""
    out = {}
    for local in (True, False):
        cfg = _sphere_cfg([f"observation.local_noise={str(local).lower()}"])
        frames = list(open_frames(cfg))
        out["clean", local] = solved(cfg, frames)[1]
        out["shifted", local] = solved(cfg, _shifted(frames))[1]
    return out


def _sigma_and_error(post):
    """Vertex sigma and the exact vertex error on the 0.15 m sphere."""
    mesh = post.extract_mesh()
    error = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.15)
    return np.asarray(mesh.vertex_attributes["sigma"], np.float64), error


def test_misregistered_frames_sigma_still_covers_the_error(runs):
    """Half the frames are 6 mm off: the surface error grows (median ~1.2 mm, 2.6x the clean
    one), and the data around it disagree. Without local_noise sigma does not notice (2-sigma
    coverage ~78 %); with it, the excess residual enters sigma (~92 %, within issue 15's 90-98 %
    target)."""
    s_on, e_on = _sigma_and_error(runs["shifted", True])
    s_off, e_off = _sigma_and_error(runs["shifted", False])
    np.testing.assert_array_equal(e_on, e_off)  # the same mesh: only sigma changes
    assert np.median(e_on) > 2.0 * np.median(_sigma_and_error(runs["clean", True])[1])
    assert np.mean(e_off <= 2 * s_off) < 0.85
    assert np.mean(e_on <= 2 * s_on) >= 0.90
    stats = runs["shifted", True].variance["local_noise"]
    assert stats["p90_b_m"] > 1.5 * runs["clean", True].variance["local_noise"]["p90_b_m"]


def test_consistent_frames_get_a_small_correction(runs):
    on, off = runs["clean", True], runs["clean", False]
    np.testing.assert_array_equal(on.mean, off.mean)  # the variance only
    s_on, _ = _sigma_and_error(on)
    s_off, _ = _sigma_and_error(off)
    assert 0.5 < np.median(s_on) / np.median(s_off) < 2.0


def test_local_noise_is_deterministic(runs):
    cfg = _sphere_cfg(["observation.local_noise=true"])
    _, again = solved(cfg, list(open_frames(cfg)))
    np.testing.assert_array_equal(again.var, runs["clean", True].var)
    np.testing.assert_array_equal(again.cov, runs["clean", True].cov)


def _window(r, y, expected, w):
    """One window's misfit sums (Observer.misfit_window's columns) of samples with residuals
    ``r``, distances ``y`` from their pixel's surface, expected squared residuals ``expected``
    and weights ``w``."""
    return np.array([[np.sum(w * r * r), np.sum(w * expected), np.sum(w), np.sum(w * r),
                      np.sum(w * y), np.sum(w * y * y), np.sum(w * r * y)]])


def test_surface_excess_leaves_out_the_residuals_slope_but_keeps_their_offset():
    """Residuals that grow along y (the mean's slope off by 30 %) over an SDF 0.4 mm off at
    the surface: the excess is that offset's square over the slope's (the surface's offset in
    distance), not the mean squared residual; with the
    slope beyond SLOPE_AGREEMENT (the mean flat where the data are not, a sheet seen from two
    sides) or without a line, the whole excess counts."""
    from bftaichi.stages.misfit import SLOPE_AGREEMENT, surface_excess

    rng = np.random.default_rng(0)
    y = rng.uniform(-0.006, 0.006, 400)  # 1.5 voxels of 4 mm either side
    w = rng.uniform(0.5, 1.0, 400)
    expected = np.full(400, 1e-7)
    scatter = rng.normal(0.0, np.sqrt(1e-7), 400)
    scatter -= np.sum(w * scatter) / np.sum(w)  # no offset of its own
    r = 0.0004 + 0.3 * y + scatter
    b2, line = surface_excess(_window(r, y, expected, w))
    whole = np.sum(w * (r * r - expected)) / np.sum(w)
    assert line[0]
    assert whole > 2 * 0.0004 ** 2  # the slope's part would double it
    # the surface's offset in distance: the SDF's over the mean's slope along the rays, 1 - 0.3
    assert b2[0] == pytest.approx((0.0004 / 0.7) ** 2, rel=0.15)

    steep = 0.0004 + (SLOPE_AGREEMENT + 0.4) * y + scatter
    b2, line = surface_excess(_window(steep, y, expected, w))
    assert not line[0]
    assert b2[0] == pytest.approx(np.sum(w * (steep ** 2 - expected)) / np.sum(w))

    flat = np.full(400, 0.0)  # every sample at its surface: no line to fit
    b2, line = surface_excess(_window(r, flat, expected, w))
    assert not line[0]
    assert b2[0] == pytest.approx(np.sum(w * (r * r - expected)) / np.sum(w))
