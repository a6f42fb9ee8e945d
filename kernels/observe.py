"""Depth observations accumulated into the 27-point data stencil (DESIGN.md 3, steps 3-4).

For every frame and every ``stride``-th valid pixel ``(u, v)`` with depth ``D`` (metres):

1. **Normal** ``n`` (:func:`pixel_normal`): the pixel and its neighbours ``r`` pixels to the
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
   depend on the image resolution. With ``normal_max_noise_rad`` a pixel takes the smallest
   ``r <= normal_radius_px`` whose normal angle noise ``sigma fx / (sqrt(2) r D)`` is at most it
   (``sigma``: its axial noise of step 4 without the incidence factor; docs/measurements.md).
2. **Samples** at camera depths ``z_j = D + j * spacing``, ``j = -m..m``,
   ``m = floor(tau / spacing)``, on the pixel ray (``z_j <= 0`` is skipped; it cannot happen for
   ``D > tau``). The sample point is ``x_j = t_WC + z_j R_WC K^-1 (u, v, 1)`` (world, metres), its
   observation ``y_j = <n, x_j - p> = (z_j - D) <n, K^-1 (u, v, 1)>``: the signed distance of
   ``x_j`` to the plane through ``p`` with normal ``n``, positive in front of the surface. It is
   *not* clamped: ``|y_j| <= tau |K^-1 (u, v, 1)|``, up to ~1.25 tau in image corners.
   2b. **Reach behind the surface** (``behind_incidence``, opt-in): a sample behind it (``j >
   0``) asserts "inside by ``|y_j|``", which holds only while the ray is still inside the
   object. A ray entering a body at incidence ``angle`` leaves it after the chord ``2 R
   cos(angle)`` (``R``: its radius of curvature); with ``behind_incidence`` the samples behind
   reach at most ``tau max(cos(angle), cos_min)`` in camera depth, the units of the truncation
   (``j <= floor(m max(cos, cos_min))``): the chord of a body ``tau`` thick, with the noise
   model's floor on the cosine. Beyond it, at a silhouette or a crease seen at a grazing angle,
   they assert "inside" in free space that no other ray sees, and the surface bulges out there
   (docs/measurements.md). In front of the surface the planar ``y_j`` underestimates the
   distance to a convex surface, which does not move the zero crossing.
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
4. **Noise**: ``sigma^2 = sigma_depth^2 + sigma_pose^2 + sigma_model^2``, the axial noise (and
   ``sigma_axial``) carried to ``y``: ``sigma_depth = sqrt((a + b (D - z0)^2)^2 + sigma_axial^2)
   max(cos(angle), cos_min) |ray|``, ``cos(angle) = -n . ray / |ray|`` (the floor stands for the
   normal estimate). All samples of a pixel share one depth error, so the pixel's information is
   counted once: each of its ``n_acc`` accepted samples gets ``w = 1 / (n_acc sigma^2)`` (the
   samples are counted first, then accumulated), so ``sum_j w_j = 1 / sigma^2`` per pixel.
5. **Accumulation**: ``Q += w a a^T``, ``h += w y a``. Entry ``(c, c')`` of ``a a^T`` joins corner
   voxels whose offset ``corner(c') - corner(c)`` is in ``{-1, 0, 1}^3``, i.e. stencil offset
   ``o = (di+1) 9 + (dj+1) 3 + (dk+1)`` of the row of corner ``c``. Only the upper half
   (``c <= c'``, which is ``o >= 13``) is accumulated; :meth:`Observer.finalize` fills
   ``S[i, o] = S[nbr(i, o), 26 - o]`` for ``o < 13``, so the stencil is symmetric bit for bit.

Super-pixels (``aggregate`` > 0, at stride 1): where a voxel spans many pixels, a k x k block
of pixels (``k = 2^l``, l = 1..MAX_LEVEL) whose depths are all valid and lie on one planar
surface (they differ by at most ``k tan(normal_max_slope) D / fx`` and deviate from their
least-squares plane by at most PLANE_NOISE = 2 times the axial noise at D, RMS, a 2 x 2 block's
plane fitted with its ring of pixels: :func:`kernels.funcs.block_is_planar`; on a plane the
block's mean depth is the surface at its centre, across a step, a crease or a bend it lies on
no surface) is observed as one pixel of the block
image (intrinsics ``fx / k``, ``(cx - (k - 1) / 2) / k``) at the block's mean depth: its
normal from the neighbouring blocks, its samples and rows as above, and the information of its
k^2 pixels (``w`` times k^2; each still counts ``sigma^2 + rho sigma_corr^2`` with ``rho`` in
full-resolution pixels). The coarsest block that spans at most ``aggregate`` voxel footprints
(``k <= aggregate f voxel / D``) takes its pixels; the rest go to finer levels, down to single
pixels at edges and where a voxel spans about a pixel or less. Every valid pixel is observed
exactly once (:func:`kernels.dataterm.superpixels`). What the block gives up is where inside it
each ray met the surface, within a voxel; a noiseless box is still fitted exactly
(tests/test_observe.py). The misfit pass sees the block's residual against the mean's variance
``(sigma_depth^2 + sigma_pose^2 + sigma_model^2) / k^2 + sigma_corr^2``.

Fixed point (determinism without float atomics): every contribution ``x`` is added to int64
accumulators as ``round(x * scale)`` (round half away from zero), ``scale = 2^FRACTION_BITS /
w_max`` rounded down to a power of two, ``w_max = 1 / ((a cos_min)^2 + sigma_pose^2 +
sigma_model^2)``
the largest possible weight (sigma_depth >= a cos_min; a frame's sigma_pose may not go below the
Observer's). One pixel's contribution to ``S`` is at most ``w_max`` (``a_c a_c' <= 1``), 2^32
units; a rounding error is at most 2^-33 w_max, far below the float32 resolution of any entry.
Each thread adds into its own copy of the accumulators (``parts``: one per CPU thread, at most
MAX_PARTS = 4), without atomics; the copies are summed when read. *Saturation*: the adds test
nothing (a test per add cost ~9 % of the pass); :meth:`Observer.integrate` sums the frames'
bounds on an entry's growth (:func:`kernels.fixedpoint.growth_bound`) and, before they pass
2^62, counts the entries beyond 2^60 (:meth:`~Observer.finalize` counts too), so none wraps
around at 2^63 unseen (for frames under ~2^30 / (mf + m + 1) pixels): a saturation count of
0 guarantees exact sums. Integer addition is associative, so the accumulated arrays are
bitwise identical whatever the thread schedule and thread count (and the frames' order).

Layout of the accumulator: ``acc`` (parts, N, 16) int64, per voxel column ``o - 13`` for ``o =
13..26``, then ``A^T W y`` and a 0: a row is two cache lines (:data:`kernels.dataterm.ACC_COLUMNS`);
the frame kernels take a flat view. Per-row counters: ``counts`` (rows, N_COUNTS) int64.

Cost (one launch per pyramid level, each thread taking runs of 4 pixel rows): per pixel a
normal (5 depth reads), per sample a cell lookup and, if accepted, 36 + 8 int64 adds (the upper
half of ``a a^T`` and ``a y``). The lookup (:func:`kernels.lookup.look_up_sample`) reads the
block table through a per-row cache of the blocks around sample j's block, looking a block up
(hashed) only when a cell reaches it (perf put 35 % of the pass in binary searches of all 8).
Per-thread copies instead of int64 atomics took the pass from ~520 to ~150 ns per sample, and
super-pixels cut the samples ~12x (docs/measurements.md; measured and not kept there: summing
a row's samples per cell before the adds, an unrolled corner loop).
"""

