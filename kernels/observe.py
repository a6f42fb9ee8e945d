"""Depth observations accumulated into the 27-point data stencil (DESIGN.md 3, steps 3-4).

For every frame and every ``stride``-th valid pixel ``(u, v)`` with depth ``D`` (metres):

1. **Normal** ``n`` (:func:`_pixel_normal`): the pixel and its neighbours ``r`` pixels to the
   left/right and up/down (``r = normal_radius_px``) are back-projected, ``P = D K^-1 (u, v, 1)``.
   A neighbour counts if its depth is valid and differs from ``D`` by at most
   ``r D tan(normal_max_slope) / f`` (``f = fx`` along u, ``fy`` along v): the depth change of a
   surface inclined by ``normal_max_slope`` from the image plane; a larger jump is taken as an
   occlusion edge (the neighbour lies on another surface). Tangents are central
   differences ``P(u+r) - P(u-r)`` where both neighbours count, one-sided differences where one
   does; ``n = t_u x t_v`` normalised and flipped to face the camera (``n . ray < 0``). Where an
   axis has no usable neighbour, or the tangents are parallel, ``n = -ray / |ray|`` (the
   *fallback*: the pixel is treated as seen head-on). The default slope limit, 85 deg, keeps
   grazing but real surfaces (their samples get little weight anyway, step 4) and does not
   depend on the image resolution.
2. **Samples** at camera depths ``z_j = D + j * spacing``, ``j = -m..m``,
   ``m = floor(tau / spacing)``, on the pixel ray (``z_j <= 0`` is skipped; it cannot happen for
   ``D > tau``). The sample point is ``x_j = t_WC + z_j R_WC K^-1 (u, v, 1)`` (world, metres), its
   observation ``y_j = <n, x_j - p> = (z_j - D) <n, K^-1 (u, v, 1)>``: the signed distance of
   ``x_j`` to the plane through ``p`` with normal ``n``, positive in front of the surface. It is
   *not* clamped: ``|y_j| <= tau |K^-1 (u, v, 1)|``, up to ~1.25 tau in image corners.
3. **Row** ``a_j``: trilinear weights of ``x_j`` over the cell whose corners are the voxel
   centres ``(ijk + 0.5) * voxel_size`` around it: base corner ``c0 = floor(x_j / voxel_size -
   0.5)``, fraction ``f = x_j / voxel_size - 0.5 - c0``, corner ``c0 + (ci, cj, ck)`` has weight
   ``prod(f if c else 1 - f)``; corner ``c = 4 ci + 2 cj + ck``. A sample is *accepted* when all
   8 corners are band voxels, otherwise *dropped* (counted).
   3b. **Side gate** (optional: a reference SDF per band voxel, e.g. the bootstrap TSDF, and
   ``gate_m > 0``): the reference interpolated at the sample, ``t = sum_c a_c ref_c``, must not
   contradict the sample's side of the surface by more than the gate: a sample behind
   (``y < 0``) with ``t > gate_m``, or in front (``y > 0``) with ``t < -gate_m``, is *gated*
   (counted, not accepted). A corner without a reference value (NaN) keeps the sample. This
   drops the samples whose cell straddles an occlusion edge: behind a foreground pixel at the
   silhouette, the cell reaches into the free space beside the object, which the reference
   saw as free.
4. **Noise**: ``sigma^2 = sigma_depth(D, angle)^2 + sigma_pose^2 + sigma_model^2`` with the
   Kinect-style axial model divided by the incidence cosine,
   ``sigma_depth = (a + b (D - z0)^2) / max(cos(angle), cos_min)``, ``cos(angle) = -n . ray /
   |ray|``. All samples of a pixel share one depth error, so the pixel's information is counted
   once: each of its ``n_acc`` accepted samples gets ``w = 1 / (n_acc sigma^2)`` (the samples are
   counted first, then accumulated), so ``sum_j w_j = 1 / sigma^2`` per pixel.
5. **Accumulation**: ``Q += w a a^T``, ``h += w y a``. Entry ``(c, c')`` of ``a a^T`` joins corner
   voxels whose offset ``corner(c') - corner(c)`` is in ``{-1, 0, 1}^3``, i.e. stencil offset
   ``o = (di+1) 9 + (dj+1) 3 + (dk+1)`` of the row of corner ``c``. Only the upper half
   (``c <= c'``, which is ``o >= 13``) is accumulated; :meth:`Observer.finalize` fills
   ``S[i, o] = S[nbr(i, o), 26 - o]`` for ``o < 13``, so the stencil is symmetric bit for bit.

Fixed point (determinism without float atomics): every contribution ``x`` is added to int64
accumulators as ``round(x * scale)`` (round half away from zero), ``scale = 2^FRACTION_BITS /
w_max`` rounded down to a power of two, ``w_max = 1 / (a^2 + sigma_pose^2 + sigma_model^2)``
the largest possible weight (sigma_depth >= a; a frame's sigma_pose may not go below the
Observer's). A contribution to ``S`` is at most ``w_max`` (``w <= w_max``,
``a_c a_c' <= 1``), i.e. at most 2^32 units; its rounding error is at most 2^-33 w_max, far below
the float32 resolution of any entry it lands in. An entry may grow to ``SATURATION = 2^62``
units, i.e. 2^30 (10^9) maximal contributions, before an add to it is counted as *saturated*;
increments are at most 2^32 units (2^32 |y| / metre for ``h``), so an entry can only wrap
around at 2^63 after being counted: a saturation count of 0 guarantees exact sums. Integer
addition is associative, so the accumulated arrays are bitwise identical whatever the thread
schedule (and whatever the order of the frames).

Layout of the accumulators: ``S_acc`` (N, 14) int64, column ``o - 13`` for ``o = 13..26``;
``h_acc`` (N,) int64. Per-row counters (no atomics): ``counts`` (rows, N_COUNTS) int64.

Cost (one frame = one launch, parallel over pixel rows): per pixel a normal (5 depth reads),
per sample a cell lookup and, if accepted, 36 + 8 int64 atomic adds (the upper half of
``a a^T`` and ``a y``). The lookup reads the block table through a per-row cache of the 8
blocks around sample j's block (one cache per sample index j: sample j of the next pixels of a
row stays in the same blocks for many pixels), so binary searches are rare. Measured on a
sphere band of 200k voxels (1 cm voxels, tau = 2 voxels: 5 samples per pixel), 640x480 frames
with 185k valid pixels, one thread of a 2-core EPYC: ~70 ns per sample for normals and lookups
and ~130 ns for the adds (~200 ms per frame at stride 1, ~55 ms at stride 2); the two threads
share it with little loss. Measured and not kept: summing the samples that fall into a row's
previous cell before the atomics (-10 % at stride 1, slower at stride 2, 3x the compile time),
an unrolled corner loop (no gain).
"""

