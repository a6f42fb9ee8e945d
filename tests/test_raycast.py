"""kernels.raycast: predicted depth of the band's mean and the NBV coverage grid.

Analytic scenes: a sphere and a tilted plane whose band mean is the exact signed distance (the
ray cast must find the exact ray-surface depth), a plain numpy march of the same sample lattice
on a band with gaps and an unobserved half (the kernel skips empty blocks, the reference does
not), and brute-force (densely sampled) ray-cell sets for the exact voxel traversal of the
coverage grid.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from kernels.lookup import build_block_table
from kernels.coverage import CoverageGrid
from kernels.raycast import raycast_depth

R_SPHERE = 0.3  # metres
CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])


# -- scenes -----------------------------------------------------------------------------------

def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_W_C of an OpenCV camera at ``eye`` looking at ``target`` (y down, towards -up)."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = (target - eye) / np.linalg.norm(target - eye)
    y = -(up - up @ z * z)
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.stack([np.cross(y, z), y, z], axis=1)
    T[:3, 3] = eye
    return T


def intrinsics(width, height, f):
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def pixel_rays_W(K, T, width, height) -> np.ndarray:
    """World-frame rays R_WC K^-1 (u, v, 1) (H, W, 3): a point at camera depth z is
    t_WC + z ray."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    uv1 = np.stack([u, v, np.ones_like(u)], axis=-1)
    return uv1 @ np.linalg.inv(K).T @ T[:3, :3].T


class Band:
    """Voxels within ``half_width`` voxels of an analytic surface, mean = exact SDF there."""

    def __init__(self, sdf, voxel, extent_m, half_width=3.0, keep=None):
        n = int(np.ceil(extent_m / voxel))
        r = np.arange(-n, n)
        ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        x = (ijk + 0.5) * voxel
        phi = sdf(x)
        sel = np.abs(phi) < half_width * voxel
        if keep is not None:
            sel &= keep(x)
        self.voxel = voxel
        self.ijk = ijk[sel].astype(np.int32)
        self.x = x[sel]
        self.mean = phi[sel].astype(np.float32)
        self.observed = np.ones(len(self.ijk), np.uint8)
        self.keys, self.table = build_block_table(self.ijk)

    def cast(self, K, T, width, height, observed=None, **kw):
        args = dict(depth_min_m=0.1, depth_max_m=3.0)
        args.update(kw)
        return raycast_depth(self.keys, self.table, self.mean,
                             self.observed if observed is None else observed, self.voxel, K, T,
                             width, height, **args)


def sphere_sdf(x):
    return np.linalg.norm(x, axis=-1) - R_SPHERE


def ray_sphere_depth(K, T, width, height):
    """Exact camera depth of the first ray-sphere intersection (0: miss) and the cosine of the
    incidence angle there."""
    d = pixel_rays_W(K, T, width, height)
    c = T[:3, 3]  # sphere centre at the origin: |c + z d| = R
    a, b, cc = (d * d).sum(-1), 2 * d @ c, c @ c - R_SPHERE ** 2
    disc = b * b - 4 * a * cc
    z = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    p = c + z[..., None] * d
    cos = np.abs((p * d).sum(-1)) / (np.linalg.norm(p, axis=-1) * np.sqrt(a))
    return z, cos


W, H = 160, 120
K_SPHERE = intrinsics(W, H, 150.0)
T_SPHERE = look_at(np.array([0.6, -0.5, 0.62]) / np.linalg.norm([0.6, -0.5, 0.62]), (0, 0, 0))


@pytest.fixture(scope="module")
def sphere():
    return Band(sphere_sdf, 0.01, 0.36)


# -- raycast_depth ----------------------------------------------------------------------------

def test_sphere_depth_is_the_ray_sphere_intersection(sphere):
    depth = sphere.cast(K_SPHERE, T_SPHERE, W, H)
    exact, cos = ray_sphere_depth(K_SPHERE, T_SPHERE, W, H)
    hit, true_hit = depth > 0, exact > 0
    assert true_hit.sum() > 5000
    # hit pattern: may differ only at the silhouette (grazing rays)
    assert (hit != true_hit).sum() < 0.02 * true_hit.sum()
    assert (cos[hit != true_hit] < 0.2).all()
    both = hit & true_hit
    err = np.abs(depth - exact)
    # trilinear interpolation of |x| - r errs ~0.01 voxel in SDF; along the ray that is divided
    # by the incidence cosine, so grazing pixels (cos < 0.1, the outer 0.5 % of the disc radius)
    # get a looser bound
    assert err[both & (cos >= 0.1)].max() < 0.1 * sphere.voxel
    assert err[both].max() < 0.5 * sphere.voxel


