"""The ``folder`` format: a generic folder of depth images, poses and ``intrinsics.json``.

Layout (DESIGN.md section 5)
----------------------------
``folder`` (anything else, :class:`FolderDataset`)::

    depth/*.png | *.npy      PNG: depth_scale units per metre (default 1000); .npy: float metres
                             (unless depth_scale is given)
    poses.txt or pose/*.txt  one row-major 4x4 (16 numbers) or 3x4 (12) per line, line k for
                             frame k (the number ending a depth stem); or one 4x4 file per depth
                             stem; T_W_C, or T_C_W with pose_convention="T_C_W" (then inverted)
    intrinsics.json          {"fx","fy","cx","cy"[,"width","height"]} or {"K": [[...]] [, ...]}
    color/<stem>.png|jpg     optional colour

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataError
from ..geometry import check_K, intrinsics
from .base import Dataset
from .readers import (POSE_CONVENTIONS, frame_number, json_numbers, pose_from_values,
                      poses_by_frame_number, read_depth_npy, read_depth_png, read_json,
                      read_pose_rows, read_pose_txt, require_files, sort_frames)


class FolderDataset(Dataset):
    """A generic folder: ``depth/``, poses (``poses.txt`` or ``pose/``), ``intrinsics.json``.

    Conventions: ``depth/<stem>.png`` integer depth with ``depth_scale`` units per metre (default
    1000, millimetres) or ``depth/<stem>.npy`` float depth in metres (divided by ``depth_scale``
    only if it is given); frames ordered by the number ending the stem (``2`` before ``10``);
    two stems with the same number (``10``, ``0010``) are an error. Poses: ``poses.txt`` (one
    pose per line: 16 numbers, a row-major 4x4, or 12, the top 3x4; line ``k`` (0-based) is
    frame ``k``, so a partial or subsampled copy of ``depth/`` with the whole file loads; with
    as many lines as images, the i-th image takes the i-th line) or else ``pose/<stem>.txt``
    (a 4x4 each). ``pose_convention`` says what they are:
    ``T_W_C`` (camera-to-world, the default) or ``T_C_W`` (world-to-camera, e.g. OpenCV
    ``solvePnP`` / COLMAP extrinsics; inverted on load); camera axes are OpenCV's either way.
    ``intrinsics.json``: ``{"fx", "fy", "cx", "cy"}`` or ``{"K": [[fx,0,cx],[0,fy,cy],[0,0,1]]}``
    in pixels, optionally with ``"width"`` and ``"height"`` (otherwise the first frame fixes the
    size). Colour, if any: ``color/<stem>.png|jpg``.
    """

    format = "folder"
    looks_for = "depth/*.png|npy + poses.txt or pose/*.txt + intrinsics.json"
    default_depth_scale = 1000.0
    options = ("pose_convention",)

    def __init__(self, path: str | Path, depth_min_m: float = 0.1, depth_max_m: float = 6.0,
                 load_rgb: bool = False, depth_scale: float | None = None,
                 pose_convention: str = "T_W_C") -> None:
        """``pose_convention``: ``T_W_C`` or ``T_C_W``; other arguments: :class:`Dataset`."""
        if pose_convention not in POSE_CONVENTIONS:
            raise ConfigError(f"pose_convention = {pose_convention!r} is not one of "
                              f"{', '.join(POSE_CONVENTIONS)}")
        self.pose_convention = pose_convention
        super().__init__(path, depth_min_m, depth_max_m, load_rgb, depth_scale)

    @classmethod
    def detect(cls, path: Path) -> bool:
        return ((path / "depth").is_dir() and (path / "intrinsics.json").is_file()
                and ((path / "poses.txt").is_file() or (path / "pose").is_dir()))

    def _scan(self) -> list[str]:
        files = {}
        for p in (self.path / "depth").iterdir():
            if p.suffix in (".png", ".npy"):
                if p.stem in files:
                    raise DataError(f"{p}: depth/ holds both {files[p.stem].name} and {p.name}")
                files[p.stem] = p
        self._files = sort_frames(files.values())
        names = [p.stem for p in self._files]
        if not names:
            return names
        poses_txt = self.path / "poses.txt"
        if poses_txt.is_file():
            # row k of poses.txt is frame k (the number ending an image's name)
            self._pose_rows = poses_by_frame_number(
                poses_txt, list(enumerate(read_pose_rows(poses_txt, (12, 16)))),
                [(frame_number(n) or (None, None))[1] for n in names], self._files)
            self._poses_txt = poses_txt
        else:
            self._pose_rows = None
            require_files([self.path / "pose" / f"{n}.txt" for n in names], "pose file",
                           [f"depth/{f.name}" for f in self._files])
        self._read_intrinsics(self.path / "intrinsics.json")
        return names

    def _read_intrinsics(self, path: Path) -> None:
        d = read_json(path, "intrinsics")
        if isinstance(d, dict) and "K" in d:
            try:
                K = np.array(d["K"], dtype=np.float64)
            except (TypeError, ValueError):
                raise DataError(f"{path}: \"K\" must be a 3x3 list of numbers") from None
            self.K = check_K(K, str(path))
        else:
            self.K = check_K(intrinsics(*json_numbers(d, ("fx", "fy", "cx", "cy"), path, "intrinsics")),
                             str(path))
        if "width" in d or "height" in d:
            self._set_image_size(*json_numbers(d, ("width", "height"), path, "intrinsics"), str(path))

    def _read_frame(self, j: int):
        depth_path = self._files[j]
        if depth_path.suffix == ".npy":
            depth = read_depth_npy(depth_path, self.depth_scale if self._depth_scale_given else 1.0)
        else:
            depth = read_depth_png(depth_path, self.depth_scale)
        if self._pose_rows is None:
            T_W_C = read_pose_txt(self.path / "pose" / f"{self._names[j]}.txt", self.pose_convention)
        else:
            lineno, values = self._pose_rows[j]
            T_W_C = pose_from_values(values, f"{self._poses_txt}: line {lineno} (frame {self._names[j]})",
                                      self.pose_convention)
        rgb = self._colour(self.path / "color" / f"{self._names[j]}{s}" for s in (".png", ".jpg"))
        return depth, depth_path, T_W_C, rgb
