"""The data term gathered per voxel: each band voxel looks its frame up, as the TSDF does
(``observation.model = "voxels"``; DESIGN.md 3, steps 3-4).

:mod:`kernels.observe` casts samples along every pixel's ray and adds their trilinear rows
``w a a^T`` (a 27-point data stencil, ~44 integer adds per sample, several samples per pixel).
Here every band voxel ``i`` (centre ``x_i``, camera point ``p = R_WC^T (x_i - t_WC)``, depth
``z = p_z``) observes its own SDF once per frame:

1. **Where it projects**: ``(u, v) = (fx p_x / z + cx, fy p_y / z + cy)``; its footprint is
   the square of ``phi = f voxel / z`` pixels a side around it. The footprints of the voxels of
   one layer tile the image, so each pixel belongs to one voxel per layer, as each pixel's ray
   crosses a layer once.
2. **The pixels of its footprint**: on level ``k = 2^l`` of the frame's pyramid, the largest
   with ``k <= phi`` (the mean depth of each k x k block whose pixels are valid and on one
   surface, 0 elsewhere: :func:`_block_means`; level 0 is the frame), the blocks whose
   centres lie in the footprint (``phi / k`` in [1, 2) blocks a side: 1 to 4 of them; none or
   one where a voxel is smaller than a pixel, ``phi < 1``) and lie on the surface of the block
   nearest the projection (within the normal's slope limit) are averaged: their mean camera
   point ``P``, ``n_pix = k^2 count`` pixels. No block there: the next finer level; no valid
   pixel: no observation.
3. **Normal** ``n`` of the nearest block (:func:`kernels.dataterm.pixel_normal` on that
   level, facing the camera); the ray ``r = p / z``; ``cos = -n . r / |r|``; the surface's
   depth along the voxel's own ray ``D = <n, P> / <n, r>`` (the plane through ``P``: exact on
   a plane, tests/test_voxelobs.py).
4. **Observation** where ``-front_m <= z - D <= tau_b`` (``tau_b = tau``, or ``tau max(cos,
   cos_min)`` with ``behind_incidence``): ``y = (z - D) <n, r>``, the signed distance of the
   voxel centre to the plane of the surface, positive in front, as a sample of
   :mod:`kernels.observe` at this position would observe.
5. **Noise**: a pixel's ``sigma^2 = (sd(D) max(cos, cos_min) |r|)^2 + sigma_pose^2 +
   sigma_model^2`` (the observe model's); the footprint's ``n_pix`` pixels average it down,
   and the frame's shared error ``sigma_corr^2`` does not: ``var = sigma^2 / n_pix +
   sigma_corr^2``. The same depth error reaches every voxel along the ray; as ``count_once =
   "voxel"`` says, each voxel counts it once: ``w = 1 / (share var)``, ``share = 1``
   (``count_once = "pixel"``: the voxels the ray's reach spans, ``(front_m + tau) / voxel``).
   Measured against ``share = 2`` in docs/measurements.md.
6. **Side gate**, as in :mod:`kernels.observe` step 3b, on the voxel's own reference value.
7. **Accumulation**: ``Q_ii += w``, ``h_i += w y`` (a diagonal data term), in int64 fixed
   point (the Observer's scale): one thread per voxel, so each sum is written by one thread,
   deterministic and exactly subtractable.

Cost: per frame one pass over the band's blocks (a block outside the image is skipped whole;
a voxel costs a projection and one depth read, and a few reads and a normal where it is
within reach of the surface), independent of the number of pixels, plus one pass over the
image for the pyramid. A voxel is looked at closely only where the pixel nearest its
projection puts it within the reach plus ``QUICK_SLACK`` voxels.
"""

import math

import numpy as np
import taichi as ti

from .dataterm import (MISFIT_CAP, MISFIT_NEAR, MISFIT_SCALE, P_COS_MIN, P_INV_VOXEL, P_JUMP,
                       P_K, P_O, P_R, P_VAR_CORR, P_VAR_EXTRA, depth_sigma,
                       pixel_normal)
from .fixedpoint import SATURATION, fixed_point
from .funcs import block_mean_depth, floor_i32
from .layout import BLOCK, decode_keys
from .observe import MAX_LEVEL, Observer
from .stencil import zeros_aligned