@pytest.mark.parametrize("voxel", [0.01, 0.02])
def test_tilted_plane_depth_at_two_voxel_sizes(voxel):
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    half = 0.25  # the band is the plane's patch |x|_inf < half
    band = Band(lambda x: x @ n - 0.05, voxel, half,
                keep=lambda x: np.abs(x).max(axis=-1) < half)
    w, h = 80, 60
    K = intrinsics(w, h, 110.0)
    T = look_at((0.35, 0.3, 0.9), (0.0, 0.0, 0.05))
    depth = band.cast(K, T, w, h)
    d = pixel_rays_W(K, T, w, h)
    exact = (0.05 - T[:3, 3] @ n) / (d @ n)  # <n, t + z d> = 0.05
    p = T[:3, 3] + exact[..., None] * d
    reach = np.abs(p).max(axis=-1)
    inside = reach < half - 4 * voxel  # well inside the patch: must hit
    outside = reach > half + 8 * voxel  # the ray never crosses the band there
    assert inside.sum() > 0.2 * w * h and outside.sum() > 100
    assert (depth[inside] > 0).all()
    assert (depth[outside] == 0).all()
    # trilinear interpolation is exact on a plane: only the float32 mean and output remain
    assert np.abs(depth - exact)[inside].max() < 0.01 * voxel


def test_depth_sigma_is_the_sdf_sigma_over_the_slope_along_the_ray():
    """Constant SDF variance s on a plane: sigma_z = sqrt(s) / (n . d), d the pixel ray with
    unit camera-z component (1 head-on), floored by slope_min at grazing angles."""
    voxel = 0.02
    n = np.array([0.0, 0.0, 1.0])
    band = Band(lambda x: x @ n, voxel, 0.4, keep=lambda x: np.abs(x[:, :2]).max(axis=-1) < 0.4)
    var = np.full(len(band.mean), (0.003) ** 2, np.float32)
    w, h = 64, 48
    K = intrinsics(w, h, 60.0)
    for eye, slope_min in (((0.0, 0.001, 1.0), 0.3), ((0.9, 0.0, 0.5), 0.3), ((0.9, 0.0, 0.5), 0.9)):
        T = look_at(eye, (0.0, 0.0, 0.0))
        depth, sigma = band.cast(K, T, w, h, var=var, slope_min=slope_min)
        hit = depth > 0
        assert hit.sum() > 100 and (sigma[~hit] == 0).all()
        slope = np.abs(pixel_rays_W(K, T, w, h) @ n)
        expected = 0.003 / np.maximum(slope, slope_min)
        np.testing.assert_allclose(sigma[hit], expected[hit], rtol=1e-3)
    # without var: the depth alone, identical
    np.testing.assert_array_equal(band.cast(K, T, w, h), depth)


def test_unobserved_patch_gives_no_depth(sphere):
    full = sphere.cast(K_SPHERE, T_SPHERE, W, H)
    centre = R_SPHERE * T_SPHERE[:3, 3]  # surface point facing the camera
    radius = 0.12
    patch = np.linalg.norm(sphere.x - centre, axis=-1) < radius
    observed = (~patch).astype(bool)  # bool is accepted as well as uint8
    depth = sphere.cast(K_SPHERE, T_SPHERE, W, H, observed=observed)
    exact, _ = ray_sphere_depth(K_SPHERE, T_SPHERE, W, H)
    p = T_SPHERE[:3, 3] + exact[..., None] * pixel_rays_W(K_SPHERE, T_SPHERE, W, H)
    dist = np.linalg.norm(p - centre, axis=-1)
    in_patch = (exact > 0) & (dist < radius - 4 * sphere.voxel)
    away = (exact > 0) & (dist > radius + 4 * sphere.voxel)
    assert in_patch.sum() > 500 and away.sum() > 1000 and (full[in_patch] > 0).all()
    # nothing found through the hole: not the front face, nor the back face seen from inside
    assert (depth[in_patch] == 0).all()
    np.testing.assert_array_equal(depth[away], full[away])


def test_camera_looking_away_sees_nothing(sphere):
    T = look_at((0.0, 0.0, -1.0), (0.0, 0.0, -2.0), up=(0.0, 1.0, 0.0))
    assert (sphere.cast(K_SPHERE, T, W, H) == 0).all()
    # and a camera inside the sphere sees only back faces (negative -> positive): nothing
    inside = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0))
    assert (sphere.cast(K_SPHERE, inside, W, H, depth_min_m=0.0) == 0).all()


