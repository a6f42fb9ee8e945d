"""Spatial chunks of the posterior solve (``run.chunk_m``, issue 20; DESIGN.md section 7).

The band is cut into cubes of ``side = 8 * round(chunk_m / (8 voxel))`` voxels (whole TSDF
blocks, at least one): chunk ``c = floor(ijk / side)``. A chunk's solve takes the bootstrap's
voxels within its core plus ``halo + 1`` voxels (the band's one-voxel dilation then reaches
``halo`` voxels around the core), builds that band, observes every frame into it (samples
outside it are dropped, as outside any band), adds the prior and solves MAP and variance as a
whole-band solve does. The voxels of its core keep their values; the halo's, which feel the
chunk's edge, are dropped. Every voxel of the whole band lies in exactly one core, and its
chunk's band holds it (the whole band's criterion applied to a superset of its neighbours), so
the stitched posterior covers the band once.

Where the chunks run: :func:`solve_chunks` solves them one after another in this process, or,
inside :func:`ray_chunks` (``bftaichi batch`` runs each run in it), as Ray tasks, each a
:class:`ChunkJob` (config, the chunk's voxels, its warm start) with the frame source shared
through Ray's object store. A chunk's solve is deterministic (integer accumulation, fixed
reduction orders), so where it runs does not change a byte of the result.
"""

from __future__ import annotations

import os
import socket
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

__all__ = ["Chunk", "ChunkJob", "ChunkPlan", "chunk_plan", "merge_stats", "ray_chunks",
           "solve_chunks"]

BLOCK = 8


@dataclass(frozen=True)
class Chunk:
    key: tuple[int, int, int]  # chunk index
    side: int  # voxels
    halo: int  # voxels

    def select(self, voxels: dict) -> dict:
        """The bootstrap's exported voxels within the core plus ``halo + 1`` voxels."""
        lo = np.array(self.key) * self.side - self.halo - 1
        hi = (np.array(self.key) + 1) * self.side + self.halo + 1
        ijk = voxels["ijk"]
        m = np.all((ijk >= lo) & (ijk < hi), axis=1)
        return {k: v[m] for k, v in voxels.items()}

    def select_warm(self, posterior) -> tuple[np.ndarray, np.ndarray] | None:
        """``(ijk, mean)`` of ``posterior`` (None: no warm start) within this chunk's box."""
        if posterior is None:
            return None
        lo = np.array(self.key) * self.side - self.halo - 1
        hi = (np.array(self.key) + 1) * self.side + self.halo + 1
        m = np.all((posterior.ijk >= lo) & (posterior.ijk < hi), axis=1)
        return np.asarray(posterior.ijk[m]), np.asarray(posterior.mean[m])

    def box(self, voxel_size_m: float, reach_m: float) -> np.ndarray:
        """(8, 3) corners, local metres, of the box that holds every sample this chunk's band
        can accept: core plus ``halo + 1`` voxels, grown by ``reach_m``."""
        lo = (np.array(self.key) * self.side - self.halo - 1) * voxel_size_m - reach_m
        hi = ((np.array(self.key) + 1) * self.side + self.halo + 1) * voxel_size_m + reach_m
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                         for z in (lo[2], hi[2])])


MASK_MARGIN_PX = 16 * (1 + 2)
"""Pixels kept around the image of a chunk's box: what a pixel or super-pixel that can reach
the box reads around itself. A super-pixel is at most 2^MAX_LEVEL = 16 pixels a side
(kernels/observe.py), its normal reads the blocks ``normal_radius_px`` = 1 away, and its ray
leaves from its centre; so every block whose samples can land in the box, and every pixel it
reads, lies within 16 (1 + 2) pixels of the box's image."""


