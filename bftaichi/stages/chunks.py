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

from .observe import NORMAL_RADIUS_MAX_PX

__all__ = ["Chunk", "ChunkJob", "ChunkPlan", "chunk_plan", "merge_stats", "ray_chunks",
           "solve_chunks"]

BLOCK = 8


@dataclass(frozen=True)
class Chunk:
    key: tuple[int, int, int]  # chunk index
    side: int  # voxels
    halo: int  # voxels

    def _inside(self, ijk: np.ndarray) -> np.ndarray:
        """Mask of ``ijk`` within the core plus ``halo + 1`` voxels."""
        lo = np.array(self.key) * self.side - self.halo - 1
        hi = (np.array(self.key) + 1) * self.side + self.halo + 1
        return np.all((ijk >= lo) & (ijk < hi), axis=1)

    def select(self, voxels: dict) -> dict:
        """The bootstrap's exported voxels within the core plus ``halo + 1`` voxels."""
        m = self._inside(voxels["ijk"])
        return {k: v[m] for k, v in voxels.items()}

    def select_warm(self, posterior) -> tuple[np.ndarray, np.ndarray] | None:
        """``(ijk, mean)`` of ``posterior`` within this chunk's box, in its order (None: no
        warm start)."""
        if posterior is None:
            return None
        m = self._inside(posterior.ijk)
        return (np.asarray(posterior.ijk[m]), np.asarray(posterior.mean[m])) if m.any() else None


MASK_MARGIN_PX = 16 * (NORMAL_RADIUS_MAX_PX + 2)
"""Pixels kept around the image of a chunk's box: what a pixel or super-pixel that can reach
the box reads around itself. A super-pixel is at most 2^MAX_LEVEL = 16 pixels a side
(kernels/observe.py), its normal reads the blocks up to ``NORMAL_RADIUS_MAX_PX`` away
(:mod:`.observe`; each pixel's own radius depends only on its own depth), and its ray leaves
from its centre; so every block whose samples can land in the box, and every pixel it reads,
lies within 16 (NORMAL_RADIUS_MAX_PX + 2) pixels of the box's image."""


def chunk_views(frames, plan, voxel_size_m: float,
                trunc_m: float) -> list[list[tuple[int, tuple | None]]]:
    """Per chunk of ``plan``, the frames (local poses) that observe it, as ``(index, window)``:
    ``window = (v0, v1, u0, u1)`` is the part of the image that can observe the chunk, None
    for the whole image. One pass over the frames, each read once.

    A sample lies on its pixel's (or super-pixel's) ray within ``trunc_m |K^-1 (u, v, 1)|`` of
    the measured surface point, and the chunk's band accepts it only inside the box of its core
    plus ``halo + 1`` voxels. So a frame observes the chunk only through the pixels whose
    surface point lies in that box grown by the truncation's reach: every valid pixel, and
    the centre of every k x k block (k = 2..16) whose pixels are all valid at their mean depth
    (the super-pixels, kernels/observe.py), is tested. The window is the bounding rectangle of
    those pixels (a block: all its pixels) plus :data:`MASK_MARGIN_PX`, the neighbourhood the
    normals read. Observing a frame masked to its window therefore gives the chunk exactly the
    samples of the whole frame (tests/test_chunks.py); the frames and pixels left out save
    their time. The points are binned into cells of one TSDF block before the boxes are tested,
    which keeps the test a superset (cells that merely touch a box count)."""
    side_m = plan.side * voxel_size_m
    chunk_codes = _linear(np.array([c.key for c in plan.chunks], np.int64))  # ascending
    views = [[] for _ in plan.chunks]
    cell = BLOCK * voxel_size_m
    for i in range(len(frames)):
        frame = frames[i]
        depth = np.asarray(frame.depth_m, np.float32)
        h, w = depth.shape[:2]
        T = np.asarray(frame.T_W_C, np.float64)
        K = np.asarray(frame.K, np.float64)
        pts, rect = _surface_points(depth, K)
        if not len(pts):
            continue
        corners = np.array([[(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], 1.0]
                            for x in (-0.5, w - 0.5) for y in (-0.5, h - 0.5)])
        reach = trunc_m * float(np.linalg.norm(corners, axis=1).max()) + 1e-3
        grow = (plan.halo + 1) * voxel_size_m + reach  # the core's box grown by this
        R, t = T[:3, :3] / cell, T[:3, 3] / cell  # straight to cell units
        c = np.floor(pts @ R.T + t).astype(np.int64)
        code = _linear(c)
        order = np.argsort(code)
        sorted_code = code[order]
        starts = np.flatnonzero(np.r_[True, sorted_code[1:] != sorted_code[:-1]])
        uniq = c[order[starts]]
        box = _group_rect(rect[order], starts)  # v0, v1, u0, u1 of each cell's pixels
        lo = np.floor((uniq * cell - grow) / side_m).astype(np.int64)  # chunks whose grown
        hi = np.floor(((uniq + 1) * cell + grow) / side_m).astype(np.int64)  # box meets it
        hit_chunk, hit_box = [], []
        for d in np.ndindex(*(int(x) + 1 for x in (hi - lo).max(axis=0))):
            key = lo + np.array(d)
            ok = np.all(key <= hi, axis=1)
            pos = np.minimum(np.searchsorted(chunk_codes, _linear(key[ok])), len(chunk_codes) - 1)
            hit = chunk_codes[pos] == _linear(key[ok])
            hit_chunk.append(pos[hit])
            hit_box.append(box[ok][hit])
        hit_chunk, hit_box = np.concatenate(hit_chunk), np.concatenate(hit_box)
        if not len(hit_chunk):
            continue
        order = np.argsort(hit_chunk, kind="stable")
        starts = np.flatnonzero(np.r_[True, hit_chunk[order][1:] != hit_chunk[order][:-1]])
        m = MASK_MARGIN_PX
        for k, (v0, v1, u0, u1) in zip(hit_chunk[order][starts].tolist(),
                                       _group_rect(hit_box[order], starts).tolist()):
            v0, v1, u0, u1 = max(0, v0 - m), min(h, v1 + m + 1), max(0, u0 - m), min(w, u1 + m + 1)
            whole = v0 == 0 and u0 == 0 and v1 == h and u1 == w
            views[k].append((i, None if whole else (v0, v1, u0, u1)))
    return views


