"""Ray casting of the posterior mean through the band, and the coverage grid of next-best-view
planning (DESIGN.md 3, step 8).

Ray geometry, shared by both parts. Pixel ``(u, v)`` (integers at pixel centres) has the camera
ray ``K^-1 (u, v, 1)``, whose z component is 1: the ray parameter is the camera depth ``z``
(metres along the camera z axis, not along the ray). In a world-aligned grid of cells with edge
``s`` metres whose cell 0 starts at the world point ``origin``, the ray point at depth ``z`` has
grid coordinate ``g(z) = o + z m`` with ``m = R_WC K^-1 (u, v, 1) / s`` and
``o = (t_WC - origin) / s`` (:func:`_ray_params`, :func:`_ray_grid`); it lies in cell
``floor(g)``. A step of ``l`` grid units along the ray is ``l / |m|`` of camera depth.

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
next sample outside the block). *Block cache*: each ray keeps the block of its last sample and
the table rows of the 8 blocks ``b + (0|1, 0|1, 0|1)`` a cell based in it can reach; b's own
row is looked up (one binary search) when the ray enters b, a neighbour's only when a cell on
b's last voxel layer first needs it. A ray thus searches about once per block it passes.

**CoverageGrid** (which space some view has seen). A dense uint8 grid over an axis-aligned box:
``s = cell_m``, ``origin = lo``. A pixel ray is walked from the camera (``z = 0``) to a camera
depth ``z_end``, clipped to the box, by the exact voxel traversal of Amanatides & Woo (1987,
"A fast voxel traversal algorithm for ray tracing"; :func:`_walk_cells`): from the entry cell,
always step across the nearest cell face, so every cell the segment crosses is visited once,
in order, and none is skipped. (A ray through an exact cell edge or corner also visits one of
the cells that only touch it there: ties step one axis at a time, x before y before z.)

Cost (2-core EPYC, both threads): a 160x120 cast of a 68k-voxel sphere shell (1 cm voxels,
r = 0.3 m, 3 voxels either side; camera 1 m away, depths 0.1-3 m, half-voxel steps) takes
~11.5 ms (~22 ms on one thread), 640x480 ~160 ms; its kernel compiles in ~0.5 s (then Taichi's
offline cache serves it). Measured: stepping through empty blocks sample by sample doubles the
time; without the band-box clip a cast took 2.2x as long and a camera looking away 40x as long
(27 ms against 0.7 ms). Measured and not kept: looking all 8 neighbour rows up on entering a
block (1.5x slower), the lazy look-ups unrolled (no faster, 3x the compile time). A
CoverageGrid of 100^3 1 cm cells takes ~4 ms to mark a 160x120 frame and ~12 ms to count a
160x120 view whose rays run to the box exit (stamps are integer atomics).

Determinism: every kernel here is one thread per pixel with pure reads, stores of one value
(``seen = 1``) or integer atomics (``stamp`` maximum, counts), so all results are bitwise
reproducible whatever the thread schedule. No float atomics.
"""

import math

import numpy as np
import taichi as ti

from .lookup import BLOCK, KEY_BIAS
from .observe import _block_row, _cell_corners, _trilinear
from .tsdf import _floor_i32

# Per-call parameters, one float64 vector (a single cheap kernel argument):
P_M = 0  # 9: m-matrix M = R_WC K^-1 / s, row-major: ray direction m = M (u, v, 1), grid units
P_O = 9  # 3: o = (t_WC - origin) / s, the camera centre in grid coordinates
P_ZMIN = 12  # raycast: first sample depth, metres (camera z)
P_ZMAX = 13  # raycast: last sample depth, metres
P_STEP = 14  # raycast: sample spacing along the ray, voxels
P_BOX = 15  # raycast: 6: grid box (lo, hi) of the band's blocks, grid units (module docstring)
N_PARAMS = 21

G_MAX = float(1 << 22)  # |grid coordinate| bound: blocks well inside lookup's KEY_BIAS range
MAX_CELLS = 1 << 27  # CoverageGrid size limit (128 MB of seen, 512 MB of stamps)
_FAR = 1e300  # "no face ahead" depth of an axis the ray does not move along
_UNKNOWN = -2  # block cache: row not looked up yet (-1: looked up, not in the band)