# voxel-model parameters (a small float64 vector besides the frame's P_* vector)
V_FRONT, V_BEHIND, V_SHARE, V_GATE, V_INCIDENCE, V_SCALE = range(6)
N_VPARAMS = 6
# counters
VC_ACCEPTED, VC_GATED, VC_SATURATED, VC_FALLBACK = range(4)
N_VCOUNTS = 4
VCOUNT_NAMES = ("observations_accepted", "observations_gated", "saturated", "normal_fallbacks")
_ACCUMULATE, _MISFIT, _DIAGONAL = 0, 1, 2
#: A voxel is looked at closely only where the depth of the pixel nearest its projection puts
#: it within the reach plus this many voxels (the footprint's depth may differ from that
#: pixel's by the surface's slope over the footprint; the exact test on the footprint's depth
#: follows). Only a voxel on a surface steeper than this slack over its footprint is lost.
QUICK_SLACK = 2.0

_NDA = ti.types.ndarray


@ti.func
def _voxel_observation(i: ti.i32, g, levels: ti.i32, ref: ti.template(),
                       d0: ti.template(), d1: ti.template(), d2: ti.template(),
                       d3: ti.template(), d4: ti.template(), p0: ti.template(),
                       p1: ti.template(), p2: ti.template(), p3: ti.template(),
                       p4: ti.template(), vp: ti.template()):
    """(status, y, var, w, n_pix, fallback) of band voxel i (``g``: its ijk) in this frame
    (module docstring): status 1 observed, 2 gated, 0 not observed."""
    prm = ti.static(p0)
    R = ti.Matrix([[prm[P_R + 3 * r + c] for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    voxel = 1.0 / prm[P_INV_VOXEL]
    # (x_i - t_WC) / voxel = ijk - P_O (P_O = t_WC / voxel - 0.5)
    d = ti.Vector([ti.cast(g[c], ti.f64) - prm[P_O + c] for c in ti.static(range(3))])
    p = (R.transpose() @ d) * voxel
    status = 0
    y, var, w, n_pix, fb = ti.f64(0.0), ti.f64(0.0), ti.f64(0.0), ti.f64(0.0), ti.f64(0.0)
    if p[2] > 1e-6:
        z = p[2]
        fx, fy, cx, cy = prm[P_K], prm[P_K + 1], prm[P_K + 2], prm[P_K + 3]
        u = fx * p[0] / z + cx
        v = fy * p[1] / z + cy
        H, W = d0.shape[0], d0.shape[1]
        go = 0
        if u > -0.5 and v > -0.5 and u < ti.cast(W, ti.f64) - 0.5 and \
                v < ti.cast(H, ti.f64) - 0.5:
            # the nearest pixel: invalid there is invalid at every level (a block holds
            # only valid pixels); more than QUICK_SLACK voxels beyond the reach: not observed
            d_near = ti.cast(d0[floor_i32(v + 0.5), floor_i32(u + 0.5)], ti.f64)
            slack = QUICK_SLACK * voxel
            if d_near > 0 and z - d_near >= -vp[V_FRONT] - slack and \
                    z - d_near <= vp[V_BEHIND] + slack:
                go = 1
        if go:
            phi2 = (fx * voxel / z) * (fy * voxel / z)
            phi = ti.sqrt(phi2)
            start = 0
            while start < levels and ti.cast(2 << start, ti.f64) <= phi:
                start += 1
            ray = ti.Vector([p[0] / z, p[1] / z, 1.0], dt=ti.f64)
            found, lvl, un_f, vn_f, count = 0, 0, 0, 0, 0
            D, k_f = ti.f64(0.0), ti.f64(1.0)
            P = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)  # mean camera point of the footprint
            for lv in ti.static(range(MAX_LEVEL + 1)):
                img = ti.static((d0, d1, d2, d3, d4)[lv])
                pl = ti.static((p0, p1, p2, p3, p4)[lv])
                k = ti.static(float(1 << lv))
                if not found and lv <= start:
                    # block (bu, bv) of this level covers pixels k bu .. k bu + k - 1, centre
                    # k bu + (k - 1) / 2; the footprint spans phi / k blocks a side
                    ub = (u - (k - 1.0) / 2.0) / k
                    vb = (v - (k - 1.0) / 2.0) / k
                    half = 0.5 * phi / k
                    Hl, Wl = img.shape[0], img.shape[1]
                    un, vn = floor_i32(ub + 0.5), floor_i32(vb + 0.5)
                    d_ref = ti.f64(0.0)
                    if un >= 0 and vn >= 0 and un < Wl and vn < Hl:
                        d_ref = ti.cast(img[vn, un], ti.f64)
                    if d_ref > 0:
                        # the blocks whose centres lie in the footprint, on the nearest one's
                        # surface (within the normal's slope limit): disjoint for neighbouring
                        # voxels, so no pixel is counted twice in one layer
                        reach = pl[P_JUMP] * d_ref / pl[P_K]  # per block of distance
                        u_lo = ti.max(-floor_i32(half - ub), 0)  # ceil(ub - half)
                        v_lo = ti.max(-floor_i32(half - vb), 0)
                        u_hi = ti.min(floor_i32(ub + half), Wl - 1)
                        v_hi = ti.min(floor_i32(vb + half), Hl - 1)
                        for bv in range(v_lo, v_hi + 1):
                            for bu in range(u_lo, u_hi + 1):
                                db = ti.cast(img[bv, bu], ti.f64)
                                dist = ti.cast(ti.abs(bu - un) + ti.abs(bv - vn), ti.f64)
                                if db > 0 and ti.abs(db - d_ref) <= reach * dist:
                                    P += db * ti.Vector([(ti.cast(bu, ti.f64) - pl[P_K + 2])
                                                        / pl[P_K], (ti.cast(bv, ti.f64)
                                                        - pl[P_K + 3]) / pl[P_K + 1], 1.0])
                                    count += 1
                        if count > 0:
                            P = P / ti.cast(count, ti.f64)
                            found, lvl, un_f, vn_f, k_f = 1, lv, un, vn, k
            if found:  # out of reach at the footprint's mean depth: no normal needed
                t = z - P[2]
                if t < -vp[V_FRONT] - QUICK_SLACK * voxel or t > vp[V_BEHIND] + QUICK_SLACK * voxel:
                    found = 0
            n = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
            if found:
                for lv in ti.static(range(MAX_LEVEL + 1)):
                    if lv == lvl:
                        img = ti.static((d0, d1, d2, d3, d4)[lv])
                        pl = ti.static((p0, p1, p2, p3, p4)[lv])
                        nf = pixel_normal(img, pl, un_f, vn_f)
                        n = ti.Vector([ti.cast(nf[0], ti.f64), ti.cast(nf[1], ti.f64),
                                       ti.cast(nf[2], ti.f64)])
                        fb = ti.cast(nf[3], ti.f64)
                if n.dot(ray) >= -1e-9:  # degenerate: seen head-on along this ray
                    n = -ray / ray.norm()
                    fb = 1.0
                # the footprint's surface point, carried along its plane to this voxel's ray
                D = n.dot(P) / n.dot(ray)
            if found:
                nr = n.dot(ray)
                rn = ray.norm()
                cos_a = -nr / rn
                cos_min = prm[P_COS_MIN]
                t = z - D
                behind = vp[V_BEHIND]
                if vp[V_INCIDENCE] > 0:
                    behind *= ti.max(cos_a, cos_min)
                if t >= -vp[V_FRONT] and t <= behind:
                    y = t * nr
                    sd = depth_sigma(prm, D) * ti.max(cos_a, cos_min) * rn
                    n_pix = k_f * k_f * ti.cast(count, ti.f64)
                    var = (sd * sd + prm[P_VAR_EXTRA]) / n_pix + prm[P_VAR_CORR]
                    w = 1.0 / (var * vp[V_SHARE])
                    status = 1
                    gate = vp[V_GATE]
                    if gate > 0:
                        r = ti.cast(ref[i], ti.f64)  # NaN fails both tests: kept
                        if (y < 0 and r > gate) or (y > 0 and r < -gate):
                            status = 2
    return status, y, var, w, n_pix, fb


@ti.kernel
def _voxel_frame(levels: ti.i32, blocks: _NDA(dtype=ti.i32, ndim=2),
                 block_table: _NDA(dtype=ti.i32, ndim=2), ref: _NDA(dtype=ti.f32, ndim=1),
                 d0: _NDA(dtype=ti.f32, ndim=2), d1: _NDA(dtype=ti.f32, ndim=2),
                 d2: _NDA(dtype=ti.f32, ndim=2), d3: _NDA(dtype=ti.f32, ndim=2),
                 d4: _NDA(dtype=ti.f32, ndim=2), p0: _NDA(dtype=ti.f64, ndim=1),
                 p1: _NDA(dtype=ti.f64, ndim=1), p2: _NDA(dtype=ti.f64, ndim=1),
                 p3: _NDA(dtype=ti.f64, ndim=1), p4: _NDA(dtype=ti.f64, ndim=1),
                 vp: _NDA(dtype=ti.f64, ndim=1), mu: _NDA(dtype=ti.f32, ndim=1),
                 var_post: _NDA(dtype=ti.f32, ndim=1), acc: _NDA(dtype=ti.i64, ndim=2),
                 counts: _NDA(dtype=ti.i64, ndim=1), tile_lo: _NDA(dtype=ti.f32, ndim=2),
                 tile_hi: _NDA(dtype=ti.f32, ndim=2), mode: ti.template()):
    """One frame, every band voxel (module docstring), block by block (``blocks`` (B, 3):
    the band's blocks, ``block_table`` their voxels' band indices); a block whose projection
    lies outside the image, or farther than the reach (plus ``QUICK_SLACK`` voxels) from
    every depth of the TILE x TILE pixel tiles it covers (``tile_lo``, ``tile_hi``: their
    smallest and largest valid depth, :func:`_tile_depths`), is skipped whole. ``mode``
    _ACCUMULATE: ``acc`` (2, N) gets ``w`` and ``w y`` (fixed point); _DIAGONAL: ``acc``
    (1, N) gets ``w``; _MISFIT: ``acc`` (N, 3) the misfit sums of
    :meth:`kernels.observe.Observer.misfit_sums` against ``mu`` and ``var_post``. Each voxel's
    entries are written by its own thread (integer
    sums; the counters are integer reductions): deterministic."""
    scale = vp[V_SCALE]
    R = ti.Matrix([[p0[P_R + 3 * r + c] for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    voxel = 1.0 / p0[P_INV_VOXEL]
    fx, fy, cx, cy = p0[P_K], p0[P_K + 1], p0[P_K + 2], p0[P_K + 3]
    H, W = ti.cast(d0.shape[0], ti.f64), ti.cast(d0.shape[1], ti.f64)
    ti.loop_config(block_dim=4)  # the visible blocks cluster: small chunks balance the threads
    for b in range(blocks.shape[0]):
        # the box of the block's voxel centres, corner by corner: its projection's bounding
        # rectangle (pixels) and depth range (metres); a corner behind the camera: no culling
        u_lo, u_hi, v_lo, v_hi = ti.f64(1e30), ti.f64(-1e30), ti.f64(1e30), ti.f64(-1e30)
        z_min, z_max = ti.f64(1e30), ti.f64(-1e30)
        for c in ti.static(range(8)):
            q = ti.Vector([ti.cast(blocks[b, a] * BLOCK, ti.f64)
                           + ti.static((BLOCK - 1.0) * ((c >> (2 - a)) & 1)) - p0[P_O + a]
                           for a in ti.static(range(3))])  # (corner - t_WC) / voxel
            pc = R.transpose() @ q
            z_min, z_max = ti.min(z_min, pc[2]), ti.max(z_max, pc[2])
            if pc[2] > 0:
                pu, pv = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy
                u_lo, u_hi = ti.min(u_lo, pu), ti.max(u_hi, pu)
                v_lo, v_hi = ti.min(v_lo, pv), ti.max(v_hi, pv)
        visible = 1
        if z_max <= 0:  # wholly behind
            visible = 0
        elif z_min > 0:  # wholly in front: a voxel's nearest pixel lies in the rectangle
            if u_hi < -0.5 or u_lo > W - 0.5 or v_hi < -0.5 or v_lo > H - 0.5:
                visible = 0
            else:  # some tile it covers must hold a depth within reach of the block
                z_lo = z_min * voxel - vp[V_BEHIND] - QUICK_SLACK * voxel
                z_hi = z_max * voxel + vp[V_FRONT] + QUICK_SLACK * voxel
                t_u0 = ti.max(floor_i32((u_lo + 0.5) / TILE), 0)
                t_u1 = ti.min(floor_i32((u_hi + 0.5) / TILE), tile_lo.shape[1] - 1)
                t_v0 = ti.max(floor_i32((v_lo + 0.5) / TILE), 0)
                t_v1 = ti.min(floor_i32((v_hi + 0.5) / TILE), tile_lo.shape[0] - 1)
                near = 0
                for tv in range(t_v0, t_v1 + 1):
                    for tu in range(t_u0, t_u1 + 1):
                        if ti.cast(tile_hi[tv, tu], ti.f64) >= z_lo and \
                                ti.cast(tile_lo[tv, tu], ti.f64) <= z_hi:
                            near = 1
                visible = near
        if visible:
            for slot in range(BLOCK * BLOCK * BLOCK):
                i = block_table[b, slot]
                if i >= 0:
                    g = ti.Vector([blocks[b, 0] * BLOCK + slot // 64,
                                   blocks[b, 1] * BLOCK + (slot // 8) % 8,
                                   blocks[b, 2] * BLOCK + slot % 8])
                    _voxel_step(i, g, levels, ref, d0, d1, d2, d3, d4, p0, p1, p2, p3, p4, vp,
                                mu, var_post, acc, counts, scale, mode)


@ti.func
def _voxel_step(i: ti.i32, g, levels: ti.i32, ref: ti.template(), d0: ti.template(),
                d1: ti.template(), d2: ti.template(), d3: ti.template(), d4: ti.template(),
                p0: ti.template(), p1: ti.template(), p2: ti.template(), p3: ti.template(),
                p4: ti.template(), vp: ti.template(), mu: ti.template(), var_post: ti.template(),
                acc: ti.template(), counts: ti.template(), scale: ti.f64, mode: ti.template()):
    """Voxel i's observation of the frame into ``acc`` (see :func:`_voxel_frame`)."""
    status, y, var, w, n_pix, fb = _voxel_observation(i, g, levels, ref, d0, d1, d2, d3,
                                                      d4, p0, p1, p2, p3, p4, vp)
    if status == 2:
        counts[VC_GATED] += 1
    elif status == 1:
        counts[VC_ACCEPTED] += 1
        if fb > 0:
            counts[VC_FALLBACK] += 1
        if ti.static(mode == _ACCUMULATE):
            old = acc[0, i]
            acc[0, i] = old + fixed_point(w * scale)
            hold = acc[1, i]
            acc[1, i] = hold + fixed_point(w * y * scale)
            if old > ti.i64(SATURATION) or hold > ti.i64(SATURATION) or \
                    hold < -ti.i64(SATURATION):
                counts[VC_SATURATED] += 1
        elif ti.static(mode == _DIAGONAL):
            acc[0, i] = acc[0, i] + fixed_point(w * scale)
        else:
            inv_voxel = p0[P_INV_VOXEL]
            if ti.abs(y) * inv_voxel < MISFIT_NEAR:
                r = y - ti.cast(mu[i], ti.f64)
                pv = ti.cast(var_post[i], ti.f64)
                inv_h2 = inv_voxel * inv_voxel
                s = w * var * n_pix * MISFIT_SCALE  # the footprint's pixels, shared
                acc[i, 0] = acc[i, 0] + fixed_point(s * ti.min(r * r, MISFIT_CAP * var)
                                                    * inv_h2)
                acc[i, 1] = acc[i, 1] + fixed_point(s * ti.max(var - pv, 0.1 * var) * inv_h2)
                acc[i, 2] = acc[i, 2] + fixed_point(s)


@ti.kernel
def _block_means(depth: _NDA(dtype=ti.f32, ndim=2), d1: _NDA(dtype=ti.f32, ndim=2),
                 d2: _NDA(dtype=ti.f32, ndim=2), d3: _NDA(dtype=ti.f32, ndim=2),
                 d4: _NDA(dtype=ti.f32, ndim=2), levels: ti.i32, reach: ti.f32):
    """Levels 1..``levels`` of a frame's pyramid: the mean depth of each k x k block (``k =
    2^l``) whose pixels are all valid and lie on one surface (they differ by at most ``k reach
    mean``, ``reach = tan(normal_max_slope) / fx``: the test of
    :func:`kernels.dataterm.superpixels`), else 0. One thread per block: deterministic."""
    for lv in ti.static(range(1, MAX_LEVEL + 1)):
        dl = ti.static((d1, d2, d3, d4)[lv - 1])
        k = ti.static(1 << lv)
        for by, bx in ti.ndrange(dl.shape[0], dl.shape[1]):  # (1, 1) above ``levels``
            if lv <= levels:
                # the range test alone, as this model's figures were measured (no plane test)
                dl[by, bx] = block_mean_depth(depth, by, bx, k, reach)


#: Pixels a side of the tiles whose depth range culls whole blocks (:func:`_voxel_frame`).
TILE = 16


@ti.kernel
def _tile_depths(depth: _NDA(dtype=ti.f32, ndim=2), lo: _NDA(dtype=ti.f32, ndim=2),
                 hi: _NDA(dtype=ti.f32, ndim=2)):
    """The smallest and largest valid depth of each TILE x TILE tile of ``depth`` (1e30 and 0
    where it has none). One thread per tile: deterministic."""
    for ty, tx in lo:
        a, b = ti.f32(1e30), ti.f32(0.0)
        for dv in range(TILE):
            for du in range(TILE):
                v, u = ty * TILE + dv, tx * TILE + du
                if v < depth.shape[0] and u < depth.shape[1]:
                    d = depth[v, u]
                    if d > 0:
                        a, b = ti.min(a, d), ti.max(b, d)
        lo[ty, tx], hi[ty, tx] = a, b


class VoxelObserver(Observer):
    """:class:`kernels.observe.Observer` with the per-voxel data term of this module: the same
    arguments, checks and methods (:meth:`integrate`, :meth:`finalize`, :meth:`misfit`,
    :meth:`information`, ...), a diagonal data term. Memory: 16 bytes per band voxel (24 more
    for the misfit pass) besides the band's lookup."""

    _blocks = None  # (B, 3) int32 block coordinates of the band's blocks, on first use

    def reset(self) -> None:
        n = max(self.n_voxels, 1)
        self.acc = zeros_aligned((2, n), np.int64)
        self.counts = np.zeros(N_VCOUNTS, np.int64)
        self.pixels_valid = 0
        self.frames = 0
        if self._R_acc is not None:
            self._R_acc = zeros_aligned(self._R_acc.shape, np.int64)

    def release(self) -> None:
        from .stencil import free_compile_arguments

        self.acc = None
        free_compile_arguments()

    def _data_term(self):
        if self.acc is None:
            raise RuntimeError("Observer.release() dropped the data term; reset() first")
        return self.acc

    def _vparams(self) -> np.ndarray:
        share = (1.0 if self.count_once == "voxel"
                 else max(1.0, (self.front_m + self.trunc_m) / self.voxel_size))
        return np.array([self.front_m, self.trunc_m, share, self.gate_m,
                         float(self.behind_incidence), self.fixed_scale], np.float64)

    def _pyramid(self, depth: np.ndarray, prm: np.ndarray) -> tuple:
        """(levels, 5 images, 5 parameter vectors): the frame and its block means up to the
        largest voxel footprint in the frame (k <= f voxel / min depth)."""
        valid = depth > 0
        levels = 0
        if valid.any():
            f = min(prm[P_K], prm[P_K + 1])
            foot = f * self.voxel_size / float(depth[valid].min())
            levels = int(math.floor(math.log2(foot))) if foot >= 2 else 0
            levels = max(0, min(levels, MAX_LEVEL, int(math.log2(min(depth.shape)))))
        H, W = depth.shape
        images = [depth] + [np.zeros((H >> lv, W >> lv) if lv <= levels else (1, 1), np.float32)
                            for lv in range(1, MAX_LEVEL + 1)]
        if levels:
            _block_means(*images, levels, float(prm[P_JUMP] / prm[P_K]))
        params = [self._level_params(prm, 1 << lv) for lv in range(MAX_LEVEL + 1)]
        return levels, images, params

    def _run(self, depth_m, K, T_W_C, sigma_pose_m, mu, var, acc, mode) -> tuple:
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        counts = np.zeros(N_VCOUNTS, np.int64)
        if self.n_voxels:
            levels, images, params = self._pyramid(depth, prm)
            if self._blocks is None:
                self._blocks = decode_keys(self.block_keys).astype(np.int32)
            H, W = depth.shape
            shape = (-(-H // TILE), -(-W // TILE))
            tile_lo, tile_hi = np.empty(shape, np.float32), np.empty(shape, np.float32)
            _tile_depths(depth, tile_lo, tile_hi)
            _voxel_frame(levels, self._blocks, self.block_table, self.reference, *images,
                         *params, self._vparams(), mu, var, acc, counts, tile_lo, tile_hi, mode)
        return counts, depth

    _EMPTY = np.zeros(1, np.float32)

    @staticmethod
    def _check_stride(stride) -> int:
        if Observer._check_stride(stride) != 1:
            raise ValueError("observation.model = 'voxels' uses every pixel: stride must be 1")
        return 1

    def integrate(self, depth_m, K, T_W_C, stride: int = 1, sigma_pose_m=None) -> dict:
        """Add one frame's per-voxel observations; return its counts. ``stride`` must be 1
        (the footprint average uses every pixel)."""
        self._check_stride(stride)
        acc = self._data_term()
        counts, depth = self._run(depth_m, K, T_W_C, sigma_pose_m, self._EMPTY, self._EMPTY,
                                  acc, _ACCUMULATE)
        self.counts += counts
        valid = int(np.count_nonzero(depth > 0))
        self.pixels_valid += valid
        self.frames += 1
        return {"pixels_valid": valid, **dict(zip(VCOUNT_NAMES, counts.tolist()))}

    def frame_rows(self, depth_m, K, T_W_C, stride: int = 1, sigma_pose_m=None) -> dict:
        """One frame's observations, one row per observed voxel (a voxel has one row with
        weight 1 at itself), accumulating nothing: ``idx`` (R,) int64 band indices, ``y`` (R,)
        metres, ``w`` (R,) 1/metre^2, and ``counts``. For tests and debugging."""
        self._check_stride(stride)
        acc = np.zeros((2, max(self.n_voxels, 1)), np.int64)
        counts, _ = self._run(depth_m, K, T_W_C, sigma_pose_m, self._EMPTY, self._EMPTY, acc,
                              _ACCUMULATE)
        idx = np.flatnonzero(acc[0, :self.n_voxels] > 0)
        w, wy = acc[0, idx] / self.fixed_scale, acc[1, idx] / self.fixed_scale
        return {"idx": idx, "y": wy / w, "w": w,
                "counts": dict(zip(VCOUNT_NAMES, counts.tolist()))}

    def misfit(self, depth_m, K, T_W_C, mu, var, stride: int = 1, sigma_pose_m=None) -> None:
        """The misfit sums of one frame against ``mu`` / ``var`` (N,) (as Observer.misfit)."""
        mu, var = self._band_fields(mu, var)
        if self._R_acc is None:
            self._R_acc = zeros_aligned((1, max(self.n_voxels, 1), 3), np.int64)
        if self.n_voxels:
            self._run(depth_m, K, T_W_C, sigma_pose_m, mu, var, self._R_acc[0], _MISFIT)

    def information(self, depth_m, K, T_W_C, stride: int = 1, sigma_pose_m=None) -> np.ndarray:
        """(N,) the diagonal data term of one frame alone (1/metre^2), accumulating nothing."""
        D = np.zeros((1, max(self.n_voxels, 1)), np.int64)
        if self.n_voxels:
            self._run(depth_m, K, T_W_C, sigma_pose_m, self._EMPTY, self._EMPTY, D, _DIAGONAL)
        return D[0, :self.n_voxels] / self.fixed_scale

    def diagonal(self) -> np.ndarray:
        return self._data_term()[0, :self.n_voxels] / self.fixed_scale

    def finalize(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """``S`` (N, 27) float32 with the data term on the diagonal (column CENTRE), ``h`` (N,)
        float32 and the stats (frames, counts, fixed_scale)."""
        from .layout import CENTRE

        acc = self._data_term()
        N = self.n_voxels
        S = np.zeros((N, 27), np.float32)
        S[:, CENTRE] = (acc[0, :N] / self.fixed_scale).astype(np.float32)
        h = (acc[1, :N] / self.fixed_scale).astype(np.float32)
        stats = {"frames": self.frames, "pixels_valid": self.pixels_valid,
                 **dict(zip(VCOUNT_NAMES, self.counts.tolist())),
                 "fixed_scale": self.fixed_scale}
        return S, h, stats
