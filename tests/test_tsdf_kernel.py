"""kernels.tsdf.SparseTSDF against a float64 numpy reference on small analytic scenes.

The reference (``RefTSDF``, ``ref_block_sets``) implements DESIGN.md section 3.1 directly: blocks
touched by the ray segments [d - tau, d + tau], then for every voxel of those blocks the nearest
pixel ``floor(K x_C / z + 0.5)``, ``sdf = D - z``, observed if ``D > 0`` and ``sdf >= -tau``,
weighted running average with a weight cap. The kernel computes in float32, so a voxel whose
projection lies within 1e-3 px of a pixel border (or whose sdf is within 1e-5 m of -tau) may
legitimately go either way; such voxels are flagged *ambiguous* by the reference and left out of
the comparison (the test checks that they are rare). Values agree to float32 precision: 2e-6 m
on tsdf (a few ulp of camera depths up to 5 m), exact on weights.
"""

import itertools

import numpy as np
import pytest

import kernels.tsdf as ktsdf
from bftaichi.backend import init
from bftaichi.geometry import intrinsics, look_at
from kernels.layout import block_key_np
from kernels.tsdf import SparseTSDF


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    """Taichi on the CPU (idempotent: keeps a runtime another test module started)."""
    init("cpu")


VOXEL = 0.02
TRUNC = 0.07  # 3.5 voxels: not a multiple of the voxel size on purpose
K_SMALL = intrinsics(29.3, 28.7, 15.3, 11.6)  # 32 x 24 pixels
SIZE_SMALL = (24, 32)
SPHERE = (np.array([0.05, -0.03, 0.22]), 0.25)
FLOOR = (np.array([0.0, 0.0, 1.0]), 0.0)  # plane n . x = h
OFFS = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij"),
                -1).reshape(-1, 3)  # voxel t = 64 a + 8 b + c of a block -> (a, b, c)
PIX_EPS = 1e-3  # px: projections this close to a pixel border are ambiguous in float32
SDF_EPS = 1e-5  # m
BLK_EPS = 1e-4  # blocks: activation samples this close to a block border are ambiguous


# -- scene -----------------------------------------------------------------------------------

def render_depth(K, T_W_C, size, spheres=(SPHERE,), planes=(FLOOR,), holes=True):
    """Exact depth (camera z, metres, float32, 0 = no hit) of spheres and planes."""
    H, W = size
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dirs_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d_W = dirs_C @ T_W_C[:3, :3].T  # camera z of d_W is 1, so the ray parameter is the depth
    o = T_W_C[:3, 3]
    depth = np.full((H, W), np.inf)
    for c, r in spheres:
        a = (d_W * d_W).sum(-1)
        b = 2 * (d_W @ (o - c))
        disc = b * b - 4 * a * ((o - c) @ (o - c) - r * r)
        t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        depth = np.where((disc >= 0) & (t > 0), np.minimum(depth, t), depth)
    for n, h in planes:
        dn = d_W @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (h - o @ n) / dn
        depth = np.where((np.abs(dn) > 1e-9) & (t > 0), np.minimum(depth, t), depth)
    depth[~np.isfinite(depth)] = 0
    if holes:  # invalid pixels, as real sensors have
        depth[(u.astype(int) * 7 + v.astype(int) * 3) % 11 == 0] = 0
    return np.ascontiguousarray(depth, dtype=np.float32)


def colour_image(size, seed):
    H, W = size
    v, u = np.mgrid[0:H, 0:W]
    return np.stack([(u * 37 + v * 11 + seed) % 256, (u * 5 + v * 29 + 3 * seed) % 256,
                     (u * v + 7 * seed) % 256], -1).astype(np.uint8)


def small_frames():
    """Three 32x24 frames of a sphere on a floor from random-ish viewpoints (third: stride 2)."""
    eyes = [(1.1, 0.3, 0.8), (-0.4, 1.0, 0.9), (0.6, -0.9, 0.6)]
    targets = [(0.0, 0.0, 0.1), (0.1, -0.05, 0.2), (-0.05, 0.02, 0.15)]
    frames = []
    for i, (eye, target) in enumerate(zip(eyes, targets)):
        T = look_at(eye, target)
        frames.append((render_depth(K_SMALL, T, SIZE_SMALL), T, colour_image(SIZE_SMALL, i),
                       2 if i == 2 else 1))
    return frames


