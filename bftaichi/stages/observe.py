"""Step 3 of Algorithm 1: depth pixels -> SDF samples -> the data term ``A^T W A``, ``A^T W y``
accumulated in the band's 27-point stencil (DESIGN.md section 3.3).

:func:`make_observer` is the one factory of :class:`kernels.observe.Observer`: the solve and the
planner both use it, so the planner predicts information from the same samples, gate and noise
as the solve. :func:`estimate_extra_noise` fits the noise the depth model does not explain."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..checks import check_choice, check_range
from ..errors import ConfigError
from .pairmodel import fit_extra

__all__ = ["ObservationConfig", "make_observer", "observe", "free_space_rows",
           "estimate_extra_noise", "FramePicks"]


@dataclass
class ObservationConfig:
    """``[observation]``: depth pixels -> SDF samples (DESIGN.md 3.3)."""

    stride: int = 1
    """Use every n-th pixel in u and v (pixels; 1 = all, as the TSDF does). A larger stride is
    faster but throws information away: the posterior then sees less than the bootstrap it
    should improve on (at 2, a quarter of the pixels; measured in docs/measurements.md)."""

    spacing_voxels: float = 1.0
    """Spacing of the samples along each ray within ``+-tsdf.trunc_m``, voxels."""

    depth_a_m: float = 0.0012
    """Depth noise model ``sigma_z(z) = a + b (z - z0)^2`` (Kinect axial, Nguyen et al. 2012):
    constant term ``a``, metres."""

    depth_b: float = 0.0019
    """Quadratic term ``b``, 1/metre."""

    depth_z0_m: float = 0.4
    """Reference depth ``z0``, metres."""

    cos_min: float = 0.5
    """How the noise of a sample depends on the incidence angle: ``sigma = sigma_z(D)
    max(cos(angle), cos_min) |ray|`` (no unit, in (0, 1]). A sample observes
    ``y = (z - D) <n, ray>``, so an axial depth error moves it by ``sigma_z cos(angle) |ray|``;
    but the normal estimated from neighbouring pixels, which ``y`` also depends on, gets worse
    as the surface turns away, so the noise is not taken below ``cos_min`` of the axial one.
    Over the development suite (tools/suite.py) 0.5 gave a lower Chamfer distance than 1 (no
    angle dependence) or 0.3, and than the previous model ``sigma_z / max(cos, 0.3)``, which
    weighted oblique pixels down instead of up (docs/measurements.md)."""

    sigma_pose_m: float = 0.0
    """Pose (trajectory) error folded into every sample, metres (0 for ground-truth poses)."""

    sigma_model_m: float = 0.0
    """Extra per-pixel noise, metres, added to every sample in quadrature. Model error (the
    trilinear SDF, the normal estimate) is not independent per pixel, so it is not modelled
    here but by ``local_noise``; 0 by default."""

    front: float = 2.0
    """How far in front of the measured surface a pixel's samples reach, in units of the
    observation truncation ``tau`` (1 to 3; behind the surface they always reach ``tau``; 1 is
    the paper's ``+-tau``). The band reaches ``alpha tau`` in front (default 2): samples out to
    there observe the free space the ray crossed, as the TSDF does, so the prior alone does not
    set those voxels (on real frames it bent them through zero: false surface in free space).
    Measured in docs/measurements.md."""

    gate: float = 0.5
    """Side gate against the bootstrap, in units of ``tau`` (0 = off): a sample behind the
    measured surface (``y < 0``) is dropped where the TSDF interpolated at it says free space by
    more than ``gate * tau``, and one in front (``y > 0``) where it says inside by more. Samples
    whose trilinear cell straddles an occlusion edge (or a flying pixel at one) assert "inside"
    in voxels that many rays saw as free; without the gate they bent the posterior through zero
    there (surfaces fattened past their silhouettes). Only the side is tested, not the value:
    the TSDF holds projective distances, which differ from ``y`` at oblique views."""

    behind: str = "tau"
    """How far behind the measured surface a pixel's samples reach: ``tau`` (the paper's
    ``+-tau``) or ``incidence``, ``tau max(cos(angle), cos_min)`` (camera depth): a ray that
    meets a silhouette or a crease at a grazing angle leaves the body again well within ``tau``,
    and beyond that its samples asserted "inside" in free space no other ray sees, which pushed
    the surface outward there (the largest vertex errors: ``tools/sigma_breakdown.py``).
    Opt-in: over the development suite it lowered the Chamfer distance on 37 of 43 cases
    (geometric mean of posterior / TSDF 0.769 -> 0.682) but lost to the TSDF on one (suzanne
    few_views, 0.95 -> 1.13: completeness where no view looks), and the probe estimate of the
    vertex variance on a coarse sparse sphere went from 6 to 14 % median error (docs/
    measurements.md, docs/suite/behind.md)."""

    fit_noise: bool = True
    """Fit the per-frame noise the depth model does not explain (pose and calibration errors of
    a recorded trajectory, or a noisier sensor) to the frames before observing them
    (:func:`estimate_extra_noise`: how the residuals of head-on pixels against the bootstrap
    differ between frames that see one point, so the bootstrap's own error drops out). The part
    neighbouring pixels share (pose, calibration) is modelled as a correlation: a frame's pixels
    over one voxel share it, so each frame tells a voxel at most ``1 / e_corr^2`` however many
    pixels cover it (``sigma_corr_m`` of :class:`kernels.observe.Observer`), instead of a stride
    that drops pixels; the rest is independent per pixel. report.json:
    ``solver.observations.noise_fit``; band.npz: ``sigma_extra_m``, ``sigma_corr_m``."""

    in_time_order: bool = True
    """The frames come in the order they were recorded, so neighbours share their pose error
    (a recorded trajectory drifts). The noise fit then also measures how many frames in a row
    one error of its extra noise spans (:func:`.sharednoise.frames_sharing_noise`; 1 where it
    finds no significant sharing, as with independent noise), and the data's part of the
    variance counts those frames as one (:func:`.sharednoise.shared_noise_factor`); the MAP
    does not change (unless ``shared_in_map``). Set false for frames in no particular order.
    report.json: ``solver.observations.noise_fit.frames_sharing_noise``."""

    shared_in_map: bool = False
    """Count the frames' shared extra noise in the MAP as well (with ``in_time_order``): each
    frame's correlated part ``sigma_corr^2`` is taken as shared by the ``L`` frames one error
    spans (at most the frames fused), so a frame tells a voxel at most ``1 / (L sigma_corr^2)``
    of it and a run of ``L`` frames about what one frame's pose error allows. The variance
    keeps its ``kappa`` (with ``kappa`` set to 1 the sigma of a drifting scan covered far too
    little of its error). Where the fit finds ``L`` = 1 (frames in no order, synthetic rings,
    independent jitter) nothing changes. Off by default: on held-out real views it lowers the
    2 cm mean error and raises the 1 cm one (docs/measurements.md, "The frames' shared pose
    error in the MAP")."""

    local_noise: bool = True
    """Judge the noise model against the data around each voxel after the solve
    (:func:`~.misfit.local_misfit`: a second pass over the frames compares every sample with the
    posterior mean) and add the excess ``b^2`` where they disagree more than the noise model
    explains (thin sheets, occlusion edges, creases finer than a voxel, misregistered frames),
    which does not average down over pixels. That is where the surface errors are. Where the
    data are quieter than the model the variance is left as it is (scaling it down by that
    ratio, as until issue 15's share fix, made sigma too small on the noisy and dense captures:
    docs/measurements.md). report.json: ``solver.variance.local_noise``.
    """

    aggregate: float = 1.0
    """Super-pixels where a voxel spans many pixels (no unit; 0 = off): a k x k block of pixels
    that lie on one planar surface (within twice the sensor's noise,
    :func:`kernels.funcs.block_is_planar`) is observed as one pixel at its mean depth carrying
    the information of all k^2 (``k`` a power of two up to 16, at most ``aggregate`` voxel
    footprints ``f voxel / depth`` pixels a side). Every valid pixel still counts, once; on a
    plane the block's mean is the surface at its centre, and where a block is not planar its
    pixels are observed in smaller blocks or one by one. The cost of the observation pass then
    grows with the voxels seen more than with the pixels: 1.0 (blocks of up to a voxel) is
    1.9x faster than 0.5 on real 1 cm frames, and where a voxel spans under 2 pixels (the
    development suite) it changes nothing. Measured in docs/measurements.md."""

    misfit_frames: int = 100
    """Frames the ``local_noise`` pass observes again: at most this many, evenly spread over
    the sequence (0: all). The misfit is a ratio of mean squared residuals to their expected
    value per 3-voxel window, a statistic that a hundred frames already give from many pixels
    per voxel; a 30 Hz sequence of 500 frames repeats each view many times over. Fewer
    frames than this: all of them (the development suite is unchanged). Measured in
    docs/measurements.md."""

    model: str = "rays"
    """How frames become the data term: ``rays`` (samples along every pixel's ray, each a
    trilinear row: a 27-point data stencil; :mod:`kernels.observe`) or ``voxels`` (each band
    voxel looks its frame up once, the depth averaged over its footprint: a diagonal data term
    whose cost grows with the voxels, not the pixels; :mod:`kernels.voxelobs`). ``voxels``
    made the observation pass 3x faster on real 2 cm frames, and over the development suite its
    vertices more accurate but its surfaces less complete where no view looks: Chamfer
    distance over the TSDF's 0.797 against 0.769 (geometric mean), 4 of 43 cases above the
    TSDF's (docs/measurements.md, docs/suite/voxels.md). ``voxels`` needs ``stride = 1``."""

    count_once: str = "voxel"
    """How a pixel's samples, which share one depth error, split its information ``1/sigma^2``:
    ``pixel`` gives each of its n samples ``1/n`` (the pixel counts once in all); ``voxel``
    gives each sample ``1/min(n, ceil(voxel / spacing))`` (the pixel counts at most once in each
    voxel's estimate: the trilinear weights its samples put on one voxel sum to at most about
    one per voxel of spacing). Dividing by n made sigma about 2x too conservative; dividing
    by the two samples that reach a voxel (the rule until issue 15's share fix) about 1.5x on
    smooth surfaces (docs/measurements.md)."""

    def axial_sigma_m(self, depth_m):
        """The axial depth noise ``a + b (D - z0)^2`` (metres) at depth ``depth_m`` (float or
        array), without the incidence factor: the model the observation kernel uses."""
        return self.depth_a_m + self.depth_b * (depth_m - self.depth_z0_m) ** 2

    def check(self) -> None:
        check_range("observation.stride", self.stride, 1, 64)
        check_range("observation.spacing_voxels", self.spacing_voxels, 0.1, 10.0)
        check_range("observation.front", self.front, 1.0, 3.0)
        check_range("observation.aggregate", self.aggregate, 0.0, 4.0)
        check_range("observation.misfit_frames", self.misfit_frames, 0, 1_000_000)
        check_range("observation.gate", self.gate, 0.0, 10.0)
        check_choice("observation.behind", self.behind, ("tau", "incidence"))
        check_range("observation.depth_a_m", self.depth_a_m, 0.0)
        check_range("observation.depth_b", self.depth_b, 0.0)
        check_range("observation.cos_min", self.cos_min, 0.01, 1.0)
        check_range("observation.sigma_pose_m", self.sigma_pose_m, 0.0)
        check_range("observation.sigma_model_m", self.sigma_model_m, 0.0)
        check_choice("observation.count_once", self.count_once, ("pixel", "voxel"))
        check_choice("observation.model", self.model, ("rays", "voxels"))
        if self.model == "voxels" and self.stride != 1:
            raise ConfigError(f"observation.stride = {self.stride}: observation.model = "
                              "'voxels' averages every pixel of a voxel's footprint (stride 1)")
        if self.depth_a_m + self.sigma_pose_m + self.sigma_model_m <= 0:
            raise ConfigError("observation: depth_a_m, sigma_pose_m and sigma_model_m are all 0, "
                              "so a sample would have zero variance (infinite weight)")


#: The normal of a pixel reads its neighbours up to this many pixels away (kernels/observe.py,
#: step 1): the longest baseline a noisy pixel's normal takes.
NORMAL_RADIUS_MAX_PX = 4
#: Largest normal angle noise, radians: each pixel takes the shortest baseline ``r`` (pixels,
#: at most NORMAL_RADIUS_MAX_PX) over which its depth noise ``sigma`` tilts the normal by at most
#: this much, ``sigma fx / (sqrt(2) r D) <= 0.6`` (about 34 degrees; the 1-pixel baseline of the
#: Kinect's 1.9 mm at 1 m, fx = 585, already tilts it by 0.8 rad). A longer baseline than
#: needed smooths creases; a shorter one gives normals that are mostly noise, so the samples in
#: front of and behind the surface land off the ray's true distance (docs/measurements.md,
#: "The rule, measured"; 0.45 scores the same, 0.8 worse).
NORMAL_MAX_NOISE_RAD = 0.6


def make_observer(band, obs: ObservationConfig, voxel_size_m: float, trunc_m: float,
                  sigma_extra_m: float = 0.0, sigma_corr_m: float = 0.0):
    """The :class:`kernels.observe.Observer` of ``band`` (a :class:`~.band.Band`) with the
    observation model ``obs``, the observation truncation ``trunc_m`` (tau, metres) and the
    fitted extra noise ``sigma_extra_m`` (metres), of which ``sigma_corr_m`` is shared by a
    frame's pixels over a voxel (``sigma_corr_m`` of the Observer) and the rest is independent
    per pixel: a depth error along the ray like the sensor's own (``sigma_axial_m``, carried to
    ``y`` by the incidence cosine; the fit measures it along the ray). The side gate tests
    against the band's bootstrap TSDF (:attr:`Band.reference`); each pixel's normal baseline
    follows its noise (:data:`NORMAL_MAX_NOISE_RAD`)."""
    from kernels.observe import Observer
    from kernels.voxelobs import VoxelObserver

    corr = min(float(sigma_corr_m), float(sigma_extra_m))
    independent = float(np.sqrt(max(sigma_extra_m ** 2 - corr ** 2, 0.0)))
    cls = VoxelObserver if obs.model == "voxels" else Observer
    return cls(band.block_keys, band.block_table, len(band), voxel_size_m, trunc_m,
               spacing_m=obs.spacing_voxels * voxel_size_m, depth_a_m=obs.depth_a_m,
               depth_b=obs.depth_b, depth_z0_m=obs.depth_z0_m, cos_min=obs.cos_min,
               sigma_pose_m=obs.sigma_pose_m, sigma_model_m=obs.sigma_model_m,
               sigma_axial_m=independent, sigma_corr_m=corr, count_once=obs.count_once,
               front_m=obs.front * trunc_m, reference=band.reference,
               gate_m=obs.gate * trunc_m, aggregate=obs.aggregate,
               behind_incidence=obs.behind == "incidence",
               normal_radius_px=NORMAL_RADIUS_MAX_PX, normal_max_noise_rad=NORMAL_MAX_NOISE_RAD)


def free_space_rows(band, trunc_m: float) -> np.ndarray:
    """Band rows whose free space ``prior.carve`` counts: the observed voxels the averaged TSDF
    does not already call free (``tsdf <= tau``; the others are in the inequality anyway)."""
    return np.flatnonzero(band.observed & (band.tsdf <= trunc_m))


def observe(observer, frames, stride: int, free_space=None):
    """Feed every frame to ``observer`` (pixel ``stride``) and, when given, to ``free_space``
    (a :class:`kernels.carve.FreeSpaceCounter`, in the same pass: frames are read once);
    return the observer's ``(S, h, stats)``: the data term's stencil (N, 27) float32,
    ``A^T W y`` (N,) and the sample counts."""
    for frame in frames:
        observer.integrate(frame.depth_m, frame.K, frame.T_W_C, stride=stride)
        if free_space is not None:
            free_space.add(frame.depth_m, frame.K, frame.T_W_C)
    return observer.finalize()


class FramePicks:
    """At most ``n`` of ``frames`` (anything with ``len`` and indexing), evenly spread over the
    sequence, first and last included (``n`` = 0 or at least ``len(frames)``: all of them)."""

    def __init__(self, frames, n: int):
        total = len(frames)
        self.frames = frames
        self.picks = (np.arange(total) if n <= 0 or n >= total
                      else np.unique(np.linspace(0, total - 1, n).round().astype(int)))

    def __len__(self) -> int:
        return len(self.picks)

    def __getitem__(self, i: int):
        return self.frames[int(self.picks[i])]


def _head_on(depth: np.ndarray, K: np.ndarray, cos_min: float = 0.8,
             stride: int = 1) -> np.ndarray:
    """(H, W) bool: valid pixels whose surface faces the camera within ``acos(cos_min)``,
    from the normal of the back-projected depth's central differences (both neighbours valid
    along u and v). Only every ``stride``-th pixel in u and v is tested (the others are
    False): the pixels the noise fit casts."""
    h, w = depth.shape
    ok = np.zeros((h, w), bool)
    vs, us = np.arange(0, h, stride), np.arange(0, w, stride)
    vs, us = vs[(vs >= 1) & (vs <= h - 2)], us[(us >= 1) & (us <= w - 2)]
    if not (len(vs) and len(us)):
        return ok
    v, u = np.meshgrid(vs, us, indexing="ij")

    def ray(vv, uu):
        vv, uu = vv.astype(np.float64), uu.astype(np.float64)
        return np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1],
                         np.ones_like(uu)], -1)

    def point(vv, uu):
        return depth[vv, uu][..., None].astype(np.float64) * ray(vv, uu)

    tu = point(v, u + 1) - point(v, u - 1)
    tv = point(v + 1, u) - point(v - 1, u)
    n = np.cross(tu, tv)
    r = ray(v, u)
    cos = np.abs((n * r).sum(-1)) / np.maximum(np.linalg.norm(n, axis=-1) *
                                                 np.linalg.norm(r, axis=-1), 1e-30)
    valid = depth > 0
    inner = (valid[v, u + 1] & valid[v, u - 1] & valid[v + 1, u] & valid[v - 1, u]
             & valid[v, u])
    ok[v, u] = inner & (cos >= cos_min)
    return ok