# -- ray geometry -----------------------------------------------------------------------------

@ti.func
def _ray_grid(prm: ti.template(), u: ti.i32, v: ti.i32):
    """Ray direction ``m = M (u, v, 1)`` (float64, grid units per metre of camera depth)."""
    p = ti.Vector([ti.cast(u, ti.f64), ti.cast(v, ti.f64), 1.0])
    return ti.Vector([prm[P_M + 3 * r] * p[0] + prm[P_M + 3 * r + 1] * p[1] + prm[P_M + 3 * r + 2]
                      for r in ti.static(range(3))])


@ti.func
def _ray_origin(prm: ti.template()):
    """Camera centre ``o`` in grid coordinates (float64)."""
    return ti.Vector([prm[P_O], prm[P_O + 1], prm[P_O + 2]])


@ti.func
def _clip_to_box(o, m, lo, hi, z_in: ti.f64, z_out: ti.f64):
    """The part ``(z_in', z_out')`` of the depth interval [z_in, z_out] where the ray
    ``g(z) = o + z m`` is inside the grid box ``lo <= g <= hi`` (slab test); empty when
    ``z_in' >= z_out'``."""
    for a in ti.static(range(3)):
        if m[a] != 0:
            t0 = (lo[a] - o[a]) / m[a]
            t1 = (hi[a] - o[a]) / m[a]
            z_in = ti.max(z_in, ti.min(t0, t1))
            z_out = ti.min(z_out, ti.max(t0, t1))
        elif o[a] < lo[a] or o[a] >= hi[a]:
            z_out = -_FAR  # parallel to the slab and outside it
    return z_in, z_out


# -- ray casting ------------------------------------------------------------------------------