def reference_march(band, observed, K, T, width, height, z_min, z_max, step_voxels):
    """Plain numpy march of the same lattice z_k = z_min + k dz (every sample, no skipping)."""
    vs = band.voxel
    lo = band.ijk.min(axis=0) - 2
    grid = np.full(band.ijk.max(axis=0) - lo + 3, -1, np.int64)
    grid[tuple((band.ijk - lo).T)] = np.arange(len(band.ijk))
    m = pixel_rays_W(K, T, width, height).reshape(-1, 3) / vs
    o = T[:3, 3] / vs - 0.5
    dz = step_voxels / np.linalg.norm(m, axis=-1)
    n = np.floor((z_max - z_min) / dz).astype(np.int64) + 1
    k = np.arange(n.max())
    z = z_min + k[None] * dz[:, None]  # (P, S)
    g = o + z[..., None] * m[:, None]
    c0 = np.floor(g).astype(np.int64)
    f = g - c0
    corner = c0[:, :, None] + CORNERS - lo  # (P, S, 8, 3)
    ok = ((corner >= 0) & (corner < grid.shape)).all(-1)
    idx = np.where(ok, grid[tuple(np.where(ok[..., None], corner, 0).transpose(3, 0, 1, 2))], -1)
    valid = (idx >= 0).all(-1) & (k[None] < n[:, None])
    valid &= (observed[np.maximum(idx, 0)] != 0).all(-1)
    a = np.where(CORNERS, f[:, :, None], 1 - f[:, :, None]).prod(-1)
    mu = (a * band.mean.astype(np.float64)[np.maximum(idx, 0)]).sum(-1)
    # entry point of each sample's cell along the ray (step 3b), after the previous sample
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = np.where(m[:, None] > 0, c0, c0 + 1)  # the face the ray enters through
        t = np.where(m[:, None] != 0, (plane - o) / m[:, None], -np.inf)
    z_e = np.maximum(np.maximum(z - dz[:, None], z_min), t.max(-1))
    f_e = np.clip(o + z_e[..., None] * m[:, None] - c0, 0.0, 1.0)
    a_e = np.where(CORNERS, f_e[:, :, None], 1 - f_e[:, :, None]).prod(-1)
    mu_e = (a_e * band.mean.astype(np.float64)[np.maximum(idx, 0)]).sum(-1)
    prev_valid = np.concatenate([np.zeros((len(z), 1), bool), valid[:, :-1]], axis=1)
    prev_mu = np.concatenate([np.zeros((len(z), 1)), mu[:, :-1]], axis=1)
    prev_z = np.concatenate([np.zeros((len(z), 1)), z[:, :-1]], axis=1)
    regular = valid & prev_valid & (prev_mu > 0) & (mu <= 0)
    entry = valid & ~prev_valid & (mu <= 0) & (mu_e > 0) & (z_e < z)
    pair = regular | entry
    first = np.argmax(pair, axis=1)
    rows = np.arange(len(first))
    e = entry[rows, first]
    z0 = np.where(e, z_e[rows, first], prev_z[rows, first])
    m0 = np.where(e, mu_e[rows, first], prev_mu[rows, first])
    z1, m1 = z[rows, first], mu[rows, first]
    has = pair.any(axis=1)
    depth = np.where(has, z0 + (z1 - z0) * m0 / np.where(has, m0 - m1, 1.0), 0.0)
    return depth.reshape(height, width)


