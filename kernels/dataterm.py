"""Taichi kernels of the data term: depth frames -> SDF samples -> the 27-point stencil.

The math is in the docstring of :mod:`kernels.observe`, whose Observer is the Python front of
these kernels: it checks the inputs and fills the per-frame parameters (``P_*`` below).
Determinism: :func:`observe_frame` and :func:`misfit_frame` add integers, each thread into its
own copy of the accumulators (``parts``, summed when read), without atomics: bitwise
reproducible whatever the thread schedule; every other kernel writes each output element from
one thread.
"""

import taichi as ti

from .funcs import (block_is_planar, block_mean_depth, block_row, corner, floor_i32, offset_of,
                    trilinear)
from .fixedpoint import fixed_point, part_sum, saturated_entries
from .layout import BLOCK, CENTRE
from .lookup import BLOCK_CACHE, SAMPLE_ACCEPTED, SAMPLE_GATED, band_index, look_up_sample
from .stencil import first_chunk, virtual_iterations

N_HALF = 27 - CENTRE  # accumulated stencil columns: offsets o = 13..26
#: Columns of a voxel's row of the data term's accumulator: 0..13 the stencil's upper half
#: (offsets o = 13..26), H_COLUMN = 14 its ``A^T W y``, 15 always 0. 16 int64 are two 64-byte
#: cache lines: the 8 corners of a sample's cell are four pairs of neighbouring voxels, four
#: lines a pair (docs/measurements.md, "The accumulator's row: two cache lines").
ACC_COLUMNS = 16
H_COLUMN = N_HALF
#: The frame kernels deal the pixel rows out to the parts (threads) in runs of this many
#: consecutive rows (part p: rows 4p..4p+3, then 4(p + parts).. and so on): neighbouring rows
#: meet the same voxels, so a part's next row finds its rows of the accumulator in cache
#: (docs/measurements.md, "The accumulator's row: two cache lines"; one row at a time, the
#: parts took turns row by row).
ROW_RUN = 4

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
P_RADIUS = 31  # normal tangent offset r, pixels (with P_NORMAL_NOISE: its largest value)
P_JUMP = 32  # tan(normal_max_slope): neighbour depth jump limit is r D tan / f
P_SCALE = 33  # fixed-point units per unit of S / h
P_SHARE = 34  # most samples of one pixel that share a depth error in one voxel's estimate
P_GATE = 35  # side gate: largest contradiction of y's side by the reference SDF, metres (0: off)
P_INV_VOXEL = 36  # 1 / voxel_size, 1/metre
P_VAR_CORR = 37  # per-frame noise shared by a voxel's pixels, metres^2 (see observe_row)
P_PIXELS = 38  # full-resolution pixels per (super-)pixel of the image observed, k^2 (1: none)
P_AGGREGATE = 39  # largest super-pixel side, in voxel footprints (0: every pixel on its own)
P_BEHIND = 40  # 1: the samples behind the surface reach tau max(cos, cos_min) (0: tau)
P_VAR_AXIAL = 41  # per-pixel depth noise beyond the sensor model, along the ray, metres^2
P_NORMAL_NOISE = 42  # > 0: r per pixel, the smallest with normal angle noise <= this, radians
N_PARAMS = 43

# Per-row counters (columns of `counts`):
C_VALID = 0  # strided pixels with valid depth
C_USED = 1  # ... of which at least one sample was accepted
C_ACCEPTED = 2  # accepted samples
C_DROPPED = 3  # samples dropped because a corner of their cell is not in the band
C_SATURATED = 4  # accumulator entries found beyond SATURATION (Observer's checks)
C_FALLBACK = 5  # used pixels whose normal fell back to the ray direction
C_GATED = 6  # samples rejected by the reference gate (all corners in the band)
N_COUNTS = 7
COUNT_NAMES = ("pixels_valid", "pixels_used", "samples_accepted", "samples_dropped", "saturated",
               "normal_fallbacks", "samples_gated")