#: The noise fit casts at least this many pixels of each frame (a smaller ``stride`` on small
#: frames): fewer leave too few pairs of frames seeing one point for a robust median.
_MIN_CAST = 5000


def _cast_frame(f, band, observed: np.ndarray, voxel_size_m: float, bootstrap_trunc_m: float,
                depth_range_m: tuple[float, float], stride: int = 4) -> tuple:
    """The noise fit's view of frame ``f``: the bootstrap (``band``, its ``observed`` cells as
    uint8) ray cast at every ``step``-th pixel (``stride``, denser on frames of fewer than
    ``_MIN_CAST stride^2`` pixels) that is valid and head-on (:func:`_head_on`; the others are
    not kept, so not cast: 0.5 s of the fit's 1.7 s at 2 cm on redkitchen) and the residuals
    ``z_tsdf - D`` of those within ``bootstrap_trunc_m``. Returns ``(residual, mask, D, K,
    T_W_C, step)``, the first three at the cast pixels (see :func:`estimate_extra_noise`)."""
    from kernels.raycast import raycast_depth

    h, w = f.depth_m.shape
    step = int(max(1, min(stride, np.sqrt(h * w / _MIN_CAST))))
    D = np.asarray(f.depth_m, np.float64)
    head_on = _head_on(D, np.asarray(f.K, np.float64), stride=step)  # valid pixels only
    z = raycast_depth(band.block_keys, band.block_table, band.tsdf, observed, voxel_size_m,
                      f.K, f.T_W_C, w, h, depth_range_m[0], depth_range_m[1], stride=step,
                      mask=head_on)  # the other pixels are not kept: not cast
    both = (z > 0) & head_on
    res = np.where(both, z - D, 0.0)
    both &= np.abs(res) < bootstrap_trunc_m
    return (res[::step, ::step], both[::step, ::step], D[::step, ::step],
            np.asarray(f.K, np.float64), np.asarray(f.T_W_C, np.float64), step)


