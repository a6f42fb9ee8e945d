"""The TSDF integrator: validated Python front of :class:`kernels.tsdf.SparseTSDF`.

Usage::

    import bftaichi as bf
    vol = bf.TSDFVolume(voxel_size_m=0.01, trunc_m=0.04)
    for frame in bf.open_dataset("path/to/7scenes-seq"):
        vol.integrate(frame.depth_m, frame.K, frame.T_W_C, name=frame.name)
    mesh = vol.extract_mesh()          # trimesh.Trimesh, world frame, metres

Coordinates: poses are world poses; the voxel grid (``export()['ijk']``) lives in a local frame,
voxel ``ijk`` at world ``vol.origin + (ijk + 0.5) * voxel_size_m`` (float64 origin, zeros for a
scene near the world origin; :func:`bftaichi.geometry.local_origin`), so a georeferenced or
kilometre-long scene fits the block map and float32.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from dataclasses import dataclass

from kernels.layout import BLOCK

from .. import backend
from ..checks import check_range
from ..errors import BftaichiError, ConfigError, DataError, NoSurfaceError
from ..geometry import MAP_VOXELS, local_origin, points_in_world, pose_in_local
from ..geometry import check_depth, check_field_of_view, check_K, check_pose

__all__ = ["TSDFConfig", "TSDFVolume", "auto_activation_stride", "MAX_OUTSIDE"]

MAX_OUTSIDE = 0.01
"""Share of a frame's valid pixels whose surface point (at the measured depth, local frame) may
lie outside the TSDF's block map before :meth:`TSDFVolume.integrate` refuses the frame with a
DataError. Up to it, the activation samples outside are dropped and counted (``stats()``
``out_of_range_samples``, report.json ``counts.out_of_range_samples``), as they always were:
stray far returns and flying pixels do not stop a run."""


@dataclass
class TSDFConfig:
    """``[tsdf]``: the projective TSDF bootstrap (DESIGN.md section 3, step 1)."""

    voxel_size_m: float = 0.01
    """Voxel edge length, metres. Voxel ``ijk`` has centre ``(ijk + 0.5) * voxel_size_m``."""

    trunc_m: float = 0.02
    """Observation truncation ``tau``, metres (samples within ``+-tau`` of the measured surface).
    Must be at least one voxel. 2 voxels by default, so the bootstrap TSDF (``alpha * tau``) uses
    4 voxels, Open3D's usual choice: on the default scene this beats 3 voxels (F@5mm 0.911 vs
    0.871) because a long truncation biases the projective distance on curved surfaces."""

    alpha: float = 2.0
    """The bootstrap TSDF runs with truncation ``tau_b = alpha * trunc_m`` so that the narrow band
    ``|sdf| < alpha * tau`` exists in it (paper: alpha in [1, 3])."""

    max_weight: float = 10000.0
    """Cap of the per-voxel weight the TSDF reports (each observation counts 1), which the
    meshing threshold ``mesh.min_weight`` and the prior's anchors read. The TSDF itself is the
    exact mean of all its observations, kept as integer sums, so that a frame can be subtracted
    exactly (``Reconstructor.update_poses`` / ``remove``): unlike a capped running average it
    does not forget old frames; remove them instead. The default is voxblox's."""

    integrate_rgb: bool = False
    """Also fuse RGB into per-voxel colour (off by default: it costs time and memory)."""

    def check(self) -> None:
        check_range("tsdf.voxel_size_m", self.voxel_size_m, 1e-4, 1.0)
        if self.trunc_m < self.voxel_size_m:
            raise ConfigError(
                f"tsdf.trunc_m = {self.trunc_m} is smaller than one voxel "
                f"(tsdf.voxel_size_m = {self.voxel_size_m}); use at least one voxel, typically 3-4")
        check_range("tsdf.trunc_m", self.trunc_m, 0.0, 10.0, lo_open=True)
        check_range("tsdf.alpha", self.alpha, 1.0, 3.0)
        check_range("tsdf.max_weight", self.max_weight, 1.0)

    @property
    def bootstrap_trunc_m(self) -> float:
        """Truncation of the bootstrap TSDF, ``tau_b = alpha * tau``, metres."""
        return self.alpha * self.trunc_m