MODE_ACCUMULATE, MODE_ROWS, MODE_MISFIT, MODE_DIAGONAL = 0, 1, 2, 3  # what observe_row does
MISFIT_SCALE = float(1 << 24)  # fixed-point units per unit of a misfit sum (shares, voxel^2)
#: Largest squared residual one sample adds to the misfit, in noise variances (10 sigma): a
#: gross residual (an occlusion edge) marks its voxels without swamping their sums.
MISFIT_CAP = 100.0
#: The misfit counts the samples within this many voxels of their pixel's measured surface
#: (``|y| < MISFIT_NEAR h``): those in the cells that hold the zero crossing, where a vertex
#: lies (1 voxel from it along an axis, sqrt(3) along a diagonal; 1, 1.5 and 2 measured on the
#: suite, docs/measurements.md). Farther samples carry the model error of the projective
#: distance and the pixel normal (tools/residual_profile.py: 1.4-2.9 mm RMS on cheburashka /
#: dropout, 1.2 at the surface), which does not move the zero crossing; counted, it made sigma
#: ~2x too large on smooth surfaces.
MISFIT_NEAR = 1.5
#: Columns of the misfit sums (per voxel, each weighted by ``a_c s``): the squared residual
#: (capped), the noise variance the model expects of it, the weight itself, and for the line the
#: residuals follow across the samples' distance ``y`` from their own pixel's surface
#: (:func:`bftaichi.stages.misfit.surface_excess`) the residual (capped alike), ``y``,
#: ``y^2`` and ``r y``. Voxel units in the kernel: each column in voxels to the power
#: :data:`MISFIT_UNITS` (the voxel observation model sums the first three only).
MISFIT_COLUMNS = 7
MISFIT_UNITS = (2, 2, 0, 1, 1, 2, 2)
ROW_ACCEPTED, ROW_DROPPED = 1, 2  # row status in frame_rows (0: no sample, or gated)


def column(ca: int, cb: int) -> int:
    """Accumulator column ``o - 13`` of the entry between corners ca <= cb, o being the stencil
    offset of ``corner(cb) - corner(ca)``."""
    d = [x - y for x, y in zip(corner(cb), corner(ca))]
    return (d[0] + 1) * 9 + (d[1] + 1) * 3 + (d[2] + 1) - CENTRE


# -- per-pixel and per-sample math ------------------------------------------------------------

@ti.func
def ray_C(prm: ti.template(), u: ti.i32, v: ti.i32):
    """K^-1 (u, v, 1), float32 (camera frame, z = 1: a point at depth z is z times this)."""
    fx, fy = ti.cast(prm[P_K], ti.f32), ti.cast(prm[P_K + 1], ti.f32)
    cx, cy = ti.cast(prm[P_K + 2], ti.f32), ti.cast(prm[P_K + 3], ti.f32)
    return ti.Vector([(ti.cast(u, ti.f32) - cx) / fx, (ti.cast(v, ti.f32) - cy) / fy, 1.0])


@ti.func
def depth_sigma(prm: ti.template(), d: ti.f64) -> ti.f64:
    """Axial depth noise of a pixel at depth ``d``, metres: the model's and the extra (step 4)."""
    return ti.sqrt((prm[P_A] + prm[P_B] * (d - prm[P_Z0]) ** 2) ** 2 + prm[P_VAR_AXIAL])


@ti.func
def pixel_normal(depth: ti.template(), prm: ti.template(), u: ti.i32, v: ti.i32):
    """Camera-frame unit normal of valid pixel (u, v) facing the camera, and a fallback flag:
    ``(nx, ny, nz, fallback)`` float32 (module docstring, step 1)."""
    H, W = depth.shape[0], depth.shape[1]
    d = depth[v, u]
    r = ti.cast(prm[P_RADIUS], ti.i32)
    if prm[P_NORMAL_NOISE] > 0:  # angle noise at r = 1: depth noise over sqrt(2) d / fx
        dd = ti.cast(d, ti.f64)
        noise = depth_sigma(prm, dd) * prm[P_K] / (ti.sqrt(2.0) * dd)
        r = ti.min(ti.max(ti.cast(ti.ceil(noise / prm[P_NORMAL_NOISE]), ti.i32), 1), r)
    reach = ti.cast(prm[P_JUMP], ti.f32) * d * ti.cast(r, ti.f32)
    jump_u = reach / ti.cast(prm[P_K], ti.f32)  # r D tan(max slope) / fx
    jump_v = reach / ti.cast(prm[P_K + 1], ti.f32)
    ray = ray_C(prm, u, v)
    p = d * ray
    # t = P(+r) - P(-r), with P(+-r) replaced by p where that neighbour is unusable
    p_r, p_l, p_d, p_u = p, p, p, p
    n_u, n_v = 0, 0  # usable neighbours per axis
    if u + r < W:
        dn = depth[v, u + r]
        if dn > 0 and ti.abs(dn - d) <= jump_u:
            p_r = dn * ray_C(prm, u + r, v)
            n_u += 1
    if u - r >= 0:
        dn = depth[v, u - r]
        if dn > 0 and ti.abs(dn - d) <= jump_u:
            p_l = dn * ray_C(prm, u - r, v)
            n_u += 1
    if v + r < H:
        dn = depth[v + r, u]
        if dn > 0 and ti.abs(dn - d) <= jump_v:
            p_d = dn * ray_C(prm, u, v + r)
            n_v += 1
    if v - r >= 0:
        dn = depth[v - r, u]
        if dn > 0 and ti.abs(dn - d) <= jump_v:
            p_u = dn * ray_C(prm, u, v - r)
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