# -- numpy reference -------------------------------------------------------------------------

def block_keys(blk):
    """int64 key of integer block indices (n, 3) (|index| < 2^20)."""
    return block_key_np(blk)


def ref_block_sets(depth, K, T_W_C, trunc, block_m, stride):
    """Keys of the blocks the activation must list (``certain``) and may list (``possible``):
    samples within BLK_EPS of a block border, or rays whose sample count is ambiguous, may fall
    on either side in float32."""
    H, W = depth.shape
    v, u = np.mgrid[0:H:stride, 0:W:stride]
    d = depth[v, u].astype(np.float64)
    keep = d > 0
    u, v, d = u[keep], v[keep], d[keep]
    rays = np.stack([u, v, np.ones_like(u)], -1) @ (T_W_C[:3, :3] @ np.linalg.inv(K)).T / block_m
    o = T_W_C[:3, 3] / block_m
    a = o + np.maximum(d - trunc, 1e-3)[:, None] * rays
    b = o + (d + trunc)[:, None] * rays
    q = np.linalg.norm(b - a, axis=1) / 0.5  # segment length in half blocks
    n_lo = np.ceil(q - 1e-6).astype(np.int64) + 1
    n_hi = np.ceil(q + 1e-6).astype(np.int64) + 1
    certain, possible = [], []
    for n in (n_lo, n_hi):
        for s in range(int(n.max()) + 1):
            m = s <= n
            x = a[m] + (b[m] - a[m]) * (s / n[m])[:, None]
            lo, hi = np.floor(x - BLK_EPS), np.floor(x + BLK_EPS)
            for pick in itertools.product((False, True), repeat=3):
                possible.append(block_keys(np.where(np.array(pick), hi, lo)))
            sure = (n_lo[m] == n_hi[m]) & (lo == hi).all(axis=1)
            certain.append(block_keys(lo[sure]))
    return np.unique(np.concatenate(certain)), np.unique(np.concatenate(possible))


class RefTSDF:
    """Float64 projective TSDF over explicitly given blocks (rows of 512 voxels, t = 64a+8b+c)."""

    def __init__(self, voxel, trunc, max_weight=1e4):
        self.voxel, self.trunc, self.max_weight = voxel, trunc, max_weight
        self.keys = np.zeros(0, np.int64)
        self.blocks = np.zeros((0, 3), np.int64)
        self.tsdf = np.zeros((0, 512))
        self.weight = np.zeros((0, 512))
        self.rgb = np.zeros((0, 512, 3))
        self.ambiguous = np.zeros((0, 512), bool)

    def _rows(self, blocks):
        keys = block_keys(blocks)
        new = ~np.isin(keys, self.keys)
        if new.any():
            n = int(new.sum())
            keys_all = np.concatenate([self.keys, keys[new]])
            order = np.argsort(keys_all)
            self.keys = keys_all[order]
            self.blocks = np.concatenate([self.blocks, blocks[new]])[order]
            self.tsdf = np.concatenate([self.tsdf, np.zeros((n, 512))])[order]
            self.weight = np.concatenate([self.weight, np.zeros((n, 512))])[order]
            self.rgb = np.concatenate([self.rgb, np.zeros((n, 512, 3))])[order]
            self.ambiguous = np.concatenate([self.ambiguous, np.zeros((n, 512), bool)])[order]
        return np.searchsorted(self.keys, keys)

    def integrate(self, depth, K, T_W_C, blocks, rgb=None):
        rows = self._rows(np.asarray(blocks, np.int64))
        ijk = self.blocks[rows][:, None, :] * 8 + OFFS[None]
        T_C_W = np.linalg.inv(T_W_C)
        x_C = ((ijk + 0.5) * self.voxel) @ T_C_W[:3, :3].T + T_C_W[:3, 3]
        z = x_C[..., 2]
        front = z > 0
        zs = np.where(front, z, 1.0)
        uh = K[0, 0] * x_C[..., 0] / zs + K[0, 2] + 0.5
        vh = K[1, 1] * x_C[..., 1] / zs + K[1, 2] + 0.5
        H, W = depth.shape
        ui, vi = np.floor(uh).astype(np.int64), np.floor(vh).astype(np.int64)
        inside = front & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
        D = np.where(inside, depth[np.clip(vi, 0, H - 1), np.clip(ui, 0, W - 1)], 0.0)
        sdf = D - z
        obs = inside & (D > 0) & (sdf >= -self.trunc)
        self.ambiguous[rows] |= front & ((np.abs(uh - np.round(uh)) < PIX_EPS)
                                         | (np.abs(vh - np.round(vh)) < PIX_EPS)
                                         | (inside & (D > 0)
                                            & (np.abs(sdf + self.trunc) < SDF_EPS)))
        w = self.weight[rows]
        self.tsdf[rows] = np.where(obs, (w * self.tsdf[rows] + np.minimum(1.0, sdf / self.trunc))
                                   / (w + 1), self.tsdf[rows])
        if rgb is not None:
            col = rgb[np.clip(vi, 0, H - 1), np.clip(ui, 0, W - 1)].astype(np.float64)
            self.rgb[rows] = np.where(obs[..., None], (w[..., None] * self.rgb[rows] + col)
                                      / (w[..., None] + 1), self.rgb[rows])
        self.weight[rows] = np.where(obs, np.minimum(w + 1, self.max_weight), w)

    def voxel_keys(self):
        """(keys of all voxels (n_blocks*512,), flat tsdf (metres), weight, rgb, ambiguous)."""
        ijk = (self.blocks[:, None, :] * 8 + OFFS[None]).reshape(-1, 3)
        return (block_keys(ijk), self.tsdf.reshape(-1) * self.trunc, self.weight.reshape(-1),
                self.rgb.reshape(-1, 3), self.ambiguous.reshape(-1))


