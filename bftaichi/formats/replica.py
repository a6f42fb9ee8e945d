"""The ``replica`` format: Replica scenes as exported by NICE-SLAM.

Layout (DESIGN.md section 5)
----------------------------
``replica`` (Replica as exported by NICE-SLAM, :class:`ReplicaDataset`)::

    results/depth000000.png  uint16 depth, 6553.5 units per metre
    results/frame000000.jpg  optional colour
    traj.txt                 one row-major 4x4 T_W_C (OpenCV camera) per line: line k is frame k
    cam_params.json          optional {"camera": {"w","h","fx","fy","cx","cy","scale"}}; otherwise
                             NICE-SLAM's camera 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import DataError
from ..geometry import check_K, intrinsics
from .base import Dataset
from .readers import (json_numbers, poses_by_frame_number, pose_from_values, read_depth_png,
                      read_json, read_pose_rows, sort_frames)


class ReplicaDataset(Dataset):
    """Replica as exported by NICE-SLAM (``Replica/room0``: ``results/``, ``traj.txt``).

    Conventions: ``results/depthNNNNNN.png`` uint16 with 6553.5 units per metre (NICE-SLAM's
    ``png_depth_scale``); ``traj.txt`` one row-major 4x4 ``T_W_C`` per line, frame ``k`` the
    ``k``-th line (0-based). An image takes the line of the frame number in its name, so a
    partial or subsampled copy of ``results/`` with the whole ``traj.txt`` loads (one warning
    gives both counts); with as many lines as images, the i-th image takes the i-th line. Those
    poses already use OpenCV camera axes; NICE-SLAM flips the y and z axes itself because it
    renders with OpenGL axes, and bftaichi does not. Intrinsics: NICE-SLAM's
    Replica camera (:attr:`NICE_SLAM_K`, 1200x680) unless a ``cam_params.json`` (Replica's
    ``{"camera": {"w","h","fx","fy","cx","cy","scale"}}``) is present; its ``scale`` is the depth
    scale unless ``depth_scale`` is given.
    """

    format = "replica"
    looks_for = "results/depthNNNNNN.png [+ results/frameNNNNNN.jpg] + traj.txt [+ cam_params.json]"
    default_depth_scale = 6553.5
    NICE_SLAM_K = (600.0, 600.0, 599.5, 339.5)
    NICE_SLAM_SIZE = (1200, 680)
    _DEPTH_RE = re.compile(r"^depth(\d+)\.png$")

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (path / "traj.txt").is_file() and any((path / "results").glob("depth*.png"))

    def _scan(self) -> list[str]:
        results = self.path / "results"
        files = sort_frames(p for p in results.glob("depth*.png") if self._DEPTH_RE.match(p.name))
        self._numbers = [self._DEPTH_RE.match(p.name).group(1) for p in files]
        if not files:
            return []
        self._traj_path = self.path / "traj.txt"
        rows = read_pose_rows(self._traj_path)
        # line k of traj.txt is frame k (depth{k:06d}.png), as NICE-SLAM indexes it
        self._poses = poses_by_frame_number(self._traj_path, list(enumerate(rows)),
                                            [int(d) for d in self._numbers], files)
        cam_path = self.path / "cam_params.json"
        if cam_path.is_file():
            cam = read_json(cam_path, "camera parameters")
            w, h, fx, fy, cx, cy = json_numbers(cam.get("camera") if isinstance(cam, dict) else cam,
                                                 ("w", "h", "fx", "fy", "cx", "cy"), cam_path, '"camera"')
            self.K = check_K(intrinsics(fx, fy, cx, cy), str(cam_path))
            self._set_image_size(w, h, str(cam_path))
            if not self._depth_scale_given and "scale" in cam["camera"]:
                self.depth_scale = json_numbers(cam["camera"], ("scale",), cam_path, '"camera"')[0]
                if not self.depth_scale > 0:
                    raise DataError(f"{cam_path}: depth scale {self.depth_scale} must be positive")
        else:
            self.K = intrinsics(*self.NICE_SLAM_K)
            self._set_image_size(*self.NICE_SLAM_SIZE, "NICE-SLAM's Replica camera (no cam_params.json)")
        return [f"frame{digits}" for digits in self._numbers]

    def _read_frame(self, j: int):
        digits = self._numbers[j]
        depth_path = self.path / "results" / f"depth{digits}.png"
        depth = read_depth_png(depth_path, self.depth_scale)
        lineno, values = self._poses[j]
        T_W_C = pose_from_values(values, f"{self._traj_path}: line {lineno} (frame {self._names[j]})")
        rgb = self._colour(self.path / "results" / f"frame{digits}{s}" for s in (".jpg", ".png"))
        return depth, depth_path, T_W_C, rgb