def test_matches_a_plain_numpy_march_on_a_band_with_gaps():
    """Two objects (empty blocks between them), a removed cap (band holes) and an unobserved
    half: empty-space skipping and the block cache must not change a single pixel."""
    vs = 0.02
    rng = np.random.default_rng(3)
    bumps = rng.normal(size=(3, 3))

    def sdf(x):  # a bumpy sphere of radius 0.15 and a wall at y = 0.4
        s = np.linalg.norm(x, axis=-1) - 0.15 + 0.01 * np.sin(x @ bumps * 20).sum(-1)
        return np.minimum(s, 0.4 - x[..., 1])

    band = Band(sdf, vs, 0.5, keep=lambda x: x[..., 2] < 0.1)
    observed = (band.x[:, 0] < 0.05).astype(np.uint8)
    w, h = 40, 30
    K = intrinsics(w, h, 50.0)
    T = look_at((0.35, -0.7, 0.25), (0.0, 0.1, 0.0))
    got = raycast_depth(band.keys, band.table, band.mean, observed, vs, K, T, w, h, 0.2, 1.6,
                        step_voxels=0.7)
    ref = reference_march(band, observed, K, T, w, h, 0.2, 1.6, 0.7)
    assert (ref > 0).sum() > 300 and (ref == 0).sum() > 100
    np.testing.assert_array_equal(got > 0, ref > 0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    # stride: the same depths on the strided pixels, 0 elsewhere
    strided = raycast_depth(band.keys, band.table, band.mean, observed, vs, K, T, w, h, 0.2, 1.6,
                            step_voxels=0.7, stride=3)
    mask = np.zeros((h, w), bool)
    mask[::3, ::3] = True
    np.testing.assert_array_equal(strided[mask], got[mask])
    assert (strided[~mask] == 0).all()


def slab_depths(ijk, vs, g_surface, focal, eye, target, z_max):
    """``(kernel, reference)`` depths (30, 40) of the band ``ijk`` whose mean is the distance
    to the plane at grid z ``g_surface`` (every voxel observed), seen from ``eye`` looking at
    ``target`` (depths 0.1 .. ``z_max``, half-voxel steps)."""
    z_surface = (g_surface + 0.5) * vs
    band = SimpleNamespace(voxel=vs, ijk=ijk,
                           mean=(z_surface - (ijk[:, 2] + 0.5) * vs).astype(np.float32))
    keys, table = build_block_table(ijk)
    observed = np.ones(len(ijk), np.uint8)
    w, h = 40, 30
    K = intrinsics(w, h, focal)
    T = look_at(eye, target, up=(0.0, -1.0, 0.0))
    got = raycast_depth(keys, table, band.mean, observed, vs, K, T, w, h, 0.1, z_max)
    return got, reference_march(band, observed, K, T, w, h, 0.1, z_max, 0.5)


@pytest.mark.parametrize("skip", ["empty blocks", "band box"])
def test_surface_just_behind_the_face_of_a_band_block(skip):
    """A block-aligned slab (voxels k = 8..23) whose surface lies 0.2 voxel into its first
    cells: the first sample after a jump must be the next lattice sample, as in a plain march.
    The jump to the slab is the band-box clip, or (an extra band block makes the box larger
    than the slab) the empty-block skip."""
    vs = 0.02
    r = np.arange(-16, 16)
    slab = np.stack(np.meshgrid(r, r, np.arange(8, 24), indexing="ij"), -1).reshape(-1, 3)
    extra = np.stack(np.meshgrid(r[:8] + 64, r[:8], np.arange(-16, -8), indexing="ij"),
                     -1).reshape(-1, 3)
    ijk = np.concatenate([slab, extra] if skip == "empty blocks" else [slab]).astype(np.int32)
    # grid coordinate g_z = z / vs - 0.5 = 8.2
    got, ref = slab_depths(ijk, vs, 8.2, 60.0, (0.013, -0.021, -0.5), (0.0, 0.0, 1.0), 1.0)
    assert (ref > 0).mean() > 0.9  # the entry point finds the surface 0.2 voxel inside
    np.testing.assert_array_equal(got > 0, ref > 0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


def test_blocks_without_a_crossing_are_those_no_cell_of_which_reaches_a_negative_mean():
    """kernels.raycast.crossing_blocks against its definition: block b may hold a crossing
    when some observed band voxel in [8 b, 8 b + 8]^3 (what the cells based in b reach) has
    mean <= 0; the others are the ones the march crosses in two samples."""
    from kernels.layout import decode_keys
    from kernels.raycast import crossing_blocks

    rng = np.random.default_rng(7)
    r = np.arange(-12, 20)
    ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    ijk = ijk[rng.random(len(ijk)) < 0.6].astype(np.int32)
    mean = np.where(rng.random(len(ijk)) < 0.01, -1.0, 1.0).astype(np.float32)
    observed = (rng.random(len(ijk)) < 0.9).astype(np.uint8)
    keys, table = build_block_table(ijk)
    blocks = decode_keys(keys)
    crossing = crossing_blocks(keys, table, mean, observed)
    negative = ijk[(observed != 0) & (mean <= 0)]
    expected = np.array([((negative >= 8 * b) & (negative <= 8 * b + 8)).all(axis=1).any()
                         for b in blocks])
    assert 0 < expected.sum() < len(blocks)
    np.testing.assert_array_equal(crossing.astype(bool), expected)


@pytest.mark.parametrize("g_surface", [7.8, 8.2, 15.9, 20.3])
def test_surface_beside_a_block_the_march_crosses_in_two_samples(g_surface):
    """A slab three blocks deep (voxels k = 0..23) seen obliquely, its surface at grid z
    ``g_surface``: in the last layer of the block before the face between blocks (7.8: only
    the next block's first layer is negative), just past it (8.2, 15.9 the same one block
    on), or inside a block (20.3). The blocks in front of the surface have no crossing and are
    crossed in two samples; every depth is the plain march's."""
    r = np.arange(-16, 16)
    ijk = np.stack(np.meshgrid(r, r, np.arange(0, 24), indexing="ij"), -1).reshape(-1, 3)
    got, ref = slab_depths(ijk.astype(np.int32), 0.02, g_surface, 40.0, (0.21, -0.17, -0.45),
                           (0.0, 0.0, 0.3), 1.5)
    assert (ref > 0).mean() > 0.5
    np.testing.assert_array_equal(got > 0, ref > 0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


def test_deterministic(sphere):
    a = sphere.cast(K_SPHERE, T_SPHERE, W, H, stride=2)
    b = sphere.cast(K_SPHERE, T_SPHERE, W, H, stride=2)
    assert (a > 0).sum() > 1000
    assert a.tobytes() == b.tobytes()


def test_mask_casts_only_its_pixels_with_the_same_bytes(sphere):
    full = sphere.cast(K_SPHERE, T_SPHERE, W, H, stride=2)
    mask = np.zeros((H, W), bool)
    mask[::3, ::5] = True  # every 3rd row and 5th column: some cast (stride 2), most not
    masked = sphere.cast(K_SPHERE, T_SPHERE, W, H, stride=2, mask=mask)
    assert (full[mask] > 0).sum() > 50
    assert masked[mask].tobytes() == full[mask].tobytes()
    assert not masked[~mask].any()
    with pytest.raises(ValueError, match="mask"):
        sphere.cast(K_SPHERE, T_SPHERE, W, H, mask=mask[:-1])
    with pytest.raises(ValueError, match="mask"):
        sphere.cast(K_SPHERE, T_SPHERE, W, H, mask=mask.astype(np.uint8))


def test_input_validation(sphere):
    ok = dict(block_keys=sphere.keys, block_table=sphere.table, mean=sphere.mean,
              observed=sphere.observed, voxel_size=0.01, K=K_SPHERE, T_W_C=T_SPHERE,
              width=W, height=H, depth_min_m=0.1, depth_max_m=3.0)
    bad_T = T_SPHERE.copy()
    bad_T[0, 0] = 2.0
    cases = [
        (TypeError, "block_keys", dict(block_keys=sphere.keys.astype(np.float64))),
        (ValueError, "block_table", dict(block_table=sphere.table[:, :100])),
        (ValueError, "block_table", dict(mean=sphere.mean[:10], observed=sphere.observed[:10])),
        (TypeError, "mean", dict(mean=sphere.mean.astype(np.int32))),
        (ValueError, "observed", dict(observed=sphere.observed[:-1])),
        (TypeError, "observed", dict(observed=sphere.observed.astype(np.float32))),
        (ValueError, "mean", dict(mean=np.full_like(sphere.mean, np.nan))),
        (ValueError, "voxel_size", dict(voxel_size=0.0)),
        (ValueError, "K", dict(K=np.eye(4))),
        (ValueError, "K", dict(K=np.where(np.eye(3) > 0, np.nan, K_SPHERE))),
        (ValueError, "K", dict(K=K_SPHERE * [[-1], [1], [1]])),
        (ValueError, "T_W_C", dict(T_W_C=np.full((4, 4), np.inf))),
        (ValueError, "T_W_C", dict(T_W_C=bad_T)),
        (ValueError, "width", dict(width=0)),
        (ValueError, "height", dict(height=2.5)),
        (ValueError, "depth_min_m", dict(depth_min_m=-0.1)),
        (ValueError, "depth_max_m", dict(depth_min_m=2.0, depth_max_m=1.0)),
        (ValueError, "depth_max_m", dict(depth_max_m=np.inf)),
        (ValueError, "depth_max_m", dict(depth_max_m=1e6)),  # beyond the band index range
        (ValueError, "step_voxels", dict(step_voxels=-1.0)),
        (ValueError, "stride", dict(stride=0)),
        (ValueError, "crossing", dict(crossing=np.zeros(1, np.uint8))),
    ]
    for error, name, change in cases:
        with pytest.raises(error, match=name):
            raycast_depth(**{**ok, **change})


# -- CoverageGrid -----------------------------------------------------------------------------

def plane_depth(K, T, width, height, n, offset):
    """Camera depth of the plane <n, x> = offset along each pixel ray (inf where parallel,
    negative behind the camera)."""
    d = pixel_rays_W(K, T, width, height)
    with np.errstate(divide="ignore"):
        return (offset - T[:3, 3] @ n) / (d @ n)


def cell_corners_W(grid):
    """World corners (nx, ny, nz, 8, 3) of every cell."""
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1)
    return grid.lo + (idx[..., None, :] + CORNERS) * grid.cell_m


N_PLANE = np.array([0.2, 0.0, -1.0]) / np.linalg.norm([0.2, 0.0, -1.0])
OFF_PLANE = N_PLANE @ [0.0, 0.0, 0.7]  # plane through (0, 0, 0.7), normal towards the camera
K_COV = intrinsics(64, 48, 60.0)
T_COV = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0))


