"""Resource guard: estimate a run's peak memory before allocating it, refuse a run that would
not fit, and measure the peak resident memory of each stage.

* :func:`estimate_memory` predicts the peak from the scene's extent and the voxel size, from a
  subsample of the frames (no Taichi, no TSDF: numpy on a few hundred thousand points).
* :func:`memory_budget` turns ``run.memory_budget_gib`` or ``run.memory_fraction`` into bytes.
* :func:`check_memory` raises :class:`ResourceError` when the estimate exceeds the budget,
  naming a voxel size that fits.
* :class:`PeakRSS` records the peak resident set size (``VmHWM``) of each stage of a run.

The memory model and its calibration are documented at :func:`estimate_memory`.
"""

from __future__ import annotations

import math
import time
import warnings
from contextlib import contextmanager

import numpy as np

from kernels.fixedpoint import accumulator_parts
from kernels.layout import KEY_BIAS, OFFSETS, decode_keys, distinct_block_keys

from ..errors import BftaichiError
from ..geometry import local_origin, points_in_local
from ..geometry import check_field_of_view
from .chunking import ChunkingWarning, choose_chunk, chunk_share

__all__ = ["ResourceError", "PeakRSS", "estimate_memory", "memory_budget", "check_memory",
           "available_memory", "suggest_voxel_size"]


class ResourceError(BftaichiError):
    """The run would need more memory than its budget (:func:`memory_budget`) allows.

    Attributes: ``estimate`` (:func:`estimate_memory`'s dict), ``budget`` (bytes),
    ``voxel_size_m`` (a voxel size whose estimate fits, or None)."""

    def __init__(self, message: str, *, estimate: dict | None = None, budget: int | None = None,
                 voxel_size_m: float | None = None):
        super().__init__(message)
        self.estimate, self.budget, self.voxel_size_m = estimate, budget, voxel_size_m


_STATUS = "/proc/self/status"
_CLEAR_REFS = "/proc/self/clear_refs"


def _status_kib(keys: tuple[str, ...]) -> dict[str, int] | None:
    """``{key: bytes}`` of ``/proc/self/status`` lines such as ``VmHWM:  1234 kB``; None where
    the file is missing (not Linux) or unreadable."""
    try:
        with open(_STATUS) as f:
            lines = f.readlines()
    except OSError:
        return None
    out = {}
    for line in lines:
        name, _, rest = line.partition(":")
        if name in keys:
            out[name] = int(rest.split()[0]) * 1024
    return out if len(out) == len(keys) else None