import math

import numpy as np
import taichi as ti

from .lookup import BLOCK, KEY_BIAS, band_index, block_key, find_block
from .tsdf import _floor_i32

FRACTION_BITS = 32  # one maximal-weight contribution = 2^32 fixed-point units
SATURATION = 1 << 62  # |entry| beyond this (before an add) is counted as saturated
N_HALF = 14  # accumulated stencil columns: offsets o = 13..26

# Per-frame parameters, one float64 vector (a single cheap kernel argument):
P_M = 0  # 9: M = R_WC K^-1 / voxel_size, row-major: pixel (u, v) at depth z is at voxel
P_O = 9  # 3:    coordinate g = o + z M (u, v, 1), o = t_WC / voxel_size - 0.5 (corner c0 = floor g)
P_R = 12  # 9: R_WC, row-major (normals to the world frame)
P_K = 21  # 4: fx, fy, cx, cy (pixels)
P_SPACING = 25  # sample spacing along the camera z axis, metres
P_A = 26  # depth model a, metres
P_B = 27  # depth model b, 1/metre
P_Z0 = 28  # depth model z0, metres
P_COS_MIN = 29  # floor of the incidence cosine
P_VAR_EXTRA = 30  # sigma_pose^2 + sigma_model^2, metres^2
P_RADIUS = 31  # normal tangent offset r, pixels
P_JUMP = 32  # tan(normal_max_slope): neighbour depth jump limit is r D tan / f
P_SCALE = 33  # fixed-point units per unit of S / h
P_SHARE = 34  # most samples of one pixel that share a depth error in one voxel's estimate
P_GATE = 35  # side gate: largest contradiction of y's side by the reference SDF, metres (0: off)
N_PARAMS = 36

# Per-row counters (columns of `counts`):
C_VALID = 0  # strided pixels with valid depth
C_USED = 1  # ... of which at least one sample was accepted
C_ACCEPTED = 2  # accepted samples
C_DROPPED = 3  # samples dropped because a corner of their cell is not in the band
C_SATURATED = 4  # accumulator adds that started beyond SATURATION
C_FALLBACK = 5  # used pixels whose normal fell back to the ray direction
C_GATED = 6  # samples rejected by the reference gate (all corners in the band)
N_COUNTS = 7
COUNT_NAMES = ("pixels_valid", "pixels_used", "samples_accepted", "samples_dropped", "saturated",
               "normal_fallbacks", "samples_gated")

# Row status in frame_rows:
ROW_NONE = 0  # no sample (pixel invalid or z <= 0)
ROW_ACCEPTED = 1
ROW_DROPPED = 2
ROW_GATED = 3  # all corners in the band, rejected by the reference gate


def _corner(c: int) -> tuple[int, int, int]:
    """Offset (ci, cj, ck) in {0, 1}^3 of cell corner c = 4 ci + 2 cj + ck."""
    return (c >> 2) & 1, (c >> 1) & 1, c & 1


def _column(ca: int, cb: int) -> int:
    """Accumulator column ``o - 13`` of the entry between corners ca <= cb, o being the stencil
    offset of ``corner(cb) - corner(ca)``."""
    d = [x - y for x, y in zip(_corner(cb), _corner(ca))]
    return (d[0] + 1) * 9 + (d[1] + 1) * 3 + (d[2] + 1) - 13


def stencil_offset(o: int) -> tuple[int, int, int]:
    """Voxel offset (di, dj, dk) in {-1, 0, 1}^3 of stencil offset
    o = (di+1) 9 + (dj+1) 3 + (dk+1)."""
    return o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1


# -- per-pixel and per-sample math ------------------------------------------------------------

@ti.func
def _ray_C(prm: ti.template(), u: ti.i32, v: ti.i32):
    """K^-1 (u, v, 1), float32 (camera frame, z = 1: a point at depth z is z times this)."""
    fx, fy = ti.cast(prm[P_K], ti.f32), ti.cast(prm[P_K + 1], ti.f32)
    cx, cy = ti.cast(prm[P_K + 2], ti.f32), ti.cast(prm[P_K + 3], ti.f32)
    return ti.Vector([(ti.cast(u, ti.f32) - cx) / fx, (ti.cast(v, ti.f32) - cy) / fy, 1.0])