@pytest.fixture()
def marked():
    grid = CoverageGrid((-0.4, -0.4, 0.2), (0.4, 0.4, 1.2), 0.05)
    depth = plane_depth(K_COV, T_COV, 64, 48, N_PLANE, OFF_PLANE).astype(np.float32)
    grid.mark(depth, K_COV, T_COV, trunc_m=0.02)
    return grid, depth


def test_mark_sees_the_space_before_a_plane_and_not_behind(marked):
    grid, _ = marked
    assert grid.shape == (16, 16, 20) and grid.seen.dtype == np.uint8
    corners = cell_corners_W(grid)
    # corners in the camera frame (T_COV: camera at the origin, axes aligned with the world)
    p_C = (corners - T_COV[:3, 3]) @ T_COV[:3, :3]
    uv = p_C[..., :2] / p_C[..., 2:] * K_COV[[0, 1], [0, 1]] + K_COV[:2, 2]
    in_view = ((uv >= 0) & (uv <= [63, 47])).all(axis=(-1, -2))
    front = (corners @ N_PLANE > OFF_PLANE + 1e-6).all(axis=-1)  # whole cell before the plane
    behind = (corners @ N_PLANE < OFF_PLANE - 0.03).all(axis=-1)  # > trunc behind it
    assert (in_view & front).sum() > 200 and (in_view & behind).sum() > 200
    assert (grid.seen[in_view & front] == 1).all()
    assert (grid.seen[behind] == 0).all()
    outside = (uv < -2).any(axis=(-1, -2)) & (uv[..., 0] < -2).all(axis=-1)  # left of the image
    assert outside.sum() > 100 and (grid.seen[outside] == 0).all()
    assert grid.seen_count() == int(grid.seen.sum())