@ti.func
def _sdf_sample(block_table: ti.template(), mean: ti.template(), observed: ti.template(),
                var: ti.template(), with_var: ti.template(), g, c0, b, rows):
    """``(mu, s, valid)`` at grid point g of cell c0 = floor(g): the trilinear mean
    ``sum_c a_c(g - c0) mean[corner c]`` (float64, metres), the same interpolation of ``var``
    (``with_var``; else 0) and 1 if all 8 corners are observed band voxels, else valid 0.
    ``b = c0 // 8``; ``rows`` (8,) holds the table rows of blocks ``b + corner(s)`` (-1: not
    in the band), at least those the cell reaches."""
    idx = _cell_corners(block_table, c0, b, rows)
    valid = ti.cast(idx[7] >= 0, ti.i32)
    mu = ti.cast(0.0, ti.f64)
    s = ti.cast(0.0, ti.f64)
    if valid:
        a = _trilinear(g - ti.cast(c0, ti.f64))
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
    z = ti.cast(_FAR, ti.f64)
    for a in ti.static(range(3)):
        if m[a] > 0:
            z = ti.min(z, (ti.cast(BLOCK * (b[a] + 1), ti.f64) - o[a]) / m[a])
        elif m[a] < 0:
            z = ti.min(z, (ti.cast(BLOCK * b[a], ti.f64) - o[a]) / m[a])
    return z


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
             with_var: ti.template()):
    """Predicted depth (camera z, metres) of every ``stride``-th pixel into ``depth`` (H, W),
    0 where the ray finds no crossing (module docstring, steps 1-3); with ``with_var``, its
    standard deviation into ``sigma`` (step 4). One thread per pixel. Deterministic (pure
    reads, one store per pixel and image)."""
    H, W = depth.shape[0], depth.shape[1]
    o = _ray_origin(prm)
    z_min, z_max = prm[P_ZMIN], prm[P_ZMAX]
    box_lo = ti.Vector([prm[P_BOX], prm[P_BOX + 1], prm[P_BOX + 2]])
    box_hi = ti.Vector([prm[P_BOX + 3], prm[P_BOX + 4], prm[P_BOX + 5]])
    for vs, us in ti.ndrange((H + stride - 1) // stride, (W + stride - 1) // stride):
        u, v = us * stride, vs * stride
        m = _ray_grid(prm, u, v)
        dz = prm[P_STEP] / m.norm()  # step_voxels along the ray, as camera depth
        # samples k = 0..n-1 on the lattice; outside the band's box (base corner in no band
        # block) none is valid, so only k = k0..k1-1 are visited
        n = ti.cast(ti.floor((z_max - z_min) / dz), ti.f64) + 1.0
        z_in, z_out = _clip_to_box(o, m, box_lo, box_hi, z_min, z_max)
        k0 = ti.cast(ti.min(ti.ceil((z_in - z_min) / dz), n), ti.i64)  # z_in >= z_min
        k1 = ti.cast(ti.max(ti.min(ti.floor((z_out - z_min) / dz) + 1.0, n), 0.0), ti.i64)
        cached = ti.Vector([1 << 30, 1 << 30, 1 << 30])  # no block has this coordinate
        rows = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
        prev_valid, prev_mu, prev_z = 0, ti.cast(0.0, ti.f64), ti.cast(0.0, ti.f64)
        prev_s = ti.cast(0.0, ti.f64)
        hit = ti.cast(0.0, ti.f64)
        hit_sigma = ti.cast(0.0, ti.f64)
        k = k0
        while k < k1:
            z = z_min + ti.cast(k, ti.f64) * dz
            g = o + z * m
            c0 = _floor_i32(g)
            b = ti.Vector([c0[0] // BLOCK, c0[1] // BLOCK, c0[2] // BLOCK])
            if (b != cached).any():  # a new block: its own row now, the neighbours' lazily
                cached = b
                rows = ti.Vector([_UNKNOWN] * 8)
                rows[0] = _block_row(block_keys, b[0], b[1], b[2])
            if rows[0] < 0:  # empty block: jump to the first sample beyond it
                k_exit = ti.ceil(ti.min((_block_exit(o, m, b) - z_min) / dz, n))
                k = ti.max(k + 1, ti.cast(k_exit, ti.i64))
                prev_valid = 0
            else:
                # a cell reaches block b + corner(s) only if c0 is on b's last layer along
                # every axis where corner(s) is 1: look such a block up the first time
                # (a run-time loop: one inlined binary search, not seven, keeps compiling fast)
                edge = ti.cast(c0 - b * BLOCK == BLOCK - 1, ti.i32)
                for s in range(1, 8):
                    cs = ti.Vector([(s >> 2) & 1, (s >> 1) & 1, s & 1])
                    if rows[s] == _UNKNOWN and (cs <= edge).all():
                        rows[s] = _block_row(block_keys, b[0] + cs[0], b[1] + cs[1],
                                             b[2] + cs[2])
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


# -- coverage grid ----------------------------------------------------------------------------

@ti.func
def _walk_cells(prm: ti.template(), u: ti.i32, v: ti.i32, z_end: ti.f64, seen: ti.template(),
                stamp: ti.template(), call: ti.i32, counting: ti.template(),
                first_only: ti.template()) -> ti.i32:
    """Visit every grid cell the ray of pixel (u, v) crosses between camera depths 0 and
    ``z_end``, clipped to the grid box, in order (Amanatides & Woo 3D DDA). ``counting`` False:
    store ``seen = 1`` in each (returns 0). ``counting`` True: stamp each unseen cell with
    ``call`` and return how many cells this thread stamped first (``atomic_max`` on the stamp:
    of all threads reaching a cell in one call exactly one sees an older stamp); with
    ``first_only`` the walk ends at the first unseen cell (the ray's *frontier* cell)."""
    n = ti.Vector([seen.shape[0], seen.shape[1], seen.shape[2]])
    o = _ray_origin(prm)
    m = _ray_grid(prm, u, v)
    z_in, z_out = _clip_to_box(o, m, ti.Vector([0.0, 0.0, 0.0], dt=ti.f64),
                               ti.cast(n, ti.f64), 0.0, z_end)
    found = 0
    if z_in < z_out:
        p = o + z_in * m
        c = _floor_i32(p)
        for a in ti.static(range(3)):  # on a face, moving down: the entry cell is below it
            if m[a] < 0 and ti.cast(c[a], ti.f64) == p[a]:
                c[a] -= 1
        c = ti.min(ti.max(c, 0), n - 1)  # entry cell (rounding at the box faces)
        for _ in range(n[0] + n[1] + n[2] + 1):  # a segment crosses at most nx+ny+nz+1 cells
            if ti.static(counting):
                if seen[c[0], c[1], c[2]] == 0:
                    if stamp[c[0], c[1], c[2]] != call:
                        if ti.atomic_max(stamp[c[0], c[1], c[2]], call) < call:
                            found += 1
                    if ti.static(first_only):
                        break
            else:
                seen[c[0], c[1], c[2]] = ti.u8(1)
            # t_next[a]: depth of the next face crossed along axis a
            t_next = ti.Vector([_FAR, _FAR, _FAR], dt=ti.f64)
            for a in ti.static(range(3)):
                if m[a] > 0:
                    t_next[a] = (ti.cast(c[a] + 1, ti.f64) - o[a]) / m[a]
                elif m[a] < 0:
                    t_next[a] = (ti.cast(c[a], ti.f64) - o[a]) / m[a]
            axis, t = 0, t_next[0]  # the axis whose face comes first (ties: x, then y, z)
            if t_next[1] < t:
                axis, t = 1, t_next[1]
            if t_next[2] < t:
                axis, t = 2, t_next[2]
            if t >= z_out:
                break
            inside = 1
            for a in ti.static(range(3)):
                if a == axis:
                    c[a] += ti.select(m[a] > 0, 1, -1)
                    inside = ti.cast((c[a] >= 0) & (c[a] < n[a]), ti.i32)
            if not inside:
                break
    return found


@ti.kernel
def _mark_frame(prm: ti.types.ndarray(dtype=ti.f64, ndim=1),
                depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                stride: ti.i32, trunc_m: ti.f64, miss_depth_m: ti.f64,
                seen: ti.types.ndarray(dtype=ti.u8, ndim=3)):
    """``seen = 1`` on every cell crossed by the ray of each ``stride``-th pixel up to camera
    depth ``D + trunc_m`` (valid depth D > 0) or ``miss_depth_m`` (invalid depth, 0).
    One thread per pixel; stores of the value 1 only, so deterministic."""
    H, W = depth.shape[0], depth.shape[1]
    for vs, us in ti.ndrange((H + stride - 1) // stride, (W + stride - 1) // stride):
        u, v = us * stride, vs * stride
        d = ti.cast(depth[v, u], ti.f64)
        z_end = ti.select(d > 0, d + trunc_m, miss_depth_m)
        if z_end > 0:
            _walk_cells(prm, u, v, z_end, seen, seen, 0, False, False)


@ti.kernel
def _count_view(prm: ti.types.ndarray(dtype=ti.f64, ndim=1),
                depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                stride: ti.i32, max_depth_m: ti.f64,
                seen: ti.types.ndarray(dtype=ti.u8, ndim=3),
                stamp: ti.types.ndarray(dtype=ti.i32, ndim=3), call: ti.i32,
                total: ti.types.ndarray(dtype=ti.i64, ndim=1), first_only: ti.template()):
    """``total[0] +=`` the number of distinct unseen cells crossed by the rays of the
    ``stride``-th pixels up to camera depth ``depth[v, u]`` (if > 0, else ``max_depth_m``);
    with ``first_only``, of the rays' first unseen cells.
    Cells stamped ``call`` count once (``stamp`` must hold values < call before). One thread
    per pixel; integer atomics only, so deterministic."""
    H, W = depth.shape[0], depth.shape[1]
    for vs, us in ti.ndrange((H + stride - 1) // stride, (W + stride - 1) // stride):
        u, v = us * stride, vs * stride
        d = ti.cast(depth[v, u], ti.f64)
        found = _walk_cells(prm, u, v, ti.select(d > 0, d, max_depth_m), seen, stamp, call, True,
                            first_only)
        if found > 0:
            ti.atomic_add(total[0], ti.cast(found, ti.i64))


# -- Python side: validation at the boundary --------------------------------------------------

def _positive(name: str, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} = {value} must be a positive finite number")
    return value


def _stride(stride) -> int:
    if isinstance(stride, bool) or int(stride) != stride or stride < 1:
        raise ValueError(f"stride = {stride} must be a positive integer")
    return int(stride)


def _camera(K, T_W_C) -> tuple[np.ndarray, np.ndarray]:
    """Check an OpenCV pinhole K (3, 3) and a rigid T_W_C (4, 4); return both as float64."""
    K = np.asarray(K, np.float64)
    T = np.asarray(T_W_C, np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or K[1, 0] != 0 or \
            not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                         f"got {K.tolist()}")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_W_C must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]) or \
            np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise ValueError("T_W_C must be a rigid transform (rotation R_WC, last row 0 0 0 1)")
    return K, T


def _ray_params(K: np.ndarray, T_W_C: np.ndarray, origin, cell: float) -> np.ndarray:
    """The float64 parameter vector of the ray geometry: M = R_WC K^-1 / cell,
    o = (t_WC - origin) / cell (module docstring)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    K_inv = np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])
    prm = np.zeros(N_PARAMS, np.float64)
    prm[P_M:P_M + 9] = (T_W_C[:3, :3] @ K_inv / cell).ravel()
    prm[P_O:P_O + 3] = (T_W_C[:3, 3] - np.asarray(origin, np.float64)) / cell
    return prm


def _image(name: str, image) -> np.ndarray:
    """(H, W) float32 depth image, metres, with every invalid pixel (NaN, inf, <= 0) set to 0."""
    image = np.asarray(image)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"{name} must be a non-empty (H, W) image, got shape {image.shape}")
    if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, got dtype {image.dtype}")
    image = image.astype(np.float32)
    return np.where(np.isfinite(image) & (image > 0), image, np.float32(0))


def _grid_corners_reach(prm: np.ndarray, width: int, height: int, z_max: float) -> float:
    """Largest |grid coordinate| of any pixel ray between depth 0 and z_max (g is multilinear
    in (u, v, z), so the extreme is at a corner of the pixel/depth box)."""
    M, o = prm[P_M:P_M + 9].reshape(3, 3), prm[P_O:P_O + 3]
    uv1 = np.array([[u, v, 1.0] for u in (0, width - 1) for v in (0, height - 1)])
    return float(np.abs(o + z_max * uv1 @ M.T).max(initial=np.abs(o).max()))


def _band_box(block_keys: np.ndarray) -> np.ndarray:
    """(lo, hi) float64 (6,): the grid box ``[8 b_min, 8 (b_max + 1)]`` of the blocks in
    ``block_keys`` (per axis; grid units of the trilinear lattice). Cells based outside it
    have no band corner."""
    if len(block_keys) == 0:
        return np.zeros(6)
    mask = (1 << 21) - 1
    k = block_keys.astype(np.int64)
    blocks = np.stack([(k >> 42) & mask, (k >> 21) & mask, k & mask], axis=1) - KEY_BIAS
    return np.concatenate([blocks.min(axis=0) * BLOCK, (blocks.max(axis=0) + 1) * BLOCK]).astype(
        np.float64)


# -- public API -------------------------------------------------------------------------------

def raycast_depth(block_keys: np.ndarray, block_table: np.ndarray, mean: np.ndarray,
                  observed: np.ndarray, voxel_size: float, K: np.ndarray, T_W_C: np.ndarray,
                  width: int, height: int, depth_min_m: float, depth_max_m: float,
                  step_voxels: float = 0.5, stride: int = 1, var: np.ndarray | None = None,
                  slope_min: float = 0.3):
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
        slope_min: floor of that slope (the observation model's ``cos_min``).

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
    if keys.ndim != 1 or table.shape != (len(keys), BLOCK ** 3):
        raise ValueError(f"block_keys {keys.shape} / block_table {table.shape} are not "
                         f"(B,) / (B, {BLOCK ** 3})")
    if mean.ndim != 1 or observed.shape != mean.shape:
        raise ValueError(f"mean {mean.shape} and observed {observed.shape} must both be (N,)")
    if table.size and (table.min() < -1 or table.max() >= len(mean)):
        raise ValueError(f"block_table holds indices outside -1..{len(mean) - 1} "
                         f"(mean has N = {len(mean)})")
    if not np.isfinite(mean).all():
        raise ValueError("mean contains NaN or inf")
    voxel_size = _positive("voxel_size", voxel_size)
    step_voxels = _positive("step_voxels", step_voxels)
    K, T = _camera(K, T_W_C)
    for name, n in (("width", width), ("height", height)):
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ValueError(f"{name} = {n} must be an integer >= 1")
    width, height = int(width), int(height)
    z_min, z_max = float(depth_min_m), float(depth_max_m)
    if not (math.isfinite(z_min) and math.isfinite(z_max) and 0 <= z_min < z_max):
        raise ValueError(f"depth_min_m = {z_min}, depth_max_m = {z_max}: need "
                         "0 <= depth_min_m < depth_max_m, both finite")
    stride = _stride(stride)
    prm = _ray_params(K, T, np.full(3, 0.5 * voxel_size), voxel_size)
    prm[P_ZMIN], prm[P_ZMAX], prm[P_STEP] = z_min, z_max, step_voxels
    prm[P_BOX:P_BOX + 6] = _band_box(keys)
    if _grid_corners_reach(prm, width, height, z_max) >= G_MAX:
        raise ValueError(f"depth_max_m = {z_max}: the rays reach beyond {G_MAX:.0f} voxels of "
                         "the origin (the band index range)")
    depth = np.zeros((height, width), np.float32)
    with_var = var is not None
    if with_var:
        var = np.asarray(var)
        if var.shape != mean.shape or not np.isfinite(var).all():
            raise ValueError(f"var must be a finite (N,) array like mean, got {var.shape}")
        slope_min = _positive("slope_min", slope_min)
    sigma = np.zeros((height, width) if with_var else (1, 1), np.float32)
    var32 = np.ascontiguousarray(var if with_var else np.zeros(1), np.float32)
    if len(keys):
        _raycast(prm, np.ascontiguousarray(keys), np.ascontiguousarray(table, np.int32),
                 np.ascontiguousarray(mean, np.float32),
                 np.ascontiguousarray(observed, np.uint8), stride, depth, var32, sigma,
                 float(slope_min), with_var)
    return (depth, sigma) if with_var else depth


class CoverageGrid:
    """Dense grid of "seen" cells over an axis-aligned box (the region of interest of
    next-best-view planning): a view's rays mark the cells they cross, a candidate view counts
    the unseen cells it would cross (module docstring).

    Args:
        lo, hi: (3,) box corners, world frame, metres, ``hi > lo``.
        cell_m: cell edge, metres. The grid has ``shape = ceil((hi - lo) / cell_m)`` cells per
            axis; cell ``(a, b, c)`` spans ``lo + [a, a + 1) cell_m`` etc., so the grid covers
            the box rounded up to whole cells.

    Attributes: ``seen`` (nx, ny, nz) uint8 (0 unknown, 1 seen), ``lo`` (3,) float64,
    ``cell_m``, ``shape``. At most ``MAX_CELLS`` = 2^27 cells (ValueError beyond); memory is 1
    byte per cell, plus 4 per cell for the stamps of :meth:`count_unknown` (allocated on its
    first call).
    """

    def __init__(self, lo, hi, cell_m: float):
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all()
                                                         and np.isfinite(hi).all()):
            raise ValueError(f"CoverageGrid: lo {lo.shape} and hi {hi.shape} must be finite (3,)")
        if not (hi > lo).all():
            raise ValueError(f"CoverageGrid: hi {hi.tolist()} must exceed lo {lo.tolist()} on "
                             "every axis")
        self.cell_m = _positive("cell_m", cell_m)
        shape = np.ceil((hi - lo) / self.cell_m - 1e-9)  # 1e-9: round ratios such as 0.8 / 0.05
        if shape.prod() > MAX_CELLS:
            raise ValueError(f"CoverageGrid: {' x '.join(f'{n:.0f}' for n in shape)} = "
                             f"{shape.prod():.0f} cells exceeds the limit of {MAX_CELLS} (2^27); "
                             f"use a cell_m larger than {self.cell_m} or a smaller box")
        self.lo = lo
        self.shape = tuple(int(n) for n in shape)
        self.seen = np.zeros(self.shape, np.uint8)
        self._stamp = None
        self._call = 0

    def _view(self, name: str, image, K, T_W_C, stride) -> tuple[np.ndarray, np.ndarray, int]:
        image = _image(name, image)
        K, T = _camera(K, T_W_C)
        stride = _stride(stride)
        prm = _ray_params(K, T, self.lo, self.cell_m)
        return image, prm, stride

    def mark(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray, trunc_m: float,
             stride: int = 1, miss_depth_m: float = 0.0) -> None:
        """Mark as seen every cell the rays of a frame cross inside the box.

        Args:
            depth_m: (H, W) camera depth (z_C), metres; invalid pixels 0, NaN, inf or < 0.
            K: (3, 3) intrinsics. T_W_C: (4, 4) camera-to-world pose.
            trunc_m: a valid pixel with depth D marks up to camera depth ``D + trunc_m``
                (metres, >= 0: the observation reaches that far behind the surface).
            stride: use every ``stride``-th pixel in u and v.
            miss_depth_m: camera depth up to which an invalid pixel marks (metres, >= 0; 0,
                the default, marks nothing: a missing return says little about free space).
        One kernel launch; stores only, deterministic.
        """
        depth, prm, stride = self._view("depth_m", depth_m, K, T_W_C, stride)
        trunc_m, miss_depth_m = float(trunc_m), float(miss_depth_m)
        for name, val in (("trunc_m", trunc_m), ("miss_depth_m", miss_depth_m)):
            if not (math.isfinite(val) and val >= 0):
                raise ValueError(f"{name} = {val} must be a finite number >= 0")
        _mark_frame(prm, depth, stride, trunc_m, miss_depth_m, self.seen)

    def count_unknown(self, depth_pred: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
                      stride: int = 1, max_depth_m: float = math.inf,
                      frontier: bool = False) -> int:
        """Number of distinct unseen cells (``seen == 0``) a candidate view's rays would cross
        (``frontier``: only the first unseen cell of each ray, where it leaves seen space).

        Args:
            depth_pred: (H, W) predicted camera depth (z_C), metres (e.g. :func:`raycast_depth`
                of the candidate): a ray counts cells up to ``depth_pred[v, u]`` where it is
                > 0, else up to ``max_depth_m``.
            K: (3, 3) intrinsics. T_W_C: (4, 4) candidate camera-to-world pose.
            stride: use every ``stride``-th pixel in u and v.
            max_depth_m: reach of rays without a predicted surface, metres (> 0; default inf:
                to where the ray leaves the box).
        Each cell counts once per call however many rays cross it. One kernel launch; integer
        atomics only, deterministic. ``seen`` is not changed.
        """
        depth, prm, stride = self._view("depth_pred", depth_pred, K, T_W_C, stride)
        max_depth_m = float(max_depth_m)
        if not (max_depth_m > 0):  # inf allowed
            raise ValueError(f"max_depth_m = {max_depth_m} must be > 0")
        if self._stamp is None or self._call >= np.iinfo(np.int32).max:
            self._stamp = np.zeros(self.shape, np.int32)  # every stamp < the next call number
            self._call = 0
        self._call += 1
        total = np.zeros(1, np.int64)
        _count_view(prm, depth, stride, min(max_depth_m, _FAR), self.seen, self._stamp,
                    self._call, total, bool(frontier))
        return int(total[0])

    def seen_count(self) -> int:
        """Number of seen cells."""
        return int(np.count_nonzero(self.seen))