def estimate_extra_noise(frames, band, obs: ObservationConfig, voxel_size_m: float,
                         bootstrap_trunc_m: float, depth_range_m: tuple[float, float], *,
                         n_frames: int = 16, stride: int = 4,
                         max_offset_px: float | None = None) -> dict:
    """Per-frame depth noise the sensor model does not explain, fitted to the frames themselves.

    Recorded trajectories carry pose and calibration errors that no axial noise model holds
    (on 7-Scenes the held-out depth residual is ~2x the Kinect model's sigma). The bootstrap TSDF
    is rendered (:func:`kernels.raycast.raycast_depth`, observed band cells) at up to
    ``n_frames`` frames spread over the sequence, every ``stride``-th pixel (denser on frames
    of fewer than ``_MIN_CAST stride^2`` pixels); the residuals
    ``r = z_tsdf - D`` of the pixels whose surface faces the camera (within 37 deg) with
    ``|r| < alpha tau`` (gross ones, e.g. at occlusion edges, are no noise) are kept.

    The bootstrap's own error (its bias on curved surfaces, its voxels) is in every residual
    too, but it is the *same* in every frame that sees a surface point, while a frame's noise
    and pose error are its own. So residuals are compared in pairs at one surface point: each
    cast pixel's point is projected into every other cast frame, and where that frame has a
    cast pixel there that sees the same point (nearest cast pixel), ``d = r_f - r_g`` holds
    no bootstrap error. The pairs are modelled as ``N(0, s^2 + 2 e^2)``, ``s^2 = sigma_D(D_f)^2
    + sigma_D(D_g)^2``, ``sigma_D = a + b (D - z0)^2``. A pair counts only where its two frames
    agree within ``t = max(2 voxels, 3 sqrt(s^2 + 2 e^2))``, 3 sigma of that model (else the
    two pixels may see different surfaces), so the kept ``|d|`` are a normal's truncated at
    ``t``, and ``e >= 0`` solves ``median P(|d'| <= |d| | |d'| <= t) = 1/2`` over the pairs
    (``d'`` of the pair's model; without the truncation this is ``median(|d| / sqrt(...)) =
    0.6745``, the median of a standard normal's ``|x|``; 0 when the model alone already
    reaches it). The cut holds ``e``, so the fit is repeated with the cut of the last ``e``
    until ``e`` moves by less than 0.5 % (at most ``_CUT_ROUNDS`` fits). A cut of the voxel
    size alone made the fit depend on it: ``max(2 voxels, 3 sigma_D)`` found 10.1 mm on
    7-Scenes at 1 cm against 10.9 mm at 2 cm (6.6 against 9.8 mm without modelling the cut);
    this one 10.9 and 11.5 mm (a fixed cut of 8 cm at both sizes found 10.9 and 11.6 mm:
    what is left is not the cut; docs/measurements.md).
    Robust to the outliers and deterministic. Fitted to the residuals themselves, the
    bootstrap's error on the development suite's curved objects read as 0.5-0.9 mm of frame
    noise (docs/measurements.md).

    The part of ``e`` that neighbouring pixels share (pose and calibration errors) is half the
    mean product of the ``d`` of neighbouring cast pixels (``stride`` apart) of one frame
    paired with two distinct cast pixels of the same other frame, ``c`` (independent noise
    averages out of it; a pixel of the other frame paired with both would put its own noise
    in):
    ``e_corr = sqrt(clip(c, 0, e^2))``; the rest, ``sqrt(e^2 - e_corr^2)``, is independent
    per pixel (:func:`make_observer` splits them).

    ``max_offset_px`` (None: every pair) keeps only the pairs whose point projects within that
    many pixels of the paired pixel's centre in the other frame: the two pixels then see nearly
    the same point, so the bootstrap's error cancels more of the way (docs/measurements.md,
    "The noise fit on synthetic captures")).

    With ``obs.in_time_order`` (frames in their recorded order), also how many frames in a row
    share one error of ``e`` (a recorded trajectory's poses drift): each of the spread frames
    is cast with the frame after it too, and :func:`.sharednoise.frames_sharing_noise` fits
    how the pairs' noise grows with their gap in time (``frames_sharing_noise``: 1 where it
    does not grow significantly; ``sharing_z``, ``sharing_length``), and
    ``shared_fraction``, the share of a frame's variance at a voxel that is the shared part
    (:func:`_shared_in_time`). The variance stage counts such runs of frames as one
    (:func:`.sharednoise.shared_noise_factor`).

    Returns ``{"sigma_extra_m": e, "sigma_corr_m": e_corr, "pixels": n, "frames": k,
    "median_normalised_model": m0, "cut_rounds": c}`` (``n`` the pixel pairs; m0: the
    statistic with ``e = 0``, 0.6745 is calibrated; ``c`` the fits the cut took), and the
    four above with ``obs.in_time_order``."""
    picks = FramePicks(frames, n_frames)
    observed = band.observed.astype(np.uint8)
    cast = [_cast_frame(f, band, observed, voxel_size_m, bootstrap_trunc_m, depth_range_m,
                        stride) for f in picks]
    # the pairs' cut is 3 sigma of the pair's own model, which holds e: fit, cut again, refit
    # until e settles (it grows with the cut; a few rounds)
    pairs = _pair_candidates(cast, obs, max_offset_px)
    e = 0.0
    for rounds in range(1, _CUT_ROUNDS + 1):
        r, s, t, shared = _cut_pairs(pairs, voxel_size_m, e)
        if len(r) < 100:
            return {"sigma_extra_m": 0.0, "sigma_corr_m": 0.0, "pixels": int(len(r)),
                    "frames": int(len(picks)), "median_normalised_model": None,
                    "cut_rounds": rounds}
        e_new = fit_extra(r, s, t)
        done = abs(e_new - e) <= 0.005 * max(e_new, 1e-6)
        e = e_new
        if done:
            break
    m0 = float(np.median(r / s))  # the model alone: 0.6745 is calibrated
    corr = float(np.sqrt(min(max(shared, 0.0), e * e)))
    out = {"sigma_extra_m": e, "sigma_corr_m": corr, "pixels": int(len(r)),
           "frames": int(len(picks)), "median_normalised_model": m0, "cut_rounds": rounds}
    if obs.in_time_order:  # frames close in time share their extra noise (drifting poses)
        out.update(_shared_in_time(frames, picks.picks, cast, pairs, band, observed, obs,
                                   voxel_size_m, bootstrap_trunc_m, depth_range_m, stride,
                                   max_offset_px, e, corr, float(np.median(s * s))))
    return out