def chunk_views(frames, plan, voxel_size_m: float, reach_m: float,
                depth_max_m: float) -> list[list[tuple[int, tuple | None]]]:
    """Per chunk of ``plan``, the frames (local poses) whose view can reach it, as ``(index,
    window)``: ``window = (v0, v1, u0, u1)`` is the part of the image that can observe the
    chunk (the image of its :meth:`Chunk.box` plus :data:`MASK_MARGIN_PX`), None for the whole
    image (the box straddles the camera plane). A frame is left out when the box is wholly
    behind the camera, beyond ``depth_max_m`` or beside the image. One pass over the frames,
    each read once. Observing a frame masked to its window gives the chunk exactly the samples
    of the whole frame (tests/test_chunks.py); it saves the time of the pixels outside."""
    boxes = np.stack([c.box(voxel_size_m, reach_m) for c in plan.chunks])  # (C, 8, 3)
    views = [[] for _ in plan.chunks]
    far = depth_max_m + reach_m
    m = MASK_MARGIN_PX
    for i in range(len(frames)):
        frame = frames[i]
        T = np.asarray(frame.T_W_C, np.float64)
        K = np.asarray(frame.K, np.float64)
        h, w = np.asarray(frame.depth_m).shape[:2]
        c = (boxes - T[:3, 3]) @ T[:3, :3]  # corners in the camera frame
        z = c[..., 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = K[0, 0] * c[..., 0] / zs + K[0, 2]
        v = K[1, 1] * c[..., 1] / zs + K[1, 2]
        straddle = np.any(z <= 1e-6, axis=1)
        out = (np.all(z <= 0, axis=1) | np.all(z > far, axis=1)
               | (~straddle & (np.all(u < -0.5, axis=1) | np.all(u > w - 0.5, axis=1)
                               | np.all(v < -0.5, axis=1) | np.all(v > h - 0.5, axis=1))))
        for k in np.flatnonzero(~out):
            if straddle[k]:
                views[k].append((i, None))
                continue
            v0 = max(0, int(np.floor(v[k].min())) - m)
            v1 = min(h, int(np.ceil(v[k].max())) + m + 1)
            u0 = max(0, int(np.floor(u[k].min())) - m)
            u1 = min(w, int(np.ceil(u[k].max())) + m + 1)
            whole = v0 == 0 and u0 == 0 and v1 == h and u1 == w
            views[k].append((i, None if whole else (v0, v1, u0, u1)))
    return views


class ChunkFrames:
    """A chunk's frame source (``len``, indexing): the frames of its :func:`chunk_views`, each
    with the depth outside its window set to 0 (invalid)."""

    def __init__(self, frames, views: list[tuple[int, tuple | None]]):
        self.frames, self.views = frames, views

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, j: int):
        from dataclasses import replace

        i, window = self.views[j]
        frame = self.frames[i]
        if window is None:
            return frame
        v0, v1, u0, u1 = window
        depth = np.zeros_like(np.asarray(frame.depth_m, np.float32))
        depth[v0:v1, u0:u1] = np.asarray(frame.depth_m, np.float32)[v0:v1, u0:u1]
        return replace(frame, depth_m=depth)

    def __iter__(self):
        return (self[j] for j in range(len(self)))


@dataclass(frozen=True)
class ChunkJob:
    """Everything one chunk's solve needs but the frames (picklable: a Ray task's argument)."""

    config: object  # bftaichi.Config
    chunk: Chunk
    voxels: dict  # the bootstrap's exported voxels of the chunk (Chunk.select)
    frames: object  # the frame source, local poses (dropped when the job is sent to Ray)
    views: list  # (frame index, window) of the frames that see the chunk (chunk_views)
    noise: dict  # the scene's noise fit (one for every chunk)
    variance: bool
    warm: tuple | None  # (ijk, mean) of the previous posterior in the chunk's box


def run_chunk(job: ChunkJob, frames=None, frame_iter=None) -> dict:
    """One chunk's steps 2-6 (``frames``: default ``job.frames``): the values of its core
    voxels (``core_ijk``, ``mean``, ``var``, ``cov``), the solve's statistics, ``seconds`` per
    sub-stage and, in ``chunk``, its band voxels, frames seen and seconds."""
    from ..reconstructor import _COLLECT_MIN, Lap, solve_band
    from .band import build_band

    cfg, chunk = job.config, job.chunk
    t0 = time.perf_counter()
    lap = Lap()
    band, x0 = build_band(job.voxels, cfg.tsdf.bootstrap_trunc_m)
    lap.collect = len(band) >= _COLLECT_MIN
    if job.warm is not None:
        x0 = _warm_start(job.warm, band.ijk, x0)
    lap("band")
    seen_by = ChunkFrames(job.frames if frames is None else frames, job.views)
    part = solve_band(cfg, band, x0, seen_by, job.variance, frame_iter, lap, job.noise)
    core = np.all(np.floor_divide(band.ijk, chunk.side) == np.array(chunk.key), axis=1)
    out = {"core_ijk": np.asarray(band.ijk[core]), "mean": part.pop("mean")[core],
           "var": part.pop("var")[core]}
    cov = part.pop("cov")
    out["cov"] = None if cov is None else cov[core]
    part["chunk"] = {"key": list(chunk.key), "band_voxels": len(band), "core_voxels":
                     int(core.sum()), "frames": len(seen_by),
                     "seconds": round(time.perf_counter() - t0, 3),
                     "worker": f"{socket.gethostname()}:{os.getpid()}"}
    return {**out, **part, "seconds": lap.seconds}