class PeakRSS:
    """Peak resident memory (bytes) of the process during each stage of a run.

    Usage::

        rss = PeakRSS()
        with rss("tsdf"):
            ...                      # integrate
        rss.peaks                    # {"tsdf": 812_000_000, ...}; None where not measurable

    or ``rss.start("tsdf")`` ... ``rss.stop("tsdf")``. At :meth:`start` the kernel's peak counter
    (``VmHWM`` of ``/proc/self/status``) is reset to the current RSS by writing ``5`` to
    ``/proc/self/clear_refs`` (Linux >= 4.0; allowed for one's own process), so the value read at
    :meth:`stop` is the highest RSS reached inside the stage. Where the reset is refused the peak
    is the process's peak so far (``reset_works`` False): still an upper bound. Where
    ``/proc/self/status`` is missing (not Linux) every value is None.

    Everything resident counts: numpy arrays, the Python heap and Taichi's own allocations
    (ndarrays, SNode trees, the LLVM JIT): they are process memory. Pages that were allocated but
    never touched do not (an ``np.zeros`` array costs RSS only as it is written).

    Stages entered several times keep the highest peak; nested stages are not supported (the
    inner start resets the outer one's peak). ``baseline`` is the RSS when the object was made,
    ``peak`` the highest peak over all stages. The reset also lowers what
    ``resource.getrusage`` reports as this process's ``ru_maxrss`` (to its parent, too): to
    measure a whole process from outside, do not use PeakRSS inside it.
    """

    def __init__(self):
        st = _status_kib(("VmRSS",))
        self.available = st is not None
        self.baseline: int | None = st["VmRSS"] if st else None
        self.peaks: dict[str, int | None] = {}
        self.reset_works = self.available and self._reset()
        self._open: dict[str, int | None] = {}

    @staticmethod
    def _reset() -> bool:
        try:
            with open(_CLEAR_REFS, "w") as f:
                f.write("5")
            return True
        except OSError:
            return False

    def current(self) -> int | None:
        """Resident set size now, bytes (None without /proc)."""
        st = _status_kib(("VmRSS",))
        return st["VmRSS"] if st else None

    def start(self, stage: str) -> None:
        """Begin measuring ``stage`` (resets the peak counter to the current RSS)."""
        if self.available:
            self._reset()
        self._open[stage] = self.current()

    def stop(self, stage: str) -> int | None:
        """End ``stage``; record and return its peak RSS, bytes (None without /proc)."""
        self._open.pop(stage, None)
        st = _status_kib(("VmHWM", "VmRSS"))
        peak = max(st["VmHWM"], st["VmRSS"]) if st else None
        if peak is not None and self.peaks.get(stage) is not None:
            peak = max(peak, self.peaks[stage])
        self.peaks[stage] = peak
        return peak

    @contextmanager
    def __call__(self, stage: str):
        self.start(stage)
        try:
            yield
        finally:
            self.stop(stage)

    @property
    def peak(self) -> int | None:
        """Highest peak RSS over the measured stages, bytes (None if none was measurable)."""
        vals = [v for v in self.peaks.values() if v is not None]
        return max(vals) if vals else None

    def to_dict(self) -> dict:
        """JSON-ready ``{"baseline": bytes, "peak": bytes, "stages": {stage: bytes}}``."""
        return {"baseline": self.baseline, "peak": self.peak, "stages": dict(self.peaks)}


# -- the estimate ----------------------------------------------------------------------------

# kernels/tsdf.py's layout, restated so that the estimate imports no Taichi (a test checks
# that they agree)
BLOCK = 8  # voxels per TSDF block edge
BLOCK_VOXELS = BLOCK ** 3
FIRST_POOL_BLOCKS = 1024  # the pool starts with this many blocks and doubles

SAMPLE_FRAMES = 40
"""Frames read by the estimate (evenly spaced over the sequence; all of a shorter one)."""
SAMPLE_PIXELS = 40_000
"""At most about this many pixels of a sampled frame are back-projected (a pixel stride)."""

# Calibration constants (measured, see tools/memory_estimate.py and the module docstring):
BASE_BYTES = 260 * 2 ** 20
"""Resident memory of a run before its data: the interpreter with numpy, scipy, trimesh and
bftaichi imported (~105 MB), ti.init (~75 MB), the JIT-compiled kernels and the TSDF block
map's top levels (~80 MB). Measured 234 MB at the end of the TSDF stage of redkitchen at 2 cm
(of which 17 MB pool)."""