def _shared_in_time(frames, picks, cast, pairs, band, observed, obs, voxel_size_m,
                    bootstrap_trunc_m, depth_range_m, stride, max_offset_px, e, corr,
                    s2) -> dict:
    """:func:`.sharednoise.frames_sharing_noise` of the fit's pairs and of each pick with the
    frame after it (a gap of one), and ``shared_fraction``: the share of a frame's variance
    at a voxel that is the pixels' shared noise ``e_corr``, the rest (``s^2 / 2 + e^2 -
    e_corr^2`` a pixel, ``s2`` the pairs' median ``s^2``) averaged over the pixels that
    cover a voxel at the median depth (``observation.stride``)."""
    from .sharednoise import frames_sharing_noise

    timed = [p[:-1] + ((int(picks[p[-1][0]]), int(picks[p[-1][1]])),) for p in pairs]
    taken = set(picks.tolist())
    for i, at in enumerate(picks):
        if at + 1 < len(frames) and at + 1 not in taken:
            after = _cast_frame(frames[int(at) + 1], band, observed, voxel_size_m,
                                bootstrap_trunc_m, depth_range_m, stride)
            timed += [p[:-1] + ((int(at), int(at) + 1),)
                      for p in _pair_candidates([cast[i], after], obs, max_offset_px)]
    out = frames_sharing_noise(timed, lambda p: _cut_pairs(p, voxel_size_m, e, shared=False)[:3],
                               e)
    px = np.concatenate([(K[0, 0] * voxel_size_m / (D[m] * obs.stride)) ** 2
                         for _, m, D, K, _, _ in cast if m.any()] or [np.ones(1)])
    per_voxel = (0.5 * s2 + e * e - corr * corr) / max(float(np.median(px)), 1.0)
    out["shared_fraction"] = corr * corr / max(corr * corr + per_voxel, 1e-30)
    return out


