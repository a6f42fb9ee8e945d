"""Ray casting of the posterior mean through the band (DESIGN.md 3, step 8): the predicted
depth of a view. The ray geometry (pixel ray ``g(z) = o + z m`` in grid coordinates) is that of
:mod:`kernels.rays`.

**raycast_depth** (predicted depth of the surface ``mu = 0``). The grid is the lattice of
trilinear cells: ``s = voxel_size``, ``origin = 0.5 voxel_size (1, 1, 1)``, so ``c0 = floor(g)`` is
the cell's base corner voxel and ``f = g - c0`` its fraction, exactly step 3 of
kernels/observe.py (``c0 = floor(x / vs - 0.5)``).

1. Samples at ``z_k = z_min + k dz``, ``k = 0 .. floor((z_max - z_min) / dz)``,
   ``dz = step_voxels / |m|``: ``step_voxels`` voxels apart along the ray, in world metres.
2. A sample is *valid* when all 8 corners ``c0 + (ci, cj, ck)`` are band voxels with
   ``observed != 0``; its value is the trilinear mean ``mu(z_k) = sum_c a_c mean[corner c]``
   (:func:`_sdf_sample`).
3. The depth is that of the first consecutive pair of valid samples with
   ``mu_k > 0 >= mu_(k+1)`` (free space, then surface or behind), the zero of the line through
   them, ``z = z_k + dz mu_k / (mu_k - mu_(k+1))`` (:func:`_zero_crossing`); 0 if there is none.
   A negative-to-positive pair (a back face, or a camera starting inside) never counts, and an
   invalid sample breaks the pair: no surface is guessed across unobserved cells.
   3b. *Entry point*: where a valid sample ``k`` with ``mu_k <= 0`` follows an invalid one (or
   starts the march), the ray's part inside sample k's cell is still observed: the point where
   the ray enters that cell, ``z_e = max(z_(k-1), z_min, entry planes of the cell)``, takes the
   invalid sample's place (trilinear mean there, fraction clipped to [0, 1]); ``mu(z_e) > 0``
   makes ``(z_e, z_k)`` the pair. Without it a surface less than one step inside the observed
   region was missed (a thin observed shell at the edge of what the frames saw).
4. With a variance field (``var``): the depth's standard deviation ``sigma_z = sqrt(s) /
   max(slope, slope_min)``, ``s`` the trilinear variance interpolated to the crossing like the
   depth, ``slope = (mu_k - mu_(k+1)) / dz`` the mean's change per metre of camera depth there.

*Empty-space skipping*, exact: samples that cannot be valid are not visited, and the samples
never leave the lattice ``z_k``, so the result equals that of a march of single steps (tested
against a plain numpy march). (a) *Band box*: the ray is first clipped to the box
``[8 b_min, 8 (b_max + 1)]`` of the band's blocks (:func:`_band_box`; a cell based outside it
has no band corner), and the march runs from the first to the last lattice sample inside it.
(b) *Empty blocks*: a sample's block is ``c0 // 8`` (the 8^3-voxel block of kernels/lookup.py
holding its base corner). If that block holds no band voxel, no sample based in it can be
valid, so the march jumps to the first lattice sample at or beyond the depth where ``g``
leaves the block (:func:`_block_exit`; snapping to the lattice is the "epsilon" that puts the
next sample outside the block). (c) *Blocks without a crossing*: where no cell based in a
band block has an observed corner with ``mean <= 0`` (:func:`_crossing_blocks`), each of its
valid samples has ``mu > 0`` (a convex combination of positive means) and no sample in it can
end a pair or take an entry point; the march visits only its last two lattice samples (the
last sets what the next block's first sample pairs with; two, so that rounding at the exit
face cannot leave the true last one out). *Block cache*: each ray keeps the block of its last
sample and the table rows of the 8 blocks ``b + (0|1, 0|1, 0|1)`` a cell based in it can
reach; b's own row is looked up (one binary search) when the ray enters b, a neighbour's only
when a cell on b's last voxel layer first needs it. A ray thus searches about once per block
it passes.

Cost (2-core EPYC, both threads): a 160x120 cast of a 68k-voxel sphere shell (1 cm voxels,
r = 0.3 m, 3 voxels either side; camera 1 m away, depths 0.1-3 m, half-voxel steps) takes
~11.5 ms (~22 ms on one thread), 640x480 ~160 ms; its kernel compiles in ~0.5 s (then Taichi's
offline cache serves it). Measured: stepping through empty blocks sample by sample doubles the
time; without the band-box clip a cast took 2.2x as long and a camera looking away 40x as long
(27 ms against 0.7 ms). Measured and not kept: looking all 8 neighbour rows up on entering a
block (1.5x slower), the lazy look-ups unrolled (no faster, 3x the compile time).

Determinism: one thread per pixel with pure reads and one store per pixel: bitwise
reproducible whatever the thread schedule. No float atomics.
"""

