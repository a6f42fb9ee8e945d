"""Pose updates and frame removal (issue 19, items 1 and 3): the TSDF is kept as integer sums,
so a frame subtracted at its old pose and added at its new one leaves the volume bitwise equal
to fusing every frame at its corrected pose; the posterior solved after the update (started
cold, as a fresh fuse's) is bitwise that of the re-fused scene."""

import numpy as np
import pytest

import bftaichi as bf
from bftaichi.errors import BftaichiError
from conftest import TINY_SCENE_SETS


def _frames(sets=()):
    from bftaichi.formats.synthetic import SyntheticDataset

    cfg = bf.load_config(None, TINY_SCENE_SETS + tuple(sets))
    return cfg, list(SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m,
                                      cfg.scene.depth_max_m))


def _drifted(T, k):
    """A pose off by a rotation of ~1 degree and 1-3 cm (what a loop closure corrects)."""
    a = np.deg2rad(1.0 + 0.3 * k)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = [0.01 * (k + 1), -0.02, 0.015]
    return D @ T


def _fused(cfg, frames, poses=None, order=None):
    recon = bf.Reconstructor(cfg)
    for i in (order if order is not None else range(len(frames))):
        f = frames[i]
        T = f.T_W_C if poses is None else poses[i]
        recon.integrate(f.depth_m, f.K, T, rgb=f.rgb, name=f.name)
    return recon


def _assert_same_volume(a, b):
    va, vb = a.voxels, b.voxels
    assert va.keys() == vb.keys()
    for key in va:
        assert va[key].dtype == vb[key].dtype
        np.testing.assert_array_equal(va[key], vb[key], err_msg=key)


@pytest.fixture(scope="module")
def scene():
    return _frames()


def test_integration_is_independent_of_the_frame_order(scene):
    cfg, frames = scene
    n = len(frames)
    _assert_same_volume(_fused(cfg, frames), _fused(cfg, frames, order=[3, 0, 5, 1, 4, 2][:n]))


def test_removing_a_frame_gives_the_volume_without_it_bitwise(scene):
    cfg, frames = scene
    recon = _fused(cfg, frames)
    before = len(recon.voxels["ijk"])
    recon.remove(frames[2].name)
    _assert_same_volume(recon, _fused(cfg, frames, order=[0, 1, 3, 4, 5]))
    assert [f.name for f in recon.frames] == [frames[i].name for i in (0, 1, 3, 4, 5)]
    assert recon.tsdf.n_frames == len(frames) - 1
    # the band shrinks where only that frame saw the surface
    assert len(recon.voxels["ijk"]) < before


def test_colour_is_removed_exactly_too():
    from dataclasses import replace

    cfg, frames = _frames(["tsdf.integrate_rgb=true"])
    rng = np.random.default_rng(1)
    frames = [replace(f, rgb=rng.integers(0, 256, f.depth_m.shape + (3,), dtype=np.uint8))
              for f in frames]
    frames[1] = replace(frames[1], rgb=None)  # a frame without colour counts for geometry only
    recon = _fused(cfg, frames)
    recon.remove(frames[4].name)
    ref = _fused(cfg, frames, order=[0, 1, 2, 3, 5])
    assert "rgb" in recon.voxels
    _assert_same_volume(recon, ref)


def test_update_poses_equals_fusing_with_the_corrected_poses(scene):
    """Three frames fused at drifted poses, then corrected: the TSDF bitwise, and the solve
    after the update (cold, as a fresh fuse's) bitwise too: band, mean, variance."""
    cfg, frames = scene
    true = [f.T_W_C for f in frames]
    wrong = [(_drifted(T, k) if k in (1, 3, 4) else T) for k, T in enumerate(true)]
    recon = _fused(cfg, frames, poses=wrong)
    recon.solve()  # the solve before the loop closure: the warm start of the next
    moved = recon.update_poses({frames[k].name: true[k] for k in (0, 1, 3, 4)})
    assert moved == [frames[k].name for k in (1, 3, 4)]  # frame 0 did not move
    ref = _fused(cfg, frames)
    _assert_same_volume(recon, ref)
    post, post_ref = recon.solve(), ref.solve()
    assert post.solver["converged"] and post_ref.solver["converged"]
    for key in ("ijk", "mean", "var", "cov"):
        np.testing.assert_array_equal(getattr(post, key), getattr(post_ref, key), err_msg=key)


def test_a_bad_update_changes_nothing(scene):
    cfg, frames = scene
    recon = _fused(cfg, frames)
    before = {k: v.copy() for k, v in recon.voxels.items()}
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(BftaichiError, match=frames[2].name):
        recon.update_poses({frames[1].name: _drifted(frames[1].T_W_C, 0),
                            frames[2].name: bad})
    with pytest.raises(BftaichiError, match="no kept frames are named 'nope'"):
        recon.update_poses({frames[1].name: _drifted(frames[1].T_W_C, 0), "nope": np.eye(4)})
    with pytest.raises(BftaichiError, match="no kept frames"):
        recon.remove("nope")
    for key, v in recon.voxels.items():
        np.testing.assert_array_equal(v, before[key])
    assert [f.T_W_C.tolist() for f in recon.frames] == [f.T_W_C.tolist() for f in frames]


def test_a_saved_state_restores_the_volume_and_can_be_updated(scene):
    """What `bftaichi update` relies on: the integer sums saved and loaded into a new volume
    give the same export, and a pose update on the loaded volume equals re-fusing."""
    from kernels.tsdf import SparseTSDF

    cfg, frames = scene
    true = [f.T_W_C for f in frames]
    wrong = [(_drifted(T, k) if k == 2 else T) for k, T in enumerate(true)]
    recon = _fused(cfg, frames, poses=wrong)
    state = recon.tsdf.state()
    fresh = bf.Reconstructor(cfg)
    fresh.tsdf.load_state(state)
    for key, v in recon.voxels.items():
        np.testing.assert_array_equal(fresh.voxels[key], v)
    f = frames[2]
    fresh.tsdf.remove(f.depth_m, f.K, wrong[2])
    fresh.tsdf.integrate(f.depth_m, f.K, true[2])
    fresh._voxels = None
    ref = _fused(cfg, frames)
    _assert_same_volume(fresh, ref)
    assert fresh.tsdf.n_frames == len(frames)
