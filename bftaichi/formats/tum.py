"""The ``tum`` format: TUM RGB-D benchmark sequences.

Layout (DESIGN.md section 5)
----------------------------
``tum`` (TUM RGB-D benchmark sequence, :class:`TUMDataset`)::

    depth.txt                "timestamp depth/<timestamp>.png" per line; '#' lines are comments
    depth/*.png              uint16 depth, 5000 units per metre; 0 = no measurement
    groundtruth.txt          "timestamp tx ty tz qx qy qz qw": T_W_C (translation, unit
                             quaternion x y z w), each depth frame takes the pose nearest in time
                             (within tolerance_s, default 0.02 s; frames without are skipped)
    rgb.txt, rgb/*.png       optional colour, associated the same way
    camera-intrinsics.txt    optional 3x3 K; otherwise the Freiburg 1/2/3 preset (640x480) named
                             by ``intrinsics`` or by the folder name (rgbd_dataset_freiburg2_...)

The conventions every loader converts to, and how to add a format: :mod:`bftaichi.formats`.
"""

from __future__ import annotations

import numbers
import re
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataError
from ..geometry import check_pose, intrinsics
from .base import Dataset
from .readers import is_number, read_depth_png, read_K_txt, read_rows, row_numbers, warn


def _quaternion_pose(values: np.ndarray, where: str) -> np.ndarray:
    """Checked ``T_W_C`` from ``tx ty tz qx qy qz qw`` (Hamilton unit quaternion, scalar last)."""
    t, q = values[:3], values[3:7]
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(values)) and abs(norm - 1.0) <= 1e-3):  # 1e-3: check_pose's tolerance
        raise DataError(f"{where}: pose quaternion (qx qy qz qw) = {q.tolist()} has norm {norm:.4g}: "
                        f"not a rotation (a unit quaternion is needed)")
    x, y, z, w = q / norm
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = t
    return check_pose(T, where)