def _warm_start(warm: tuple, ijk: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x0`` with the voxels of ``ijk`` that ``warm = (ijk, mean)`` holds set to its mean
    (as :meth:`bftaichi.Posterior.warm_start`)."""
    prev_ijk, prev_mean = warm
    k_prev, k_new = _linear(prev_ijk), _linear(ijk)
    order = np.argsort(k_prev)
    pos = np.clip(np.searchsorted(k_prev[order], k_new), 0, max(len(k_prev) - 1, 0))
    out = np.array(x0, np.float32, copy=True)
    if len(k_prev):
        same = k_prev[order][pos] == k_new
        out[same] = prev_mean[order[pos[same]]]
    return out


def core_positions(full_ijk: np.ndarray, core_ijk: np.ndarray, key) -> np.ndarray:
    """Positions in the whole band (sorted by (i, j, k)) of a chunk's core voxels."""
    keys_full, keys_core = _linear(full_ijk), _linear(core_ijk)
    where = np.searchsorted(keys_full, keys_core)
    if not np.array_equal(keys_full[np.minimum(where, len(keys_full) - 1)], keys_core):
        raise AssertionError(f"chunk {tuple(key)}: its core voxels are not in the whole band")
    return where


_RAY = {"on": False}


@contextmanager
def ray_chunks():
    """Within: :func:`solve_chunks` sends each chunk to Ray as a task (``num_cpus=1``,
    retried once if its worker dies), when Ray is initialised in this process."""
    before = _RAY["on"]
    _RAY["on"] = True
    try:
        yield
    finally:
        _RAY["on"] = before


def _remote_chunk(job: ChunkJob, frames) -> dict:
    """A chunk's solve in a Ray worker: Taichi once per worker process, then :func:`run_chunk`."""
    from .. import backend

    backend.init(job.config.run.arch)
    return run_chunk(job, frames)


def solve_chunks(jobs, frame_iter=None):
    """The results of :func:`run_chunk` for ``jobs`` (an iterable of :class:`ChunkJob`), in
    order: here, one after another (each job made when its turn comes, so one chunk's data is
    held at a time), or as Ray tasks inside :func:`ray_chunks`."""
    import sys

    ray = sys.modules.get("ray")
    if not (_RAY["on"] and ray is not None and ray.is_initialized()):
        for job in jobs:
            yield run_chunk(job, frame_iter=frame_iter)
        return
    from dataclasses import replace

    task = ray.remote(num_cpus=1, max_retries=1)(_remote_chunk)
    refs, frames_ref = [], None
    for job in jobs:
        if frames_ref is None:
            frames_ref = ray.put(job.frames)
        refs.append(task.remote(replace(job, frames=None), frames_ref))
    for ref in refs:
        yield ray.get(ref)


@dataclass(frozen=True)
class ChunkPlan:
    chunks: list[Chunk]
    side: int  # voxels
    halo: int
    core_voxels: list[int]  # band voxels in each chunk's core


def chunk_plan(band_ijk: np.ndarray, chunk_m: float, voxel_size_m: float, halo: int) -> ChunkPlan:
    """The chunks whose cores hold band voxels, in (i, j, k) order."""
    side = BLOCK * max(1, int(round(chunk_m / (BLOCK * voxel_size_m))))
    keys, counts = np.unique(np.floor_divide(band_ijk, side), axis=0, return_counts=True)
    return ChunkPlan(chunks=[Chunk(tuple(int(x) for x in k), side, int(halo)) for k in keys],
                     side=side, halo=int(halo), core_voxels=[int(c) for c in counts])


def merge_stats(parts: list[dict], plan: ChunkPlan) -> dict:
    """The Posterior's scalar fields from the chunks' solves: converged only if every chunk
    converged, the worst residual and the most iterations; noise fits and counts per chunk."""
    maps = [p["solver"] for p in parts]
    worst = max(range(len(maps)), key=lambda i: maps[i].get("relative_residual", 0.0))
    solver = dict(maps[worst], converged=all(m["converged"] for m in maps),
                  iterations=max(m["iterations"] for m in maps),
                  chunks={"n": len(parts), "side_voxels": plan.side, "halo_voxels": plan.halo,
                          "core_voxels": plan.core_voxels,
                          "iterations": [m["iterations"] for m in maps],
                          "converged": [bool(m["converged"]) for m in maps],
                          "per_chunk": [p["chunk"] for p in parts]})
    variance = dict(parts[0]["variance"])
    if any("n_not_converged" in p["variance"] for p in parts):
        variance["n_not_converged"] = sum(p["variance"].get("n_not_converged", 0) for p in parts)
    observations = {k: sum(p["observations"][k] for p in parts)
                    for k, v in parts[0]["observations"].items() if isinstance(v, int)}
    observations["note"] = "summed over the chunks: samples in a halo count in two chunks"
    extra = float(np.median([p["sigma_extra_m"] for p in parts]))
    corr = float(np.median([p["sigma_corr_m"] for p in parts]))
    observations["noise_fit"] = {"sigma_extra_m": extra, "sigma_corr_m": corr,
                                 "per_chunk": [p["observations"].get("noise_fit") for p in parts]}
    return {"solver": solver, "variance": variance, "observations": observations,
            "sigma_extra_m": extra, "sigma_corr_m": corr}


def _linear(ijk: np.ndarray) -> np.ndarray:
    """Sortable int64 keys of voxel indices (lexicographic order), within +-2^20."""
    i = np.asarray(ijk, np.int64) + (1 << 20)
    return (i[:, 0] << 42) | (i[:, 1] << 21) | i[:, 2]