@ti.func
def _pixel_normal(depth: ti.template(), prm: ti.template(), u: ti.i32, v: ti.i32):
    """Camera-frame unit normal of valid pixel (u, v) facing the camera, and a fallback flag:
    ``(nx, ny, nz, fallback)`` float32 (module docstring, step 1)."""
    H, W = depth.shape[0], depth.shape[1]
    r = ti.cast(prm[P_RADIUS], ti.i32)
    d = depth[v, u]
    reach = ti.cast(prm[P_JUMP], ti.f32) * d * ti.cast(r, ti.f32)
    jump_u = reach / ti.cast(prm[P_K], ti.f32)  # r D tan(max slope) / fx
    jump_v = reach / ti.cast(prm[P_K + 1], ti.f32)
    ray = _ray_C(prm, u, v)
    p = d * ray
    # t = P(+r) - P(-r), with P(+-r) replaced by p where that neighbour is unusable
    p_r, p_l, p_d, p_u = p, p, p, p
    n_u, n_v = 0, 0  # usable neighbours per axis
    if u + r < W:
        dn = depth[v, u + r]
        if dn > 0 and ti.abs(dn - d) <= jump_u:
            p_r = dn * _ray_C(prm, u + r, v)
            n_u += 1
    if u - r >= 0:
        dn = depth[v, u - r]
        if dn > 0 and ti.abs(dn - d) <= jump_u:
            p_l = dn * _ray_C(prm, u - r, v)
            n_u += 1
    if v + r < H:
        dn = depth[v + r, u]
        if dn > 0 and ti.abs(dn - d) <= jump_v:
            p_d = dn * _ray_C(prm, u, v + r)
            n_v += 1
    if v - r >= 0:
        dn = depth[v - r, u]
        if dn > 0 and ti.abs(dn - d) <= jump_v:
            p_u = dn * _ray_C(prm, u, v - r)
            n_v += 1
    t_u = p_r - p_l
    t_v = p_d - p_u
    n = t_u.cross(t_v)
    nn = n.norm()
    fallback = 1.0
    if n_u > 0 and n_v > 0 and nn > 1e-6 * t_u.norm() * t_v.norm():  # sin(t_u, t_v) > 1e-6
        n = n / nn
        if n.dot(ray) > 0:
            n = -n
        fallback = 0.0
    else:
        n = -ray / ray.norm()
    return ti.Vector([n[0], n[1], n[2], fallback])


@ti.func
def _block_row(block_keys: ti.template(), bi: ti.i32, bj: ti.i32, bk: ti.i32) -> ti.i32:
    """Row of block (bi, bj, bk) in the block table, or -1."""
    return find_block(block_keys, block_key(ti.cast(bi, ti.i64), ti.cast(bj, ti.i64),
                                            ti.cast(bk, ti.i64)))


@ti.func
def _block_rows(block_keys: ti.template(), b):
    """Table rows (8,) int32 of blocks ``b + corner(s)``, s = 0..7 (-1: not in the band): every
    block a cell with its base corner in block b can reach."""
    rows = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
    for s in range(8):
        rows[s] = _block_row(block_keys, b[0] + ((s >> 2) & 1), b[1] + ((s >> 1) & 1),
                             b[2] + (s & 1))
    return rows


@ti.func
def _cell_corners(block_table: ti.template(), c0, b, rows):
    """Band indices (8,) int32 of the corners ``c0 + corner(c)`` of the cell with base corner
    c0, given its block ``b = c0 // 8`` and :func:`_block_rows` of b. Stops at the first corner
    outside the band (it and the later ones are -1). Table reads only; the run-time corner loop
    keeps the compiled code (and Taichi's compile time) small."""
    loc = c0 - b * BLOCK
    idx = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
    for c in range(8):
        lc = loc + ti.Vector([(c >> 2) & 1, (c >> 1) & 1, c & 1])
        up = ti.cast(lc >= BLOCK, ti.i32)  # corner in the next block along that axis
        row = rows[up[0] * 4 + up[1] * 2 + up[2]]
        lc -= up * BLOCK
        found = -1
        if row >= 0:
            found = block_table[row, lc[0] * 64 + lc[1] * 8 + lc[2]]
        idx[c] = found
        if found < 0:
            break
    return idx


@ti.func
def _trilinear(f):
    """The 8 trilinear weights (float64) of fraction f in [0, 1)^3, corner c = 4 ci + 2 cj + ck."""
    w = ti.Matrix([[1.0 - f[0], f[0]], [1.0 - f[1], f[1]], [1.0 - f[2], f[2]]], dt=ti.f64)
    return ti.Vector([w[0, ti.static(_corner(c)[0])] * w[1, ti.static(_corner(c)[1])]
                      * w[2, ti.static(_corner(c)[2])] for c in ti.static(range(8))], dt=ti.f64)


@ti.func
def _fixed(x: ti.f64) -> ti.i64:
    """round(x) half away from zero, as int64 (no libm call)."""
    return ti.cast(x + ti.select(x >= 0, 0.5, -0.5), ti.i64)


# -- kernels ----------------------------------------------------------------------------------

