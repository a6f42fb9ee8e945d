"""Algorithm 1 of BayesFusion-SDF, top to bottom: the :class:`Reconstructor`.

::

    import bftaichi as bf

    recon = bf.Reconstructor(bf.Config.from_toml("scenes/bunny.toml"))
    for frame in bf.open_dataset("path/to/frames"):
        recon.integrate(frame.depth_m, frame.K, frame.T_W_C)      # step 1
    post = recon.solve()               # steps 2-6: bftaichi.Posterior (mean, var, cov, band)
    mesh = post.extract_mesh()         # step 7: trimesh, vertex "sigma", "sigma_pos" (m)
    ranked = bf.nbv.rank(post, bf.nbv.candidates_around(post, n=48), recon.K, recon.image_size)
    recon.save("out/")                 # mesh.ply, tsdf_mesh.ply, band.npz (DESIGN.md section 4)

This is the one place the stages are put together: ``bftaichi run`` / ``fuse`` (the pipeline
adds staging, reports and outputs), ``scan``, ``evalviews``, ``tools/`` and ``examples/`` all
drive it. Each step is a module of :mod:`bftaichi.stages` owning its ``[section]``.

Conventions (DESIGN.md section 2): metres; depth along the camera z axis, (H, W), 0 / NaN
invalid; ``K`` the 3x3 OpenCV pinhole matrix; ``T_W_C`` the 4x4 camera-to-world pose.

Coordinates: what goes in and comes out is in world coordinates (poses, meshes, NBV poses,
ground truth); the grid is built in a local frame, ``recon.origin`` (float64, metres) from the
first frame (:func:`bftaichi.geometry.local_origin`: zeros near the world origin), and the
band's integer ``ijk`` stay local: voxel ``ijk`` is at ``origin + (ijk + 0.5) * voxel_size``.
Methods that return geometry take ``local=True`` for the local frame (float32-exact).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .config import Config
from .errors import BftaichiError, NoSurfaceError
from .frame import Frame, clean_depth, local_frames
from .geometry import check_K, check_pose
from .posterior import Posterior
from .stages.band import build_band
from .stages.integrate import TSDFVolume
from .stages.bandsolve import _COLLECT_MIN, Lap, fit_noise, solve_band

__all__ = ["Reconstructor"]


class Reconstructor:
    """Depth frames in, a Gaussian posterior of the SDF out (DESIGN.md section 3, steps 1-7).

    Args:
        config: the :class:`~bftaichi.config.Config` (voxel size, truncation, observation
            model, prior, solver); default: the built-in defaults (1 cm voxels).

    :meth:`integrate` fuses each frame into the TSDF bootstrap at once and keeps the frame
    (its depth image: 4 bytes a pixel, plus pose and intrinsics), because :meth:`solve` turns
    every frame into observations on the band the bootstrap defines. ``solve`` can be called
    again after more frames; it warm-starts from the previous solution (not after
    :meth:`update_poses` or :meth:`remove`: those solve as a fresh fuse would, exactly).
    """

    def __init__(self, config: Config | None = None):
        self.config = (config or Config()).check()
        t, s = self.config.tsdf, self.config.scene
        self.tsdf = TSDFVolume(t.voxel_size_m, t.bootstrap_trunc_m, max_weight=t.max_weight,
                               integrate_rgb=t.integrate_rgb, depth_max_m=s.depth_max_m,
                               arch=self.config.run.arch)
        self.frames: list[Frame] = []
        self.posterior: Posterior | None = None
        self._voxels = None  # the bootstrap's export, until the next frame
        self._n_integrated = 0  # frames integrated ever (default names stay unique)
        self._cold = False  # after update_poses / remove: the next solve starts cold

    @property
    def origin(self) -> np.ndarray:
        """(3,) float64 world position of the local grid's origin, metres (zeros until the first
        frame, and for a scene near the world origin; :class:`TSDFVolume` ``origin``)."""
        return self.tsdf.origin

    @property
    def K(self) -> np.ndarray | None:
        """(3, 3) intrinsics of the first kept frame (None before any)."""
        return self.frames[0].K if self.frames else None

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the first kept frame, pixels (None before any)."""
        if not self.frames:
            return None
        h, w = self.frames[0].depth_m.shape
        return w, h

    @property
    def voxels(self) -> dict:
        """The bootstrap's observed voxels (:meth:`TSDFVolume.export`: ``ijk, tsdf, weight``;
        ``ijk`` in the local grid of :attr:`origin`)."""
        if self._voxels is None:
            self._voxels = self.tsdf.export()
        return self._voxels

    def integrate(self, depth_m, K, T_W_C, rgb=None, name: str | None = None, *,
                  keep: bool = True) -> None:
        """Step 1: fuse one frame into the TSDF bootstrap. ``depth_m`` (H, W) metres (invalid:
        0, NaN, inf, negative or outside ``[scene.depth_min_m, scene.depth_max_m]``); ``K``
        (3, 3); ``T_W_C`` (4, 4); optional ``rgb`` (H, W, 3) uint8. ``keep=False`` does not keep
        the frame for :meth:`solve` (the caller then passes its own frame source to ``solve``).
        Raises BftaichiError naming ``name`` (default ``frame-<n>``) for a bad shape, K or pose."""
        name = name or f"frame-{self._n_integrated}"
        K = check_K(K, name)
        T_W_C = check_pose(T_W_C, name)
        depth = np.asarray(depth_m)
        if depth.ndim != 2:
            raise BftaichiError(f"{name}: depth must be (H, W), got shape {depth.shape}")
        s = self.config.scene
        depth = clean_depth(depth, s.depth_min_m, s.depth_max_m)
        self.tsdf.integrate(depth, K, T_W_C, rgb=rgb, name=name)
        self._n_integrated += 1
        self._voxels = None
        if keep:  # the colour too when the volume fuses it, so the frame can be removed
            rgb = (np.ascontiguousarray(rgb) if rgb is not None and self.tsdf.integrate_rgb
                   else None)
            self.frames.append(Frame(index=len(self.frames), name=name, depth_m=depth, K=K,
                                     T_W_C=T_W_C, rgb=rgb))

    def update_poses(self, poses: dict) -> list[str]:
        """Move kept frames to corrected poses (after a loop closure) without re-fusing the rest:
        ``poses`` maps a frame's ``name`` (as given to :meth:`integrate`) to its new ``T_W_C``
        (4, 4). Each moved frame is subtracted from the bootstrap at its old pose and added at
        the new one; the TSDF's sums are integers, so the result is bitwise what integrating
        every frame at its corrected pose gives (in the grid of :attr:`origin`, which the first
        frame fixed). The next :meth:`solve` rebuilds the band where the surface moved, takes
        every frame's observations at its current pose and starts the MAP cold, from the
        bootstrap, as a fresh fuse does, so its mean and sigma are bitwise those of fusing every
        frame at its corrected pose. (A warm start from the last solution is not exact: the
        free-space active set is chosen by a threshold on the mean, so it depends on the start;
        on 8 redkitchen frames at 8 cm one voxel's mean differed by 1.8 voxels.) Every name
        and pose is checked before anything changes. Returns the names of the frames
        that moved (a pose equal to the kept one is skipped)."""
        moves = [(self._kept(name, "update_poses"), check_pose(T, name))
                 for name, T in poses.items()]
        moved = []
        for i, T in moves:
            f = self.frames[i]
            if np.array_equal(T, f.T_W_C):
                continue
            self.tsdf.remove(f.depth_m, f.K, f.T_W_C, rgb=f.rgb, name=f.name)
            self.tsdf.integrate(f.depth_m, f.K, T, rgb=f.rgb, name=f.name)
            self.frames[i] = replace(f, T_W_C=T)
            moved.append(f.name)
        if moved:
            self._voxels = None
            self._cold = True
        return moved

    def remove(self, name: str) -> None:
        """Take kept frame ``name`` out: subtracted from the bootstrap exactly (bitwise as if it
        had never been integrated) and dropped from the frames :meth:`solve` observes; the next
        :meth:`solve` starts cold, as after :meth:`update_poses`."""
        i = self._kept(name, "remove")
        f = self.frames.pop(i)
        self.tsdf.remove(f.depth_m, f.K, f.T_W_C, rgb=f.rgb, name=f.name)
        self._voxels = None
        self._cold = True

    def _kept(self, name: str, what: str) -> int:
        """Position in :attr:`frames` of the one kept frame called ``name``."""
        hits = [i for i, f in enumerate(self.frames) if f.name == name]
        if len(hits) != 1:
            raise BftaichiError(
                f"{what}: {'no' if not hits else len(hits)} kept frames are named {name!r}"
                + ("; frames integrated with keep=False cannot be moved or removed" if not hits
                   else "; give each frame a unique name in integrate(..., name=...)"))
        return hits[0]

    def solve(self, frames=None, *, variance: bool = True, frame_iter=None) -> Posterior:
        """Steps 2-6 on everything integrated so far: the band, the observations of ``frames``
        (default: the kept frames; a dataset with ``len`` and indexing), the GMRF prior, the PCG
        MAP (warm-started from the last solve, unless frames were moved or removed since) and,
        unless ``variance=False``, the probe variance and face-neighbour covariance (else
        ``var`` is ``1/Q_ii``, a lower bound, and ``cov`` None). ``frame_iter(frames, desc)``
        yields the frames of the observation pass (the pipeline's prefetching reader). Frames
        hold world poses; they are moved into the local frame of :attr:`origin` as they are
        read. Raises NoSurfaceError when no voxel was observed."""
        cfg, frames = self.config, self.frames if frames is None else frames
        frames = local_frames(frames, self.origin)
        if len(self.voxels["ijk"]) == 0:
            raise NoSurfaceError(f"no surface was observed in {self.tsdf.n_frames} frames: check "
                                 "the depth range, the depth scale and that poses are T_W_C")
        lap = Lap()
        if cfg.run.chunk_m > 0:
            post = self._solve_chunked(frames, variance, frame_iter, lap)
        else:
            band, x0 = build_band(self.voxels, cfg.tsdf.bootstrap_trunc_m)           # step 2
            lap.collect = len(band) >= _COLLECT_MIN
            lap("band")
            part = self._solve_band(band, x0, frames, variance, frame_iter, lap)
            post = Posterior(band=band, **part, **self._posterior_fields(), seconds=lap.seconds)
        self.posterior, self._cold = post, False
        return post

    def _posterior_fields(self) -> dict:
        cfg = self.config
        return {"voxel_size": cfg.tsdf.voxel_size_m, "observation": cfg.observation,
                "trunc_m": cfg.tsdf.trunc_m, "bootstrap_trunc_m": cfg.tsdf.bootstrap_trunc_m,
                "origin": self.origin.copy()}

    def _warm(self) -> Posterior | None:
        """The posterior the next solve starts from: the last one, unless there is none or frames
        were moved or removed since (:meth:`update_poses`)."""
        if self._cold or self.posterior is None or not len(self.posterior.ijk):
            return None
        return self.posterior

    def _fit_noise(self, band, frames) -> dict:
        """The frames' extra noise (``observation.fit_noise``) seen on ``band``."""
        return fit_noise(self.config, band, frames)

    def _solve_band(self, band, x0, frames, variance: bool, frame_iter, lap) -> dict:
        """Steps 3-6 on ``band`` (start ``x0``, or the last posterior's mean: :meth:`_warm`)."""
        prev = self._warm()
        if prev is not None:
            x0 = prev.warm_start(band.ijk, x0)
        return solve_band(self.config, band, x0, frames, variance, frame_iter, lap)

    def _solve_chunked(self, frames, variance: bool, frame_iter, lap) -> Posterior:
        """Steps 2-6 in spatial chunks (``run.chunk_m``, :mod:`.stages.chunks`): each chunk's
        band (its core plus a halo of ``run.chunk_halo`` voxels) is solved on its own, with the
        observations that fall in it, one after another or, under ``bftaichi batch``, as Ray
        tasks (:func:`.stages.chunks.solve_chunks`); each voxel of the whole band takes the
        values of the chunk whose core holds it."""
        from .stages.chunks import (ChunkJob, chunk_plan, chunk_views, core_positions, merge_stats,
                                     solve_chunks)

        cfg = self.config
        full, _ = build_band(self.voxels, cfg.tsdf.bootstrap_trunc_m)
        lap("band")
        plan = chunk_plan(full.ijk, cfg.run.chunk_m, cfg.tsdf.voxel_size_m, cfg.run.chunk_halo)
        noise = self._fit_noise(full, frames)  # one noise model for the whole scene
        lap("noise")
        views = chunk_views(frames, plan, cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m)
        lap("chunk_views")
        n = len(full)
        out = {"mean": np.empty(n, np.float32), "var": np.empty(n, np.float32),
               "cov": np.zeros((n, 3), np.float32) if variance else None}
        prev = self._warm()
        jobs = (ChunkJob(cfg, chunk, chunk.select(self.voxels), frames, views[c], noise,
                         variance, chunk.select_warm(prev))
                for c, chunk in enumerate(plan.chunks))
        parts = []
        for part in solve_chunks(jobs, frame_iter):
            where = core_positions(full.ijk, part.pop("core_ijk"), part["chunk"]["key"])
            for key in ("mean", "var", "cov"):
                if out[key] is not None:
                    out[key][where] = part.pop(key)
            for stage, sec in part.pop("seconds").items():
                lap.seconds[stage] = round(lap.seconds.get(stage, 0.0) + sec, 4)
            parts.append(part)  # statistics only: the arrays are stitched and dropped
        lap.t0 = time.perf_counter()
        return Posterior(band=full, **out, **merge_stats(parts, plan), **self._posterior_fields(),
                         seconds=lap.seconds)

    def tsdf_mesh(self, *, local: bool = False):
        """Step 7 for the bootstrap: its mesh (cells whose 8 corners have weight >=
        ``mesh.min_weight``), the baseline ``tsdf_mesh.ply``; world coordinates, or the local
        frame with ``local``."""
        return self.tsdf.extract_mesh(self.config.mesh.min_weight, voxels=self.voxels,
                                      local=local)

    def save(self, out_dir: str | os.PathLike) -> Path:
        """Write ``tsdf_mesh.ply`` and, after :meth:`solve`, ``mesh.ply`` (with ``sigma`` and
        ``sigma_pos``) and ``band.npz`` into ``out_dir`` (created; files written atomically);
        return the folder."""
        from .io import ensure_out_dir, write_mesh_ply
        from .running.folder import staged

        out = ensure_out_dir(out_dir)
        mesh = self.tsdf_mesh(local=True)
        with staged(out) as staging:  # the files replaced together, one writer at a time
            write_mesh_ply(staging / "tsdf_mesh.ply", mesh.vertices, mesh.faces, origin=self.origin)
            if self.posterior is not None:
                self.posterior._write(staging)
        return out