#: Rounds of the noise fit's cut (3 sigma of the pair model, which holds the fitted noise).
_CUT_ROUNDS = 6


def _pair_candidates(cast, obs: ObservationConfig, max_offset_px: float | None) -> list:
    """The noise fit's candidate pairs, per pair of cast frames (i, j): each cast pixel of i
    whose point lands on a cast pixel of j. Per pair of frames ``(shape_i, v, u, into, gap, s,
    d, (i, j))``: the pixels of i, the pixel of j each landed on (``cv width_j + cu``),
    ``|D_j - z_j|`` (how far j's depth is from the point), the two frames' sensor sigma in
    quadrature, ``d = r_i - r_j`` and the two frames' indices in ``cast``. Which of them see
    one point is :func:`_cut_pairs`'s."""
    pairs = []
    for i, (g_i, m_i, D_i, K_i, T_i, st_i) in enumerate(cast):
        v, u = np.nonzero(m_i)
        if not len(v):
            continue
        dep = D_i[v, u]
        sd_i = obs.axial_sigma_m(dep)
        p_w = np.stack([(u * st_i - K_i[0, 2]) / K_i[0, 0] * dep,
                        (v * st_i - K_i[1, 2]) / K_i[1, 1] * dep, dep], 1) @ T_i[:3, :3].T \
            + T_i[:3, 3]
        for j, (g_j, m_j, D_j, K_j, T_j, st_j) in enumerate(cast[i + 1:], i + 1):
            p = (p_w - T_j[:3, 3]) @ T_j[:3, :3]  # into frame j's camera (each pair once)
            zj = p[:, 2]
            front = zj > 0
            cu = np.full(len(p), -1)
            cv = np.full(len(p), -1)
            fu = (K_j[0, 0] * p[front, 0] / zj[front] + K_j[0, 2]) / st_j
            fv = (K_j[1, 1] * p[front, 1] / zj[front] + K_j[1, 2]) / st_j
            cu[front], cv[front] = np.rint(fu), np.rint(fv)
            inside = front & (cu >= 0) & (cv >= 0) & (cu < m_j.shape[1]) & (cv < m_j.shape[0])
            if max_offset_px is not None:  # the paired pixel's centre near the projected point
                near = np.zeros(len(p), bool)
                near[front] = np.hypot(fu - cu[front], fv - cv[front]) * st_j <= max_offset_px
                inside &= near
            ok = np.zeros(len(p), bool)
            ok[inside] = m_j[cv[inside], cu[inside]]
            if not ok.any():
                continue
            D_ok = D_j[cv[ok], cu[ok]]
            pairs.append((g_i.shape, v[ok], u[ok], cv[ok] * m_j.shape[1] + cu[ok],
                          np.abs(D_ok - zj[ok]), np.hypot(sd_i[ok], obs.axial_sigma_m(D_ok)),
                          g_i[v[ok], u[ok]] - g_j[cv[ok], cu[ok]], (i, j)))
    return pairs