def auto_activation_stride(K: np.ndarray, voxel_size_m: float, depth_max_m: float) -> int:
    """Pixel stride for block activation: the largest stride <= 4 (Open3D's fixed choice) whose
    ray spacing at ``depth_max_m`` stays within half a block (8 voxels), so skipping pixels
    cannot skip a block. 1 for small images / far depth."""
    f = float(min(K[0, 0], K[1, 1]))
    spacing_per_stride = depth_max_m / f  # metres between neighbouring pixel rays at depth_max
    stride = int(math.floor(0.5 * 8 * voxel_size_m / spacing_per_stride))
    return max(1, min(4, stride))


class TSDFVolume:
    """Sparse projective TSDF volume (DESIGN.md section 3, step 1).

    Args:
        voxel_size_m: voxel edge, metres (voxel ``ijk`` has centre ``(ijk + 0.5) * voxel_size_m``).
        trunc_m: truncation of the TSDF, metres (at least one voxel).
        max_weight: cap of the exported weight (each observation counts 1; the TSDF is the exact
            mean of all observations, kept as integer sums so frames can be removed).
        integrate_rgb: also average per-voxel colour from ``rgb`` images.
        depth_max_m: depth beyond this is ignored (also sets the activation stride).
        arch: Taichi backend used if Taichi is not initialised yet.

    Integration is deterministic: the same frames give bitwise the same volume.

    Attributes:
        origin: (3,) float64 world position of the grid's origin, metres, set by the first
            :meth:`integrate` (:func:`bftaichi.geometry.local_origin`: zeros when its camera is
            near the world origin, else the block corner nearest it). Voxel ``ijk`` has world
            centre ``origin + (ijk + 0.5) * voxel_size_m``; poses are subtracted ``origin`` in
            float64 before the kernels see them.
    """

    def __init__(self, voxel_size_m: float, trunc_m: float, *, max_weight: float = 1e4,
                 integrate_rgb: bool = False, depth_max_m: float = 6.0, arch: str = "cpu"):
        voxel_size_m, trunc_m = float(voxel_size_m), float(trunc_m)
        if not (math.isfinite(voxel_size_m) and 1e-4 <= voxel_size_m <= 1.0):
            raise BftaichiError(f"voxel_size_m = {voxel_size_m} is out of range [0.0001, 1] m")
        if not (math.isfinite(trunc_m) and trunc_m >= voxel_size_m):
            raise BftaichiError(f"trunc_m = {trunc_m} must be at least one voxel ({voxel_size_m} m)")
        if not (max_weight >= 1):
            raise BftaichiError(f"max_weight = {max_weight} must be >= 1")
        if not (depth_max_m > 0):
            raise BftaichiError(f"depth_max_m = {depth_max_m} must be > 0")
        if not backend.is_initialized():
            backend.init(arch)
        from kernels.tsdf import SparseTSDF

        self.voxel_size_m = voxel_size_m
        self.trunc_m = trunc_m
        self.depth_max_m = float(depth_max_m)
        self.integrate_rgb = bool(integrate_rgb)
        self._vol = SparseTSDF(voxel_size_m, trunc_m, max_weight=max_weight,
                               with_color=integrate_rgb)
        self._stride: int | None = None
        self.n_frames = 0
        self.n_pixels = 0  # valid depth pixels integrated
        self.n_empty_frames = 0  # frames that updated no voxel
        self.origin = np.zeros(3)

    @property
    def kernel(self):
        """The underlying :class:`kernels.tsdf.SparseTSDF` (for embedding)."""
        return self._vol

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
                  rgb: np.ndarray | None = None, name: str = "frame") -> int:
        """Fuse one depth frame; return the number of voxel updates it made.

        Args:
            depth_m: (H, W) depth along the camera z axis, metres. NaN, inf, <= 0 and values beyond
                ``depth_max_m`` are ignored.
            K: (3, 3) pinhole intrinsics.
            T_W_C: (4, 4) camera-to-world pose.
            rgb: optional (H, W, 3) uint8 colour registered to the depth.
            name: used in error messages.

        Raises DataError when more than :data:`MAX_OUTSIDE` of the frame's valid pixels see
        surface outside the block map (:meth:`_check_in_map`).
        """
        depth = check_depth(depth_m, name)
        K = check_K(K, name)
        check_field_of_view(K, depth.shape[:2], name)
        T_W_C = check_pose(T_W_C, name)
        depth = depth.astype(np.float32, copy=False)
        valid = np.isfinite(depth) & (depth > 0) & (depth <= self.depth_max_m)
        depth = np.ascontiguousarray(np.where(valid, depth, np.float32(0)))
        if rgb is not None and self.integrate_rgb:
            rgb = np.asarray(rgb)
            if rgb.shape != depth.shape + (3,) or rgb.dtype != np.uint8:
                raise BftaichiError(f"{name}: rgb must be (H, W, 3) uint8 matching the depth "
                                    f"{depth.shape}, got {rgb.shape} {rgb.dtype}")
            rgb = np.ascontiguousarray(rgb)
        if self._stride is None:
            self._stride = auto_activation_stride(K, self.voxel_size_m, self.depth_max_m)
        if self.n_frames == 0:
            self.origin = local_origin(T_W_C[:3, 3], self.voxel_size_m)
        T_L_C = pose_in_local(T_W_C, self.origin)
        n_valid = int(valid.sum())
        out_before = self._vol.stats()["out_of_range_samples"]
        updates = self._vol.integrate(depth, K, T_L_C, rgb=rgb, activation_stride=self._stride)
        self.n_frames += 1
        self.n_pixels += n_valid
        if updates == 0:
            self.n_empty_frames += 1
        if self._vol.stats()["out_of_range_samples"] > out_before:
            self._check_in_map(depth, K, T_L_C, name)
        return updates

    def remove(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
               rgb: np.ndarray | None = None, name: str = "frame") -> int:
        """Subtract a frame :meth:`integrate` added before with the same ``depth_m``, ``K``,
        ``T_W_C`` (and ``rgb``); return the number of voxel updates removed. The volume is then
        bitwise what integrating every other frame gives (the sums are integers; the grid's
        :attr:`origin` stays where the first frame put it). Subtracting a frame that was never
        added corrupts the volume: :class:`bftaichi.Reconstructor` keeps the frames and is the
        safe way (``update_poses``, ``remove``)."""
        if self.n_frames == 0:
            raise BftaichiError(f"{name}: the volume is empty, there is no frame to remove")
        depth = np.ascontiguousarray(np.asarray(depth_m, np.float32))
        valid = np.isfinite(depth) & (depth > 0) & (depth <= self.depth_max_m)
        depth = np.ascontiguousarray(np.where(valid, depth, np.float32(0)))
        if rgb is not None and self.integrate_rgb:
            rgb = np.ascontiguousarray(rgb)
        T_L_C = pose_in_local(check_pose(T_W_C, name), self.origin)
        if self._stride is None:  # a loaded state: the stride its frames were added with
            self._stride = auto_activation_stride(K, self.voxel_size_m, self.depth_max_m)
        removed = self._vol.integrate(depth, check_K(K, name), T_L_C, rgb=rgb,
                                      activation_stride=self._stride, sign=-1)
        self.n_frames -= 1
        self.n_pixels -= int(valid.sum())
        if removed == 0:
            self.n_empty_frames -= 1
        return removed

    def state(self) -> dict[str, np.ndarray]:
        """The volume's exact state (:meth:`kernels.tsdf.SparseTSDF.state`: every observed
        voxel's integer sums) plus ``origin`` and ``counts`` (frames, pixels, empty frames), for
        :meth:`load_state`. About 16 bytes an observed voxel (24 with colour)."""
        st = self._vol.state()
        st["origin"] = self.origin.copy()
        st["counts"] = np.array([self.n_frames, self.n_pixels, self.n_empty_frames], np.int64)
        return st

    def load_state(self, state: dict) -> None:
        """Restore :meth:`state` into this new volume (same voxel size, truncation, colour and
        ``depth_max_m``): frames can then be added and removed exactly as before it was saved."""
        if self.n_frames:
            raise BftaichiError("load_state needs a volume no frame was integrated into")
        if ("rgb_sum" in state) != self.integrate_rgb:
            raise BftaichiError("the saved state and this volume differ in colour "
                                "(tsdf.integrate_rgb)")
        self._vol.load_state(state)
        self.origin = np.asarray(state["origin"], np.float64).copy()
        self.n_frames, self.n_pixels, self.n_empty_frames = (int(c) for c in state["counts"])

    def _check_in_map(self, depth: np.ndarray, K: np.ndarray, T_L_C: np.ndarray,
                      name: str) -> None:
        """After a frame whose activation left the block map: DataError when more than
        :data:`MAX_OUTSIDE` of its valid pixels' surface points lie outside it. The message
        gives the extent of the scene so far (the allocated blocks and the frame's points
        between their 0.5 and 99.5 percentiles, so stray returns do not count) along its
        longest axis, and what the map holds at this voxel size."""
        vs = self.voxel_size_m
        v, u = np.nonzero(depth > 0)
        if len(v) == 0:
            return
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))], 1)
        points = (rays * depth[v, u].astype(np.float64)[:, None]) @ T_L_C[:3, :3].T + T_L_C[:3, 3]
        half = MAP_VOXELS // 2 * vs
        outside = np.any((points < -half) | (points >= half), axis=1)
        share = float(np.count_nonzero(outside)) / len(points)
        if share <= MAX_OUTSIDE:
            return
        lo, hi = np.percentile(points, [0.5, 99.5], axis=0)
        blocks = self._vol.blocks()
        if len(blocks):
            block_m = BLOCK * vs
            lo = np.minimum(lo, blocks.min(axis=0) * block_m)
            hi = np.maximum(hi, (blocks.max(axis=0) + 1) * block_m)
        extent = hi - lo
        a = int(np.argmax(extent))
        span = MAP_VOXELS * vs
        centre = ("the world origin" if not np.any(self.origin) else
                  f"the first frame's camera (local origin {np.round(self.origin, 3).tolist()})")
        where = (f"{name}: {share:.0%} of its valid pixels see surface outside the TSDF's block "
                 f"map, which holds {MAP_VOXELS} voxels = {span:g} m per axis at "
                 f"tsdf.voxel_size_m = {vs:g} m, centred on {centre}")
        if extent[a] > span:
            raise DataError(
                f"{where}. The scene spans {extent[a]:.1f} m along {'xyz'[a]}: it does not fit. "
                f"Use a voxel of at least {extent[a] / MAP_VOXELS:.3g} m (tsdf.voxel_size_m, "
                f"--voxel), or split the scene into parts under {span:g} m")
        reach = float(np.abs(points[outside]).max())
        raise DataError(
            f"{where}. The scene spans {extent[a]:.1f} m along {'xyz'[a]}, which would fit, "
            f"but this frame sees surface {reach:.1f} m from that centre (more than "
            f"{half:g} m): start the sequence with a frame nearer the middle of the scene "
            "(scene.frames), use a larger voxel or a smaller scene.depth_max_m, or split the "
            "scene")

    def export(self) -> dict[str, np.ndarray]:
        """Observed voxels sorted by ijk: ``ijk`` (N,3) int32 in the local grid (world centre
        ``origin + (ijk + 0.5) * voxel_size_m``), ``tsdf`` (N,) float32 metres (clamped to
        +-trunc_m), ``weight`` (N,) float32 [, ``rgb`` (N,3) float32 0..255]."""
        return self._vol.export()

    def extract_mesh(self, min_weight: float = 1.0, voxels: dict | None = None, *,
                     local: bool = False) -> trimesh.Trimesh:
        """Marching cubes at tsdf = 0 over cells whose 8 corners have weight >= ``min_weight``.

        Returns a mesh with outward (toward free space) face orientation, in world coordinates
        (float64 ``origin + vertex``), or with ``local`` in the grid's local frame (the float32
        marching-cubes vertices). Raises NoSurfaceError when no voxel was observed. ``voxels``
        reuses an :meth:`export` result.
        """
        from .surface import extract_mesh, sample_field

        v = self.export() if voxels is None else voxels
        if len(v["ijk"]) == 0:
            raise NoSurfaceError("no voxel was observed: every frame was empty or all-invalid, "
                                 "or the poses point away from the surface")
        vertices, faces = extract_mesh(v["ijk"], v["tsdf"], v["weight"] >= min_weight,
                                       self.voxel_size_m)
        colors = None
        if "rgb" in v and len(vertices):
            rgb = sample_field(v["ijk"], v["rgb"], v["weight"] > 0, self.voxel_size_m, vertices)
            colors = np.clip(np.nan_to_num(rgb), 0, 255).astype(np.uint8)
        if not local:
            vertices = points_in_world(vertices, self.origin)
        return trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)

    def stats(self) -> dict[str, int]:
        """Counts: frames, valid pixels, empty frames, allocated blocks, out-of-range samples."""
        s = self._vol.stats()
        return {"frames": self.n_frames, "pixels": self.n_pixels,
                "empty_frames": self.n_empty_frames, "activation_stride": self._stride or 0, **s}