_NDA = ti.types.ndarray

@ti.func
def observe_row(vs: ti.i32, depth: ti.template(), mask: ti.template(), prm: ti.template(),
                 block_hash: ti.template(), block_table: ti.template(), ref: ti.template(),
                 stride: ti.i32, m: ti.i32, mf: ti.i32, counts: ti.template(),
                 scratch: ti.template(), blocks: ti.template(), sink: ti.template(),
                 mode: ti.template(), base: ti.i32):
    """Strided pixel row ``vs`` of a frame (module docstring, steps 1-5) where ``mask`` is 1
    (``depth``: the frame or a level of its super-pixel pyramid, ``prm`` that level's): each
    pixel counts its accepted samples, then adds them to ``sink = (acc,)`` (this thread's
    copy, the voxels ``base ..`` of the flat accumulator: plain int64 adds), or their
    diagonal ``w a_c^2`` to ``(D_acc,)`` (MODE_DIAGONAL), or (MODE_ROWS) writes each sample to
    ``(row_idx, row_a, row_y, row_w, row_z, row_status)`` at row ``(vs ceil(W / stride) + u /
    stride) (mf + m + 1) + j + mf`` (MODE_MISFIT: :func:`misfit_frame`). Counters to
    ``counts[vs]``; ``scratch`` (rows, mf + m + 1, 8): the corners of the pixel's samples,
    ``blocks`` (.., BLOCK_CACHE) the block cache, both flat
    (:func:`kernels.lookup.look_up_sample`)."""
    H, W = depth.shape[0], depth.shape[1]
    n_us = (W + stride - 1) // stride
    M = ti.Matrix([[prm[P_M + 3 * r + c] for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    o = ti.Vector([prm[P_O], prm[P_O + 1], prm[P_O + 2]])
    spacing = prm[P_SPACING]
    scale = prm[P_SCALE]
    cos_min = prm[P_COS_MIN]
    gate = prm[P_GATE]
    v = vs * stride
    n_valid, n_used, n_acc_row, n_drop, n_fb, n_gate = 0, 0, 0, 0, 0, 0
    row = vs * (mf + m + 1) + mf  # the slot of sample j is row + j
    for j in range(-mf, m + 1):
        blocks[(row + j) * BLOCK_CACHE] = 1 << 30  # no block has this coordinate: empty cache
    pixels = ti.cast(prm[P_PIXELS], ti.i32)
    for us in range(n_us):
        u = us * stride
        d = depth[v, u]
        if d > 0 and mask[v, u] == 1:
            n_valid += pixels
            nf = pixel_normal(depth, prm, u, v)
            n_C = ti.Vector([nf[0], nf[1], nf[2]])
            ray = ray_C(prm, u, v)
            n_dot_ray = ti.cast(n_C.dot(ray), ti.f64)  # = -cos(angle) |ray| <= 0
            cos_a = -n_dot_ray / ti.cast(ray.norm(), ti.f64)
            D = ti.cast(d, ti.f64)
            m_b = m  # behind the surface: tau, or tau max(cos, cos_min) in depth (step 2b)
            if prm[P_BEHIND] > 0:
                m_b = ti.cast(ti.cast(m, ti.f64) * ti.max(cos_a, cos_min), ti.i32)
            # y = (z - D) <n, ray>: an axial depth error e moves y by e |<n, ray>|
            sd = depth_sigma(prm, D) * ti.max(cos_a, cos_min) * ti.cast(ray.norm(), ti.f64)
            # a frame's pixels over one voxel share its pose / calibration error (variance
            # P_VAR_CORR): their mean has variance sd^2 / rho + corr, so each of the rho pixels
            # counts as sd^2 + rho corr (rho: the voxel's footprint in full-resolution pixels)
            rho = ti.max(1.0, (prm[P_K] / (D * prm[P_INV_VOXEL] * ti.cast(stride, ti.f64))) ** 2
                         * prm[P_PIXELS])
            var_pixel = sd * sd + prm[P_VAR_EXTRA] + prm[P_VAR_CORR]  # one pixel's noise
            inv_var = 1.0 / (var_pixel + (rho - 1.0) * prm[P_VAR_CORR])
            m_ray = M @ ti.Vector([ti.cast(u, ti.f64), ti.cast(v, ti.f64), 1.0])
            # pass 0 looks the cells up and counts the pixel's accepted samples n_acc (corner
            # indices wait in the scratch); pass 1 adds them (or writes rows), w = 1 / (n_acc s^2)
            n_acc = 0
            # the misfit adds only the samples near the surface (MISFIT_NEAR): it looks those
            # up first, the others only until min(n_acc, share) is settled (run-time sweeps)
            for sweep in range(ti.static(2 if mode == MODE_MISFIT else 1)):
                for j in range(-mf, m_b + 1):
                    z = D + ti.cast(j, ti.f64) * spacing
                    look = 0
                    if z > 0:
                        look = 1
                        if ti.static(mode == MODE_MISFIT):
                            near = ti.abs(ti.cast(j, ti.f64) * spacing * n_dot_ray) \
                                * prm[P_INV_VOXEL] < MISFIT_NEAR
                            if sweep == 0:
                                look = ti.cast(near, ti.i32)
                            elif near or ti.cast(n_acc, ti.f64) >= prm[P_SHARE]:
                                look = 0
                    if look:
                        status = look_up_sample(row + j, j == -mf, z, o, m_ray,
                                                ti.cast(j, ti.f64) * spacing * n_dot_ray, gate,
                                                block_hash, block_table, ref, scratch, blocks)
                        if status == SAMPLE_GATED:
                            n_gate += 1
                        elif status == SAMPLE_ACCEPTED:
                            n_acc += 1
                        else:
                            n_drop += 1
            todo = n_acc
            if ti.static(mode == MODE_ROWS):
                todo = 1  # every sample gets a row, accepted or not
            if todo > 0:
                # a super-pixel is the mean of its k^2 pixels: it carries their information
                w = prm[P_PIXELS] * inv_var / ti.min(ti.cast(ti.max(n_acc, 1), ti.f64),
                                                     prm[P_SHARE])
                ws = w * scale
                for j in range(-mf, m_b + 1):
                    delta = ti.cast(j, ti.f64) * spacing
                    z = D + delta
                    if z <= 0:
                        continue
                    if ti.static(mode == MODE_MISFIT):  # only the near samples count there
                        if ti.abs(delta * n_dot_ray) * prm[P_INV_VOXEL] >= MISFIT_NEAR:
                            continue
                    g = o + z * m_ray
                    c0 = floor_i32(g)
                    a = trilinear(g - ti.cast(c0, ti.f64))
                    y = delta * n_dot_ray  # <n, x - p>, x - p = delta K^-1 (u, v, 1)
                    idx = ti.Vector([scratch[(row + j) * 8 + c] for c in ti.static(range(8))])
                    accepted = idx[7] >= 0
                    if ti.static(mode == MODE_ROWS):
                        row_idx, row_a, row_y, row_w, row_z, row_status = ti.static(
                            sink[0], sink[1], sink[2], sink[3], sink[4], sink[5])
                        r = (vs * n_us + us) * (mf + m + 1) + mf + j
                        row_status[r] = ti.select(accepted, ROW_ACCEPTED, ti.select(
                            idx[7] == -1, ROW_DROPPED, 0))  # -2: gated
                        row_y[r] = y
                        row_w[r] = ti.select(accepted, w, 0.0)
                        row_z[r] = z
                        for c in ti.static(range(8)):
                            row_idx[r, c] = idx[c]
                            row_a[r, c] = a[c]
                    elif ti.static(mode == MODE_MISFIT):
                        if accepted and ti.abs(y) * prm[P_INV_VOXEL] < MISFIT_NEAR:
                            # the sample's squared residual against the posterior mean
                            # (capped at MISFIT_CAP sigma^2) and what the model expects of
                            # it, sigma^2 - a^T Sigma a (the fit absorbs part of the noise;
                            # a^T Sigma a ~ sum a_c^2 var_c), both in voxel^2 and weighted by
                            # the sample's share of its pixel s = 1 / min(n_acc, share),
                            # spread over its corners by a
                            mu, var, R_acc = ti.static(sink[0], sink[1], sink[2])
                            r = y
                            p = ti.f64(0.0)
                            for c in ti.static(range(8)):
                                r -= a[c] * ti.cast(mu[idx[c]], ti.f64)
                                p += a[c] * a[c] * ti.cast(var[idx[c]], ti.f64)
                            share = w / inv_var
                            # the residual of a super-pixel is that of the mean of its k^2
                            # pixels: their shared part P_VAR_CORR does not average down
                            var_k = (sd * sd + prm[P_VAR_EXTRA]) / prm[P_PIXELS] + prm[P_VAR_CORR]
                            inv_h2 = prm[P_INV_VOXEL] * prm[P_INV_VOXEL]
                            r2 = ti.min(r * r, MISFIT_CAP * var_k) * inv_h2
                            v2 = ti.max(var_k - p, 0.1 * var_k) * inv_h2
                            # the residual capped as its square is, and y, in voxels
                            cap = ti.sqrt(MISFIT_CAP * var_k)
                            rv = ti.min(ti.max(r, -cap), cap) * prm[P_INV_VOXEL]
                            yv = y * prm[P_INV_VOXEL]
                            for c in ti.static(range(8)):
                                sa = a[c] * share * MISFIT_SCALE
                                # this thread's copy: plain adds (`+=` would be atomic)
                                e = (base + idx[c]) * MISFIT_COLUMNS
                                R_acc[e] = R_acc[e] + fixed_point(sa * r2)
                                R_acc[e + 1] = R_acc[e + 1] + fixed_point(sa * v2)
                                R_acc[e + 2] = R_acc[e + 2] + fixed_point(sa)
                                R_acc[e + 3] = R_acc[e + 3] + fixed_point(sa * rv)
                                R_acc[e + 4] = R_acc[e + 4] + fixed_point(sa * yv)
                                R_acc[e + 5] = R_acc[e + 5] + fixed_point(sa * yv * yv)
                                R_acc[e + 6] = R_acc[e + 6] + fixed_point(sa * rv * yv)
                    elif ti.static(mode == MODE_DIAGONAL):  # (A^T W A)_ii alone, as below
                        if accepted:
                            D_acc = ti.static(sink[0])
                            for c in ti.static(range(8)):
                                e = base + idx[c]
                                D_acc[e] = D_acc[e] + fixed_point(ws * a[c] * a[c])
                    elif accepted:
                        acc = ti.static(sink[0])
                        for ca in ti.static(range(8)):
                            wa = ws * a[ca]
                            r0 = (base + idx[ca]) * ACC_COLUMNS  # the row, computed once
                            for cb in ti.static(range(ca, 8)):
                                col = ti.static(column(ca, cb))
                                # this thread's copy: plain adds, no atomic; no overflow
                                # test either (Observer.integrate bounds the growth)
                                acc[r0 + col] = acc[r0 + col] + fixed_point(wa * a[cb])
                            acc[r0 + H_COLUMN] = acc[r0 + H_COLUMN] + fixed_point(wa * y)
            if n_acc > 0:
                n_used += pixels
                n_acc_row += n_acc
                if nf[3] > 0:
                    n_fb += pixels
    counts[vs, C_VALID] = n_valid
    counts[vs, C_USED] = n_used
    counts[vs, C_ACCEPTED] = n_acc_row
    counts[vs, C_DROPPED] = n_drop
    counts[vs, C_FALLBACK] = n_fb
    counts[vs, C_GATED] = n_gate


@ti.func
def observe_part(part: ti.i32, n_parts: ti.i32, n_vox: ti.i32, depth: ti.template(),
                 mask: ti.template(), prm: ti.template(), block_hash: ti.template(),
                 block_table: ti.template(), ref: ti.template(), stride: ti.i32, m: ti.i32,
                 mf: ti.i32, counts: ti.template(), scratch: ti.template(),
                 blocks: ti.template(), sink: ti.template(), mode: ti.template()):
    """:func:`observe_row` on every strided pixel row of ``part`` (of ``n_parts``), into its
    copy of the sums (voxels ``part * n_vox ..``): runs of ROW_RUN consecutive rows dealt out
    to the parts in turn, every row to exactly one part (the frame kernels' one loop)."""
    n_rows = (depth.shape[0] + stride - 1) // stride
    span = ROW_RUN * n_parts
    for q in range((n_rows + span - 1) // span * ROW_RUN):
        r = q // ROW_RUN * span + part * ROW_RUN + q % ROW_RUN
        if r < n_rows:
            observe_row(r, depth, mask, prm, block_hash, block_table, ref, stride, m, mf,
                        counts, scratch, blocks, sink, mode, part * n_vox)


@ti.kernel
def observe_frame(depth: _NDA(dtype=ti.f32, ndim=2), mask: _NDA(dtype=ti.i8, ndim=2),
                  prm: _NDA(dtype=ti.f64, ndim=1),
                   block_hash: _NDA(dtype=ti.i64, ndim=1), block_table: _NDA(dtype=ti.i32, ndim=2),
                   ref: _NDA(dtype=ti.f32, ndim=1), stride: ti.i32, m: ti.i32, mf: ti.i32,
                   n_parts: ti.i32, acc: _NDA(dtype=ti.i64, ndim=1),
                   counts: _NDA(dtype=ti.i64, ndim=2), scratch: _NDA(dtype=ti.i32, ndim=1),
                   blocks: _NDA(dtype=ti.i32, ndim=1)):
    """One frame into the accumulator ``acc`` ((parts, N, ACC_COLUMNS), flattened: a flat
    index is computed once per row, where a 3-d index reloaded the shape after every add),
    parallel over strided pixel rows (:func:`observe_row`), each thread into
    its own part (runs of ROW_RUN rows, :func:`observe_part`): integer adds only, bitwise
    reproducible whatever the thread schedule."""
    n_vox = acc.shape[0] // (n_parts * ACC_COLUMNS)
    # the parts dealt out like the stencil kernels' chunks (kernels.stencil.first_chunk): each
    # part goes to exactly one virtual iteration (no race) and the parts to different threads
    n_virtual = ti.max(n_parts, ti.static(virtual_iterations()))
    for t in range(n_virtual):
        for part in range(first_chunk(t, n_parts, n_virtual),
                          first_chunk(t + 1, n_parts, n_virtual)):
            observe_part(part, n_parts, n_vox, depth, mask, prm, block_hash, block_table, ref,
                         stride, m, mf, counts, scratch, blocks, (acc,), MODE_ACCUMULATE)


@ti.kernel
def observe_rows(depth: _NDA(dtype=ti.f32, ndim=2), mask: _NDA(dtype=ti.i8, ndim=2),
                 prm: _NDA(dtype=ti.f64, ndim=1),
                  block_hash: _NDA(dtype=ti.i64, ndim=1), block_table: _NDA(dtype=ti.i32, ndim=2),
                  ref: _NDA(dtype=ti.f32, ndim=1), stride: ti.i32, m: ti.i32, mf: ti.i32,
                  counts: _NDA(dtype=ti.i64, ndim=2), scratch: _NDA(dtype=ti.i32, ndim=1),
                  blocks: _NDA(dtype=ti.i32, ndim=1), row_idx: _NDA(dtype=ti.i32, ndim=2),
                  row_a: _NDA(dtype=ti.f64, ndim=2), row_y: _NDA(dtype=ti.f64, ndim=1),
                  row_w: _NDA(dtype=ti.f64, ndim=1), row_z: _NDA(dtype=ti.f64, ndim=1),
                  row_status: _NDA(dtype=ti.i32, ndim=1)):
    """One frame's samples into the ``row_*`` arrays (:meth:`Observer.frame_rows`), touching
    no accumulator; the same per-row code as :func:`observe_frame`. Deterministic (each row
    written by one thread, no atomics)."""
    ti.loop_config(block_dim=4)
    for vs in range((depth.shape[0] + stride - 1) // stride):
        observe_row(vs, depth, mask, prm, block_hash, block_table, ref, stride, m, mf, counts,
                    scratch, blocks, (row_idx, row_a, row_y, row_w, row_z, row_status), MODE_ROWS,
                    0)


@ti.func
def superpixel_fits(depth: ti.template(), v: ti.i32, u: ti.i32, k: ti.i32, foot: ti.f64) -> ti.i32:
    """1 if pixel (v, u) of the pyramid level of side ``k`` exists, is valid and spans at most
    the voxel footprints ``foot`` allows (``k * depth <= foot``; any valid pixel at k = 1)."""
    ok = 0
    if v < depth.shape[0] and u < depth.shape[1]:
        d = ti.cast(depth[v, u], ti.f64)
        ok = ti.cast(d > 0 and (k == 1 or ti.cast(k, ti.f64) * d <= foot), ti.i32)
    return ok


@ti.kernel
def superpixels(depth: _NDA(dtype=ti.f32, ndim=2), d1: _NDA(dtype=ti.f32, ndim=2),
                d2: _NDA(dtype=ti.f32, ndim=2), d3: _NDA(dtype=ti.f32, ndim=2),
                d4: _NDA(dtype=ti.f32, ndim=2), m0: _NDA(dtype=ti.i8, ndim=2),
                m1: _NDA(dtype=ti.i8, ndim=2), m2: _NDA(dtype=ti.i8, ndim=2),
                m3: _NDA(dtype=ti.i8, ndim=2), m4: _NDA(dtype=ti.i8, ndim=2),
                prm: _NDA(dtype=ti.f64, ndim=1), levels: ti.i32):
    """A frame's super-pixel pyramid in one launch (``prm``: its full-resolution parameters).
    Levels l = 1..``levels`` (``d1..d4``, blocks of ``k = 2^l`` pixels a side, the image size
    divided by k, rounded down): the mean depth of each k x k block of valid pixels on one
    plane (:func:`kernels.funcs.block_is_planar`), else 0. Masks ``m0..m4`` (level 0: the
    frame): 1 where the level observes the pixel (valid, spanning at most ``prm[P_AGGREGATE]``
    voxel footprints, ``k <= aggregate f voxel / depth``, f the smaller focal length, and no
    coarser block containing it does), 2 where a coarser block observes it, else 0: every valid
    pixel is observed exactly once. Deterministic (one thread per output pixel)."""
    reach = ti.cast(prm[P_JUMP] / prm[P_K], ti.f32)
    foot = prm[P_AGGREGATE] * ti.min(prm[P_K], prm[P_K + 1]) / prm[P_INV_VOXEL]
    for lv in ti.static(range(1, 5)):
        dl = ti.static((d1, d2, d3, d4)[lv - 1])
        k = ti.static(1 << lv)
        for by, bx in ti.ndrange(dl.shape[0], dl.shape[1]):
            if lv <= levels:
                mean = block_mean_depth(depth, by, bx, k, reach)
                if mean > 0:
                    if not block_is_planar(depth, by, bx, k, mean, prm[P_A], prm[P_B], prm[P_Z0]):
                        mean = ti.f32(0.0)
                dl[by, bx] = mean
    for top in ti.static(range(5)):  # coarsest first: a pixel is covered where its parent
        lv = ti.static(4 - top)  # block's mask is 1 or 2 (a coarser block observes it)
        ml = ti.static((m0, m1, m2, m3, m4)[lv])
        dl = ti.static((depth, d1, d2, d3, d4)[lv])
        for v, u in ti.ndrange(ml.shape[0], ml.shape[1]):
            if lv <= levels:
                covered = 0
                if ti.static(lv < 4):
                    mp = ti.static((m0, m1, m2, m3, m4)[lv + 1])
                    if lv < levels and v >> 1 < mp.shape[0] and u >> 1 < mp.shape[1]:
                        covered = ti.cast(mp[v >> 1, u >> 1] != 0, ti.i32)
                m = 2
                if not covered:
                    m = superpixel_fits(dl, v, u, 1 << lv, foot)
                ml[v, u] = ti.cast(m, ti.i8)


@ti.kernel
def window_sums(nbr: _NDA(dtype=ti.i32, ndim=2), sums: _NDA(dtype=ti.f64, ndim=2),
                out: _NDA(dtype=ti.f64, ndim=2)):
    """``out[i] = sum over the 27 stencil neighbours j of voxel i (nbr[i, o] >= 0) of
    sums[j]``, the columns of ``sums`` (N, C) separately, offsets in order 0..26.
    Deterministic (one thread per voxel, a fixed order)."""
    for i in range(nbr.shape[0]):
        for c in range(sums.shape[1]):
            total = ti.f64(0.0)
            for o in ti.static(range(27)):
                j = nbr[i, o]
                if j >= 0:
                    total += sums[j, c]
            out[i, c] = total


@ti.kernel
def estimate_normals(depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
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
            nf = pixel_normal(depth, prm, u, v)
            n_W = R @ ti.Vector([nf[0], nf[1], nf[2]])
            fb = ti.cast(nf[3], ti.i32)
        for c in ti.static(range(3)):
            normals[v, u, c] = n_W[c]
        fallback[v, u] = fb


@ti.kernel
def finalize_stencil(block_keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
              block_table: ti.types.ndarray(dtype=ti.i32, ndim=2),
              ijk: ti.types.ndarray(dtype=ti.i32, ndim=2),
              acc: ti.types.ndarray(dtype=ti.i64, ndim=3),
              inv_scale: ti.f64,
              S: ti.types.ndarray(dtype=ti.f32, ndim=2),
              h: ti.types.ndarray(dtype=ti.f32, ndim=1),
              saturated: ti.types.ndarray(dtype=ti.i64, ndim=1)):
    """Fixed point -> float32 stencil, ``acc`` (parts, N, ACC_COLUMNS) summed over its parts:
    ``S[i, o] = acc[i, o - 13] / scale`` for o >= 13 and the mirror ``S[i, o] = acc[j, 13 - o]
    / scale``, ``j`` = band index of ``ijk_i + offset(o)`` (0 if not in the band), for o < 13;
    ``h = acc[i, H_COLUMN] / scale``; ``saturated[0] +=`` the entries
    beyond SATURATION (:func:`kernels.fixedpoint.count_saturated`). Deterministic (reads,
    integer atomics)."""
    for i in range(S.shape[0]):
        n_sat = saturated_entries(acc, i)
        if n_sat > 0:
            ti.atomic_add(saturated[0], n_sat)
        for o in range(CENTRE, 27):  # a run-time loop: unrolled, it was 14 copies to build
            S[i, o] = ti.cast(ti.cast(part_sum(acc, i, o - CENTRE), ti.f64) * inv_scale, ti.f32)
        v = ti.Vector([ijk[i, 0], ijk[i, 1], ijk[i, 2]])
        b = ti.Vector([v[0] // BLOCK, v[1] // BLOCK, v[2] // BLOCK])
        row = block_row(block_keys, b[0], b[1], b[2])  # >= 0: voxel i is in the band
        loc = v - b * BLOCK
        for o in range(CENTRE):
            d = offset_of(o)
            lc = loc + d
            j = -1
            if (lc >= 0).all() and (lc < BLOCK).all():  # neighbour in voxel i's block
                j = block_table[row, lc[0] * 64 + lc[1] * 8 + lc[2]]
            else:
                j = band_index(block_keys, block_table, v[0] + d[0], v[1] + d[1], v[2] + d[2])
            val = 0.0
            if j >= 0:
                val = ti.cast(ti.cast(part_sum(acc, j, CENTRE - o), ti.f64) * inv_scale, ti.f32)
            S[i, o] = val
        h[i] = ti.cast(ti.cast(part_sum(acc, i, H_COLUMN), ti.f64) * inv_scale, ti.f32)


@ti.kernel
def misfit_frame(depth: _NDA(dtype=ti.f32, ndim=2), mask: _NDA(dtype=ti.i8, ndim=2),
                 prm: _NDA(dtype=ti.f64, ndim=1),
                 block_hash: _NDA(dtype=ti.i64, ndim=1), block_table: _NDA(dtype=ti.i32, ndim=2),
                 ref: _NDA(dtype=ti.f32, ndim=1), stride: ti.i32, m: ti.i32, mf: ti.i32,
                 mu: _NDA(dtype=ti.f32, ndim=1), var: _NDA(dtype=ti.f32, ndim=1),
                 n_parts: ti.i32, R_acc: _NDA(dtype=ti.i64, ndim=1),
                 counts: _NDA(dtype=ti.i64, ndim=2),
                 scratch: _NDA(dtype=ti.i32, ndim=1), blocks: _NDA(dtype=ti.i32, ndim=1)):
    """One frame's misfit against the band values ``mu`` into ``R_acc`` ((parts, N,
    MISFIT_COLUMNS), flattened as in :func:`observe_frame`),
    per voxel, in 1 / MISFIT_SCALE: ``sum_k a_k s_k min(r_k^2, MISFIT_CAP sigma_k^2)``, ``sum_k
    a_k s_k (sigma_k^2 - p_k)`` (voxel^2; ``p_k = sum_c a_c^2 var_c`` <= 0.9 sigma_k^2, the part
    the fit absorbs), ``sum_k a_k s_k``, and ``sum_k a_k s_k`` times ``rc_k``, ``y_k``, ``y_k^2``
    and ``rc_k y_k`` (voxels; ``rc_k`` is ``r_k`` clipped to ``+-sqrt(MISFIT_CAP) sigma_k``, as
    its square is), over the accepted samples k within ``MISFIT_NEAR`` voxels of their pixel's
    surface (as :func:`observe_frame`): ``r_k = y_k - a_k . mu``, ``sigma_k`` its noise, ``s_k =
    w_k sigma_k^2`` its share of its pixel. Per-thread integer adds."""
    n_vox = R_acc.shape[0] // (n_parts * MISFIT_COLUMNS)
    n_virtual = ti.max(n_parts, ti.static(virtual_iterations()))  # as in observe_frame
    for t in range(n_virtual):
        for part in range(first_chunk(t, n_parts, n_virtual),
                          first_chunk(t + 1, n_parts, n_virtual)):
            observe_part(part, n_parts, n_vox, depth, mask, prm, block_hash, block_table, ref,
                         stride, m, mf, counts, scratch, blocks, (mu, var, R_acc), MODE_MISFIT)