import math

import numpy as np
import taichi as ti

from .funcs import (block_row, cell_corners, corner_offset, floor_i32, reaches_block,
                    trilinear)
from .layout import BLOCK, BLOCK_VOXELS, band_box, decode_keys
from .rays import (N_RAY_PARAMS, NO_FACE, P_M, P_O, check_camera, check_positive, check_stride,
                   clip_to_box, ray_grid, ray_origin, ray_params)

P_ZMIN = N_RAY_PARAMS  # first sample depth, metres (camera z)
P_ZMAX = N_RAY_PARAMS + 1  # last sample depth, metres
P_STEP = N_RAY_PARAMS + 2  # sample spacing along the ray, voxels
P_BOX = N_RAY_PARAMS + 3  # 6: grid box (lo, hi) of the band's blocks, grid units (module docstring)
N_PARAMS = N_RAY_PARAMS + 9

G_MAX = float(1 << 22)  # |grid coordinate| bound: blocks well inside the block keys' range
_UNKNOWN = -2  # block cache: row not looked up yet (-1: looked up, not in the band)


# -- ray casting ------------------------------------------------------------------------------

@ti.func
def _sdf_sample(block_table: ti.template(), mean: ti.template(), observed: ti.template(),
                var: ti.template(), with_var: ti.template(), g, c0, b, rows):
    """``(mu, s, valid)`` at grid point g of cell c0 = floor(g): the trilinear mean
    ``sum_c a_c(g - c0) mean[corner c]`` (float64, metres), the same interpolation of ``var``
    (``with_var``; else 0) and 1 if all 8 corners are observed band voxels, else valid 0.
    ``b = c0 // 8``; ``rows`` (8,) holds the table rows of blocks ``b + corner(s)`` (-1: not
    in the band), at least those the cell reaches."""
    idx = cell_corners(block_table, c0, b, rows)
    valid = ti.cast(idx[7] >= 0, ti.i32)
    mu = ti.cast(0.0, ti.f64)
    s = ti.cast(0.0, ti.f64)
    if valid:
        a = trilinear(g - ti.cast(c0, ti.f64))
        for c in ti.static(range(8)):
            if observed[idx[c]] == 0:
                valid = 0
            mu += a[c] * ti.cast(mean[idx[c]], ti.f64)
            if ti.static(with_var):
                s += a[c] * ti.cast(var[idx[c]], ti.f64)
    return mu, s, valid


@ti.func
def _zero_crossing(z0: ti.f64, mu0: ti.f64, z1: ti.f64, mu1: ti.f64) -> ti.f64:
    """Depth of the zero of the line through ``(z0, mu0)`` and ``(z1, mu1)``, mu0 > 0 >= mu1."""
    return z0 + (z1 - z0) * mu0 / (mu0 - mu1)


@ti.func
def _block_exit(o, m, b) -> ti.f64:
    """Camera depth where the ray ``g(z) = o + z m`` leaves block b (grid cells
    ``[8 b, 8 b + 8)`` per axis; the ray is inside it)."""
    z = ti.cast(NO_FACE, ti.f64)
    for a in ti.static(range(3)):
        if m[a] > 0:
            z = ti.min(z, (ti.cast(BLOCK * (b[a] + 1), ti.f64) - o[a]) / m[a])
        elif m[a] < 0:
            z = ti.min(z, (ti.cast(BLOCK * b[a], ti.f64) - o[a]) / m[a])
    return z


