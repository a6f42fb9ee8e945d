"""Plausibility checks of a run's input (issue 17): input the loaders accept, that would give
a wrong result with exit code 0.

The loaders check each file on its own (it parses, has the right shape, holds a rigid pose);
they cannot see that the frames *together* make no sense. :func:`check_inputs` looks at a few
frames after loading and before the TSDF (cheap: at most :data:`SAMPLE_FRAMES` frames and
:data:`SAMPLE_PIXELS` pixels of each) and returns its :class:`Finding` s. Each finding is a
:class:`PlausibilityWarning` (the CLI prints ``warning: ...`` on stderr, ``-q`` or not) and is
recorded in ``report.json`` (``warnings``: code and message; ``checks``: what was measured);
with ``run.strict`` (``--strict``) the run is refused instead (:class:`ImplausibleInputError`,
exit code 2) before anything is written.

The checks (code: rule, and why that rule):

``backend_fallback``
    The Taichi backend that runs (:func:`bftaichi.backend.effective_arch`) differs from the
    requested ``run.arch`` (Taichi falls back to the CPU when a GPU backend is unavailable).
    The run records what ran: ``cfg.run.arch`` (and so ``config.toml`` and the report's
    ``config``) becomes the arch in use, ``machine`` holds ``arch`` and ``arch_requested``.
``image_size``
    The depth image's size against the principal point of K, by
    :func:`~bftaichi.formats.base.principal_point_misfit`: an exact rule (no tolerance) that
    catches a transposed image and intrinsics for twice or half the resolution, yet accepts a
    principal point far off centre along one axis.
    Layouts that declare the image size (bfsdf, replica, redwood, co3d, a folder with
    ``width``/``height``, the 7-Scenes / TUM / PrimeSense presets) already refuse any depth
    image of another size; those that do not (7-Scenes and TUM with their own K file, ScanNet,
    a folder without the size) take the size of the first frame, and the loader refuses one
    that K's principal point puts outside, or fits another resolution better
    (:meth:`~bftaichi.formats.base.Dataset._check_size`). What the loader lets through,
    a transposed image, or a declared size that is itself the transpose of K's, is this
    warning.
``depth_8bit``
    A depth file stored as an 8-bit image (Pillow mode ``L``): at most 256 depth levels, up to
    0.255 m in millimetres; no RGB-D sensor writes that, a grey picture saved as .png does.
``depth_range``
    The median measured depth (every positive depth, before the depth range drops any) lies
    outside ``[depth_min_m, depth_max_m]``: most of what the sensor measured would be thrown
    away, which is what a depth scale off by a power of ten does (the range is the sensor's,
    e.g. 0.1-6 m for a Kinect-class camera, 0.3-4 m in ``scenes/redkitchen.toml``; synthetic
    objects at 0.3-1.5 m pass). The warning names the power of ten that would bring the median
    into the range.
``pose_convention``, ``depth_scale``
    Frames that overlap must agree: a sampled pixel of frame i, back-projected and projected
    into frame j, lands on j's measured depth (within :data:`DEPTH_TOLERANCE`, relative) or
    behind it (occluded); landing *in front* of it puts a surface where j saw empty space
    (a conflict). :func:`frame_consistency` measures this for the poses as given, for the
    poses inverted (T_C_W read as T_W_C) and for the depth scaled by 10 and by 1/10. The
    warning fires when an alternative is consistent (conflicts at most
    :data:`ALTERNATIVE_CONFLICT` of its tested points), agrees on at least
    :data:`AGREEMENT_GAIN` more of the sampled points than the given reading, and the given
    reading is contradicted (conflicts at least :data:`GIVEN_CONFLICT`) or, for the depth
    scale only, explains little (agreement under :data:`GIVEN_AGREEMENT`). Conflicts rather
    than agreement alone decide the pose convention because agreement also measures overlap:
    a sphere seen from a ring of cameras agrees better with every camera collapsed onto one
    point (the inverted look-at poses) than with the true ring, yet nothing conflicts as
    given. Ambiguous input stays silent: a few frames with little motion (every reading
    agrees), or an object a ring of cameras sees alike from everywhere.
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from . import backend
from .errors import BftaichiError, BftaichiWarning
from .formats.base import Dataset, misfit_text, principal_point_misfit
from .formats.readers import invert_rigid

__all__ = ["Finding", "Checks", "PlausibilityWarning", "ImplausibleInputError", "check_inputs",
           "frame_consistency"]

SAMPLE_FRAMES = 8
"""Frames read by the checks, evenly spread over the sequence (all pairs of them are compared:
28 pairs for 8)."""

SAMPLE_PIXELS = 1000
"""Valid pixels per frame back-projected by the consistency check (evenly spaced in raster
order); the depth-range check takes at most as many per frame."""

DEPTH_TOLERANCE = 0.05
"""Relative depth difference within which a reprojected point agrees with the other frame's
depth: 5 %, above Kinect-class noise plus pose error (about 1 % at 3 m), below the 10x or
inverted-pose disagreements. Relative, so the depth-scale hypotheses are judged alike."""

MIN_PAIR_OVERLAP = 0.1
"""A frame pair counts when at least this fraction of its sampled points agrees under some
reading (given, inverted or rescaled); pairs that see nothing of each other under every
reading carry no information."""

GIVEN_CONFLICT = 0.15
"""Conflict fraction at which the given poses and scale are contradicted. Measured on the
shipped data: at most 0.04 (redkitchen, 8 frames of 100-500; synthetic scenes 0.03), against
0.18-0.85 for inverted poses and 0.17-0.78 for a depth scale off by 10 (redkitchen frames
5-60 apart; the synthetic scenes)."""

GIVEN_AGREEMENT = 0.1
"""Agreement (fraction of sampled points) under which the given depth scale explains too
little of frames that a rescaled depth makes overlap (a synthetic orbit with the depth 10x
off: no sampled point lands on another frame's surface at all)."""

ALTERNATIVE_CONFLICT = 0.1
"""An alternative reading must be consistent: at most this conflict fraction."""

AGREEMENT_GAIN = 0.1
"""... and agree on at least this many more of the sampled points than the given one."""

MIN_POINTS = 100
"""Agreeing points (over all pairs) an alternative needs before it can be believed."""


@dataclass(frozen=True)
class Finding:
    """One implausible input: ``code`` (short, stable) and ``message`` (names the file, frame or
    option and the fix)."""

    code: str
    message: str

    def to_dict(self) -> dict:
        return {"code": self.code, "message": self.message}

    def __str__(self) -> str:
        return f"{self.message} [{self.code}]"


class PlausibilityWarning(BftaichiWarning):
    """An input that is read without error but is probably wrong (:class:`Finding`)."""


class ImplausibleInputError(BftaichiError):
    """``run.strict`` refuses a run whose input failed a plausibility check."""


@dataclass
class Checks:
    """What :func:`check_inputs` found and measured.

    Attributes:
        findings: the failed checks, in check order.
        arch_requested: ``run.arch`` as asked for; arch: the backend Taichi runs on.
        measured: per check, the numbers it decided on (``report.json``'s ``checks``).
    """

    findings: list[Finding] = field(default_factory=list)
    arch_requested: str = "cpu"
    arch: str = "cpu"
    measured: dict = field(default_factory=dict)

    def warnings(self) -> list[dict]:
        """``report.json``'s ``warnings``: one ``{code, message}`` per finding."""
        return [f.to_dict() for f in self.findings]


def check_inputs(cfg, frames) -> Checks:
    """Initialise the backend of ``cfg.run.arch`` and run every check on ``frames`` (a frame
    source with ``len`` and indexing). Sets ``cfg.run.arch`` to the backend Taichi runs on.

    Each finding is issued as a :class:`PlausibilityWarning`; with ``cfg.run.strict`` none is,
    and :class:`ImplausibleInputError` lists them all instead.
    """
    checks = Checks(arch_requested=cfg.run.arch)
    _check_backend(cfg, checks)
    idx = sample_indices(len(frames), SAMPLE_FRAMES)
    if idx:
        measured, full_range = _measured_depth_view(frames)
        sampled = [measured[i] for i in idx]
        _check_image_size(sampled[0], checks)
        _check_bit_depth(sampled, frames, checks)
        _check_depth_range(sampled, frames, cfg, full_range, checks)
        _check_consistency(sampled, frames, cfg, checks)
    if checks.findings and cfg.run.strict:
        listed = "\n".join(f"  - {f}" for f in checks.findings)
        raise ImplausibleInputError(
            f"run.strict (--strict) refuses input that failed {len(checks.findings)} plausibility "
            f"check{'s' if len(checks.findings) > 1 else ''}:\n{listed}\nFix the input as said, "
            "or run without --strict (the run then warns and records this in report.json).")
    for f in checks.findings:
        warnings.warn(PlausibilityWarning(str(f)), stacklevel=2)
    return checks


def sample_indices(n: int, k: int) -> list[int]:
    """At most ``k`` indices of ``range(n)``, evenly spread, first and last included."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, k))})


def _measured_depth_view(frames):
    """``(view, True)``: a recorded dataset with its depth range opened to every positive depth
    (so the checks see what the sensor measured, not what the range kept); ``(frames, False)``
    for other sources (synthetic scenes render within their range)."""
    if not isinstance(frames, Dataset):
        return frames, False
    view = copy.copy(frames)
    view.depth_min_m, view.depth_max_m = 0.0, math.inf
    return view, True


# -- backend ---------------------------------------------------------------------------------

def _check_backend(cfg, checks: Checks) -> None:
    backend.init(cfg.run.arch)
    effective = backend.effective_arch()
    checks.arch = effective
    checks.measured["backend"] = {"requested": cfg.run.arch, "effective": effective}
    wanted_gpu = cfg.run.arch == "gpu" and effective != "cpu"
    if effective != cfg.run.arch and not wanted_gpu:
        checks.findings.append(Finding("backend_fallback", (
            f"run.arch = {cfg.run.arch!r} (--arch {cfg.run.arch}) was requested but Taichi "
            f"found no usable {cfg.run.arch} device and runs on the {effective}: the run is "
            f"recorded as {effective} (config.toml, report.json machine.arch); install the "
            f"GPU driver, or ask for --arch cpu")))
    cfg.run.arch = effective


# -- image size against K --------------------------------------------------------------------

def _check_image_size(frame, checks: Checks) -> None:
    h, w = frame.depth_m.shape
    misfit = principal_point_misfit(frame.K, w, h)
    checks.measured["image_size"] = {"width": w, "height": h,
                                     "cx": float(frame.K[0, 2]), "cy": float(frame.K[1, 2])}
    if misfit is None:
        return
    kind, (W, H) = misfit
    where = _frame_file(frame)
    fix = ("the depth images look transposed (rows and columns swapped): write them "
           f"{W}x{H}, or give intrinsics for {w}x{h} (cx and cy, fx and fy swapped)"
           if kind == "transposed" else
           f"the intrinsics are for another image size: give the K of the {w}x{h} depth camera")
    checks.findings.append(Finding("image_size", (
        f"{where}: depth image is {w}x{h} (WxH) but the principal point (cx, cy) = "
        f"({frame.K[0, 2]:g}, {frame.K[1, 2]:g}) of the intrinsics {misfit_text(misfit)}: {fix}")))


def _frame_file(frame) -> str:
    path = getattr(frame, "depth_path", None)
    return str(path) if path is not None else f"frame {frame.name}"


# -- depth bit depth and range ---------------------------------------------------------------

def _depth_scale(frames) -> float | None:
    return getattr(frames, "depth_scale", None)


def _check_bit_depth(sampled, frames, checks: Checks) -> None:
    from PIL import Image

    eight_bit = []
    for frame in sampled:
        path = getattr(frame, "depth_path", None)
        if path is None or path.suffix.lower() == ".npy":
            continue
        try:
            with Image.open(path) as im:  # reads the header only
                mode = im.mode
        except OSError:
            continue  # the loader read it a moment ago; nothing to add here
        if mode == "L":
            eight_bit.append(path)
    checks.measured["depth_8bit_frames"] = len(eight_bit)
    if not eight_bit:
        return
    scale = _depth_scale(frames) or 1000.0
    checks.findings.append(Finding("depth_8bit", (
        f"{eight_bit[0]}: the depth image is 8-bit (Pillow mode 'L'; {len(eight_bit)} of the "
        f"{len(sampled)} frames checked): at {scale:g} units per metre it holds at most 256 "
        f"depth levels up to {255 / scale:.3g} m, which no depth sensor writes: a grey picture "
        "(e.g. a JPEG saved as .png) instead of a depth map? Depth must be a 16-bit PNG "
        "(millimetres unless --depth-scale says otherwise)")))


def _valid_subsample(depth: np.ndarray, n: int) -> np.ndarray:
    """Flat indices of at most ``n`` valid (positive) pixels, evenly spaced in raster order."""
    idx = np.flatnonzero(depth.ravel() > 0)
    if len(idx) > n:
        idx = idx[np.linspace(0, len(idx) - 1, n).astype(np.int64)]
    return idx


SCALE_FACTORS = (10.0, 0.1, 100.0, 0.01, 1000.0, 0.001)
"""Depth-scale errors the range check names (powers of ten, nearest first)."""


def _check_depth_range(sampled, frames, cfg, full_range: bool, checks: Checks) -> None:
    lo = float(getattr(frames, "depth_min_m", cfg.scene.depth_min_m))
    hi = float(getattr(frames, "depth_max_m", cfg.scene.depth_max_m))
    values = np.concatenate([f.depth_m.ravel()[_valid_subsample(f.depth_m, SAMPLE_PIXELS)]
                             for f in sampled])
    if values.size == 0:
        return
    median = float(np.median(values))
    kept = float(np.mean((values >= lo) & (values <= hi)))
    checks.measured["depth_range"] = {"median_m": median, "kept_fraction": kept,
                                      "range_m": [lo, hi], "before_range": full_range}
    if lo <= median <= hi:
        return
    side = f"below scene.depth_min_m = {lo:g}" if median < lo else \
        f"beyond scene.depth_max_m = {hi:g}"
    factor = next((f for f in SCALE_FACTORS if lo <= median * f <= hi), None)
    scale = _depth_scale(frames)
    if factor is None:
        fix = "check the depth unit and scene.depth_min_m / depth_max_m"
    elif scale is None:
        fix = f"depth {factor:g} times as large would lie in the range: check the depth unit"
    else:
        fix = (f"read at {scale:g} units per metre; with --depth-scale {scale / factor:g} "
               f"(scene.depth_scale) the median would be {median * factor:.3g} m: is the depth "
               f"scale off by {max(factor, 1 / factor):g}?")
    checks.findings.append(Finding("depth_range", (
        f"{_source(frames, cfg)}: the median measured depth of {len(sampled)} frames is "
        f"{median:.3g} m, {side} m, so {1 - kept:.0%} of the measured pixels would be dropped; "
        f"{fix}")))


def _source(frames, cfg) -> str:
    return str(getattr(frames, "path", None) or cfg.scene.data or getattr(frames, "name", "scene"))


# -- frame consistency: pose convention and depth scale --------------------------------------

READINGS = {"given": (False, 1.0), "T_C_W": (True, 1.0), "depth_x10": (False, 10.0),
            "depth_div10": (False, 0.1)}
"""The readings the consistency check compares: (poses inverted, depth factor)."""


def _invert(T: np.ndarray) -> np.ndarray:
    return invert_rigid(np.asarray(T, np.float64))


def _pair_counts(src, dst, T_dst_src: np.ndarray, factor: float) -> np.ndarray:
    """(agree, conflict, sampled) for the sampled pixels of frame ``src`` (a dict of its pixel
    rays and depths) moved into frame ``dst`` by ``T_dst_src``, depths times ``factor``."""
    p = src["rays"] * (src["depth"] * factor)  # (3, n) camera points of src, metres
    q = T_dst_src[:3, :3] @ p + T_dst_src[:3, 3:4]
    z = q[2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    K, depth = dst["K"], dst["depth_m"]
    u = np.rint(K[0, 0] * q[0] / zs + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * q[1] / zs + K[1, 2]).astype(np.int64)
    h, w = depth.shape
    tested = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros_like(z)
    d[tested] = depth[v[tested], u[tested]] * factor
    tested &= d > 0
    agree = tested & (np.abs(z - d) <= DEPTH_TOLERANCE * d)
    conflict = tested & (z < d * (1.0 - DEPTH_TOLERANCE))  # in space dst saw as empty
    return np.array([agree.sum(), conflict.sum(), len(z)], np.int64)


def frame_consistency(frames: list) -> dict | None:
    """How well pairs of ``frames`` (:class:`~bftaichi.frame.Frame` s) agree under each of
    :data:`READINGS`; None with fewer than 2 frames or no overlapping pair.

    For every pair (i < j) of frames, up to :data:`SAMPLE_PIXELS` valid pixels of frame i are
    back-projected (depth times the reading's factor), moved into frame j by the reading's
    poses (``T_W_j^-1 T_W_i``, or with both poses inverted) and projected; each lands on j's
    depth (agree, within :data:`DEPTH_TOLERANCE`), behind it (occluded), in front of it
    (conflict), or outside j's valid pixels (untested). Pairs that overlap under no reading
    (:data:`MIN_PAIR_OVERLAP`) are left out. Returns ``{"pairs": n, reading: {"agree": fraction
    of sampled points, "conflict": fraction of tested points (agree + conflict), "agree_points":
    count}}``. Vectorised numpy, a few ms per pair.
    """
    if len(frames) < 2:
        return None
    prepared = []
    for f in frames:
        K = np.asarray(f.K, np.float64)
        depth = np.asarray(f.depth_m, np.float32)
        idx = _valid_subsample(depth, SAMPLE_PIXELS)
        v, u = np.divmod(idx, depth.shape[1])
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(idx))])
        prepared.append({"K": K, "depth_m": depth, "rays": rays,
                         "depth": depth.ravel()[idx].astype(np.float64),
                         "T": np.asarray(f.T_W_C, np.float64)})
    totals = {name: np.zeros(3, np.int64) for name in READINGS}
    pairs = 0
    for i in range(len(prepared)):
        for j in range(i + 1, len(prepared)):
            a, b = prepared[i], prepared[j]
            if not len(a["depth"]):
                continue
            counts = {}
            for name, (inverted, factor) in READINGS.items():
                Ta, Tb = (_invert(a["T"]), _invert(b["T"])) if inverted else (a["T"], b["T"])
                counts[name] = _pair_counts(a, b, _invert(Tb) @ Ta, factor)
            if max(c[0] / c[2] for c in counts.values()) < MIN_PAIR_OVERLAP:
                continue
            pairs += 1
            for name in READINGS:
                totals[name] += counts[name]
    if not pairs:
        return None
    out = {"pairs": pairs}
    for name, (agree, conflict, n) in totals.items():
        out[name] = {"agree": float(agree / n), "conflict": float(conflict / max(agree + conflict, 1)),
                     "agree_points": int(agree)}
    return out


def _check_consistency(sampled, frames, cfg, checks: Checks) -> None:
    result = frame_consistency(sampled)
    checks.measured["consistency"] = result
    if result is None:
        return
    given = result["given"]
    contradicted = given["conflict"] >= GIVEN_CONFLICT
    if not contradicted and given["agree"] >= GIVEN_AGREEMENT:
        return

    def believable(name):
        alt = result[name]
        return (alt["conflict"] <= ALTERNATIVE_CONFLICT and alt["agree_points"] >= MIN_POINTS
                and alt["agree"] >= given["agree"] + AGREEMENT_GAIN)

    # A rescaled depth keeps the cameras where they are: it agrees better only by explaining
    # the parallax. Inverted look-at poses put every camera at one point, where views of a
    # symmetric object agree whatever the truth: T_C_W needs the given poses contradicted.
    candidates = [name for name in ("depth_x10", "depth_div10") if believable(name)]
    if not candidates and contradicted and believable("T_C_W"):
        candidates = ["T_C_W"]
    if not candidates:
        return
    best = max(candidates, key=lambda name: result[name]["agree"])
    alt = result[best]
    measured = (f"of {len(sampled)} frames ({result['pairs']} overlapping pairs, "
                f"{SAMPLE_PIXELS} pixels each), as given {given['agree']:.0%} of the "
                f"reprojected points agree with the other frame's depth and "
                f"{given['conflict']:.0%} of those tested lie in space it saw empty; ")
    source = _source(frames, cfg)
    if best == "T_C_W":
        if getattr(frames, "pose_convention", "T_W_C") == "T_C_W":
            fix = "drop --pose-convention T_C_W (scene.pose_convention): the files hold T_W_C"
        elif getattr(frames, "format", None) == "folder":
            fix = "pass --pose-convention T_C_W (scene.pose_convention)"
        else:
            fix = ("invert the pose files (this format's poses are T_W_C), or store the frames "
                   "in the folder layout and pass --pose-convention T_C_W")
        checks.findings.append(Finding("pose_convention", (
            f"{source}: the poses look like T_C_W (world-to-camera), not T_W_C "
            f"(camera-to-world): {measured}with the poses inverted {alt['agree']:.0%} agree and "
            f"{alt['conflict']:.0%} conflict; {fix}")))
        return
    factor = READINGS[best][1]
    scale = _depth_scale(frames)
    fix = (f"read at {scale:g} units per metre: pass --depth-scale {scale / factor:g} "
           "(scene.depth_scale)" if scale else "check the depth unit")
    checks.findings.append(Finding("depth_scale", (
        f"{source}: the depth looks off by a factor {max(factor, 1 / factor):g} "
        f"({'too small' if factor > 1 else 'too large'}): {measured}with the depth times "
        f"{factor:g} {alt['agree']:.0%} agree and {alt['conflict']:.0%} conflict; {fix}")))