def _group_rect(r: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """The bounding rectangle (v0, v1, u0, u1) of each group of rows of ``r`` (sorted into
    groups beginning at ``starts``)."""
    if not len(r):
        return np.zeros((0, 4), np.int64)
    return np.stack([np.minimum.reduceat(r[:, 0], starts), np.maximum.reduceat(r[:, 1], starts),
                     np.minimum.reduceat(r[:, 2], starts), np.maximum.reduceat(r[:, 3], starts)],
                    axis=1)


def _surface_points(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame surface points of every valid pixel and of the centre of every k x k block
    (k = 2, 4, 8, 16) whose pixels are all valid, at their mean depth, with the pixel
    rectangle (v0, v1, u0, u1; inclusive) each stands for."""
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    pts = [_back_project(u.astype(np.float64), v.astype(np.float64),
                         depth[v, u].astype(np.float64), K)]
    rects = [np.stack([v, v, u, u], axis=1).astype(np.int32)]
    h, w = depth.shape
    for lv in range(1, 5):
        k = 1 << lv
        hb, wb = h // k, w // k
        if hb == 0 or wb == 0:
            break
        blocks = np.where(valid, depth, 0)[:hb * k, :wb * k].reshape(hb, k, wb, k)
        full = (blocks > 0).all(axis=(1, 3))
        by, bx = np.nonzero(full)
        if not len(by):
            continue
        mean = blocks.mean(axis=(1, 3), dtype=np.float64)[by, bx]
        pts.append(_back_project(k * bx + (k - 1) / 2, k * by + (k - 1) / 2, mean, K))
        rects.append(np.stack([k * by, k * by + k - 1, k * bx, k * bx + k - 1],
                              axis=1).astype(np.int32))
    return np.concatenate(pts), np.concatenate(rects)


def _back_project(u, v, z, K) -> np.ndarray:
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)


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
    from ..posterior import warm_start
    from .bandsolve import _COLLECT_MIN, Lap, solve_band
    from .band import build_band

    cfg, chunk = job.config, job.chunk
    t0 = time.perf_counter()
    lap = Lap()
    band, x0 = build_band(job.voxels, cfg.tsdf.bootstrap_trunc_m)
    lap.collect = len(band) >= _COLLECT_MIN
    if job.warm is not None:
        x0 = warm_start(*job.warm, band.ijk, x0)
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
    scene = parts[0]["observations"].get("noise_fit") or {}  # one fit for every chunk
    observations["noise_fit"] = {"sigma_extra_m": extra, "sigma_corr_m": corr,
                                 **{k: scene[k] for k in _SCENE_FIT if k in scene},
                                 "per_chunk": [p["observations"].get("noise_fit") for p in parts]}
    return {"solver": solver, "variance": variance, "observations": observations,
            "sigma_extra_m": extra, "sigma_corr_m": corr}


#: What the scene's noise fit says of its frames as a whole, the same in every chunk.
_SCENE_FIT = ("frames_sharing_noise", "sharing_z", "sharing_length", "shared_fraction")


def _linear(ijk: np.ndarray) -> np.ndarray:
    """Sortable int64 keys of voxel indices (lexicographic order), within +-2^20."""
    i = np.asarray(ijk, np.int64) + (1 << 20)
    return (i[:, 0] << 42) | (i[:, 1] << 21) | i[:, 2]
