"""The library's front door: a :class:`Reconstructor` you integrate frames into and ``solve``.

::

    import bftaichi as bf

    recon = bf.Reconstructor(bf.Config.from_toml("scenes/bunny.toml"))
    for frame in bf.open_dataset("path/to/frames"):
        recon.integrate(frame.depth_m, frame.K, frame.T_W_C)
    post = recon.solve()               # bftaichi.Posterior: mean, var, band, solver stats
    mesh = post.extract_mesh()         # trimesh.Trimesh, vertex attribute "sigma" (metres)
    ranked = bf.nbv.rank(post, bf.nbv.candidates_around(post, n=48), recon.K, recon.image_size)
    recon.save("out/")                 # mesh.ply, tsdf_mesh.ply, band.npz (DESIGN.md section 4)

Conventions (DESIGN.md section 2): metres; depth along the camera z axis, (H, W), 0 / NaN
invalid; ``K`` the 3x3 OpenCV pinhole matrix; ``T_W_C`` the 4x4 camera-to-world pose.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .config import Config
from .errors import BftaichiError, NoSurfaceError
from .frame import Frame, clean_depth
from .geometry import check_K, check_pose

__all__ = ["Reconstructor"]


class Reconstructor:
    """Depth frames in, a Gaussian posterior of the SDF out (DESIGN.md section 3, steps 1-7).

    Args:
        config: the :class:`~bftaichi.config.Config` (voxel size, truncation, observation
            model, prior, solver); default: the built-in defaults (1 cm voxels).

    :meth:`integrate` fuses each frame into the TSDF bootstrap at once and keeps the frame
    (its depth image: 4 bytes a pixel, plus pose and intrinsics), because :meth:`solve` turns
    every frame into observations on the band the bootstrap defines. ``solve`` can be called
    again after more frames; it warm-starts from the previous solution.
    """

    def __init__(self, config: Config | None = None):
        from .stages.integrate import TSDFVolume

        self.config = (config or Config()).check()
        t, s = self.config.tsdf, self.config.scene
        self.tsdf = TSDFVolume(t.voxel_size_m, t.bootstrap_trunc_m, max_weight=t.max_weight,
                               integrate_rgb=t.integrate_rgb, depth_max_m=s.depth_max_m,
                               arch=self.config.run.arch)
        self.frames: list[Frame] = []
        self.posterior = None

    @property
    def K(self) -> np.ndarray | None:
        """(3, 3) intrinsics of the first frame (None before any)."""
        return self.frames[0].K if self.frames else None

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the first frame, pixels (None before any)."""
        if not self.frames:
            return None
        h, w = self.frames[0].depth_m.shape
        return w, h

    def integrate(self, depth_m, K, T_W_C, rgb=None, name: str | None = None) -> None:
        """Fuse one frame. ``depth_m`` (H, W) metres (invalid: 0, NaN, inf, negative or outside
        ``[scene.depth_min_m, scene.depth_max_m]``); ``K`` (3, 3); ``T_W_C`` (4, 4);
        optional ``rgb`` (H, W, 3) uint8. Raises BftaichiError naming ``name`` (default
        ``frame-<n>``) for a bad shape, K or pose."""
        name = name or f"frame-{len(self.frames)}"
        K = check_K(K, name)
        T_W_C = check_pose(T_W_C, name)
        depth = np.asarray(depth_m)
        if depth.ndim != 2:
            raise BftaichiError(f"{name}: depth must be (H, W), got shape {depth.shape}")
        s = self.config.scene
        depth = clean_depth(depth, s.depth_min_m, s.depth_max_m)
        self.tsdf.integrate(depth, K, T_W_C, rgb=rgb, name=name)
        self.frames.append(Frame(index=len(self.frames), name=name, depth_m=depth, K=K,
                                 T_W_C=T_W_C, rgb=None))

    def solve(self, *, variance: bool = True):
        """The posterior of everything integrated so far (:class:`bftaichi.Posterior`): the
        band, the observations of every frame, the GMRF prior, the PCG MAP (warm-started from
        the last solve) and, unless ``variance=False``, the probe variance. Raises
        NoSurfaceError when no voxel was observed."""
        from .posterior import solve_posterior

        voxels = self.tsdf.export()
        if len(voxels["ijk"]) == 0:
            raise NoSurfaceError(f"no surface was observed in {len(self.frames)} frames: check "
                                 "the depth range, the depth scale and that poses are T_W_C")
        self.posterior = solve_posterior(self.frames, voxels, self.config,
                                         warm_start=self.posterior, variance=variance)
        return self.posterior

    def save(self, out_dir: str | os.PathLike) -> Path:
        """Write ``tsdf_mesh.ply`` and, after :meth:`solve`, ``mesh.ply`` (with ``sigma``) and
        ``band.npz`` into ``out_dir`` (created; files written atomically); return the folder.
        """
        from .io import ensure_out_dir, write_mesh_ply

        out = ensure_out_dir(out_dir)
        mesh = self.tsdf.extract_mesh(self.config.mesh.min_weight)
        write_mesh_ply(out / "tsdf_mesh.ply", mesh.vertices, mesh.faces)
        if self.posterior is not None:
            self.posterior.save(out)
        return out