def assert_matches_reference(vol, ref):
    """Observed voxel sets equal and values equal (to float32 precision), ambiguous voxels
    excluded. Returns the number of voxels compared."""
    out = vol.export()
    keys = block_keys(out["ijk"])
    assert np.all(np.diff(keys) > 0), "export must be sorted by (i, j, k) without duplicates"
    r_keys, r_tsdf, r_w, r_rgb, r_amb = ref.voxel_keys()
    assert r_amb.mean() < 0.02, "too many ambiguous voxels: the comparison would be weak"
    amb_keys = r_keys[r_amb]
    ours = ~np.isin(keys, amb_keys)
    theirs = (r_w > 0) & ~r_amb
    order = np.argsort(r_keys[theirs])
    np.testing.assert_array_equal(keys[ours], r_keys[theirs][order])
    np.testing.assert_array_equal(out["weight"][ours], r_w[theirs][order])
    # float32 camera z of floor voxels up to ~5 m away: a few ulp of 4.8e-7 m.
    np.testing.assert_allclose(out["tsdf"][ours], r_tsdf[theirs][order], rtol=0, atol=2e-6)
    if vol.with_color:
        np.testing.assert_allclose(out["rgb"][ours], r_rgb[theirs][order], rtol=0, atol=2e-3)
    return int(ours.sum())


# -- tests -----------------------------------------------------------------------------------

@pytest.mark.parametrize("with_color", [False, True])
def test_matches_numpy_reference_voxel_by_voxel(with_color):
    vol = SparseTSDF(VOXEL, TRUNC, with_color=with_color)
    ref = RefTSDF(VOXEL, TRUNC)
    for depth, T, rgb, stride in small_frames():
        updates = vol.integrate(depth, K_SMALL, T, rgb=rgb if with_color else None,
                                activation_stride=stride)
        blocks = vol.frame_blocks()
        certain, possible = ref_block_sets(depth, K_SMALL, T, TRUNC, 8 * VOXEL, stride)
        listed = block_keys(blocks)
        assert np.all(np.isin(certain, listed)), "a block on a ray segment was not activated"
        assert np.all(np.isin(listed, possible)), "a block off every ray segment was activated"
        assert len(np.unique(listed)) == len(listed), "frame block list has duplicates"
        w_before = ref.weight.sum()
        ref.integrate(depth, K_SMALL, T, blocks, rgb if with_color else None)
        assert updates == ref.weight.sum() - w_before  # weights are below the cap here
    n = assert_matches_reference(vol, ref)
    assert n > 5000
    assert vol.stats()["blocks"] == len(ref.keys)
    assert vol.stats()["out_of_range_samples"] == 0


