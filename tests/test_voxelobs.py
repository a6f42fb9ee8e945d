"""The per-voxel data term (``observation.model = "voxels"``, kernels/voxelobs.py): what each
voxel observes, how much it counts, and that the sums are exact and order-free."""

import numpy as np
import pytest

from kernels.layout import CENTRE
from kernels.voxelobs import VoxelObserver

from test_observe import NOISE, R_OBJ, TRUNC, VOXEL, Band, box_faces, box_sdf, frames_of, shell


@pytest.fixture(scope="module")
def box():
    return Band(shell(box_sdf, 4.5)), frames_of("box")


def voxel_observer(band, **kw):
    args = dict(count_once="voxel", front_m=2 * TRUNC, gate_m=0.0)
    return VoxelObserver(band.keys, band.table, len(band.ijk), VOXEL, TRUNC,
                         **{**NOISE, **args, **kw})


def projection(frame, x):
    """Camera depth z and pixel (u, v) of world points x (M, 3)."""
    R, t = frame.T_W_C[:3, :3], frame.T_W_C[:3, 3]
    p = (x - t) @ R
    K = frame.K
    return p[:, 2], K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]


def one_frame(obs, frame):
    obs.reset()
    obs.integrate(frame.depth_m, frame.K, frame.T_W_C)
    S, h, _ = obs.finalize()
    return S, h


def test_voxels_observe_their_signed_distance_to_a_flat_face(box):
    """Where a voxel's projection falls between 4 pixels of one box face, its observation
    ``h / Q_ii`` is the signed distance of its centre to that face (positive in front), and
    only voxels within [-front, tau] of the surface along their ray are observed."""
    band, frames = box
    obs = voxel_observer(band)
    x = (band.ijk + 0.5) * VOXEL
    checked = 0
    for frame in frames:
        S, h = one_frame(obs, frame)
        seen = S[:, CENTRE] > 0
        assert np.array_equal(S[:, np.arange(27) != CENTRE], 0 * S[:, np.arange(27) != CENTRE])
        face, flat = box_faces(frame)
        z, u, v = projection(frame, x)
        u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
        H, W = face.shape
        inside = (z > 0) & (u0 >= 0) & (v0 >= 0) & (u0 + 1 < W) & (v0 + 1 < H)
        f = np.full(len(x), -1)
        same = inside.copy()
        f[inside] = face[v0[inside], u0[inside]]
        for dv, du in ((0, 0), (0, 1), (1, 0), (1, 1)):
            same[inside] &= face[v0[inside] + dv, u0[inside] + du] == f[inside]
            same[inside] &= flat[v0[inside] + dv, u0[inside] + du]
        same &= f >= 0
        # the face plane's signed distance and depth along the voxel's ray
        axis, sign = f // 2, np.where(f % 2 == 1, 1.0, -1.0)
        plane = sign * x[np.arange(len(x)), np.maximum(axis, 0)] - R_OBJ
        check = same & seen
        y = h[check] / S[check, CENTRE]
        np.testing.assert_allclose(y, plane[check], atol=1e-4)
        checked += check.sum()
        # reach: observed voxels lie within [-front, tau] of the face along their ray
        cam = frame.T_W_C[:3, 3]
        ray = (x - cam) / z[:, None]
        n = np.zeros((len(x), 3))
        n[np.arange(len(x)), np.maximum(axis, 0)] = sign
        t_hit = (R_OBJ - (n * cam).sum(1)) / (n * ray).sum(1)  # depth where the ray meets it
        along = z - t_hit
        assert (along[check] >= -2 * TRUNC - 2e-3).all() and (along[check] <= TRUNC + 2e-3).all()
        missing = same & ~seen & (along > -2 * TRUNC + 2e-3) & (along < TRUNC - 2e-3)
        assert not missing.any()
    assert checked > 500


def test_sums_are_exact_deterministic_and_order_free(box):
    """Integer sums: any order of frames gives the same bits, a frame's information alone is
    bitwise the diagonal it adds, and subtracting is exact."""
    band, frames = box
    a, b = voxel_observer(band), voxel_observer(band)
    for f in frames:
        a.integrate(f.depth_m, f.K, f.T_W_C)
    for f in frames[::-1]:
        b.integrate(f.depth_m, f.K, f.T_W_C)
    Sa, ha, _ = a.finalize()
    Sb, hb, _ = b.finalize()
    assert np.array_equal(Sa, Sb) and np.array_equal(ha, hb)
    f = frames[1]
    S1, _ = one_frame(b, f)
    assert np.array_equal(b.information(f.depth_m, f.K, f.T_W_C), b.diagonal())
    assert np.array_equal(b.diagonal().astype(np.float32), S1[:, CENTRE])
    rows = b.frame_rows(f.depth_m, f.K, f.T_W_C)  # the same observations, one row per voxel
    assert np.array_equal(rows["idx"], np.flatnonzero(S1[:, CENTRE] > 0))
    np.testing.assert_allclose(rows["y"], b._data_term()[1][rows["idx"]] / b.fixed_scale
                               / rows["w"], rtol=1e-12)