def test_count_unknown_of_views(marked):
    grid, depth = marked
    before = grid.seen.copy()
    assert grid.count_unknown(depth, K_COV, T_COV) == 0  # the marked view sees nothing new
    np.testing.assert_array_equal(grid.seen, before)  # counting never marks
    # a slightly shifted re-observation vs a view from the side, both with the plane predicted
    T_again = look_at((0.03, 0.02, 0.0), (0.03, 0.02, 1.0), up=(0.0, -1.0, 0.0))
    T_side = look_at((1.2, 0.0, 0.7), (0.0, 0.0, 0.7))
    preds = []
    for T in (T_again, T_side):
        pred = plane_depth(K_COV, T, 64, 48, N_PLANE, OFF_PLANE)
        preds.append(np.where(np.isfinite(pred) & (pred > 0), pred, 0).astype(np.float32))
    again = grid.count_unknown(preds[0], K_COV, T_again)
    side = grid.count_unknown(preds[1], K_COV, T_side)
    assert side > 100 and side > 10 * again
    assert grid.count_unknown(preds[1], K_COV, T_side) == side  # deterministic
    # without a predicted surface the rays reach the box exit: more cells
    no_surface = np.zeros((48, 64), np.float32)
    assert grid.count_unknown(no_surface, K_COV, T_side) > side
    # rays that end before reaching the box (it starts 0.8 m away) count nothing
    assert grid.count_unknown(no_surface, K_COV, T_side, max_depth_m=0.7) == 0