def medium_frames(n=4, size=(120, 160)):
    K = intrinsics(150.0, 151.0, 79.3, 59.6)
    frames = []
    for i in range(n):
        ang = 0.7 * i
        T = look_at((1.2 * np.cos(ang), 1.2 * np.sin(ang), 0.7 + 0.1 * i), (0.0, 0.0, 0.15))
        frames.append((render_depth(K, T, size), K, T))
    return frames


def test_integration_is_bitwise_deterministic():
    """Two volumes fed the same frames (interleaved, so thread timing differs) export the same
    bytes."""
    frames = medium_frames()
    a, b = SparseTSDF(0.01, 0.04), SparseTSDF(0.01, 0.04)
    for depth, K, T in frames:
        a.integrate(depth, K, T, activation_stride=2)
        b.integrate(depth, K, T, activation_stride=2)
    ea, eb = a.export(), b.export()
    assert len(ea["ijk"]) > 10000
    for key in ("ijk", "tsdf", "weight"):
        assert ea[key].tobytes() == eb[key].tobytes(), key


def test_pool_and_frame_list_growth_keep_results(monkeypatch):
    """A volume that starts with room for 1 block and a 2-entry frame list (so every frame
    grows both) ends bitwise equal to one with the default capacities."""
    frames = medium_frames(3)
    ref = SparseTSDF(0.01, 0.04)
    for depth, K, T in frames:
        ref.integrate(depth, K, T, activation_stride=2)
    monkeypatch.setattr(ktsdf, "FIRST_POOL_BLOCKS", 1)
    monkeypatch.setattr(ktsdf, "FIRST_LIST_BLOCKS", 2)
    small = SparseTSDF(0.01, 0.04)
    for depth, K, T in frames:
        small.integrate(depth, K, T, activation_stride=2)
    assert small.pool_blocks >= small.stats()["blocks"] > 1000
    e_ref, e_small = ref.export(), small.export()
    for key in ("ijk", "tsdf", "weight"):
        assert e_ref[key].tobytes() == e_small[key].tobytes(), key


def test_rgb_is_the_weighted_average_of_observed_colours():
    depth, T, _, _ = small_frames()[0]
    vol = SparseTSDF(VOXEL, TRUNC, with_color=True)
    for c in ((10, 20, 30), (50, 100, 200)):
        rgb = np.empty(SIZE_SMALL + (3,), np.uint8)
        rgb[:] = c
        vol.integrate(depth, K_SMALL, T, rgb=rgb)
    out = vol.export()
    assert len(out["weight"]) > 1000
    assert np.all(out["weight"] == 2)
    np.testing.assert_array_equal(out["rgb"], np.broadcast_to([30.0, 60.0, 115.0],
                                                              out["rgb"].shape))
    # A frame without colour updates the geometry and leaves the colours as they were.
    vol.integrate(depth, K_SMALL, T)
    out3 = vol.export()
    assert np.all(out3["weight"] == 3)
    np.testing.assert_array_equal(out3["rgb"], out["rgb"])


def test_max_weight_caps_the_running_weight():
    depth, T, _, _ = small_frames()[1]
    once = SparseTSDF(VOXEL, TRUNC)
    once.integrate(depth, K_SMALL, T)
    capped = SparseTSDF(VOXEL, TRUNC, max_weight=3.0)
    for _ in range(6):
        assert capped.integrate(depth, K_SMALL, T) > 0
    e1, e6 = once.export(), capped.export()
    np.testing.assert_array_equal(e6["ijk"], e1["ijk"])
    assert np.all(e6["weight"] == 3.0)
    # The same observation six times: the average stays that observation.
    np.testing.assert_allclose(e6["tsdf"], e1["tsdf"], rtol=0, atol=1e-6)