def _nearest(sorted_times: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index into ``sorted_times`` of the nearest time to each query, and the absolute gap."""
    hi = np.clip(np.searchsorted(sorted_times, queries), 1, max(len(sorted_times) - 1, 1))
    lo = hi - 1
    hi = np.minimum(hi, len(sorted_times) - 1)
    pick = np.where(np.abs(sorted_times[hi] - queries) < np.abs(sorted_times[lo] - queries), hi, lo)
    return pick, np.abs(sorted_times[pick] - queries)


class TUMDataset(Dataset):
    """TUM RGB-D benchmark sequence (Sturm et al. 2012), e.g. ``rgbd_dataset_freiburg1_xyz``.

    Conventions:

    - ``depth.txt``/``rgb.txt``: "timestamp path" per line (seconds; path relative to the folder);
      lines starting with '#' are comments. Depth PNGs hold 5000 units per metre, 0 = invalid.
    - ``groundtruth.txt``: "timestamp tx ty tz qx qy qz qw", the pose of the camera's optical frame
      in the world (``T_W_C``, OpenCV axes), quaternion Hamilton with the scalar last; it must be
      a unit quaternion (within 1e-3).
    - Association: each depth frame takes the ground-truth row nearest in time; if that is more
      than ``tolerance_s`` away (default 0.02 s, TUM's ``associate.py`` default) the frame is
      skipped; :attr:`skipped` counts them and one warning says how many. Colour is associated the
      same way (a frame without colour within tolerance gets ``rgb = None``).
    - Frame names are the depth timestamps as written in ``depth.txt``.
    - Intrinsics, first that applies: ``intrinsics`` ("fr1", "fr2", "fr3": the Freiburg presets
      of :attr:`PRESETS`, 640x480); a ``camera-intrinsics.txt`` (3x3 K, as 7-Scenes) in the
      folder; the preset named by the folder ("freiburg2" in its name); else fr1 with a warning.
      The presets are the published calibrations; the images are not undistorted (TUM's
      documented practice for its depth images).
    """

    format = "tum"
    looks_for = "depth.txt + groundtruth.txt (+ depth/*.png) [+ rgb.txt, camera-intrinsics.txt]"
    default_depth_scale = 5000.0
    options = ("intrinsics", "tolerance_s")
    PRESETS = {"fr1": (517.3, 516.5, 318.6, 255.3),
               "fr2": (520.9, 521.0, 325.1, 249.7),
               "fr3": (535.4, 539.2, 320.1, 247.6)}
    """fx, fy, cx, cy of the Freiburg 1/2/3 Kinects (TUM's "camera calibration" page), 640x480."""
    PRESET_SIZE = (640, 480)
    _FOLDER_RE = re.compile(r"freiburg([123])")

    def __init__(self, path: str | Path, depth_min_m: float = 0.1, depth_max_m: float = 6.0,
                 load_rgb: bool = False, depth_scale: float | None = None,
                 intrinsics: str | None = None, tolerance_s: float = 0.02) -> None:
        """``intrinsics``: a key of :attr:`PRESETS` or None (see the class docstring);
        ``tolerance_s``: largest depth-to-pose time gap, seconds. Other arguments: :class:`Dataset`."""
        if intrinsics is not None and intrinsics not in self.PRESETS:
            raise ConfigError(f"TUM intrinsics = {intrinsics!r} is not one of {', '.join(self.PRESETS)}")
        if not (isinstance(tolerance_s, numbers.Real) and np.isfinite(tolerance_s) and tolerance_s > 0):
            raise ConfigError(f"TUM tolerance_s = {tolerance_s} must be a positive number of seconds")
        self.intrinsics_preset = intrinsics
        self.tolerance_s = float(tolerance_s)
        super().__init__(path, depth_min_m, depth_max_m, load_rgb, depth_scale)

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (path / "depth.txt").is_file() and (path / "groundtruth.txt").is_file()

    def _timed_files(self, list_path: Path) -> list[tuple[float, str, str]]:
        """(timestamp, timestamp as written, relative path) of each row of depth.txt / rgb.txt."""
        rows = []
        for lineno, tokens in read_rows(list_path, "file list"):
            if len(tokens) != 2 or not is_number(tokens[0]):
                raise DataError(f"{list_path}: line {lineno}: expected 'timestamp path', "
                                f"got {' '.join(tokens)!r}")
            rows.append((float(tokens[0]), tokens[0], tokens[1]))
        return rows

    def _scan(self) -> list[str]:
        depth_rows = self._timed_files(self.path / "depth.txt")
        self._gt_path = self.path / "groundtruth.txt"
        gt = sorted(((row_numbers(tokens, self._gt_path, lineno, "groundtruth", (8,)), lineno)
                     for lineno, tokens in read_rows(self._gt_path, "ground truth")),
                    key=lambda row: row[0][0])
        if not depth_rows:
            return []
        if not gt:
            raise DataError(f"{self._gt_path}: no poses (a TUM groundtruth.txt has lines "
                            f"'timestamp tx ty tz qx qy qz qw')")
        gt_times = np.array([values[0] for values, _ in gt])
        pick, gap = _nearest(gt_times, np.array([t for t, _, _ in depth_rows]))
        keep = gap <= self.tolerance_s
        # per kept frame: (depth path, tx ty tz qx qy qz qw, line number in groundtruth.txt)
        self._frames = [(rel, gt[k][0][1:], gt[k][1])
                        for (_, _, rel), k, ok in zip(depth_rows, pick, keep) if ok]
        names = [stamp for (_, stamp, _), ok in zip(depth_rows, keep) if ok]
        self.skipped = int(np.count_nonzero(~keep))
        if not names:
            raise DataError(f"{self._gt_path}: none of the {len(depth_rows)} depth frames of depth.txt "
                            f"has a pose within {self.tolerance_s:g} s")
        if self.skipped:
            warn(f"{self.path}: skipped {self.skipped} of {len(depth_rows)} depth frames without a "
                  f"ground-truth pose within {self.tolerance_s:g} s")
        self._rgb: list[str | None] = [None] * len(names)
        rgb_list = self.path / "rgb.txt"
        if rgb_list.is_file():
            rgb_rows = sorted(self._timed_files(rgb_list))
            if rgb_rows:
                times = np.array([float(n) for n in names])
                k, gap = _nearest(np.array([t for t, _, _ in rgb_rows]), times)
                self._rgb = [rgb_rows[i][2] if g <= self.tolerance_s else None for i, g in zip(k, gap)]
        self._set_intrinsics()
        return names

    def _set_intrinsics(self) -> None:
        k_path = self.path / "camera-intrinsics.txt"
        preset = self.intrinsics_preset
        if preset is None and k_path.is_file():
            self.K = read_K_txt(k_path)
            return
        if preset is None:
            m = self._FOLDER_RE.search(self.name)
            if m:
                preset = f"fr{m.group(1)}"
            else:
                preset = "fr1"
                warn(f"{self.path}: neither intrinsics=, camera-intrinsics.txt nor a 'freiburgN' "
                      f"folder name says which TUM camera this is; using the Freiburg 1 intrinsics "
                      f"{self.PRESETS['fr1']}")
        self.K = intrinsics(*self.PRESETS[preset])
        self._set_image_size(*self.PRESET_SIZE, f"the TUM {preset} intrinsics")

    def _read_frame(self, j: int):
        rel, pose_values, lineno = self._frames[j]
        depth_path = self.path / rel
        depth = read_depth_png(depth_path, self.depth_scale)
        T_W_C = _quaternion_pose(pose_values, f"{self._gt_path}: line {lineno} (pose of depth frame "
                                              f"{self._names[j]})")
        rgb = self._colour([self.path / self._rgb[j]] if self._rgb[j] else [])
        return depth, depth_path, T_W_C, rgb