import math

import numpy as np
import taichi as ti

from .dataterm import (C_SATURATED, COUNT_NAMES, N_COUNTS, N_PARAMS, P_A, P_B, P_COS_MIN,
                       P_AGGREGATE, P_BEHIND, P_GATE, P_INV_VOXEL, P_JUMP, P_K, P_M,
                       P_NORMAL_NOISE, P_O, P_PIXELS, P_R, P_RADIUS, P_SCALE, P_SHARE, P_SPACING,
                       P_VAR_AXIAL, P_VAR_CORR, P_VAR_EXTRA, P_Z0, ROW_ACCEPTED, ROW_DROPPED,
                       ACC_COLUMNS, MISFIT_COLUMNS, MISFIT_SCALE, MISFIT_UNITS, estimate_normals,
                       finalize_stencil, misfit_frame, observe_frame, observe_rows, superpixels,
                       window_sums)
from .fixedpoint import (FRACTION_BITS, GROWTH_LIMIT, accumulator_parts, growth_bound,
                         saturated_count)
from .layout import BLOCK_VOXELS
from .lookup import BLOCK_CACHE, band_ijk_from_table, build_block_hash
from .stencil import free_compile_arguments, zeros_aligned

def _pinhole_inverse(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """K^-1 of pinhole intrinsics, (3, 3) float64."""
    return np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])