@ti.kernel
def _observe_frame(depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                   prm: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   block_keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
                   block_table: ti.types.ndarray(dtype=ti.i32, ndim=2),
                   ref: ti.types.ndarray(dtype=ti.f32, ndim=1),
                   stride: ti.i32, m: ti.i32, mf: ti.i32,
                   S_acc: ti.types.ndarray(dtype=ti.i64, ndim=2),
                   h_acc: ti.types.ndarray(dtype=ti.i64, ndim=1),
                   counts: ti.types.ndarray(dtype=ti.i64, ndim=2),
                   scratch: ti.types.ndarray(dtype=ti.i32, ndim=3),
                   blocks: ti.types.ndarray(dtype=ti.i32, ndim=3),
                   row_idx: ti.types.ndarray(dtype=ti.i32, ndim=2),
                   row_a: ti.types.ndarray(dtype=ti.f64, ndim=2),
                   row_y: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   row_w: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   row_z: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   row_status: ti.types.ndarray(dtype=ti.i32, ndim=1),
                   to_rows: ti.i32):
    """One frame, parallel over strided pixel rows (module docstring, steps 1-5). Each pixel
    first counts its accepted samples, then (``to_rows`` False) adds them to ``S_acc``/``h_acc``
    with int64 atomics, or (``to_rows`` True) writes every sample to the ``row_*`` arrays at row
    ``(pixel slot) * (mf + m + 1) + (j + mf)``, pixel slot ``(v / stride) * ceil(W / stride) + u /
    stride``, touching no accumulator. Per-row counters go to ``counts[v / stride]``;
    ``scratch`` (rows, mf + m + 1, 8) holds the corner indices of the pixel a row thread is on,
    ``blocks`` (rows, mf + m + 1, 11) each row's block cache per sample index (block, 8 rows).

    Determinism: integer atomics only; the accumulated values and the rows are bitwise
    reproducible."""
    H, W = depth.shape[0], depth.shape[1]
    n_us = (W + stride - 1) // stride
    M = ti.Matrix([[prm[P_M + 3 * r + c] for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    o = ti.Vector([prm[P_O], prm[P_O + 1], prm[P_O + 2]])
    spacing = prm[P_SPACING]
    scale = prm[P_SCALE]
    cos_min = prm[P_COS_MIN]
    gate = prm[P_GATE]
    ti.loop_config(block_dim=4)  # rows differ in valid pixels: small chunks balance threads
    for vs in range((H + stride - 1) // stride):
        v = vs * stride
        n_valid, n_used, n_acc_row, n_drop, n_sat, n_fb, n_gate = 0, 0, 0, 0, 0, 0, 0
        for jj in range(mf + m + 1):
            blocks[vs, jj, 0] = 1 << 30  # no block has this coordinate: empty cache
        for us in range(n_us):
            u = us * stride
            d = depth[v, u]
            if d > 0:
                n_valid += 1
                nf = _pixel_normal(depth, prm, u, v)
                n_C = ti.Vector([nf[0], nf[1], nf[2]])
                ray = _ray_C(prm, u, v)
                n_dot_ray = ti.cast(n_C.dot(ray), ti.f64)  # = -cos(angle) |ray| <= 0
                cos_a = -n_dot_ray / ti.cast(ray.norm(), ti.f64)
                D = ti.cast(d, ti.f64)
                sd = (prm[P_A] + prm[P_B] * (D - prm[P_Z0]) ** 2) / ti.max(cos_a, cos_min)
                inv_var = 1.0 / (sd * sd + prm[P_VAR_EXTRA])  # 1 / sigma^2 of the pixel
                m_ray = M @ ti.Vector([ti.cast(u, ti.f64), ti.cast(v, ti.f64), 1.0])
                # pass 0 looks the cells up and counts the pixel's accepted samples n_acc (the
                # corner indices wait in this row's scratch); pass 1 adds the accepted samples
                # (or writes rows) with w = 1 / (n_acc sigma^2).
                n_acc = 0
                for j in range(-mf, m + 1):
                    z = D + ti.cast(j, ti.f64) * spacing
                    if z > 0:
                        c0 = _floor_i32(o + z * m_ray)
                        b = ti.Vector([c0[0] // BLOCK, c0[1] // BLOCK, c0[2] // BLOCK])
                        # block cache per sample index j: sample j of the next pixels in the
                        # row is mostly in the same block (8 voxels = many pixels)
                        cached = ti.Vector([blocks[vs, j + mf, t] for t in ti.static(range(3))])
                        if (b != cached).any():
                            rows = _block_rows(block_keys, b)
                            for t in ti.static(range(3)):
                                blocks[vs, j + mf, t] = b[t]
                            for t in ti.static(range(8)):
                                blocks[vs, j + mf, 3 + t] = rows[t]
                        idx = _cell_corners(block_table, c0, b, ti.Vector(
                            [blocks[vs, j + mf, 3 + t] for t in ti.static(range(8))]))
                        gated = 0
                        if idx[7] >= 0 and gate > 0:
                            # step 3b: the reference SDF interpolated at the sample must not
                            # put it on the other side of the surface by more than the gate
                            g = o + z * m_ray
                            a = _trilinear(g - ti.cast(c0, ti.f64))
                            t_ref = ti.f64(0.0)
                            for c in ti.static(range(8)):
                                t_ref += a[c] * ti.cast(ref[idx[c]], ti.f64)
                            y = ti.cast(j, ti.f64) * spacing * n_dot_ray
                            # NaN (a corner without reference) fails both tests: kept
                            if (y < 0 and t_ref > gate) or (y > 0 and t_ref < -gate):
                                gated = 1
                        for c in ti.static(range(8)):
                            scratch[vs, j + mf, c] = idx[c]
                        if gated:
                            scratch[vs, j + mf, 7] = -2
                            n_gate += 1
                        elif idx[7] >= 0:
                            n_acc += 1
                        else:
                            n_drop += 1
                if n_acc > 0 or to_rows:
                    w = inv_var / ti.min(ti.cast(ti.max(n_acc, 1), ti.f64), prm[P_SHARE])
                    ws = w * scale
                    for j in range(-mf, m + 1):
                        delta = ti.cast(j, ti.f64) * spacing
                        z = D + delta
                        if z <= 0:
                            continue
                        g = o + z * m_ray
                        c0 = _floor_i32(g)
                        a = _trilinear(g - ti.cast(c0, ti.f64))
                        y = delta * n_dot_ray  # <n, x - p>, x - p = delta K^-1 (u, v, 1)
                        idx = ti.Vector([scratch[vs, j + mf, c] for c in ti.static(range(8))])
                        accepted = idx[7] >= 0
                        if to_rows:
                            r = (vs * n_us + us) * (mf + m + 1) + mf + j
                            row_status[r] = ti.select(accepted, ROW_ACCEPTED, ti.select(
                                idx[7] == -2, ROW_GATED, ROW_DROPPED))
                            row_y[r] = y
                            row_w[r] = ti.select(accepted, w, 0.0)
                            row_z[r] = z
                            for c in ti.static(range(8)):
                                row_idx[r, c] = idx[c]
                                row_a[r, c] = a[c]
                        elif accepted:
                            for ca in ti.static(range(8)):
                                wa = ws * a[ca]
                                for cb in ti.static(range(ca, 8)):
                                    old = ti.atomic_add(S_acc[idx[ca], ti.static(_column(ca, cb))],
                                                        _fixed(wa * a[cb]))
                                    if old > ti.i64(SATURATION):
                                        n_sat += 1
                                old = ti.atomic_add(h_acc[idx[ca]], _fixed(wa * y))
                                if old > ti.i64(SATURATION) or old < -ti.i64(SATURATION):
                                    n_sat += 1
                if n_acc > 0:
                    n_used += 1
                    n_acc_row += n_acc
                    if nf[3] > 0:
                        n_fb += 1
        counts[vs, C_VALID] = n_valid
        counts[vs, C_USED] = n_used
        counts[vs, C_ACCEPTED] = n_acc_row
        counts[vs, C_DROPPED] = n_drop
        counts[vs, C_SATURATED] = n_sat
        counts[vs, C_FALLBACK] = n_fb
        counts[vs, C_GATED] = n_gate


@ti.kernel
def _frame_normals(depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                   prm: ti.types.ndarray(dtype=ti.f64, ndim=1),
                   normals: ti.types.ndarray(dtype=ti.f32, ndim=3),
                   fallback: ti.types.ndarray(dtype=ti.i32, ndim=2)):
    """World-frame unit normals (H, W, 3) of every valid pixel (0 elsewhere) and their fallback
    flags (1 = ray direction used). Deterministic (one thread per pixel, no atomics)."""
    R = ti.Matrix([[ti.cast(prm[P_R + 3 * r + c], ti.f32) for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    for v, u in ti.ndrange(depth.shape[0], depth.shape[1]):
        n_W = ti.Vector([0.0, 0.0, 0.0])
        fb = 0
        if depth[v, u] > 0:
            nf = _pixel_normal(depth, prm, u, v)
            n_W = R @ ti.Vector([nf[0], nf[1], nf[2]])
            fb = ti.cast(nf[3], ti.i32)
        for c in ti.static(range(3)):
            normals[v, u, c] = n_W[c]
        fallback[v, u] = fb


@ti.kernel
def _finalize(block_keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
              block_table: ti.types.ndarray(dtype=ti.i32, ndim=2),
              ijk: ti.types.ndarray(dtype=ti.i32, ndim=2),
              S_acc: ti.types.ndarray(dtype=ti.i64, ndim=2),
              h_acc: ti.types.ndarray(dtype=ti.i64, ndim=1),
              inv_scale: ti.f64,
              S: ti.types.ndarray(dtype=ti.f32, ndim=2),
              h: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    """Fixed point -> float32 stencil: ``S[i, o] = S_acc[i, o - 13] / scale`` for o >= 13 and the
    mirror ``S[i, o] = S_acc[j, 13 - o] / scale``, ``j`` = band index of ``ijk_i + offset(o)``
    (0 if not in the band), for o < 13; ``h = h_acc / scale``. Deterministic (pure reads)."""
    for i in range(S.shape[0]):
        for o in ti.static(range(13, 27)):
            S[i, o] = ti.cast(ti.cast(S_acc[i, o - 13], ti.f64) * inv_scale, ti.f32)
        v = ti.Vector([ijk[i, 0], ijk[i, 1], ijk[i, 2]])
        b = ti.Vector([v[0] // BLOCK, v[1] // BLOCK, v[2] // BLOCK])
        row = _block_row(block_keys, b[0], b[1], b[2])  # >= 0: voxel i is in the band
        loc = v - b * BLOCK
        for o in range(13):
            d = ti.Vector([o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1])
            lc = loc + d
            j = -1
            if (lc >= 0).all() and (lc < BLOCK).all():  # neighbour in voxel i's block
                j = block_table[row, lc[0] * 64 + lc[1] * 8 + lc[2]]
            else:
                j = band_index(block_keys, block_table, v[0] + d[0], v[1] + d[1], v[2] + d[2])
            val = 0.0
            if j >= 0:
                val = ti.cast(ti.cast(S_acc[j, 13 - o], ti.f64) * inv_scale, ti.f32)
            S[i, o] = val
        h[i] = ti.cast(ti.cast(h_acc[i], ti.f64) * inv_scale, ti.f32)


# -- Python side ------------------------------------------------------------------------------

def band_ijk_from_table(block_keys: np.ndarray, block_table: np.ndarray,
                        n_voxels: int) -> np.ndarray:
    """Invert :func:`kernels.lookup.build_block_table`: voxel ``ijk`` (N, 3) int32 of every band
    index 0..N-1. Raises ValueError unless the table holds each index exactly once."""
    keys = np.asarray(block_keys, np.int64)
    table = np.asarray(block_table, np.int32)
    rows, t = np.nonzero(table >= 0)
    idx = table[rows, t].astype(np.int64)
    if len(idx) != n_voxels or (len(idx) and (idx.min() < 0 or idx.max() >= n_voxels
                                              or np.bincount(idx, minlength=n_voxels).max() != 1)):
        raise ValueError(f"block table does not hold band indices 0..{n_voxels - 1} exactly once "
                         f"({len(idx)} entries)")
    mask = (1 << 21) - 1
    k = keys[rows]
    blocks = np.stack([(k >> 42) & mask, (k >> 21) & mask, k & mask], axis=1) - KEY_BIAS
    local = np.stack([t >> 6, (t >> 3) & 7, t & 7], axis=1)
    ijk = np.empty((n_voxels, 3), np.int32)
    ijk[idx] = blocks * BLOCK + local
    return ijk


def sample_count(trunc_m: float, spacing_m: float) -> int:
    """Samples per pixel, 2 m + 1 with m = floor(trunc / spacing) (1e-6 tolerance for round
    ratios such as 0.06 / 0.03)."""
    return 2 * int(math.floor(trunc_m / spacing_m + 1e-6)) + 1


class Observer:
    """Accumulates depth frames into the data term of the posterior, as a 27-point stencil.

    Args:
        block_keys, block_table: the band lookup of :func:`kernels.lookup.build_block_table`
            ((B,) int64 and (B, 512) int32) over the band's N voxels.
        n_voxels: band size N.
        voxel_size: voxel edge, metres (voxel ``ijk`` has centre ``(ijk + 0.5) * voxel_size``).
        trunc_m: observation truncation ``tau``, metres: samples within ``+-tau`` of the surface.
        spacing_m: sample spacing along the camera z axis, metres (default one voxel).
        depth_a_m, depth_b, depth_z0_m: axial depth noise ``a + b (D - z0)^2`` (metres,
            1/metre, metres); the defaults are the Kinect v1 fit of Nguyen et al. 2012.
        cos_min: floor of the incidence cosine dividing the axial noise (0.3: at most 3.3x the
            head-on noise, reached at 72.5 deg).
        sigma_pose_m: pose noise, metres; also the smallest per-frame value :meth:`integrate`
            accepts (the fixed-point scale is sized for the largest weight).
        sigma_model_m: model noise (planar approximation, discretisation), metres.
        normal_radius_px: tangent offset r of the normal estimate, pixels (module docstring).
        reference, gate_m: the side gate of step 3b: (N,) reference SDF (metres; NaN where
            there is none) and the gate in metres (default 0: no gate, no reference needed).
        front_m: how far in front of the measured surface the samples reach, metres (>=
            ``trunc_m``; default ``trunc_m``). Samples there observe ``y = <n, x - p>`` like
            the others: the free space the ray crossed, as the TSDF sees it.
        normal_max_slope_deg: steepest surface inclination (from the image plane) whose
            neighbouring depths still count as one surface in the normal estimate, degrees.

    Raises ValueError for inconsistent inputs (the weight needs a floor: one of ``depth_a_m``,
    ``sigma_pose_m``, ``sigma_model_m`` > 0). Taichi must be initialised first. Memory: 136
    bytes per band voxel (int64 accumulators, ijk, the gate's float32 reference).
    """

    def __init__(self, block_keys: np.ndarray, block_table: np.ndarray, n_voxels: int,
                 voxel_size: float, trunc_m: float, *, spacing_m: float | None = None,
                 depth_a_m: float = 0.0012, depth_b: float = 0.0019, depth_z0_m: float = 0.4,
                 cos_min: float = 0.3, sigma_pose_m: float = 0.0, sigma_model_m: float = 0.001,
                 normal_radius_px: int = 1, normal_max_slope_deg: float = 85.0,
                 count_once: str = "pixel", front_m: float | None = None,
                 reference: np.ndarray | None = None, gate_m: float = 0.0):
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.spacing_m = self.voxel_size if spacing_m is None else float(spacing_m)
        if count_once not in ("pixel", "voxel"):
            raise ValueError(f"Observer: count_once = {count_once!r} is not 'pixel' or 'voxel'")
        # "pixel": the n_acc samples of a pixel share its 1/sigma^2 (w = 1 / (n_acc sigma^2)).
        # "voxel": each voxel gets about one pixel's information: only the samples in the two
        # cells around a voxel along the ray (ceil(2 voxel / spacing) of them) share the depth
        # error there, so w = 1 / (min(n_acc, share) sigma^2).
        self.count_once = count_once
        self.share = (float(math.ceil(2.0 * self.voxel_size / self.spacing_m - 1e-9))
                      if count_once == "voxel" else 1e30)
        values = {"voxel_size": self.voxel_size, "trunc_m": self.trunc_m,
                  "spacing_m": self.spacing_m, "cos_min": cos_min,
                  "normal_max_slope_deg": normal_max_slope_deg}
        for name, val in values.items():
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"Observer: {name} = {val} must be a positive number")
        for name, val in {"depth_a_m": depth_a_m, "depth_b": depth_b,
                          "sigma_pose_m": sigma_pose_m, "sigma_model_m": sigma_model_m}.items():
            if not (math.isfinite(val) and val >= 0):
                raise ValueError(f"Observer: {name} = {val} must be >= 0")
        if cos_min > 1:
            raise ValueError(f"Observer: cos_min = {cos_min} must be in (0, 1]")
        if normal_max_slope_deg >= 90:
            raise ValueError(f"Observer: normal_max_slope_deg = {normal_max_slope_deg} must be "
                             "in (0, 90)")
        if int(normal_radius_px) < 1:
            raise ValueError(f"Observer: normal_radius_px = {normal_radius_px} must be >= 1")
        var_floor = depth_a_m ** 2 + sigma_pose_m ** 2 + sigma_model_m ** 2
        if var_floor <= 0:
            raise ValueError("Observer: depth_a_m, sigma_pose_m and sigma_model_m are all 0 (the "
                             "observation weight 1 / sigma^2 needs a floor)")
        self.n_voxels = int(n_voxels)
        self.block_keys = np.ascontiguousarray(block_keys, np.int64)
        self.block_table = np.ascontiguousarray(block_table, np.int32)
        if self.block_table.ndim != 2 or self.block_table.shape[1] != BLOCK ** 3 or \
                self.block_keys.shape != (self.block_table.shape[0],):
            raise ValueError(f"Observer: block_keys {self.block_keys.shape} / block_table "
                             f"{self.block_table.shape} are not (B,) / (B, 512)")
        self.ijk = band_ijk_from_table(self.block_keys, self.block_table, self.n_voxels)
        self.depth_model = (float(depth_a_m), float(depth_b), float(depth_z0_m), float(cos_min))
        self.sigma_pose_m = float(sigma_pose_m)
        self.sigma_model_m = float(sigma_model_m)
        self.normal_radius_px = int(normal_radius_px)
        self.normal_max_slope_deg = float(normal_max_slope_deg)
        self.m = sample_count(self.trunc_m, self.spacing_m) // 2
        # samples in front of the surface reach front_m (default: tau, like those behind)
        self.front_m = self.trunc_m if front_m is None else float(front_m)
        if not (math.isfinite(self.front_m) and self.front_m >= self.trunc_m):
            raise ValueError(f"Observer: front_m = {front_m} must be >= trunc_m = {self.trunc_m}")
        self.mf = sample_count(self.front_m, self.spacing_m) // 2
        self.gate_m = float(gate_m)
        if not (math.isfinite(self.gate_m) and self.gate_m >= 0):
            raise ValueError(f"Observer: gate_m = {gate_m} must be >= 0 (0: no gate)")
        if self.gate_m > 0:
            if reference is None:
                raise ValueError("Observer: gate_m > 0 needs a reference SDF (N,)")
            self.reference = np.ascontiguousarray(reference, np.float32)
            if self.reference.shape != (int(n_voxels),):
                raise ValueError(f"Observer: reference has shape {self.reference.shape}, "
                                 f"expected ({int(n_voxels)},)")
        else:
            self.reference = np.zeros(1, np.float32)
        # scale = 2^FRACTION_BITS / w_max, rounded down to a power of two (exact multiplies)
        self.w_max = 1.0 / var_floor
        self.fixed_scale = 2.0 ** math.floor(FRACTION_BITS - math.log2(self.w_max))
        n = max(self.n_voxels, 1)
        self.S_acc = ti.ndarray(ti.i64, shape=(n, N_HALF))
        self.h_acc = ti.ndarray(ti.i64, shape=(n,))
        self._dummy_rows = (np.zeros((1, 8), np.int32), np.zeros((1, 8)), np.zeros(1),
                            np.zeros(1), np.zeros(1), np.zeros(1, np.int32))
        self._params = np.zeros(N_PARAMS, np.float64)
        self._scratch_buf = None
        self.reset()

    def reset(self) -> None:
        """Forget all frames (zero the accumulators and counters)."""
        self.S_acc.fill(0)
        self.h_acc.fill(0)
        self.counts = np.zeros(N_COUNTS, np.int64)
        self.frames = 0

    # -- per frame ---------------------------------------------------------------------------
    def _frame_params(self, depth_m, K, T_W_C, sigma_pose_m):
        """Check a frame (ValueError naming the problem) and fill the parameter vector."""
        depth = np.ascontiguousarray(depth_m, np.float32)
        K = np.asarray(K, np.float64)
        T = np.asarray(T_W_C, np.float64)
        if depth.ndim != 2 or depth.size == 0:
            raise ValueError(f"depth must be a non-empty (H, W) image, got shape {depth.shape}")
        if not np.isfinite(depth).all():
            raise ValueError("depth contains NaN or inf (invalid pixels must be 0)")
        if K.shape != (3, 3) or T.shape != (4, 4) or not (np.isfinite(K).all()
                                                          and np.isfinite(T).all()):
            raise ValueError(f"K must be finite 3x3 and T_W_C finite 4x4, got {K.shape}, {T.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}")
        sp = self.sigma_pose_m if sigma_pose_m is None else float(sigma_pose_m)
        if not (math.isfinite(sp) and sp >= self.sigma_pose_m):
            raise ValueError(f"sigma_pose_m = {sp} of a frame must be at least the Observer's "
                             f"sigma_pose_m = {self.sigma_pose_m}")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        K_inv = np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])
        R_WC, t_WC = T[:3, :3], T[:3, 3]
        a, b, z0, cos_min = self.depth_model
        prm = self._params
        prm[P_M:P_M + 9] = (R_WC @ K_inv / self.voxel_size).ravel()
        prm[P_O:P_O + 3] = t_WC / self.voxel_size - 0.5
        prm[P_R:P_R + 9] = R_WC.ravel()
        prm[P_K:P_K + 4] = fx, fy, cx, cy
        prm[P_SPACING] = self.spacing_m
        prm[P_A], prm[P_B], prm[P_Z0], prm[P_COS_MIN] = a, b, z0, cos_min
        prm[P_VAR_EXTRA] = sp ** 2 + self.sigma_model_m ** 2
        prm[P_RADIUS] = self.normal_radius_px
        prm[P_JUMP] = math.tan(math.radians(self.normal_max_slope_deg))
        prm[P_SCALE] = self.fixed_scale
        prm[P_SHARE] = self.share
        prm[P_GATE] = self.gate_m
        return depth, prm

    def _scratch(self, n_rows: int) -> tuple:
        """Per-row scratch arrays of the frame kernel (see _observe_frame), reused."""
        if self._scratch_buf is None or self._scratch_buf[0].shape[0] < n_rows:
            n_s = self.mf + self.m + 1
            self._scratch_buf = (np.empty((n_rows, n_s, 8), np.int32),
                                 np.empty((n_rows, n_s, 11), np.int32))
        return self._scratch_buf

    @staticmethod
    def _check_stride(stride) -> int:
        if int(stride) != stride or stride < 1:
            raise ValueError(f"stride = {stride} must be a positive integer")
        return int(stride)

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray, stride: int = 1,
                  sigma_pose_m: float | None = None) -> dict:
        """Add one frame's observations to the accumulators; return its counts (COUNT_NAMES).

        Args:
            depth_m: (H, W) float32 depth along the camera z axis, metres; invalid pixels 0.
            K: (3, 3) pinhole intrinsics. T_W_C: (4, 4) camera-to-world pose (float64 kept).
            stride: use pixels with u % stride == 0 and v % stride == 0.
            sigma_pose_m: this frame's pose noise, metres (default: the constructor's).
        One kernel launch. Deterministic (integer atomics).
        """
        stride = self._check_stride(stride)
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        n_vs = (depth.shape[0] + stride - 1) // stride
        counts = np.zeros((n_vs, N_COUNTS), np.int64)
        if self.n_voxels:
            _observe_frame(depth, prm, self.block_keys, self.block_table, self.reference, stride,
                           self.m, self.mf,
                           self.S_acc, self.h_acc, counts, *self._scratch(n_vs),
                           *self._dummy_rows, 0)
        frame = counts.sum(axis=0)
        self.counts += frame
        self.frames += 1
        return dict(zip(COUNT_NAMES, frame.tolist()))

    def frame_rows(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray, stride: int = 1,
                   sigma_pose_m: float | None = None) -> dict:
        """The raw observation rows of one frame (same kernel as :meth:`integrate`, nothing is
        accumulated). For tests and debugging: memory grows with pixels x samples.

        Returns a dict of the R accepted samples, in (v, u, z) order:
            ``idx`` (R, 8) int32 band indices of the cell corners (corner c = 4 ci + 2 cj + ck),
            ``a`` (R, 8) float64 trilinear weights, ``y`` (R,) float64 metres, ``w`` (R,)
            float64 1/metre^2, ``z`` (R,) float64 camera depth of the sample, ``pixel`` (R,)
            int64 flat pixel index ``v * W + u``; and ``dropped_pixel``, ``dropped_z``: pixel
            and depth of the dropped samples; ``counts``: the frame's counts (COUNT_NAMES).
        """
        stride = self._check_stride(stride)
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        H, W = depth.shape
        n_vs, n_us = (H + stride - 1) // stride, (W + stride - 1) // stride
        n_s = self.mf + self.m + 1
        R = n_vs * n_us * n_s
        rows = (np.full((R, 8), -1, np.int32), np.zeros((R, 8)), np.zeros(R), np.zeros(R),
                np.zeros(R), np.zeros(R, np.int32))
        counts = np.zeros((n_vs, N_COUNTS), np.int64)
        if self.n_voxels:
            _observe_frame(depth, prm, self.block_keys, self.block_table, self.reference, stride,
                           self.m, self.mf,
                           self.S_acc, self.h_acc, counts, *self._scratch(n_vs), *rows, 1)
        idx, a, y, w, z, status = rows
        slot = np.arange(R) // n_s
        pixel = (slot // n_us) * stride * W + (slot % n_us) * stride
        ok = status == ROW_ACCEPTED
        drop = status == ROW_DROPPED
        return {"idx": idx[ok], "a": a[ok], "y": y[ok], "w": w[ok], "z": z[ok],
                "pixel": pixel[ok], "dropped_pixel": pixel[drop], "dropped_z": z[drop],
                "counts": dict(zip(COUNT_NAMES, counts.sum(axis=0).tolist()))}

    def frame_normals(self, depth_m: np.ndarray, K: np.ndarray,
                      T_W_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-frame unit normals (H, W, 3) float32 of every valid pixel, facing the camera
        (0 at invalid pixels), and (H, W) bool: True where the normal fell back to the negated
        ray direction (module docstring, step 1)."""
        depth, prm = self._frame_params(depth_m, K, T_W_C, None)
        normals = np.zeros(depth.shape + (3,), np.float32)
        fallback = np.zeros(depth.shape, np.int32)
        _frame_normals(depth, prm, normals, fallback)
        return normals, fallback.astype(bool)

    # -- result ------------------------------------------------------------------------------
    def diagonal(self) -> np.ndarray:
        """(N,) float64 diagonal of the data term so far, ``(A^T W A)_ii`` (1/metre^2): what
        next-best-view planning needs of a hypothetical frame, without assembling the
        stencil (:meth:`finalize`). Exact (from the fixed-point sums)."""
        if not self.n_voxels:
            return np.zeros(0)
        return self.S_acc.to_numpy()[:, 0] / self.fixed_scale

    def finalize(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """The data term so far: ``S_data`` (N, 27) float32 (stencil of A^T W A, symmetric:
        ``S[i, o] == S[nbr[i, o], 26 - o]``, 0 towards voxels outside the band), ``h_data`` (N,)
        float32 (A^T W y, 1/metre), and stats: ``frames``, the summed COUNT_NAMES counts and
        ``fixed_scale``. ``saturated`` > 0 means an accumulator came within 2x of int64
        overflow (then the sums may be wrong). The accumulators are kept (more frames may
        follow). Deterministic."""
        N = self.n_voxels
        S = np.zeros((N, 27), np.float32)
        h = np.zeros(N, np.float32)
        if N:
            _finalize(self.block_keys, self.block_table, self.ijk, self.S_acc, self.h_acc,
                      1.0 / self.fixed_scale, S, h)
        stats = {"frames": self.frames, **dict(zip(COUNT_NAMES, self.counts.tolist())),
                 "fixed_scale": self.fixed_scale}
        return S, h, stats