def brute_force_cells(grid, K, T, width, height, z_end, step=2e-4):
    """Cells hit by samples every ``step`` cells along each pixel ray from depth 0 to z_end
    (H, W): the exact traversal must find these and no others."""
    d = pixel_rays_W(K, T, width, height).reshape(-1, 3)
    z_end = np.broadcast_to(z_end, (height, width)).reshape(-1)
    cells = set()
    for ray, z1 in zip(d, z_end):
        dz = step * grid.cell_m / np.linalg.norm(ray)
        z = np.arange(0.5 * dz, z1, dz)  # from just after the camera: the cell it moves into
        c = np.floor((T[:3, 3] + z[:, None] * ray - grid.lo) / grid.cell_m).astype(np.int64)
        c = c[((c >= 0) & (c < grid.shape)).all(axis=1)]
        cells.update(map(tuple, np.unique(c, axis=0).tolist()))
    return cells


def test_exact_traversal_and_dedup_on_a_tiny_grid():
    grid = CoverageGrid((0.0, 0.0, 0.0), (0.6, 0.5, 0.4), 0.1)
    assert grid.shape == (6, 5, 4)
    K = intrinsics(3, 2, 1.5)
    T = look_at((0.0317, 0.0461, 0.0523), (0.43, 0.27, 0.13))  # inside the box: shared cells
    z_end = np.array([[0.31, 0.47, 0.62], [0.77, 0.58, 2.0]])  # the last leaves the box
    expected = brute_force_cells(grid, K, T, 3, 2, z_end)
    # counting: distinct cells, each once although rays share cells
    per_ray = [len(brute_force_cells(grid, K, T, 3, 2, np.where(np.arange(6).reshape(2, 3) == r,
                                                                   z_end, 0.0)))
               for r in range(6)]
    assert len(expected) < sum(per_ray)
    assert grid.count_unknown(z_end.astype(np.float32), K, T) == len(expected)
    # marking: exactly those cells (no skipped cell), and then nothing is unknown
    grid.mark(z_end.astype(np.float32), K, T, trunc_m=0.0)
    np.testing.assert_array_equal(np.argwhere(grid.seen), sorted(expected))
    assert grid.count_unknown(z_end.astype(np.float32), K, T) == 0

    # two identical rays count once: a ray along +z through cell centres, twice
    grid = CoverageGrid((0.0, 0.0, 0.0), (0.6, 0.5, 0.4), 0.1)
    K2 = np.array([[1e12, 0.0, 0.5], [0.0, 1e12, 0.0], [0.0, 0.0, 1.0]])
    T2 = look_at((0.25, 0.25, -1.0), (0.25, 0.25, 0.0), up=(0.0, -1.0, 0.0))
    two = np.zeros((1, 2), np.float32)  # no predicted surface: to the box exit
    assert grid.count_unknown(two, K2, T2) == 4  # the 4 cells of column (2, 2)
    assert grid.count_unknown(two[:, :1], K2, T2) == 4
    # frontier: only the first unseen cell of the column, once for both rays; after the first
    # two cells are seen, the third
    assert grid.count_unknown(two, K2, T2, frontier=True) == 1
    grid.seen[2, 2, :2] = 1
    assert grid.count_unknown(two, K2, T2) == 2
    assert grid.count_unknown(two, K2, T2, frontier=True) == 1
    grid.seen[2, 2, :] = 1
    assert grid.count_unknown(two, K2, T2, frontier=True) == 0


def test_frontier_cells_and_the_tally_of_crossed_cells():
    """count_frontier counts the unseen cells next to seen ones that the rays cross (each
    once); tally counts every crossing of unseen and seen cells (the entropy baseline's sums),
    so two identical rays count twice."""
    grid = CoverageGrid((0.0, 0.0, 0.0), (0.6, 0.5, 0.4), 0.1)
    K2 = np.array([[1e12, 0.0, 0.5], [0.0, 1e12, 0.0], [0.0, 0.0, 1.0]])
    T2 = look_at((0.25, 0.25, -1.0), (0.25, 0.25, 0.0), up=(0.0, -1.0, 0.0))
    two = np.zeros((1, 2), np.float32)  # two rays down column (2, 2), to the box exit
    assert grid.count_frontier(two, K2, T2) == 0  # nothing seen: no frontier
    assert grid.tally(two, K2, T2) == (8, 0)
    grid.seen[2, 2, :2] = 1  # the column's first two cells
    assert grid.count_frontier(two, K2, T2) == 1  # (2, 2, 2): unseen, next to (2, 2, 1)
    assert grid.tally(two, K2, T2) == (4, 4)
    grid.seen[3, 2, 3] = 1  # makes (2, 2, 3) a frontier cell too
    assert grid.count_frontier(two, K2, T2) == 2
    grid.seen[2, 2, :] = 1
    assert grid.count_frontier(two, K2, T2) == 0 and grid.tally(two, K2, T2) == (0, 8)
    # the planning wrapper's average entropy: all seen -> H(P_SEEN), all unseen -> ln 2
    from bftaichi.planning.nbv import P_SEEN, CoverageGrid as PlanGrid

    plan = PlanGrid((0.0, 0.0, 0.0), (0.6, 0.5, 0.4), 6, 0.1, 0.0)
    assert plan.average_entropy(two, K2, T2, 1, 10.0) == pytest.approx(np.log(2.0))
    plan.grid.seen[2, 2, :] = 1
    h = -P_SEEN * np.log(P_SEEN) - (1 - P_SEEN) * np.log(1 - P_SEEN)
    assert plan.average_entropy(two, K2, T2, 1, 10.0) == pytest.approx(h)
    plan.grid.seen[2, 2, 2:] = 0
    assert plan.average_entropy(two, K2, T2, 1, 10.0) == pytest.approx((np.log(2.0) + h) / 2)


