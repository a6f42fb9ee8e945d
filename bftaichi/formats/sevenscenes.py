"""The ``7scenes`` format: Microsoft 7-Scenes and 3DMatch sequences.

Layout (DESIGN.md section 5)
----------------------------
``7scenes`` (Microsoft 7-Scenes / 3DMatch, one sequence folder, or a folder of ``seq-XX/`` ones)::

    frame-000000.depth.png   uint16 depth, depth_scale units per metre (default 1000: millimetres);
                             0 and 65535 mean "no measurement"
    frame-000000.pose.txt    4x4 T_W_C (camera-to-world), metres, 16 whitespace-separated numbers
    frame-000000.color.jpg   optional 8-bit RGB, read only with load_rgb
    camera-intrinsics.txt    optional 3x3 K (9 numbers); if absent, the published 7-Scenes Kinect
                             intrinsics fx = fy = 585, cx = 320, cy = 240 (640x480) are used
                             and a warning says so
    seq-01/, seq-02/ ...     instead of the frames above: sequences of the same layout, whose
                             frames are concatenated in sequence order (frame names
                             ``seq-01/frame-000000``); camera-intrinsics.txt in the top folder or
                             in the sequences (they must agree)

Frames are ordered by their number. All depth images must have the size of the first frame read.

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import intrinsics
from .base import Dataset
from .readers import read_depth_png, read_K_txt, read_pose_txt, require_files, sort_frames, warn


class SevenScenesDataset(Dataset):
    """Microsoft 7-Scenes / 3DMatch sequence folder, or a folder of ``seq-XX/`` sequences.

    Conventions: depth uint16 millimetres (0 and 65535 invalid); ``frame-*.pose.txt`` are 4x4
    ``T_W_C`` with OpenCV camera axes; ``camera-intrinsics.txt`` a 3x3 K (else the published
    7-Scenes Kinect K, with a warning). With ``seq-XX/`` sub-folders the frames of all sequences
    are concatenated in sequence-number order (they share one world frame, as in 7-Scenes and
    3DMatch); the intrinsics file may be in the top folder or in each sequence, and all copies
    must agree.
    """

    format = "7scenes"
    looks_for = ("frame-<6 digits>.depth.png + frame-<6 digits>.pose.txt "
                 "[+ camera-intrinsics.txt], or seq-<2 digits>/ folders of them")
    default_depth_scale = 1000.0
    INVALID_CODES = (0, 65535)
    """Raw depth values that mean "no measurement" (Kinect v1 as stored by 7-Scenes)."""
    PUBLISHED_K = (585.0, 585.0, 320.0, 240.0)
    """fx, fy, cx, cy of the 7-Scenes Kinect, for 640x480 images (used without camera-intrinsics.txt)."""
    PUBLISHED_SIZE = (640, 480)

    _DEPTH_RE = re.compile(r"^frame-(\d+)\.depth\.png$")
    _SEQ_RE = re.compile(r"^seq-(\d+)$")

    @classmethod
    def detect(cls, path: Path) -> bool:
        return any(path.glob("frame-*.depth.png")) or any(path.glob("seq-*/frame-*.depth.png"))

    def _sequences(self) -> list[Path]:
        """The folders holding frames: the dataset folder itself, or its seq-XX/ sub-folders."""
        if any(self.path.glob("frame-*.depth.png")):
            return [self.path]
        seqs = [(int(m.group(1)), p) for p in self.path.iterdir()
                if p.is_dir() and (m := self._SEQ_RE.match(p.name))]
        return [p for _, p in sorted(seqs)]

    def _scan(self) -> list[str]:
        names = []
        sequences = self._sequences()
        for folder in sequences:
            prefix = "" if folder == self.path else folder.name + "/"
            files = sort_frames((p for p in folder.iterdir() if self._DEPTH_RE.match(p.name)),
                                stem=lambda p: p.name[: -len(".depth.png")])
            names += [prefix + p.name[: -len(".depth.png")] for p in files]
        if not names:
            return names
        require_files([self.path / f"{n}.pose.txt" for n in names], "pose file", names)
        k_paths = [p for p in dict.fromkeys(f / "camera-intrinsics.txt" for f in [self.path, *sequences])
                   if p.is_file()]
        if k_paths:
            self.K = read_K_txt(k_paths[0])
            for other in k_paths[1:]:
                if not np.allclose(read_K_txt(other), self.K, rtol=1e-9, atol=0):
                    raise DataError(f"{other}: intrinsics differ from {k_paths[0]}; the sequences of "
                                    f"one dataset must share one camera")
        else:
            fx, fy, cx, cy = self.PUBLISHED_K
            warn(f"{self.path}: no camera-intrinsics.txt; using the published 7-Scenes "
                  f"intrinsics fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g} (for 640x480 images)")
            self.K = intrinsics(fx, fy, cx, cy)
            self._set_image_size(*self.PUBLISHED_SIZE,
                                 "the published 7-Scenes intrinsics (no camera-intrinsics.txt)")
        return names

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / f"{name}.depth.png"
        depth = read_depth_png(depth_path, self.depth_scale, self.INVALID_CODES)
        T_W_C = read_pose_txt(self.path / f"{name}.pose.txt")
        return depth, depth_path, T_W_C, self._colour([self.path / f"{name}.color.jpg"])