def test_out_of_range_samples_are_counted_not_fatal(monkeypatch):
    """The map spans +-512 blocks (+-81.92 m at 2 cm voxels) per axis."""
    limit_m = ktsdf.BLOCK_OFFSET * 8 * VOXEL
    K = intrinsics(60.0, 60.0, 31.5, 23.5)
    # A wall just inside the +x edge: the far end of the truncation band leaves the map.
    wall = (np.array([1.0, 0.0, 0.0]), limit_m - 0.03)
    T = look_at((limit_m - 1.0, 0.0, 0.0), (limit_m + 5.0, 0.0, 0.0))
    depth = render_depth(K, T, (48, 64), spheres=(), planes=(wall,), holes=False)
    vol = SparseTSDF(VOXEL, 0.1)
    updates = vol.integrate(depth, K, T)
    st = vol.stats()
    assert st["out_of_range_samples"] > 0
    assert updates > 0
    out = vol.export()
    assert out["ijk"][:, 0].max() < ktsdf.BLOCK_OFFSET * 8  # nothing wrapped around
    assert np.all(np.abs(out["ijk"][:, 0] * VOXEL - (limit_m - 0.03)) < 0.2)
    # A volume that must grow its pool and frame list during this frame (so the frame is
    # listed several times) counts each sample once and ends the same.
    monkeypatch.setattr(ktsdf, "FIRST_POOL_BLOCKS", 1)
    monkeypatch.setattr(ktsdf, "FIRST_LIST_BLOCKS", 1)
    regrown = SparseTSDF(VOXEL, 0.1)
    assert regrown.integrate(depth, K, T) == updates
    assert regrown.stats() == st
    assert regrown.export()["tsdf"].tobytes() == out["tsdf"].tobytes()
    monkeypatch.undo()
    # Entirely outside: nothing is integrated, every sample is counted.
    far = look_at((1000.0, 0.0, 0.0), (1005.0, 0.0, 0.0))
    plane_far = (np.array([1.0, 0.0, 0.0]), 1002.0)
    depth_far = render_depth(K, far, (48, 64), spheres=(), planes=(plane_far,), holes=False)
    vol2 = SparseTSDF(VOXEL, 0.1)
    assert vol2.integrate(depth_far, K, far) == 0
    assert vol2.stats()["out_of_range_samples"] >= 48 * 64
    assert vol2.stats()["blocks"] == 0 and len(vol2.export()["ijk"]) == 0


def test_fronto_parallel_plane_gives_exact_tsdf_and_frame_count_weight():
    """Plane z = 1 m seen head-on from three camera positions shifted in x/y: every voxel has
    sdf = 1 - z_centre in each frame."""
    K = intrinsics(40.0, 40.0, 19.5, 14.5)
    plane = (np.array([0.0, 0.0, 1.0]), 1.0)
    vol = SparseTSDF(VOXEL, 0.06)
    n_frames = 3
    for i in range(n_frames):
        T = np.eye(4)
        T[:2, 3] = (0.013 * i, -0.021 * i)
        depth = render_depth(K, T, (30, 40), spheres=(), planes=(plane,), holes=False)
        vol.integrate(depth, K, T)
    out = vol.export()
    centre = (out["ijk"] + 0.5) * VOXEL
    sdf_true = 1.0 - centre[:, 2]
    seen_by_all = np.all(np.abs(centre[:, :2]) < 0.2, axis=1)
    assert seen_by_all.sum() > 500
    assert np.all(out["weight"][seen_by_all] == n_frames)
    band = seen_by_all & (np.abs(sdf_true) < 0.06)
    np.testing.assert_allclose(out["tsdf"][band], sdf_true[band], rtol=0, atol=1e-5)
    free = seen_by_all & (sdf_true >= 0.06)
    np.testing.assert_allclose(out["tsdf"][free], 0.06, rtol=0, atol=1e-7)
    # The zero crossing is between the voxel layers k = 49 (centre 0.99) and k = 50 (1.01).
    near = seen_by_all & np.isin(out["ijk"][:, 2], (49, 50))
    assert np.all((out["tsdf"][near] > 0) == (out["ijk"][near, 2] == 49))
    assert np.all(centre[:, 2] <= 1.0 + 0.06 + VOXEL)  # nothing behind the band is observed