@pytest.mark.parametrize("dx, dy", [(0.31, 0.47), (-0.31, 0.47), (0.31, -0.47), (-0.31, -0.47)])
def test_ray_starting_on_a_cell_corner(dx, dy):
    """The camera sits on a cell corner inside the grid: the ray starts in the cell it moves
    into (below the corner along axes it moves down), not in the one floor() names."""
    grid = CoverageGrid((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), 0.1)
    K = np.array([[1.0, 0.0, -dx], [0.0, 1.0, -dy], [0.0, 0.0, 1.0]])  # one pixel: (dx, dy, 1)
    T = look_at((0.2, 0.2, 0.2), (0.2, 0.2, 1.0), up=(0.0, -1.0, 0.0))
    z_end = np.full((1, 1), 0.35)
    expected = brute_force_cells(grid, K, T, 1, 1, z_end)
    assert grid.count_unknown(z_end.astype(np.float32), K, T) == len(expected)
    grid.mark(z_end.astype(np.float32), K, T, trunc_m=0.0)
    np.testing.assert_array_equal(np.argwhere(grid.seen), sorted(expected))


def test_mark_invalid_depth_and_miss_depth():
    grid = CoverageGrid((-0.2, -0.2, 0.0), (0.2, 0.2, 1.0), 0.05)
    K = intrinsics(8, 6, 10.0)
    invalid = np.array([[np.nan, 0.0, -1.0, np.inf] * 2] * 6, np.float32)
    T = look_at((0.0123, -0.0071, -0.05), (0.02, 0.01, 1.0))  # rays off the cell edges
    grid.mark(invalid, K, T, trunc_m=0.05)
    assert grid.seen_count() == 0  # invalid pixels mark nothing by default
    grid.mark(invalid, K, T, trunc_m=0.05, miss_depth_m=0.5)
    expected = brute_force_cells(grid, K, T, 8, 6, 0.5)
    assert len(expected) > 20
    np.testing.assert_array_equal(np.argwhere(grid.seen), sorted(expected))


def test_coverage_grid_validation():
    with pytest.raises(ValueError, match="134217728"):
        CoverageGrid((0, 0, 0), (10, 10, 10), 0.01)  # 10^9 cells
    with pytest.raises(ValueError, match="hi"):
        CoverageGrid((0, 0, 0), (1, 0, 1), 0.1)
    with pytest.raises(ValueError, match="cell_m"):
        CoverageGrid((0, 0, 0), (1, 1, 1), -0.1)
    grid = CoverageGrid((0, 0, 0), (1, 1, 1), 0.1)
    depth = np.ones((4, 4), np.float32)
    K = intrinsics(4, 4, 4.0)
    with pytest.raises(ValueError, match="depth_m"):
        grid.mark(depth[0], K, np.eye(4), trunc_m=0.1)
    with pytest.raises(ValueError, match="trunc_m"):
        grid.mark(depth, K, np.eye(4), trunc_m=-0.1)
    with pytest.raises(ValueError, match="T_W_C"):
        grid.mark(depth, K, np.zeros((4, 4)), trunc_m=0.1)
    with pytest.raises(ValueError, match="stride"):
        grid.count_unknown(depth, K, np.eye(4), stride=0)
    with pytest.raises(ValueError, match="max_depth_m"):
        grid.count_unknown(depth, K, np.eye(4), max_depth_m=0.0)
    with pytest.raises(TypeError, match="depth_pred"):
        grid.count_unknown(depth.astype(complex), K, np.eye(4))
