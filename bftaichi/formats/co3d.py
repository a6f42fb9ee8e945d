"""The ``co3d`` format: Common Objects in 3D sequences, and the PyTorch3D camera conversion.

Layout (DESIGN.md section 5)
----------------------------
``co3d`` (one CO3D category folder or sequence, :class:`CO3DDataset`)::

    frame_annotations.jgz    gzip JSON list of frame annotations (or frame_annotations.json):
                             image size, depth PNG path + scale_adjustment (+ depth mask), fg
                             mask, PyTorch3D NDC camera; paths relative to the CO3D root (the
                             folder's parent) or to the folder itself

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

import numbers
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import check_K, check_pose, intrinsics
from .base import Dataset
from .readers import first_file, invert_rigid, read_float16_png, read_json, read_mask


def pytorch3d_to_opencv(R, T, focal_length, principal_point, image_size_wh, intrinsics_format: str,
                        where: str) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(K, T_W_C)`` of a PyTorch3D NDC camera as stored in CO3D's viewpoint annotations.

    PyTorch3D maps a world point (row vector) to the camera as ``X_cam = X_world @ R + T`` with
    camera axes +X left, +Y up, +Z forward, then to NDC as ``x_ndc = f_x X/Z + p_x``; NDC +x points
    left and +y up. ``intrinsics_format`` says how NDC scales to pixels (``s`` pixels per NDC unit,
    ``W, H`` the image size): ``ndc_isotropic``, ``s = min(W, H) / 2`` on both axes;
    ``ndc_norm_image_bounds``, ``s = (W / 2, H / 2)`` (NDC spans [-1, 1] on each axis). In
    PyTorch3D's screen coordinates, pixel ``i`` has its centre at ``i + 0.5``; in OpenCV's at ``i``.
    So (as ``pytorch3d.utils.opencv_from_cameras_projection``, except for its missing half pixel)::

        fx, fy = f * s                          cx, cy = (W / 2, H / 2) - p * s - 0.5
        R_C_W = F @ R.T,  t_C_W = F @ T         F = diag(-1, -1, 1)   (x and y axes flipped)
        T_W_C = inverse([R_C_W | t_C_W])

    Returns float64 ``K`` (3, 3) and ``T_W_C`` (4, 4); DataError naming ``where`` for an unknown
    format, non-finite values or a rotation that is not orthonormal.
    """
    R = np.asarray(R, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    f = np.asarray(focal_length, dtype=np.float64) * np.ones(2)
    p = np.asarray(principal_point, dtype=np.float64)
    if R.shape != (3, 3) or T.shape != (3,) or p.shape != (2,):
        raise DataError(f"{where}: camera R must be 3x3, T 3 and principal_point 2 numbers, got shapes "
                        f"{R.shape}, {T.shape}, {p.shape}")
    half = 0.5 * np.asarray(image_size_wh, dtype=np.float64)
    if intrinsics_format == "ndc_isotropic":
        s = np.full(2, half.min())
    elif intrinsics_format == "ndc_norm_image_bounds":
        s = half
    else:
        raise DataError(f"{where}: intrinsics_format {intrinsics_format!r} is not one of "
                        f"ndc_isotropic, ndc_norm_image_bounds")
    fx, fy = f * s
    cx, cy = half - p * s - 0.5
    K = check_K(intrinsics(fx, fy, cx, cy), where)
    flip = np.diag([-1.0, -1.0, 1.0])
    T_C_W = np.eye(4)
    T_C_W[:3, :3] = flip @ R.T
    T_C_W[:3, 3] = flip @ T
    return K, invert_rigid(check_pose(T_C_W, where))


class CO3DDataset(Dataset):
    """One sequence of Common Objects in 3D (CO3D v1/v2, Reizenstein et al. 2021).

    The folder holds ``frame_annotations.jgz`` (gzip JSON list; or ``frame_annotations.json``),
    normally a CO3D category folder (``<root>/teddybear/``) whose annotations cover many
    sequences: choose one with ``sequence`` (a folder with one sequence needs none). Per frame
    it reads ``image.size`` ([H, W]), ``depth.path`` (a 16-bit PNG of float16 bit patterns),
    ``depth.scale_adjustment`` (depth = PNG value * scale_adjustment / depth_scale), the optional
    ``depth.mask_path`` (CO3D's depth-validity mask, used with ``use_depth_masks``, the default)
    and ``mask.path`` (the foreground probability, used with ``use_masks``: depth where it is
    below 50 % is dropped), and ``viewpoint`` (PyTorch3D NDC camera, converted by
    :func:`pytorch3d_to_opencv`: each ``Frame.K`` is the frame's own). Paths are relative to the
    CO3D root, the folder's parent; a path relative to the folder itself is accepted too. Frames
    are ordered by ``frame_number``; all must have one image size (as CO3D's video frames do).

    CO3D's world scale is arbitrary (COLMAP units), so a fixed voxel size makes no sense:
    :attr:`suggested_voxel_m` is 1/256 of the scene's extent.
    """

    format = "co3d"
    looks_for = "frame_annotations.jgz or frame_annotations.json (CO3D)"
    default_depth_scale = 1.0
    """CO3D depth is in the scene's (arbitrary) units: 1 unit = 1 "metre" of the reconstruction."""
    options = ("sequence", "use_masks", "use_depth_masks")
    ANNOTATION_FILES = ("frame_annotations.jgz", "frame_annotations.json")
    VOXEL_FRACTION = 1.0 / 256.0
    """:attr:`suggested_voxel_m` as a fraction of the scene extent: 256 voxels across the scene."""

    def __init__(self, path: str | Path, depth_min_m: float = 0.0, depth_max_m: float = 1e6,
                 load_rgb: bool = False, depth_scale: float | None = None, sequence: str | None = None,
                 use_masks: bool = False, use_depth_masks: bool = True) -> None:
        """``sequence``: the ``sequence_name`` to read (None: the only one in the annotations);
        ``use_masks`` / ``use_depth_masks``: apply the foreground / depth-validity masks. The
        depth range defaults to "everything positive" because CO3D's units are arbitrary."""
        self.sequence = sequence
        self.use_masks = bool(use_masks)
        self.use_depth_masks = bool(use_depth_masks)
        super().__init__(path, depth_min_m, depth_max_m, load_rgb, depth_scale)

    @classmethod
    def detect(cls, path: Path) -> bool:
        return any((path / name).is_file() for name in cls.ANNOTATION_FILES)

    def _scan(self) -> list[str]:
        self._ann_path = first_file(self.path / name for name in self.ANNOTATION_FILES)
        entries = read_json(self._ann_path, "frame annotations")
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise DataError(f"{self._ann_path}: frame annotations must be a JSON list of objects")
        sequences = sorted({str(e.get("sequence_name", "")) for e in entries})
        if self.sequence is None and len(sequences) > 1:
            shown = ", ".join(sequences[:8]) + (", ..." if len(sequences) > 8 else "")
            raise DataError(f"{self._ann_path}: annotations of {len(sequences)} sequences ({shown}); "
                            f"choose one with sequence=")
        if self.sequence is not None:
            entries = [e for e in entries if str(e.get("sequence_name")) == self.sequence]
            if not entries:
                raise DataError(f"{self._ann_path}: no frames of sequence {self.sequence!r} "
                                f"(sequences: {', '.join(sequences[:8])})")
        for e in entries:
            if not isinstance(e.get("frame_number"), int):
                raise DataError(f"{self._ann_path}: a frame annotation lacks an integer 'frame_number'")
        self._entries = sorted(entries, key=lambda e: e["frame_number"])
        names = [f"{e.get('sequence_name', '')}/{e['frame_number']}" for e in self._entries]
        if not names:
            return names
        sizes = [self._image_size_wh(j, e) for j, e in enumerate(self._entries)]
        odd = next((j for j, s in enumerate(sizes) if s != sizes[0]), None)
        if odd is not None:
            raise DataError(f"{self._ann_path}: frame {self._entries[odd]['frame_number']} has image "
                            f"size {sizes[odd]} (WxH) but frame {self._entries[0]['frame_number']} has "
                            f"{sizes[0]}; the frames of a sequence must share one size")
        self._set_image_size(*sizes[0], f"{self._ann_path.name} (image.size)")
        self.K = self._camera(0)[0]
        return names

    def _where(self, j: int) -> str:
        return f"{self._ann_path}: frame {self._entries[j]['frame_number']}"

    def _image_size_wh(self, j: int, e: dict) -> tuple[int, int]:
        size = (e.get("image") or {}).get("size")
        if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
            raise DataError(f"{self._where(j)}: image.size must be [height, width], got {size!r}")
        return size[1], size[0]

    def _camera(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(K, T_W_C) of frame ``j``."""
        vp = self._entries[j].get("viewpoint")
        if not isinstance(vp, dict):
            raise DataError(f"{self._where(j)}: no 'viewpoint' camera")
        missing = [k for k in ("R", "T", "focal_length", "principal_point") if k not in vp]
        if missing:
            raise DataError(f"{self._where(j)}: viewpoint lacks {', '.join(missing)}")
        try:
            R, T, f, p = (np.asarray(vp[k], dtype=np.float64)
                          for k in ("R", "T", "focal_length", "principal_point"))
        except (TypeError, ValueError) as e:
            raise DataError(f"{self._where(j)}: viewpoint values are not numbers ({e})") from None
        # CO3D's ViewpointAnnotation defaults intrinsics_format to ndc_norm_image_bounds
        fmt = vp.get("intrinsics_format", "ndc_norm_image_bounds")
        return pytorch3d_to_opencv(R, T, f, p, self.image_size, fmt, self._where(j))

    def _frame_K(self, j: int) -> np.ndarray:
        return self._camera(j)[0]

    def _file(self, j: int, rel) -> Path:
        """An annotation path resolved against the CO3D root (the folder's parent) or the folder."""
        if not isinstance(rel, str) or not rel:
            raise DataError(f"{self._where(j)}: file path {rel!r} is not a path")
        candidates = [self.path.parent / rel, self.path / rel]
        return first_file(candidates) or candidates[0]

    def _read_frame(self, j: int):
        e = self._entries[j]
        depth_ann = e.get("depth") or {}
        if "path" not in depth_ann:
            raise DataError(f"{self._where(j)}: no depth.path")
        depth_path = self._file(j, depth_ann["path"])
        scale = depth_ann.get("scale_adjustment", 1.0)
        if not (isinstance(scale, numbers.Real) and np.isfinite(scale) and scale > 0):
            raise DataError(f"{self._where(j)}: depth.scale_adjustment = {scale!r} must be a positive number")
        depth = read_float16_png(depth_path) * np.float32(scale / self.depth_scale)
        masks = []
        if self.use_depth_masks and depth_ann.get("mask_path"):
            masks.append(self._file(j, depth_ann["mask_path"]))
        if self.use_masks:
            mask_ann = e.get("mask") or {}
            if not mask_ann.get("path"):
                raise DataError(f"{self._where(j)}: use_masks is set but the frame has no mask.path")
            masks.append(self._file(j, mask_ann["path"]))
        for mask_path in masks:
            mask = read_mask(mask_path)
            if mask.shape != depth.shape:
                raise DataError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]} (WxH) but the "
                                f"depth image {depth_path.name} is {depth.shape[1]}x{depth.shape[0]}")
            depth[~mask] = 0.0
        image = (e.get("image") or {}).get("path")
        rgb = self._colour([self._file(j, image)] if image else [])
        return depth, depth_path, self._camera(j)[1], rgb

    @property
    def suggested_voxel_m(self) -> float:
        """A voxel size for this sequence, in its units: :attr:`VOXEL_FRACTION` of the scene extent.

        The extent is the diagonal of the camera centres' bounding box (CO3D cameras orbit the
        object, so this is about the orbit's diameter); if the cameras do not move, twice the
        median valid depth of the first frame. Not wired to the voxel-size default yet.
        """
        centres = np.array([self._camera(j)[1][:3, 3] for j in self._indices])
        extent = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0)))
        if extent <= 1e-9:
            depth = self[0].depth_m
            valid = depth[depth > 0]
            if valid.size == 0:
                raise DataError(f"{self.path}: cannot suggest a voxel size: the cameras do not move "
                                f"and the first frame has no valid depth")
            extent = 2.0 * float(np.median(valid))
        return extent * self.VOXEL_FRACTION
