"""The ``bfsdf`` format: bftaichi's own layout (written e.g. by ``bftaichi synth``).

Layout (DESIGN.md section 5)
----------------------------
``bfsdf`` (this project's own layout, written e.g. by ``bftaichi synth``)::

    depth/000000.png         uint16 (or 8-bit) depth, depth_scale units per metre (default 1000)
    pose/000000.txt          4x4 T_W_C (camera-to-world), metres, 16 numbers
    color/000000.png|jpg     optional 8-bit RGB, read only with load_rgb
    intrinsic/intrinsic.txt  line 1 "w h" (image size, pixels), line 2 "fx fy cx cy" (pixels)
    gt_mesh.ply              optional ground-truth mesh (metres, world frame)

Frames are ordered by file stem (numerically when the stems are numbers). All depth images must
have the size given in ``intrinsic/intrinsic.txt``.

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import check_K, intrinsics
from .base import Dataset
from .readers import parse_numbers, read_depth_png, read_pose_txt, read_text, require_files, sort_frames


class BFSDFDataset(Dataset):
    """bftaichi's own layout: ``depth/``, ``pose/``, ``intrinsic/intrinsic.txt`` (module docstring).

    Conventions: depth uint16 millimetres; poses 4x4 ``T_W_C``, OpenCV axes; image size in the
    intrinsics file."""

    format = "bfsdf"
    looks_for = "depth/NNNNNN.png + pose/NNNNNN.txt + intrinsic/intrinsic.txt"
    default_depth_scale = 1000.0
    COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (path / "depth").is_dir() and (path / "intrinsic" / "intrinsic.txt").is_file()

    def _scan(self) -> list[str]:
        depth_dir = self.path / "depth"
        if not depth_dir.is_dir():
            raise DataError(f"{depth_dir}: folder missing (a bfsdf dataset has {self.looks_for})")
        names = [p.stem for p in sort_frames(depth_dir.glob("*.png"))]
        if not names:
            return names
        require_files([self.path / "pose" / f"{n}.txt" for n in names], "pose file",
                       [f"depth/{n}.png" for n in names])
        k_path = self.path / "intrinsic" / "intrinsic.txt"
        self.K, size = self._read_intrinsics(k_path)
        self._set_image_size(*size, "intrinsic/intrinsic.txt")
        return names

    @staticmethod
    def _read_intrinsics(path: Path) -> tuple[np.ndarray, tuple[float, float]]:
        """Parse ``w h`` / ``fx fy cx cy``; return (K, (W, H))."""
        lines = [line for line in read_text(path, "intrinsics").splitlines() if line.strip()]
        if len(lines) != 2:
            raise DataError(f"{path}: intrinsics file must have 2 lines, 'w h' then 'fx fy cx cy'; "
                            f"found {len(lines)} non-empty lines")
        size = parse_numbers(lines[0], path, "intrinsics")
        params = parse_numbers(lines[1], path, "intrinsics")
        if size.size != 2:
            raise DataError(f"{path}: line 1 must be 'w h' (2 numbers), found {size.size} numbers")
        if params.size != 4:
            raise DataError(f"{path}: line 2 must be 'fx fy cx cy' (4 numbers), found {params.size} numbers")
        if not all(np.isfinite(v) and v >= 1 and float(v).is_integer() for v in size):
            raise DataError(f"{path}: image size 'w h' must be positive integers, got {lines[0].strip()!r}")
        K = check_K(intrinsics(*params), str(path))
        return K, (float(size[0]), float(size[1]))

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / "depth" / f"{name}.png"
        depth = read_depth_png(depth_path, self.depth_scale)
        T_W_C = read_pose_txt(self.path / "pose" / f"{name}.txt")
        rgb = self._colour(self.path / "color" / f"{name}{s}" for s in self.COLOR_SUFFIXES)
        return depth, depth_path, T_W_C, rgb