def _frame_points(frame, stride: int, depth_max_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World points (P, 3) float64 and camera centre (3,) of every ``stride``-th valid pixel."""
    depth = np.asarray(frame.depth_m, np.float32)[::stride, ::stride]
    H, W = depth.shape
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0) & (depth <= depth_max_m))
    z = depth[v, u].astype(np.float64)
    K = np.asarray(frame.K, np.float64)
    T = np.asarray(frame.T_W_C, np.float64)
    x = (u * stride - K[0, 2]) / K[0, 0]
    y = (v * stride - K[1, 2]) / K[1, 1]
    rays_C = np.stack([x, y, np.ones_like(x)], axis=1)  # camera z = 1
    rays_W = rays_C @ T[:3, :3].T
    return rays_W * z[:, None] + T[:3, 3], rays_W, z, T[:3, 3]


class SceneSample:
    """Points of a subsample of the frames (in the TSDF's local frame, ``origin``), read once;
    :meth:`measure` voxelises them at any voxel size (cheap), so a voxel size can be searched
    without reading frames again.

    ``n_frames`` frames evenly spaced over the sequence (all of a shorter one), every
    ``stride``-th pixel: the stride keeps neighbouring rays at ``depth_max_m`` within 2 voxels of
    ``voxel_size_m`` (finer for the larger voxels :meth:`measure` may be asked about) and at most
    ~:data:`SAMPLE_PIXELS` pixels a frame.
    """

    def __init__(self, frames, voxel_size_m: float, depth_max_m: float,
                 n_frames: int = SAMPLE_FRAMES):
        n = len(frames)
        self.picks = (np.unique(np.linspace(0, n - 1, min(n, n_frames)).round().astype(int))
                      if n else np.zeros(0, int))
        self.stride = 1
        self.views = []  # (points_L (P, 3), rays_W (P, 3) at camera z = 1, z (P,), centre_L (3,))
        self.origin = np.zeros(3)  # of the local frame L (the first sampled frame's)
        self._cells: dict[float, np.ndarray] = {}  # surface_cells by voxel size
        for j, i in enumerate(self.picks):
            frame = frames[int(i)]
            if j == 0:
                H, W = np.asarray(frame.depth_m).shape
                # a focal length in the wrong unit would make the ray segments below endless
                check_field_of_view(frame.K, (H, W), frame.name)
                f = float(min(frame.K[0][0], frame.K[1][1]))
                self.stride = max(1, int(f * 2 * voxel_size_m / depth_max_m),
                                  math.ceil(math.sqrt(H * W / SAMPLE_PIXELS)))
            if j == 0:  # the TSDF's local frame (bftaichi.geometry.local_origin): block keys
                self.origin = local_origin(np.asarray(frame.T_W_C)[:3, 3], voxel_size_m)
            points, rays, z, centre = _frame_points(frame, self.stride, depth_max_m)
            view = (points_in_local(points, self.origin), rays, z,
                    points_in_local(centre, self.origin))
            if len(view[2]):
                self.views.append(view)
                self._f = float(min(frame.K[0][0], frame.K[1][1]))
        #: (3,) extent of the sampled points' bounding box, metres
        self.extent_m = (np.ptp(np.concatenate([v[0] for v in self.views]), axis=0)
                         if self.views else np.zeros(3))
        #: distance between neighbouring sampled rays at the 90th percentile depth, metres
        self.spacing_m = (float(np.quantile(np.concatenate([v[2] for v in self.views]), 0.9))
                          * self.stride / self._f if self.views else 0.0)

    def surface_cells(self, voxel_size_m: float) -> tuple[np.ndarray, float]:
        """``(cells, cell_m)``: the distinct cells (C, 3) int64 of edge ``cell_m`` that hold a
        sampled point (see :meth:`measure`), computed once per voxel size."""
        cell_m = max(4 * voxel_size_m, 2 * self.spacing_m)
        if voxel_size_m not in self._cells:
            cells = (np.concatenate([np.floor(p / cell_m).astype(np.int64)
                                     for p, *_ in self.views]) if self.views
                     else np.zeros((0, 3), np.int64))
            if len(cells) and np.abs(cells).max() < KEY_BIAS:
                # distinct packed keys (ascending keys = lexicographic cells): the same sorted
                # cells as np.unique(axis=0), without its row sort
                cells = decode_keys(distinct_block_keys(cells))
            else:
                cells = np.unique(cells, axis=0)
            self._cells[voxel_size_m] = cells
        return self._cells[voxel_size_m], cell_m

    def measure(self, voxel_size_m: float, trunc_b_m: float) -> dict:
        """Counts at ``voxel_size_m`` with bootstrap truncation ``trunc_b_m`` (metres):

        * ``blocks``: the 8^3-voxel blocks the TSDF's activation lists, i.e. those met by the
          ray segments [max(d - tau_b, 1e-3), d + tau_b] sampled every half block
          (kernels/tsdf.py ``_activate_row``), united over the sampled frames;
        * ``candidate_blocks``: those blocks and their 26 neighbours (kernels/band.py's working
          layout);
        * ``surface_cells``: cells of edge ``cell_m`` holding a point, and
          ``area_m2 = surface_cells * cell^2 / 1.5``: a plane of area A crosses about
          ``|n|_1 A / cell^2`` cells, ``|n|_1`` 1.5 on average over orientations. The cell is
          half a block (4 voxels), or twice the ray spacing if that is more, so the sampled
          points cover every cell the surface crosses.
        """
        block_m = BLOCK * voxel_size_m
        cell_ijk, cell_m = self.surface_cells(voxel_size_m)
        block_keys = []
        for pts, rays, z, centre in self.views:
            steps = int(math.ceil(2 * trunc_b_m * float(np.linalg.norm(rays, axis=1).max())
                                  / (0.5 * block_m))) + 1
            z0, z1 = np.maximum(z - trunc_b_m, 1e-3), z + trunc_b_m
            block_keys.append(distinct_block_keys(np.concatenate(
                [np.floor((centre + rays * (z0 + (z1 - z0) * (s / steps))[:, None]) / block_m)
                 for s in range(steps + 1)])))
        if not block_keys:
            return {"blocks": 0, "candidate_blocks": 0, "surface_cells": 0, "cell_m": cell_m,
                    "area_m2": 0.0}
        blocks = np.unique(np.concatenate(block_keys))
        candidates = distinct_block_keys(decode_keys(blocks)[:, None] + OFFSETS[None])
        cells = len(cell_ijk)
        return {"blocks": len(blocks), "candidate_blocks": len(candidates),
                "surface_cells": cells, "cell_m": cell_m, "area_m2": cells * cell_m ** 2 / 1.5}


# Per-element costs of each stage, bytes (the arrays each stage holds; the factors on top are
# calibrated on measured peaks, tools/memory_estimate.py):
OBSERVED_FILL = 0.59
"""Observed voxels (TSDF weight > 0) per voxel of an allocated block: a listed block also holds
the unobserved voxels behind the surface (sdf < -tau_b) and outside the view. Measured 0.59 on
redkitchen at 2 cm (794746 voxels in 2650 blocks)."""
BLOCK_COVERAGE = 1.12
"""Allocated blocks per block listed by the sampled frames: the frames left out of the sample
see a little more. Measured 2650 / 2358 on redkitchen at 2 cm (40 of 500 frames)."""
BAND_FILL = 1.0
"""Band voxels per voxel of the slab ``area x (2 tau_b + 2 voxel)`` (the core |tsdf| < tau_b
on both sides of the surface, one dilation layer each side; kernels/band.py)."""


def _stage_bytes(n_band: float, n_obs: float, pool_blocks: int, cand_blocks: float,
                 band_blocks: float, mesh_vertices: float, chunk: float,
                 n_chunk: float | None = None) -> dict[str, float]:
    """Bytes above :data:`BASE_BYTES` that each stage holds at its peak (persistent arrays of
    the earlier stages included). N = band voxels, M = observed voxels, ``chunk`` = bytes of
    one marching-cubes chunk; ``n_chunk``: band voxels of the largest spatial chunk
    (``run.chunk_m``; None: one solve for the whole band)."""
    N, M = n_band, n_obs
    pool = pool_blocks * (BLOCK_VOXELS * 12 + 12)  # tsdf sum i64, count i32, slot_block (3,) i32
    voxels = 20 * M  # export: ijk (3,) i32, tsdf, weight f32
    mesh = 36 * mesh_vertices  # vertices (3,) f32 + ~2 faces (3,) i32 per vertex
    out = {}
    # growing the pool copies it: the old (half) and the new pool exist at once
    out["tsdf"] = 1.5 * pool
    # export: to_numpy copies of the pool's count and sums, int64 index temporaries (flat
    # index, slot, local, (M, 3) ijk, sort key and order: ~100 B per voxel), the float64
    # mean, the result
    out["export"] = pool + pool_blocks * BLOCK_VOXELS * 12 + 108 * M + voxels
    # marching cubes: sort of the voxels, one chunk (meshing.py), the mesh
    out["mesh"] = pool + voxels + 60 * M + chunk + mesh
    persist = pool + voxels + mesh  # the TSDF volume, its export and mesh live on
    # band build: 14 B per candidate cell (tsdf, weight f32, level, known i8, cell_band i32),
    # per band voxel ~205 B (compaction temporaries, nbr (27,) i32, ijk, tsdf, weight, core)
    out["band"] = persist + cand_blocks * BLOCK_VOXELS * 14 + 205 * N
    band = 133 * N + band_blocks * BLOCK_VOXELS * 4  # ijk, nbr, tsdf, weight, core, x0; table
    # observe: the Observer's 128 B per voxel per thread (its accumulator row: 16 i64, one
    # copy per thread, at most 4) and 16 B (ijk, reference f32); finalize adds S (27,) f32
    # and h (112 B) plus its scratch
    obs = 128 * accumulator_parts() + 16
    out["observe"] = persist + band + obs * N + 112 * N
    # the Observer drops its accumulators after observing (Observer.release)
    post = band + 16 * N + 112 * N + 24 * N  # + prior's b0, h, the MAP mean
    # MAP: the compact layout (64 B) and its build temporaries (~250 B), five float64 vectors
    out["map"] = persist + post + 370 * N
    # variance: K = 16 float32 probes: Z, U, and the padded B, X, R, P, AP blocks (64 B each)
    # plus the signs and einsum temporaries
    out["variance"] = persist + post + 630 * N
    if n_chunk is not None:  # the whole band and the stitched mean, var, cov (20 B) stay; each
        c = n_chunk          # chunk builds, observes and solves its own band as above
        whole = band + 20 * N
        post_c = 133 * c + 152 * c
        out["observe"] = persist + whole + 133 * c + obs * c + 112 * c
        out["map"] = persist + whole + post_c + 370 * c
        out["variance"] = persist + whole + post_c + 630 * c
    # the posterior mesh: Posterior arrays (ijk, mean, var, tsdf, weight, core, S, nbr: 245 B)
    # and marching cubes over the band
    out["posterior_mesh"] = persist + 245 * N + 365 * N + chunk
    return out


MESH_VERTICES_PER_AREA = 1.3
"""TSDF mesh vertices per ``area / voxel^2``: 89600 on redkitchen at 2 cm (27.5 m^2)."""


def _pool_blocks(blocks: float) -> int:
    """Pool capacity (blocks) after allocating ``blocks``: 1024 doubled until it holds them."""
    cap = FIRST_POOL_BLOCKS
    while cap < blocks:
        cap *= 2
    return cap


def _model(sample: SceneSample, voxel_size_m: float, trunc_b_m: float, full: bool,
           chunking: tuple[int, int] | None = None) -> dict:
    """The estimate of :func:`estimate_memory` from a scene sample (see there); ``chunking``:
    ``(side, halo)`` voxels of a chunked solve."""
    c = sample.measure(voxel_size_m, trunc_b_m)
    v = voxel_size_m
    blocks = c["blocks"] * BLOCK_COVERAGE
    n_obs = blocks * BLOCK_VOXELS * OBSERVED_FILL
    n_band = c["area_m2"] * (2 * trunc_b_m + 2 * v) / v ** 3 * BAND_FILL
    mesh_vertices = MESH_VERTICES_PER_AREA * c["area_m2"] / v ** 2
    pool = _pool_blocks(blocks)
    # a chunk of marching cubes: 20 B per cell of at most 129^3 (meshing.py), fewer in a
    # scene smaller than that
    cells = np.minimum(np.asarray(sample.extent_m) / v + 3, 129)
    chunk = 20 * float(np.prod(cells))
    n_chunk = (None if chunking is None
               else n_band * chunk_share(sample, voxel_size_m, *chunking))
    stages = _stage_bytes(n_band, n_obs, pool, c["candidate_blocks"] * BLOCK_COVERAGE, blocks,
                          mesh_vertices, chunk, n_chunk)
    if not full:
        stages = {k: stages[k] for k in ("tsdf", "export", "mesh")}
    stages = {k: int(BASE_BYTES + b) for k, b in stages.items()}
    peak_stage = max(stages, key=stages.get)
    return {"peak_bytes": stages[peak_stage], "peak_stage": peak_stage, "stages": stages,
            "base_bytes": BASE_BYTES, "voxel_size_m": v, "bootstrap_trunc_m": trunc_b_m,
            "inputs": {"blocks": int(round(blocks)), "pool_blocks": pool,
                       "observed_voxels": int(round(n_obs)),
                       "band_voxels": int(round(n_band)) if full else 0,
                       "chunk_band_voxels": None if n_chunk is None else int(round(n_chunk)),
                       "mesh_vertices": int(round(mesh_vertices)),
                       "area_m2": round(c["area_m2"], 3),
                       "frames_sampled": len(sample.picks), "pixel_stride": sample.stride}}


def estimate_memory(cfg, frames, *, sample: SceneSample | None = None) -> dict:
    """Peak resident memory of ``bftaichi.run(cfg)`` on ``frames``, estimated before anything
    big is allocated.

    The scene enters through a :class:`SceneSample` (a few dozen frames back-projected;
    synthetic frames render lazily, so the same works for them): the TSDF blocks the activation
    would list, and the surface area. From them, with the voxel size ``v`` and the bootstrap
    truncation ``tau_b = alpha * tau``:

    * allocated blocks ``B`` = listed blocks x :data:`BLOCK_COVERAGE`; the pool holds
      1024 x 2^k >= B blocks of 512 voxels x 8 bytes;
    * observed voxels ``M = 512 B x`` :data:`OBSERVED_FILL`;
    * band voxels ``N = area x (2 tau_b + 2 v) / v^3``: the core ``|tsdf| < tau_b`` on both
      sides of the surface plus one dilation layer each side (kernels/band.py); so memory grows
      as 1/v^2 for a fixed truncation in voxels, 1/v^3 for a fixed one in metres;
    * per stage, the arrays it holds (:func:`_stage_bytes`: per-voxel byte counts from the
      kernels' documented layouts, e.g. the Observer's 136 B and the 16 float32 probe columns
      of the variance) on top of :data:`BASE_BYTES`.

    Calibration (tools/memory_estimate.py runs it), estimate / measured peak RSS of a fresh
    process, redkitchen (500 frames): 2 cm, tau 4 cm: 976 / 965 MiB (band voxels 688k / 706k);
    1 cm, tau 2 cm: 3641 / 3714 MiB (3.27M / 3.45M); 1 cm, tau 4 cm: 6237 / 4868 MiB
    (5.89M / 4.79M: an 18-voxel band fills less of its slab, the estimate errs high). The tiny
    default scene (tests): 307 / 298 MiB.

    Returns a dict: ``peak_bytes`` (the estimate of the run's peak RSS), ``peak_stage``,
    ``stages`` (``{stage: bytes}``: the process's resident memory at each stage's peak,
    including ``base_bytes``), ``inputs`` (blocks, pool_blocks, observed_voxels, band_voxels,
    mesh_vertices, area_m2, frames_sampled, pixel_stride), ``voxel_size_m``,
    ``bootstrap_trunc_m`` and ``seconds`` (time the estimate took; ~1 s on redkitchen, reading
    40 of 500 frames). ``sample``: a SceneSample to reuse (its frames are not read again).
    """
    t0 = time.perf_counter()
    if sample is None:
        sample = SceneSample(frames, cfg.tsdf.voxel_size_m, cfg.scene.depth_max_m)
    out = _model(sample, cfg.tsdf.voxel_size_m, cfg.tsdf.bootstrap_trunc_m,
                 cfg.run.stages == "full", _chunk(cfg))
    out["seconds"] = round(time.perf_counter() - t0, 4)
    return out


def _chunk(cfg) -> tuple[int, int] | None:
    """``(side, halo)`` voxels of ``run.chunk_m`` (as :func:`~bftaichi.stages.chunks.chunk_plan`
    rounds it), None for a whole-band solve."""
    r = cfg.run
    if r.chunk_m <= 0 or r.stages != "full":
        return None
    return BLOCK * max(1, int(round(r.chunk_m / (BLOCK * cfg.tsdf.voxel_size_m)))), r.chunk_halo


# -- the budget ------------------------------------------------------------------------------

GIB = 2 ** 30


def available_memory() -> int | None:
    """Memory the run may still take, bytes: ``MemAvailable`` of ``/proc/meminfo``, lowered to
    the cgroup (v2) limit minus its usage when a container has one; None where unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        with open("/sys/fs/cgroup/memory.current") as f:
            used = int(f.read().strip())
        if limit != "max":
            room = max(0, int(limit) - used)
            avail = room if avail is None else min(avail, room)
    except (OSError, ValueError):
        pass
    return avail


def memory_budget(cfg) -> int | None:
    """The run's memory budget in bytes: ``run.memory_budget_gib`` GiB, whatever is free, when
    set; else ``run.memory_fraction`` of :func:`available_memory` (default 0.8: a fifth is left
    to the rest of the machine), None when the available memory is unknown (no check).

    The estimate it is compared with is the process's whole peak RSS, including what the process
    already holds, so a fraction budget errs on the safe side by that much.
    """
    r = cfg.run
    if r.memory_budget_gib > 0:
        return int(r.memory_budget_gib * GIB)
    avail = available_memory()
    return None if avail is None else int(r.memory_fraction * avail)


def _describe_budget(cfg, budget: int) -> str:
    r = cfg.run
    what = (f"run.memory_budget_gib = {r.memory_budget_gib:g}" if r.memory_budget_gib > 0
            else f"{r.memory_fraction * 100:g} % of the available RAM, run.memory_fraction = "
                 f"{r.memory_fraction:g}")
    return f"the budget {_gib(budget)} ({what})"


def _gib(n: float) -> str:
    return f"{n / GIB:.2f} GiB" if n < 10 * GIB else f"{n / GIB:.1f} GiB"


_NICE = (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)


def _nice_up(x: float) -> float:
    """Smallest value of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k that is >= x (x > 0)."""
    e = math.floor(math.log10(x))
    for k in (e, e + 1):
        for m in _NICE:
            if round(m * 10.0 ** k, 6) >= x * (1 - 1e-9):
                return round(m * 10.0 ** k, 6)
    return round(10.0 ** (e + 1), 6)


def _next_nice(x: float) -> float:
    return _nice_up(x * 1.0001)


def suggest_voxel_size(cfg, frames, budget: int, *, sample: SceneSample | None = None,
                       estimate: dict | None = None) -> tuple[float, dict] | None:
    """The smallest "nice" voxel size (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k metres) above
    ``cfg.tsdf.voxel_size_m`` whose estimate fits ``budget`` bytes, with that estimate; None if
    none up to 1 m does. ``tsdf.trunc_m`` stays (raised to one voxel where it would be less).

    Start: memory above :data:`BASE_BYTES` scales about as 1/v^2 (surface-bound arrays) to
    1/v^3 (the band for a truncation fixed in metres), so ``v * (excess / room)^(1/3)`` is a
    lower bound; each candidate is verified by re-estimating from the same scene sample."""
    v0 = cfg.tsdf.voxel_size_m
    if sample is None:
        sample = SceneSample(frames, v0, cfg.scene.depth_max_m)
    if estimate is None:
        estimate = estimate_memory(cfg, frames, sample=sample)
    room = budget - BASE_BYTES
    if room <= 0:
        return None
    excess = max(estimate["peak_bytes"] - BASE_BYTES, 1)
    v = _nice_up(max(v0 * 1.0001, v0 * (excess / room) ** (1.0 / 3.0)))
    full = cfg.run.stages == "full"
    while v <= 1.0:
        trunc = max(cfg.tsdf.trunc_m, v)
        est = _model(sample, v, cfg.tsdf.alpha * trunc, full)
        if est["peak_bytes"] <= budget:
            return v, est
        v = _next_nice(v)
    return None


def check_memory(cfg, frames, *, budget: int | None = None) -> dict:
    """:func:`estimate_memory`, compared with :func:`memory_budget` (or ``budget`` bytes).

    Returns the estimate with ``budget_bytes`` added (None: unknown, not checked). When a
    whole-band solve exceeds the budget and a chunked one fits, the estimate is the chunked
    run's, with ``chunk_m_chosen`` (the largest chunk side that fits,
    :func:`.chunking.choose_chunk`; the run then solves in chunks of it) and
    ``whole_band_peak_bytes``, and a :class:`~.chunking.ChunkingWarning` says so. Raises
    :class:`ResourceError` when nothing fits, with the estimate, the budget and a voxel size
    that fits (:func:`suggest_voxel_size`)."""
    t0 = time.perf_counter()
    sample = SceneSample(frames, cfg.tsdf.voxel_size_m, cfg.scene.depth_max_m)
    est = estimate_memory(cfg, frames, sample=sample)
    if budget is None:
        budget = memory_budget(cfg)
    est["budget_bytes"] = budget
    if (budget is not None and est["peak_bytes"] > budget and cfg.run.stages == "full"
            and cfg.run.chunk_m <= 0):  # solve in chunks, if a chunk size fits
        fit = choose_chunk(cfg, sample, budget, lambda side, halo: _model(
            sample, cfg.tsdf.voxel_size_m, cfg.tsdf.bootstrap_trunc_m, True, (side, halo)))
        if fit is not None:
            chunk_m, chunked = fit
            warnings.warn(ChunkingWarning(
                f"estimated peak memory {_gib(est['peak_bytes'])} of one whole-band solve "
                f"(stage {est['peak_stage']}) exceeds {_describe_budget(cfg, budget)}: solving "
                f"in chunks of {chunk_m:g} m (run.chunk_m; estimated peak "
                f"{_gib(chunked['peak_bytes'])}, stage {chunked['peak_stage']})"), stacklevel=2)
            est = dict(chunked, budget_bytes=budget, chunk_m_chosen=chunk_m,
                       whole_band_peak_bytes=est["peak_bytes"])
    if budget is not None and est["peak_bytes"] > budget:
        v = cfg.tsdf.voxel_size_m
        inp = est["inputs"]
        count = (f"{inp['band_voxels'] / 1e6:.2f} M band voxels" if inp["band_voxels"]
                 else f"{inp['observed_voxels'] / 1e6:.2f} M observed voxels")
        msg = (f"estimated peak memory {_gib(est['peak_bytes'])} (stage {est['peak_stage']}, "
               f"{count}) exceeds {_describe_budget(cfg, budget)} at tsdf.voxel_size_m = {v:g}"
               + (", and no chunk size (run.chunk_m) fits either; "
                  if cfg.run.stages == "full" and cfg.run.chunk_m <= 0 else "; "))
        fit = suggest_voxel_size(cfg, frames, budget, sample=sample, estimate=est)
        if fit is None:
            msg += "no voxel size up to 1 m fits. "
        else:
            v_fit, est_fit = fit
            trunc = ("" if cfg.tsdf.trunc_m >= v_fit
                     else f" with tsdf.trunc_m = {v_fit:g}")
            msg += (f"tsdf.voxel_size_m = {v_fit:g}{trunc} would need ~"
                    f"{_gib(est_fit['peak_bytes'])}. ")
        msg += ("Set run.memory_fraction (of the available RAM) or run.memory_budget_gib to "
                "override.")
        raise ResourceError(msg, estimate=est, budget=budget,
                            voxel_size_m=None if fit is None else fit[0])
    est["seconds"] = round(time.perf_counter() - t0, 4)
    return est