def _cut_pairs(pairs: list, voxel_size_m: float, e: float, shared: bool = True):
    """The candidate pairs whose frames agree within ``t = max(2 voxels, 3 sqrt(s^2 + 2
    e^2))``, 3 sigma of the pair's model for an extra noise ``e`` (else the two pixels may see
    different surfaces): their ``|d|``, ``s`` and ``t``, and the shared part's mean product
    (see :func:`estimate_extra_noise`; 0 without ``shared``)."""
    d_all, s_all, t_all = [], [], []
    lag_sum, lag_n = 0.0, 0
    for shape_i, v, u, into_j, gap, s, d, _ in pairs:
        tol = np.maximum(2.0 * voxel_size_m, 3.0 * np.sqrt(s * s + 2.0 * e * e))
        ok = gap < tol  # the same point, else not
        if not ok.any():
            continue
        d_all.append(d[ok])
        t_all.append(tol[ok])  # the pair was kept only if it agreed within this
        s_all.append(s[ok])
        if not shared:
            continue
        # neighbouring cast pixels of frame i paired with frame j: the product of their d
        # keeps what the pixels of a frame share (2 e_corr^2), not independent noise, where
        # they pair with two pixels of frame j (with one, seen at an angle, the product would
        # hold that pixel's own noise, var(r_j), as if shared)
        grid = np.zeros(shape_i)
        into = np.full(shape_i, -1, np.int64)  # the frame-j cast pixel each was paired to
        grid[v[ok], u[ok]] = d[ok]
        into[v[ok], u[ok]] = into_j[ok]
        for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1], np.s_[1:])):  # along u, v
            pair = (into[a] >= 0) & (into[b] >= 0) & (into[a] != into[b])
            lag_sum += 0.5 * float(np.sum(grid[a][pair] * grid[b][pair]))
            lag_n += int(pair.sum())
    r = np.abs(np.concatenate(d_all)) if d_all else np.zeros(0)
    s = np.concatenate(s_all) if s_all else np.zeros(0)
    t = np.concatenate(t_all) if t_all else np.zeros(0)
    return r, s, t, (lag_sum / lag_n if lag_n else 0.0)
