"""The ``redwood`` format: Redwood / Open3D RGB-D sequences with a ``.log`` trajectory.

Layout (DESIGN.md section 5)
----------------------------
``redwood`` (Redwood / Open3D RGB-D sequences, :class:`RedwoodDataset`)::

    depth/*.png              uint16 depth in millimetres, frames in frame-number order
    color/*.jpg|png          optional colour, same order
    *.log                    Open3D trajectory: per frame a line "id id frame", then 4 lines of a
                             4x4 T_W_C; depth/N.png takes the block whose id is N
    camera_intrinsic.json    optional Open3D PinholeCameraIntrinsic (width, height,
                             intrinsic_matrix: 9 values column-major); otherwise PrimeSense
                             (525, 525, 319.5, 239.5, 640x480)

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

import numbers
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import check_K, intrinsics
from .base import Dataset
from .readers import (frame_number, json_numbers, pose_from_values, poses_by_frame_number,
                      read_depth_png, read_json, read_rows, row_numbers, sort_frames, stem_key, warn)


class RedwoodDataset(Dataset):
    """Redwood / Open3D RGB-D sequence: ``depth/``, ``color/`` and an Open3D ``.log`` trajectory.

    Conventions: ``depth/*.png`` uint16 millimetres, ordered by file name (numerically for numeric
    stems), colour the same order in ``color/``; the ``.log`` (Open3D's trajectory format, the
    only ``*.log`` in the folder) holds per frame a line "id id frame" and 4 lines of a 4x4
    ``T_W_C`` (OpenCV axes). A depth image takes the block whose first id is the number ending
    its name, so a partial or subsampled copy of ``depth/`` with the whole ``.log`` loads (one
    warning gives both counts); with as many blocks as images, the ``k``-th block goes to the
    ``k``-th image. Intrinsics: an Open3D
    ``camera_intrinsic.json`` (``width``, ``height``, ``intrinsic_matrix``: 9 numbers column-major,
    as Open3D writes it) or, without it, Open3D's PrimeSense default (with a warning).
    """

    format = "redwood"
    looks_for = "depth/*.png [+ color/] + a *.log trajectory [+ camera_intrinsic.json]"
    default_depth_scale = 1000.0
    PRIMESENSE_K = (525.0, 525.0, 319.5, 239.5)
    """Open3D's ``PinholeCameraIntrinsicParameters.PrimeSenseDefault`` (640x480)."""
    PRIMESENSE_SIZE = (640, 480)

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (path / "depth").is_dir() and any(path.glob("*.log"))

    def _scan(self) -> list[str]:
        depth_files = sort_frames((self.path / "depth").glob("*.png"))
        self._files = [p.name for p in depth_files]
        if not depth_files:
            return []
        colour_dir = self.path / "color"
        colours = sorted((p for p in colour_dir.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg")),
                         key=lambda p: stem_key(p.stem)) if colour_dir.is_dir() else []
        self._colours = colours if len(colours) == len(depth_files) else []
        logs = sorted(self.path.glob("*.log"))
        if len(logs) > 1:
            raise DataError(f"{self.path}: several trajectories ({', '.join(p.name for p in logs)}); "
                            f"keep one .log file")
        if not logs:
            raise DataError(f"{self.path}: no trajectory (a redwood dataset has {self.looks_for})")
        self._log_path = logs[0]
        blocks = self._read_log(self._log_path)
        # a block's header 'id id frame' starts with its frame number
        self._poses = poses_by_frame_number(
            self._log_path, [(frame_id, (lineno, values)) for frame_id, lineno, values in blocks],
            [(frame_number(p.stem) or (None, None))[1] for p in depth_files], depth_files)
        k_path = self.path / "camera_intrinsic.json"
        if k_path.is_file():
            cam = read_json(k_path, "camera intrinsics")
            w, h = json_numbers(cam, ("width", "height"), k_path, "camera intrinsics")
            M = cam.get("intrinsic_matrix")
            if not (isinstance(M, list) and len(M) == 9 and all(_is_real(v) for v in M)):
                raise DataError(f"{k_path}: intrinsic_matrix must be 9 numbers (column-major 3x3)")
            self.K = check_K(np.array(M, dtype=np.float64).reshape(3, 3).T, str(k_path))
            self._set_image_size(w, h, str(k_path))
        else:
            warn(f"{self.path}: no camera_intrinsic.json; using Open3D's PrimeSense default "
                  f"intrinsics {self.PRIMESENSE_K} (640x480)")
            self.K = intrinsics(*self.PRIMESENSE_K)
            self._set_image_size(*self.PRIMESENSE_SIZE, "the PrimeSense default intrinsics")
        return [p.stem for p in depth_files]

    @staticmethod
    def _read_log(path: Path) -> list[tuple[int, int, np.ndarray]]:
        """(frame id, line number of the header, 16 numbers) per block of an Open3D .log
        trajectory; the frame id is the first number of the block's header."""
        rows = read_rows(path, "trajectory")
        if len(rows) % 5:
            raise DataError(f"{path}: an Open3D .log has 5 lines per frame ('id id frame' and 4 rows "
                            f"of 4x4); found {len(rows)} lines")
        poses = []
        for b in range(0, len(rows), 5):
            lineno, header = rows[b]
            ids = row_numbers(header, path, lineno, "frame header ('id id frame')", (3,))
            values = [row_numbers(tokens, path, n, "pose", (4,)) for n, tokens in rows[b + 1: b + 5]]
            frame_id = int(ids[0]) if float(ids[0]).is_integer() else None
            poses.append((frame_id, lineno, np.concatenate(values)))
        return poses

    def _read_frame(self, j: int):
        depth_path = self.path / "depth" / self._files[j]
        depth = read_depth_png(depth_path, self.depth_scale)
        lineno, values = self._poses[j]
        T_W_C = pose_from_values(values, f"{self._log_path}: lines {lineno}-{lineno + 4} "
                                          f"(frame {self._names[j]})")
        return depth, depth_path, T_W_C, self._colour(self._colours[j: j + 1])


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)