def test_a_frame_tells_a_voxel_at_most_its_correlated_noise(box):
    """With a per-frame noise shared by a voxel's pixels (sigma_corr), one frame gives a voxel
    at most ``1 / sigma_corr^2`` (each voxel counts a frame's shared error once), and
    without it at most the pixels whose centres its footprint holds, at the floor noise."""
    band, frames = box
    corr = 0.004
    obs = voxel_observer(band, sigma_corr_m=corr)
    for f in frames:
        info = obs.information(f.depth_m, f.K, f.T_W_C)
        assert info.max() > 0
        assert 0.9 / corr ** 2 < info.max() <= 1.0 / corr ** 2  # many pixels: near the cap
    plain = voxel_observer(band)
    x = (band.ijk + 0.5) * VOXEL
    floor = (NOISE["depth_a_m"] * NOISE["cos_min"]) ** 2 + NOISE["sigma_pose_m"] ** 2 + \
        NOISE["sigma_model_m"] ** 2
    for f in frames:
        z, _, _ = projection(f, x)
        side = f.K[0, 0] * VOXEL / z  # pixels a voxel spans, a side
        info = plain.information(f.depth_m, f.K, f.T_W_C)
        assert (info <= np.floor(side + 1) ** 2 / floor * (1 + 1e-9)).all()


def test_side_gate_drops_the_voxels_the_reference_contradicts(box):
    band, frames = box
    x = (band.ijk + 0.5) * VOXEL
    ref = box_sdf(x).astype(np.float32)
    flipped = ref.copy()
    flipped[::3] *= -1  # a third of the reference says the other side
    gate = 0.5 * TRUNC
    f = frames[0]
    open_ = voxel_observer(band)
    gated = voxel_observer(band, gate_m=gate, reference=flipped)
    S0, h0 = one_frame(open_, f)
    S1, h1 = one_frame(gated, f)
    seen = S0[:, CENTRE] > 0
    y = np.where(seen, h0 / np.where(seen, S0[:, CENTRE], 1), 0)
    drop = seen & (((y < 0) & (flipped > gate)) | ((y > 0) & (flipped < -gate)))
    assert drop.any()
    assert not (S1[drop, CENTRE] > 0).any()
    assert np.array_equal(S1[seen & ~drop, CENTRE], S0[seen & ~drop, CENTRE])


def test_model_voxels_rejects_a_stride():
    from bftaichi.errors import ConfigError
    from bftaichi.stages.observe import ObservationConfig

    with pytest.raises(ConfigError, match="stride"):
        ObservationConfig(model="voxels", stride=2).check()


@pytest.mark.parametrize("voxel", [0.02, 0.03])
def test_noiseless_sphere_posterior_with_voxel_observations_beats_its_tsdf(tmp_path, voxel):
    """End to end (``bftaichi run`` with ``observation.model = "voxels"``): the posterior mesh
    of a noiseless sphere is at least as close to it as the TSDF's, with a finite sigma."""
    import bftaichi as bf
    from bftaichi.io import read_mesh_ply
    from test_posterior import _rms_sphere, _sphere_cfg

    report = bf.run(_sphere_cfg(voxel, ["observation.model=voxels"]), tmp_path / "out",
                    progress=False)
    assert report["solver"]["map"]["converged"]
    assert report["solver"]["observations"]["observations_accepted"] > 0
    v_tsdf, _, _ = read_mesh_ply(tmp_path / "out" / "tsdf_mesh.ply")
    v_post, f_post, extra = read_mesh_ply(tmp_path / "out" / "mesh.ply")
    assert len(f_post) > 1000
    assert _rms_sphere(v_post) <= _rms_sphere(v_tsdf)
    assert report["metrics"]["mesh.ply"]["chamfer_l2"] <= \
        report["metrics"]["tsdf_mesh.ply"]["chamfer_l2"]
    assert np.all(np.isfinite(extra["sigma"])) and np.all(extra["sigma"] > 0)