@ti.func
def _first_sample_beyond(o, m, b, z_min: ti.f64, dz: ti.f64, n: ti.f64) -> ti.i64:
    """Index of the first lattice sample ``z_min + k dz`` at or beyond the depth where the ray
    leaves block b (at most ``n``, the sample count)."""
    return ti.cast(ti.ceil(ti.min((_block_exit(o, m, b) - z_min) / dz, n)), ti.i64)


@ti.kernel
def _raycast(prm: ti.types.ndarray(dtype=ti.f64, ndim=1),
             block_keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
             block_table: ti.types.ndarray(dtype=ti.i32, ndim=2),
             mean: ti.types.ndarray(dtype=ti.f32, ndim=1),
             observed: ti.types.ndarray(dtype=ti.u8, ndim=1),
             stride: ti.i32,
             depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
             var: ti.types.ndarray(dtype=ti.f32, ndim=1),
             sigma: ti.types.ndarray(dtype=ti.f32, ndim=2), slope_min: ti.f64,
             with_var: ti.template(), mask: ti.types.ndarray(dtype=ti.u8, ndim=2),
             masked: ti.i32, crossing: ti.types.ndarray(dtype=ti.u8, ndim=1)):
    """Predicted depth (camera z, metres) of every ``stride``-th pixel into ``depth`` (H, W),
    0 where the ray finds no crossing (module docstring, steps 1-3); with ``with_var``, its
    standard deviation into ``sigma`` (step 4); with ``masked``, only the pixels where
    ``mask`` (H, W) is nonzero (the others 0). One thread per pixel. Deterministic (pure
    reads, one store per pixel and image)."""
    H, W = depth.shape[0], depth.shape[1]
    o = ray_origin(prm)
    z_min, z_max = prm[P_ZMIN], prm[P_ZMAX]
    box_lo = ti.Vector([prm[P_BOX], prm[P_BOX + 1], prm[P_BOX + 2]])
    box_hi = ti.Vector([prm[P_BOX + 3], prm[P_BOX + 4], prm[P_BOX + 5]])
    for vs, us in ti.ndrange((H + stride - 1) // stride, (W + stride - 1) // stride):
        u, v = us * stride, vs * stride
        m = ray_grid(prm, u, v)
        dz = prm[P_STEP] / m.norm()  # step_voxels along the ray, as camera depth
        # samples k = 0..n-1 on the lattice; outside the band's box (base corner in no band
        # block) none is valid, so only k = k0..k1-1 are visited
        n = ti.cast(ti.floor((z_max - z_min) / dz), ti.f64) + 1.0
        z_in, z_out = clip_to_box(o, m, box_lo, box_hi, z_min, z_max)
        k0 = ti.cast(ti.min(ti.ceil((z_in - z_min) / dz), n), ti.i64)  # z_in >= z_min
        k1 = ti.cast(ti.max(ti.min(ti.floor((z_out - z_min) / dz) + 1.0, n), 0.0), ti.i64)
        cached = ti.Vector([1 << 30, 1 << 30, 1 << 30])  # no block has this coordinate
        rows = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
        prev_valid, prev_mu, prev_z = 0, ti.cast(0.0, ti.f64), ti.cast(0.0, ti.f64)
        prev_s = ti.cast(0.0, ti.f64)
        hit = ti.cast(0.0, ti.f64)
        hit_sigma = ti.cast(0.0, ti.f64)
        k = k0
        if masked and mask[v, u] == 0:
            k = k1  # not cast: no march
        while k < k1:
            z = z_min + ti.cast(k, ti.f64) * dz
            g = o + z * m
            c0 = floor_i32(g)
            b = ti.Vector([c0[0] // BLOCK, c0[1] // BLOCK, c0[2] // BLOCK])
            if (b != cached).any():  # a new block: its own row now, the neighbours' lazily
                cached = b
                rows = ti.Vector([_UNKNOWN] * 8)
                rows[0] = block_row(block_keys, b[0], b[1], b[2])
                if rows[0] >= 0 and crossing[rows[0]] == 0:
                    # no cell based here reaches an observed mean <= 0 (step (c) of the
                    # module docstring): only the block's second-to-last sample on is visited
                    k_last = _first_sample_beyond(o, m, b, z_min, dz, n) - 2
                    if k_last > k:
                        k = k_last
                        continue
            if rows[0] < 0:  # empty block: jump to the first sample beyond it
                k = ti.max(k + 1, _first_sample_beyond(o, m, b, z_min, dz, n))
                prev_valid = 0
            else:
                # look a block the cell reaches up the first time (a run-time loop: one
                # inlined binary search, not seven, keeps compiling fast)
                for s in range(1, 8):
                    if rows[s] == _UNKNOWN and reaches_block(c0, b, s):
                        nb = b + corner_offset(s)
                        rows[s] = block_row(block_keys, nb[0], nb[1], nb[2])
                mu, s, valid = _sdf_sample(block_table, mean, observed, var, with_var, g, c0, b,
                                           rows)
                if valid and not prev_valid and mu <= 0:
                    # entering observed cells: the previous sample is unusable, but this
                    # cell's part of the ray between them is observed; its entry point (step
                    # 3b) stands in for the previous sample
                    z_e = ti.max(z - dz, z_min)
                    for ax in ti.static(range(3)):
                        if m[ax] > 0:
                            z_e = ti.max(z_e, (ti.cast(c0[ax], ti.f64) - o[ax]) / m[ax])
                        elif m[ax] < 0:
                            z_e = ti.max(z_e, (ti.cast(c0[ax] + 1, ti.f64) - o[ax]) / m[ax])
                    f_e = ti.min(ti.max(o + z_e * m - ti.cast(c0, ti.f64), 0.0), 1.0)
                    mu_e, s_e, _v = _sdf_sample(block_table, mean, observed, var, with_var,
                                                ti.cast(c0, ti.f64) + f_e, c0, b, rows)
                    if mu_e > 0 and z_e < z:
                        prev_valid, prev_mu, prev_z, prev_s = 1, mu_e, z_e, s_e
                if valid and prev_valid and prev_mu > 0 and mu <= 0:
                    hit = _zero_crossing(prev_z, prev_mu, z, mu)
                    if ti.static(with_var):
                        # sigma_z = sigma_mu / (d mu / d z): the variance at the crossing (the
                        # same linear interpolation), over the mean's slope along the ray
                        t = prev_mu / (prev_mu - mu)
                        s_hit = ti.max(prev_s + t * (s - prev_s), 0.0)
                        slope = ti.max((prev_mu - mu) / (z - prev_z), slope_min)
                        hit_sigma = ti.sqrt(s_hit) / slope
                    break
                prev_valid, prev_mu, prev_z, prev_s = valid, mu, z, s
                k += 1
        depth[v, u] = ti.cast(hit, ti.f32)
        if ti.static(with_var):
            sigma[v, u] = ti.cast(hit_sigma, ti.f32)


@ti.kernel
def _crossing_blocks(block_keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
                     block_table: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     blocks: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     mean: ti.types.ndarray(dtype=ti.f32, ndim=1),
                     observed: ti.types.ndarray(dtype=ti.u8, ndim=1),
                     crossing: ti.types.ndarray(dtype=ti.u8, ndim=1)):
    """``crossing[r] = 1`` for every block (table row r) where a cell based in it has a corner
    that is an observed band voxel with ``mean <= 0``: its own such voxels, and those on the
    first voxel layer of the blocks after it (``blocks``: the rows' block coordinates). One
    thread per table entry, stores of the value 1 only: deterministic."""
    for r, t in ti.ndrange(block_table.shape[0], BLOCK_VOXELS):
        i = block_table[r, t]
        if i >= 0:
            if observed[i] != 0 and mean[i] <= 0:
                crossing[r] = ti.u8(1)
                loc = ti.Vector([t >> 6, (t >> 3) & 7, t & 7])
                for s in range(1, 8):  # the blocks whose cells reach this one's first layer
                    e = corner_offset(s)
                    if ((e == 0) | (loc == 0)).all():
                        row = block_row(block_keys, blocks[r, 0] - e[0], blocks[r, 1] - e[1],
                                        blocks[r, 2] - e[2])
                        if row >= 0:
                            crossing[row] = ti.u8(1)


def _grid_corners_reach(prm: np.ndarray, width: int, height: int, z_max: float) -> float:
    """Largest |grid coordinate| of any pixel ray between depth 0 and z_max (g is multilinear
    in (u, v, z), so the extreme is at a corner of the pixel/depth box)."""
    M, o = prm[P_M:P_M + 9].reshape(3, 3), prm[P_O:P_O + 3]
    uv1 = np.array([[u, v, 1.0] for u in (0, width - 1) for v in (0, height - 1)])
    return float(np.abs(o + z_max * uv1 @ M.T).max(initial=np.abs(o).max()))


# -- public API -------------------------------------------------------------------------------

def raycast_depth(block_keys: np.ndarray, block_table: np.ndarray, mean: np.ndarray,
                  observed: np.ndarray, voxel_size: float, K: np.ndarray, T_W_C: np.ndarray,
                  width: int, height: int, depth_min_m: float, depth_max_m: float,
                  step_voxels: float = 0.5, stride: int = 1, var: np.ndarray | None = None,
                  slope_min: float = 0.3, mask: np.ndarray | None = None,
                  crossing: np.ndarray | None = None):
    """Predicted depth image of the surface ``mean = 0`` seen by a camera (module docstring).

    Args:
        block_keys, block_table: the band lookup of :func:`kernels.lookup.build_block_table`,
            (B,) int64 and (B, 512) integer (band indices 0..N-1 or -1).
        mean: (N,) float posterior mean SDF, metres, positive in front of the surface.
        observed: (N,) uint8 or bool, nonzero where the voxel was observed; a sample counts
            only if all 8 corners of its cell are observed band voxels.
        voxel_size: voxel edge, metres (voxel ``ijk`` has centre ``(ijk + 0.5) voxel_size``).
        K: (3, 3) pinhole intrinsics. T_W_C: (4, 4) camera-to-world pose.
        width, height: image size, pixels.
        depth_min_m, depth_max_m: camera-depth range of the march, metres, 0 <= min < max.
        step_voxels: sample spacing along the ray, voxels (world metres / voxel_size). The
            default 0.5: the trilinear mean is a cubic along each ray piece inside one cell
            (about a voxel long), so half-voxel steps keep the error of the linear crossing
            small and put at least 4 samples across a band 2 voxels thick.
        stride: cast every ``stride``-th pixel in u and v (u % stride == v % stride == 0).
        var: optional (N,) float posterior variance of the SDF, metres^2: also return the
            standard deviation of each predicted depth, ``sigma_z = sqrt(var at the crossing)
            / max(d mu / d z, slope_min)`` (the SDF's uncertainty turned into depth along the
            ray by the mean's slope there: 1 head-on, smaller at grazing angles).
        slope_min: floor of that slope (no unit).
        mask: optional (height, width) bool: cast only the pixels where it is True (the
            others are 0, as if no surface were found): e.g. the pixels a caller will keep.
        crossing: optional (B,) uint8, :func:`crossing_blocks` of these block_keys,
            block_table, mean and observed (computed here when None): a caller casting many
            views of one band computes it once.

    Returns:
        (height, width) float32 camera depth (z_C) of the first front-facing zero crossing,
        metres; 0 where there is none and at the pixels skipped by ``stride``. With ``var``:
        ``(depth, sigma_z)``, sigma_z (height, width) float32 metres (0 where depth is 0).

    Raises ValueError/TypeError naming the argument. One kernel launch, deterministic.
    """
    keys = np.asarray(block_keys)
    table = np.asarray(block_table)
    mean = np.asarray(mean)
    observed = np.asarray(observed)
    if keys.dtype != np.int64:
        raise TypeError(f"block_keys must be int64 (build_block_table), got {keys.dtype}")
    if not np.issubdtype(table.dtype, np.integer):
        raise TypeError(f"block_table must be an integer array, got {table.dtype}")
    if not np.issubdtype(mean.dtype, np.floating):
        raise TypeError(f"mean must be a float array, got {mean.dtype}")
    if observed.dtype not in (np.uint8, np.bool_):
        raise TypeError(f"observed must be uint8 or bool, got {observed.dtype}")
    if keys.ndim != 1 or table.shape != (len(keys), BLOCK_VOXELS):
        raise ValueError(f"block_keys {keys.shape} / block_table {table.shape} are not "
                         f"(B,) / (B, {BLOCK_VOXELS})")
    if mean.ndim != 1 or observed.shape != mean.shape:
        raise ValueError(f"mean {mean.shape} and observed {observed.shape} must both be (N,)")
    if table.size and (table.min() < -1 or table.max() >= len(mean)):
        raise ValueError(f"block_table holds indices outside -1..{len(mean) - 1} "
                         f"(mean has N = {len(mean)})")
    if not np.isfinite(mean).all():
        raise ValueError("mean contains NaN or inf")
    voxel_size = check_positive("voxel_size", voxel_size)
    step_voxels = check_positive("step_voxels", step_voxels)
    K, T = check_camera(K, T_W_C)
    for name, n in (("width", width), ("height", height)):
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ValueError(f"{name} = {n} must be an integer >= 1")
    width, height = int(width), int(height)
    z_min, z_max = float(depth_min_m), float(depth_max_m)
    if not (math.isfinite(z_min) and math.isfinite(z_max) and 0 <= z_min < z_max):
        raise ValueError(f"depth_min_m = {z_min}, depth_max_m = {z_max}: need "
                         "0 <= depth_min_m < depth_max_m, both finite")
    stride = check_stride(stride)
    prm = ray_params(K, T, np.full(3, 0.5 * voxel_size), voxel_size, N_PARAMS)
    prm[P_ZMIN], prm[P_ZMAX], prm[P_STEP] = z_min, z_max, step_voxels
    prm[P_BOX:P_BOX + 6] = band_box(keys)
    if _grid_corners_reach(prm, width, height, z_max) >= G_MAX:
        raise ValueError(f"depth_max_m = {z_max}: the rays reach beyond {G_MAX:.0f} voxels of "
                         "the origin (the band index range)")
    depth = np.zeros((height, width), np.float32)
    with_var = var is not None
    if with_var:
        var = np.asarray(var)
        if var.shape != mean.shape or not np.isfinite(var).all():
            raise ValueError(f"var must be a finite (N,) array like mean, got {var.shape}")
        slope_min = check_positive("slope_min", slope_min)
    sigma = np.zeros((height, width) if with_var else (1, 1), np.float32)
    var32 = np.ascontiguousarray(var if with_var else np.zeros(1), np.float32)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (height, width) or mask.dtype != np.bool_:
            raise ValueError(f"mask must be a ({height}, {width}) bool array, got "
                             f"{mask.shape} {mask.dtype}")
    mask8 = np.ascontiguousarray(np.zeros((1, 1), np.uint8) if mask is None else mask, np.uint8)
    if len(keys):
        keys, table = np.ascontiguousarray(keys), np.ascontiguousarray(table, np.int32)
        mean32 = np.ascontiguousarray(mean, np.float32)
        observed8 = np.ascontiguousarray(observed, np.uint8)
        if crossing is None:
            crossing = crossing_blocks(keys, table, mean32, observed8)
        crossing = np.asarray(crossing)
        if crossing.shape != keys.shape or crossing.dtype != np.uint8:
            raise ValueError(f"crossing must be a ({len(keys)},) uint8 array "
                             f"(crossing_blocks), got {crossing.shape} {crossing.dtype}")
        _raycast(prm, keys, table, mean32, observed8, stride, depth, var32, sigma,
                 float(slope_min), with_var, mask8, int(mask is not None),
                 np.ascontiguousarray(crossing))
    return (depth, sigma) if with_var else depth


def crossing_blocks(block_keys: np.ndarray, block_table: np.ndarray, mean: np.ndarray,
                    observed: np.ndarray) -> np.ndarray:
    """(B,) uint8: 1 for every block of the band lookup (:func:`raycast_depth`'s arguments)
    where a cell based in it has an observed corner with ``mean <= 0``, the blocks whose
    samples the march may not skip (module docstring, step (c))."""
    keys = np.ascontiguousarray(block_keys, np.int64)
    crossing = np.zeros(len(keys), np.uint8)
    if len(keys):
        _crossing_blocks(keys, np.ascontiguousarray(block_table, np.int32),
                         decode_keys(keys).astype(np.int32),
                         np.ascontiguousarray(mean, np.float32),
                         np.ascontiguousarray(observed, np.uint8), crossing)
    return crossing
