"""The ``scannet`` format: ScanNet scenes exported by ScanNet's SensReader.

Layout (DESIGN.md section 5)
----------------------------
``scannet`` (a ScanNet scene exported by its SensReader, :class:`ScanNetDataset`)::

    depth/0.png ...          uint16 depth in millimetres
    pose/0.txt ...           4x4 T_W_C; all inf/NaN = tracking lost: the frame is skipped
    color/0.jpg ...          optional colour (must be resized to the depth size to be used)
    intrinsic/intrinsic_depth.txt   4x4 whose top-left 3x3 is the depth camera's K
                             (intrinsic_color.txt is the colour camera's and is not used)

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from .base import Dataset
from .readers import parse_numbers, read_depth_png, read_K_txt, read_pose_txt, require_files, sort_frames, warn


class ScanNetDataset(Dataset):
    """A ScanNet scene exported by ScanNet's SensReader (``depth/``, ``color/``, ``pose/``,
    ``intrinsic/``).

    Conventions: ``depth/N.png`` uint16 millimetres; ``pose/N.txt`` 4x4 ``T_W_C`` (OpenCV axes);
    K is the top-left 3x3 of ``intrinsic/intrinsic_depth.txt`` (``intrinsic_color.txt`` belongs to
    the 1296x968 colour camera and is not used). A pose of inf or NaN is how ScanNet marks lost
    tracking: those frames are skipped at open (:attr:`skipped` counts them, one warning). Colour
    images are used only if they have the depth's size (the raw export's are larger: resize them).
    """

    format = "scannet"
    looks_for = "depth/N.png + pose/N.txt + intrinsic/intrinsic_depth.txt"
    default_depth_scale = 1000.0

    @classmethod
    def detect(cls, path: Path) -> bool:
        return ((path / "depth").is_dir() and (path / "pose").is_dir()
                and (path / "intrinsic" / "intrinsic_depth.txt").is_file())

    def _scan(self) -> list[str]:
        names = [p.stem for p in sort_frames((self.path / "depth").glob("*.png"))]
        if not names:
            return names
        pose_paths = [self.path / "pose" / f"{n}.txt" for n in names]
        require_files(pose_paths, "pose file", [f"depth/{n}.png" for n in names])
        lost = [self._tracking_lost(p) for p in pose_paths]
        kept = [n for n, bad in zip(names, lost) if not bad]
        self.skipped = len(names) - len(kept)
        if self.skipped:
            warn(f"{self.path}: skipped {self.skipped} of {len(names)} frames whose pose is inf/NaN "
                  f"(ScanNet's mark for lost tracking)")
        self.K = read_K_txt(self.path / "intrinsic" / "intrinsic_depth.txt", 16)
        return kept

    @staticmethod
    def _tracking_lost(pose_path: Path) -> bool:
        """True for a pose file of 16 numbers with an inf or NaN (a malformed file is not "lost":
        reading that frame reports it)."""
        try:
            values = parse_numbers(pose_path.read_text(), pose_path, "pose")
        except (OSError, UnicodeDecodeError, DataError):
            return False
        return values.size == 16 and not np.all(np.isfinite(values))

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / "depth" / f"{name}.png"
        depth = read_depth_png(depth_path, self.depth_scale)
        T_W_C = read_pose_txt(self.path / "pose" / f"{name}.txt")
        rgb = self._colour([self.path / "color" / f"{name}.jpg", self.path / "color" / f"{name}.png"])
        if rgb is not None and rgb.shape[:2] != depth.shape:
            rgb = None  # the raw 1296x968 colour: not registered pixel-for-pixel to the depth
        return depth, depth_path, T_W_C, rgb