#: Largest super-pixel: 2^MAX_LEVEL = 16 pixels a side.
MAX_LEVEL = 4


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
        cos_min: floor of the incidence cosine multiplying the axial noise (step 4).
        sigma_pose_m: pose noise, metres; also the smallest per-frame value :meth:`integrate`
            accepts (the fixed-point scale is sized for the largest weight).
        sigma_model_m: model noise (planar approximation, discretisation), metres.
        sigma_axial_m: extra axial depth noise per pixel, metres, added to ``a + b (D - z0)^2``
            in quadrature (step 4; docs/experiments/axial_extra_noise.py; default 0).
        normal_radius_px: tangent offset r of the normal estimate, pixels (module docstring);
            with ``normal_max_noise_rad`` > 0 (radians; default 0) the largest, r per pixel.
        count_once: how a pixel's shared depth error is counted (no default): ``"pixel"``,
            its samples share one ``1 / sigma^2``; ``"voxel"``, each voxel gets at most one
            pixel's information (see the constructor's comment).
        front_m: how far in front of the measured surface the samples reach, metres (>=
            ``trunc_m``, no default; ``trunc_m``: as far as behind). Samples there observe
            ``y = <n, x - p>`` like the others: the free space the ray crossed, as the TSDF
            sees it.
        sigma_corr_m: per-frame noise (pose and calibration errors), metres, shared by the pixels
            of one frame over one voxel: each of the ``rho = (fx / (D voxel_size^-1 stride))^2``
            pixels a voxel spans gets ``rho sigma_corr^2`` more variance, so one frame tells a
            voxel at most ``1 / sigma_corr^2`` however many pixels cover it (0: independent).
        gate_m, reference: the side gate of step 3b: the gate in metres (no default; 0: no
            gate, no reference needed) and the (N,) reference SDF (metres; NaN where there is
            none).
        behind_incidence: the samples behind the surface reach ``tau max(cos, cos_min)`` in
            depth instead of ``tau`` (step 2b; default False).
        normal_max_slope_deg: steepest surface inclination (from the image plane) whose
            neighbouring depths still count as one surface in the normal estimate, degrees.

    Raises ValueError for inconsistent inputs (the weight needs a floor: one of ``depth_a_m``,
    ``sigma_pose_m``, ``sigma_model_m`` > 0). Taichi must be initialised first. Memory: 128
    bytes per band voxel per CPU thread (int64 accumulators, one copy per thread, at most
    MAX_PARTS; :meth:`release` drops them) plus 16 (ijk, the gate's float32 reference); the
    misfit pass adds 56 per voxel per thread.
    """

    def __init__(self, block_keys: np.ndarray, block_table: np.ndarray, n_voxels: int,
                 voxel_size: float, trunc_m: float, *, spacing_m: float | None = None,
                 depth_a_m: float = 0.0012, depth_b: float = 0.0019, depth_z0_m: float = 0.4,
                 cos_min: float = 0.3, sigma_pose_m: float = 0.0, sigma_model_m: float = 0.001,
                 normal_radius_px: int = 1, normal_max_slope_deg: float = 85.0,
                 count_once: str, front_m: float, gate_m: float,
                 reference: np.ndarray | None = None, sigma_corr_m: float = 0.0,
                 aggregate: float = 0.0, behind_incidence: bool = False,
                 sigma_axial_m: float = 0.0, normal_max_noise_rad: float = 0.0):
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.spacing_m = self.voxel_size if spacing_m is None else float(spacing_m)
        if count_once not in ("pixel", "voxel"):
            raise ValueError(f"Observer: count_once = {count_once!r} is not 'pixel' or 'voxel'")
        # "pixel": the n_acc samples of a pixel share its 1/sigma^2 (w = 1 / (n_acc sigma^2)).
        # "voxel": each voxel gets at most one pixel's information. The trilinear weights a
        # ray's samples put on one voxel sum to at most about voxel / spacing (1 on an axis,
        # 0.87 on a diagonal), so with w = 1 / (min(n_acc, share) sigma^2), share =
        # ceil(voxel / spacing), a voxel's share of the pixel, sum_k w a_k^2 <= sum_k w a_k,
        # is at most about 1 / sigma^2 (docs/measurements.md).
        self.count_once = count_once
        self.share = (float(math.ceil(self.voxel_size / self.spacing_m - 1e-9))
                      if count_once == "voxel" else 1e30)
        values = {"voxel_size": self.voxel_size, "trunc_m": self.trunc_m,
                  "spacing_m": self.spacing_m, "cos_min": cos_min,
                  "normal_max_slope_deg": normal_max_slope_deg}
        for name, val in values.items():
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"Observer: {name} = {val} must be a positive number")
        for name, val in {"depth_a_m": depth_a_m, "depth_b": depth_b, "sigma_pose_m": sigma_pose_m,
                          "sigma_model_m": sigma_model_m, "sigma_axial_m": sigma_axial_m,
                          "normal_max_noise_rad": normal_max_noise_rad}.items():
            if not (math.isfinite(val) and val >= 0):
                raise ValueError(f"Observer: {name} = {val} must be >= 0")
        if cos_min > 1:
            raise ValueError(f"Observer: cos_min = {cos_min} must be in (0, 1]")
        if normal_max_slope_deg >= 90:
            raise ValueError(f"Observer: normal_max_slope_deg = {normal_max_slope_deg} must be "
                             "in (0, 90)")
        if int(normal_radius_px) < 1:
            raise ValueError(f"Observer: normal_radius_px = {normal_radius_px} must be >= 1")
        var_floor = (depth_a_m * cos_min) ** 2 + sigma_pose_m ** 2 + sigma_model_m ** 2
        if var_floor <= 0:
            raise ValueError("Observer: depth_a_m, sigma_pose_m and sigma_model_m are all 0 (the "
                             "observation weight 1 / sigma^2 needs a floor)")
        self.n_voxels = int(n_voxels)
        self.block_keys = np.ascontiguousarray(block_keys, np.int64)
        self.block_table = np.ascontiguousarray(block_table, np.int32)
        if self.block_table.ndim != 2 or self.block_table.shape[1] != BLOCK_VOXELS or \
                self.block_keys.shape != (self.block_table.shape[0],):
            raise ValueError(f"Observer: block_keys {self.block_keys.shape} / block_table "
                             f"{self.block_table.shape} are not (B,) / (B, 512)")
        self.ijk = band_ijk_from_table(self.block_keys, self.block_table, self.n_voxels)
        self.block_hash = build_block_hash(self.block_keys)  # the frame kernels' block lookup
        self.depth_model = (float(depth_a_m), float(depth_b), float(depth_z0_m), float(cos_min))
        self.sigma_pose_m = float(sigma_pose_m)
        self.sigma_model_m = float(sigma_model_m)
        self.sigma_axial_m = float(sigma_axial_m)
        if not (math.isfinite(sigma_corr_m) and sigma_corr_m >= 0):
            raise ValueError(f"Observer: sigma_corr_m = {sigma_corr_m} must be >= 0")
        self.sigma_corr_m = float(sigma_corr_m)
        if not (math.isfinite(aggregate) and aggregate >= 0):
            raise ValueError(f"Observer: aggregate = {aggregate} must be >= 0 (0: off)")
        self.aggregate = float(aggregate)
        self.normal_radius_px = int(normal_radius_px)
        self.normal_max_noise_rad = float(normal_max_noise_rad)
        self.normal_max_slope_deg = float(normal_max_slope_deg)
        self.m = sample_count(self.trunc_m, self.spacing_m) // 2
        # samples in front of the surface reach front_m (trunc_m: as far as those behind)
        self.front_m = float(front_m)
        if not (math.isfinite(self.front_m) and self.front_m >= self.trunc_m):
            raise ValueError(f"Observer: front_m = {front_m} must be >= trunc_m = {self.trunc_m}")
        self.mf = sample_count(self.front_m, self.spacing_m) // 2
        self.gate_m = float(gate_m)
        self.behind_incidence = bool(behind_incidence)
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
        # one copy of the accumulators per thread (the kernels add without atomics)
        self.parts = accumulator_parts()
        self._params = np.zeros(N_PARAMS, np.float64)
        self._scratch_buf = None
        self._R_acc = None  # misfit sums (N, 3), allocated by the first misfit()
        self.reset()

    def reset(self) -> None:
        """Forget all frames (zero the accumulators, the misfit sums and the counters)."""
        # fresh zeroed memory, not zeros written over the old: pages are zeroed as the kernels
        # first touch them (writing 0 over 420 MB took 1.1 s on a 1.86M-voxel band); numpy,
        # not ti.ndarray: what release() drops goes back to the system
        n = max(self.n_voxels, 1)
        self.acc = zeros_aligned((self.parts, n, ACC_COLUMNS), np.int64)
        self.counts = np.zeros(N_COUNTS, np.int64)
        self.frames = 0
        self._unchecked = 0.0  # bound on any entry's growth since the last saturation count
        if self._R_acc is not None:
            self._R_acc = zeros_aligned(self._R_acc.shape, np.int64)

    def release(self) -> None:
        """Drop the data term's accumulator (128 bytes per voxel per thread) once
        :meth:`finalize` has given what they hold: :meth:`misfit` and :meth:`frame_rows` do not
        need them. :meth:`integrate`, :meth:`diagonal` and :meth:`finalize` then raise until
        :meth:`reset`."""
        self.acc = None
        free_compile_arguments()  # else the compiling calls' references keep them resident

    def _data_term(self) -> np.ndarray:
        if self.acc is None:
            raise RuntimeError("Observer.release() dropped the data term; reset() first")
        return self.acc

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
        K_inv = _pinhole_inverse(fx, fy, cx, cy)
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
        prm[P_VAR_AXIAL] = self.sigma_axial_m ** 2
        prm[P_RADIUS] = self.normal_radius_px
        prm[P_NORMAL_NOISE] = self.normal_max_noise_rad
        prm[P_JUMP] = math.tan(math.radians(self.normal_max_slope_deg))
        prm[P_SCALE] = self.fixed_scale
        prm[P_SHARE] = self.share
        prm[P_GATE] = self.gate_m
        prm[P_INV_VOXEL] = 1.0 / self.voxel_size
        prm[P_VAR_CORR] = self.sigma_corr_m ** 2
        prm[P_PIXELS] = 1.0
        prm[P_AGGREGATE] = self.aggregate
        prm[P_BEHIND] = float(self.behind_incidence)
        return depth, prm

    def _levels(self, depth: np.ndarray, prm: np.ndarray, stride: int) -> list:
        """The frame as ``[(image, mask, params, k)]``, one entry per level of its super-pixel
        pyramid, coarsest first: level l observes the pixels of ``image`` (the frame averaged
        over k x k blocks, ``k = 2^l``) where ``mask`` is 1, each as the mean of its k^2 pixels
        with their information (module docstring, "Super-pixels"). Without aggregation (or at
        ``stride`` > 1) one level: the frame itself, every valid pixel."""
        valid = depth > 0
        levels = 0
        if self.aggregate > 0 and stride == 1 and valid.any():
            f = min(prm[P_K], prm[P_K + 1])
            foot = self.aggregate * f * self.voxel_size / float(depth[valid].min())
            levels = int(math.floor(math.log2(foot))) if foot >= 2 else 0
            levels = max(0, min(levels, MAX_LEVEL, int(math.log2(min(depth.shape)))))
        if levels == 0:
            return [(depth, valid.view(np.int8), prm, 1)]
        H, W = depth.shape
        images = [depth] + [np.zeros((H >> lv, W >> lv) if lv <= levels else (1, 1), np.float32)
                            for lv in range(1, MAX_LEVEL + 1)]
        masks = [np.zeros((H >> lv, W >> lv) if lv <= levels else (1, 1), np.int8)
                 for lv in range(MAX_LEVEL + 1)]
        superpixels(*images, *masks, prm, levels)
        return [(images[lv], masks[lv], self._level_params(prm, 1 << lv), 1 << lv)
                for lv in range(levels, -1, -1)]

    @staticmethod
    def _level_params(prm: np.ndarray, k: int) -> np.ndarray:
        """The parameters of pyramid level ``k`` (pixels a side): intrinsics of the k x k
        blocks (block u covers pixels k u .. k u + k - 1, centre k u + (k - 1) / 2)."""
        if k == 1:
            return prm
        out = prm.copy()
        fx, fy, cx, cy = prm[P_K:P_K + 4]
        fx, fy, cx, cy = fx / k, fy / k, (cx - (k - 1) / 2) / k, (cy - (k - 1) / 2) / k
        out[P_K:P_K + 4] = fx, fy, cx, cy
        R_WC = prm[P_R:P_R + 9].reshape(3, 3)
        K_inv = _pinhole_inverse(fx, fy, cx, cy)
        out[P_M:P_M + 9] = (R_WC @ K_inv * prm[P_INV_VOXEL]).ravel()
        out[P_PIXELS] = float(k * k)
        return out

    def _level_runs(self, depth: np.ndarray, prm: np.ndarray, stride: int):
        """Per level of :meth:`_levels`, what a frame kernel takes besides the band: ``(image,
        mask, params, counts, scratch)``, ``counts`` zeroed (strided rows, N_COUNTS)."""
        for image, mask, prm_l, _ in self._levels(depth, prm, stride):
            n_vs = (image.shape[0] + stride - 1) // stride
            yield image, mask, prm_l, np.zeros((n_vs, N_COUNTS), np.int64), self._scratch(n_vs)

    def _scratch(self, n_rows: int) -> tuple:
        """Per-row scratch arrays of the frame kernel (see observe_frame), flat, reused."""
        slots = n_rows * (self.mf + self.m + 1)
        if self._scratch_buf is None or len(self._scratch_buf[0]) < 8 * slots:
            self._scratch_buf = tuple(np.empty(k * slots, np.int32) for k in (8, BLOCK_CACHE))
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
        acc = self._data_term()
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        frame = np.zeros(N_COUNTS, np.int64)
        growth = growth_bound(depth.shape, *prm[P_K:P_K + 4], prm[P_SPACING], prm[P_SHARE],
                              self.m, self.mf)  # module docstring, "Saturation"
        found = self._count_saturated() if self._unchecked + growth > GROWTH_LIMIT else 0
        self._unchecked += growth
        for image, mask, prm_l, counts, scratch in self._level_runs(depth, prm, stride):
            if self.n_voxels:
                observe_frame(image, mask, prm_l, self.block_hash, self.block_table,
                              self.reference, stride, self.m, self.mf, self.parts,
                              acc.reshape(-1), counts, *scratch)
            frame += counts.sum(axis=0)
        self.counts += frame
        self.frames += 1
        frame[C_SATURATED] = found  # what a count before this frame found (0: none ran)
        return dict(zip(COUNT_NAMES, frame.tolist()))

    def _count_saturated(self, found: int | None = None) -> int:
        """Count the entries beyond 2^60 (or take finalize's count); ``counts`` keeps the max."""
        if found is None:
            found = saturated_count(self._data_term()) if self.n_voxels else 0
        self.counts[C_SATURATED] = max(self.counts[C_SATURATED], int(found))
        self._unchecked = 0.0
        return found

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
        W = depth.shape[1]
        n_s = self.mf + self.m + 1
        parts, total = [], np.zeros(N_COUNTS, np.int64)
        for image, mask, prm_l, k in self._levels(depth, prm, stride):
            n_vs = (image.shape[0] + stride - 1) // stride
            n_us = (image.shape[1] + stride - 1) // stride
            R = n_vs * n_us * n_s
            rows = (np.full((R, 8), -1, np.int32), np.zeros((R, 8)), np.zeros(R), np.zeros(R),
                    np.zeros(R), np.zeros(R, np.int32))
            counts = np.zeros((n_vs, N_COUNTS), np.int64)
            if self.n_voxels:
                observe_rows(image, mask, prm_l, self.block_hash, self.block_table,
                             self.reference, stride, self.m, self.mf, counts,
                             *self._scratch(n_vs), *rows)
            total += counts.sum(axis=0)
            idx, a, y, w, z, status = rows
            slot = np.arange(R) // n_s
            # a super-pixel's rows are reported at its first (top-left) pixel
            pixel = (slot // n_us) * stride * k * W + (slot % n_us) * stride * k
            ok, drop = status == ROW_ACCEPTED, status == ROW_DROPPED
            parts.append((idx[ok], a[ok], y[ok], w[ok], z[ok], pixel[ok], pixel[drop], z[drop]))
        cat = [np.concatenate(col) for col in zip(*parts)]
        return {"idx": cat[0], "a": cat[1], "y": cat[2], "w": cat[3], "z": cat[4],
                "pixel": cat[5], "dropped_pixel": cat[6], "dropped_z": cat[7],
                "counts": dict(zip(COUNT_NAMES, total.tolist()))}

    def frame_normals(self, depth_m: np.ndarray, K: np.ndarray,
                      T_W_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-frame unit normals (H, W, 3) float32 of every valid pixel, facing the camera
        (0 at invalid pixels), and (H, W) bool: True where the normal fell back to the negated
        ray direction (module docstring, step 1)."""
        depth, prm = self._frame_params(depth_m, K, T_W_C, None)
        normals = np.zeros(depth.shape + (3,), np.float32)
        fallback = np.zeros(depth.shape, np.int32)
        estimate_normals(depth, prm, normals, fallback)
        return normals, fallback.astype(bool)

    def misfit(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray, mu: np.ndarray,
               var: np.ndarray, stride: int = 1, sigma_pose_m: float | None = None) -> None:
        """Add one frame's misfit against the band values ``mu`` (N,) (metres; the posterior
        mean, ``var`` its variance, metres^2) to :meth:`misfit_sums`: the samples and weights of
        :meth:`integrate`; nothing else changes. Deterministic."""
        stride = self._check_stride(stride)
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        mu, var = self._band_fields(mu, var)
        if self._R_acc is None:
            shape = (self.parts, max(self.n_voxels, 1), MISFIT_COLUMNS)
            self._R_acc = zeros_aligned(shape, np.int64)
        if not self.n_voxels:
            return
        for image, mask, prm_l, counts, scratch in self._level_runs(depth, prm, stride):
            misfit_frame(image, mask, prm_l, self.block_hash, self.block_table, self.reference,
                         stride, self.m, self.mf, mu, var, self.parts, self._R_acc.reshape(-1),
                         counts, *scratch)

    def _band_fields(self, mu, var) -> tuple[np.ndarray, np.ndarray]:
        """``mu``, ``var`` as (N,) float32 (ValueError naming their shapes otherwise)."""
        mu = np.ascontiguousarray(mu, np.float32)
        var = np.ascontiguousarray(var, np.float32)
        if mu.shape != (self.n_voxels,) or var.shape != (self.n_voxels,):
            raise ValueError(f"mu {mu.shape} and var {var.shape} must have shape "
                             f"({self.n_voxels},)")
        return mu, var

    def misfit_sums(self) -> np.ndarray:
        """(N, 7) float64 sums over the frames given to :meth:`misfit`, per voxel, of ``a_k s_k``
        times ``min(r_k^2, cap sigma_k^2)``, ``sigma_k^2`` (metres^2), 1, ``r_k`` clipped as its
        square is, the distance ``y_k`` from the pixel's surface (metres), ``y_k^2`` and ``r_k
        y_k`` (metres^2), over the samples within ``MISFIT_NEAR`` voxels of it (``s_k``: its share
        of the pixel; :func:`kernels.dataterm.misfit_frame`). The voxel model: the first three."""
        if self._R_acc is None or not self.n_voxels:
            return np.zeros((self.n_voxels, MISFIT_COLUMNS))
        R = self._R_acc.sum(axis=0)[:self.n_voxels] / MISFIT_SCALE
        for c, power in enumerate(MISFIT_UNITS[:R.shape[1]]):  # to metres
            R[:, c] *= self.voxel_size ** power
        return R

    def misfit_window(self, nbr: np.ndarray) -> np.ndarray:
        """:meth:`misfit_sums` summed over each voxel's 27-point window (N, 7 or 3) float64,
        ``nbr`` (N, 27) int32 naming the voxels (-1: outside the band). One kernel."""
        sums = np.ascontiguousarray(self.misfit_sums(), np.float64)
        nbr = np.ascontiguousarray(nbr, np.int32)
        if nbr.shape != (self.n_voxels, 27):
            raise ValueError(f"nbr must have shape ({self.n_voxels}, 27), got {nbr.shape}")
        out = np.zeros_like(sums)
        if self.n_voxels:
            window_sums(nbr, sums, out)
        return out

    def information(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
                    stride: int = 1, sigma_pose_m: float | None = None) -> np.ndarray:
        """(N,) float64 ``(A^T W A)_ii`` of one frame alone (1/metre^2), accumulating nothing:
        bitwise :meth:`diagonal` after :meth:`reset` and :meth:`integrate` of that frame, at a
        fraction of the cost (:mod:`kernels.information`; what a planner asks of each
        candidate view). Works after :meth:`release`."""
        from .information import information_frame

        stride = self._check_stride(stride)
        depth, prm = self._frame_params(depth_m, K, T_W_C, sigma_pose_m)
        D_acc = np.zeros((self.parts, max(self.n_voxels, 1)), np.int64)
        if self.n_voxels:
            for image, mask, prm_l, counts, scratch in self._level_runs(depth, prm, stride):
                information_frame(image, mask, prm_l, self.block_hash, self.block_table,
                                  self.reference, stride, self.m, self.mf, self.parts,
                                  D_acc.reshape(-1), counts, *scratch)
        return D_acc.sum(axis=0)[:self.n_voxels] / self.fixed_scale

    # -- result ------------------------------------------------------------------------------
    def diagonal(self) -> np.ndarray:
        """(N,) float64 diagonal of the data term so far, ``(A^T W A)_ii`` (1/metre^2): what
        next-best-view planning needs of a hypothetical frame, without assembling the
        stencil (:meth:`finalize`). Exact (from the fixed-point sums)."""
        if not self.n_voxels:
            return np.zeros(0)
        self._count_saturated()
        return self._data_term()[:, :, 0].sum(axis=0) / self.fixed_scale

    def finalize(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """The data term so far: ``S_data`` (N, 27) float32 (stencil of A^T W A, symmetric:
        ``S[i, o] == S[nbr[i, o], 26 - o]``, 0 towards voxels outside the band), ``h_data`` (N,)
        float32 (A^T W y, 1/metre), and stats: ``frames``, the COUNT_NAMES counts (``saturated``
        > 0: entries came within 2x of int64 overflow, the sums may be wrong) and
        ``fixed_scale``. The accumulators are kept (more frames may follow). Deterministic."""
        N = self.n_voxels
        S = np.zeros((N, 27), np.float32)
        h = np.zeros(N, np.float32)
        if N:
            found = np.zeros(1, np.int64)
            finalize_stencil(self.block_keys, self.block_table, self.ijk, self._data_term(),
                             1.0 / self.fixed_scale, S, h, found)
            self._count_saturated(found[0])
        stats = {"frames": self.frames, **dict(zip(COUNT_NAMES, self.counts.tolist())),
                 "fixed_scale": self.fixed_scale}
        return S, h, stats
