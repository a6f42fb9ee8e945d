"""Recorded RGB-D sequences on disk, read lazily as :class:`~bftaichi.frame.Frame` objects.

Opening a dataset lists its frames and reads the intrinsics; a frame's depth image, pose and
(optionally) colour image are read only when that frame is requested, so a corrupt frame 7 does not
stop frames 0-6 from loading. Every user error (missing or unreadable file, malformed text,
inconsistent sizes, a pose that is not a rigid transform) raises :class:`~bftaichi.errors.DataError`
with a message that names the offending file.

Conventions (DESIGN.md section 2): depth is returned in metres as float32 along the camera z axis;
invalid pixels (0, the sensor's "no return" codes, NaN, inf, negative, or outside
``[depth_min_m, depth_max_m]``) are set to 0 by :func:`bftaichi.frame.clean_depth`. Cameras are
OpenCV pinhole (x right, y down, z forward), ``K = [[fx,0,cx],[0,fy,cy],[0,0,1]]`` (float64), and
poses are ``T_W_C`` (4x4 float64 camera-to-world, metres: ``p_W = T_W_C @ p_C``).

Layouts (DESIGN.md section 5)
-----------------------------
``7scenes`` (Microsoft 7-Scenes, one sequence folder)::

    frame-000000.depth.png   uint16 depth, depth_scale units per metre (default 1000: millimetres);
                             0 and 65535 mean "no measurement"
    frame-000000.pose.txt    4x4 T_W_C (camera-to-world), metres, 16 whitespace-separated numbers
    frame-000000.color.jpg   optional 8-bit RGB, read only with load_rgb
    camera-intrinsics.txt    optional 3x3 K (9 numbers); if absent, the published 7-Scenes Kinect
                             intrinsics fx = fy = 585, cx = 320, cy = 240 (640x480) are used
                             and a warning says so

Frames are ordered by their number. All depth images must have the size of the first frame read.

``bfsdf`` (this project's own layout, written e.g. by ``bftaichi synth``)::

    depth/000000.png         uint16 (or 8-bit) depth, depth_scale units per metre (default 1000)
    pose/000000.txt          4x4 T_W_C (camera-to-world), metres, 16 numbers
    color/000000.png|jpg     optional 8-bit RGB, read only with load_rgb
    intrinsic/intrinsic.txt  line 1 "w h" (image size, pixels), line 2 "fx fy cx cy" (pixels)
    gt_mesh.ply              optional ground-truth mesh (metres, world frame)

Frames are ordered by file stem (numerically when the stems are numbers). All depth images must
have the size given in ``intrinsic/intrinsic.txt``.

Any layout may hold a ``gt_mesh.ply`` next to the frames; :attr:`Dataset.gt_mesh_path` points to it.

Adding a format
---------------
Subclass :class:`Dataset`: set ``format``, ``looks_for`` and ``default_depth_scale``, implement
``detect`` (does a folder look like this layout?), ``_scan`` (list the frames, set ``K`` and, if
known, ``image_size``) and ``_read_frame`` (read one frame's raw depth in metres, pose and colour,
with the helpers :func:`read_depth_png`, :func:`read_numbers_txt` and :func:`read_rgb`), then add one
line to :data:`FORMATS`.
"""

from __future__ import annotations

import copy
import numbers
import re
import warnings
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
from PIL import Image

from .errors import ConfigError, DataError
from .frame import Frame, clean_depth
from .geometry import check_K, check_pose, intrinsics

__all__ = [
    "Dataset",
    "SevenScenesDataset",
    "BFSDFDataset",
    "FORMATS",
    "detect_format",
    "open_dataset",
    "read_depth_png",
    "read_numbers_txt",
    "read_rgb",
]

# Everything Pillow raises for a missing, unidentifiable, corrupt or truncated image file
# (UnidentifiedImageError is an OSError; bad chunks raise SyntaxError; short reads OSError/EOFError).
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)


# --------------------------------------------------------------------------------------------
# File readers shared by all formats
# --------------------------------------------------------------------------------------------

def read_depth_png(path: Path, depth_scale: float, invalid_codes: tuple[int, ...] = ()) -> np.ndarray:
    """Read a single-channel integer depth image and convert it to metres.

    Args:
        path: image file (PNG, or anything Pillow reads as a 16-bit or 8-bit grey image).
        depth_scale: stored units per metre (1000 for millimetres); ``depth_m = raw / depth_scale``.
        invalid_codes: raw values that mean "no measurement" (e.g. 65535 in 7-Scenes); they become
            NaN so that :func:`~bftaichi.frame.clean_depth` drops them.

    Returns:
        (H, W) float32 depth in metres, not yet range-checked (0 and NaN mark invalid pixels).

    Raises:
        DataError naming ``path`` if the file is missing, unreadable, corrupt or truncated, or is not a
        single-channel 16-bit or 8-bit integer image (mode ``I;16``/``L``, or 32-bit mode ``I`` with
        values in 0..65535).
    """
    try:
        with Image.open(path) as im:
            mode = im.mode
            im.load()
            raw = np.array(im)
    except FileNotFoundError:
        raise DataError(f"{path}: depth image not found") from None
    except _PIL_ERRORS as e:
        raise DataError(f"{path}: cannot read depth image, the file is corrupt or truncated "
                        f"({type(e).__name__}: {e})") from e
    if mode.startswith("I;16") or mode == "L":
        pass  # uint16 (any byte order) or uint8
    elif mode == "I":
        # 32-bit signed integers: some writers/Pillow versions give 16-bit PNGs this mode.
        if raw.size and (raw.min() < 0 or raw.max() > 65535):
            raise DataError(f"{path}: 32-bit integer depth image with values in "
                            f"[{raw.min()}, {raw.max()}]; expected a 16-bit depth image (0..65535)")
    else:
        channels = f"{raw.shape[2]}-channel " if raw.ndim == 3 else ""
        raise DataError(f"{path}: depth must be a single-channel 16-bit or 8-bit integer image, got "
                        f"a {channels}image of Pillow mode {mode!r} (shape {raw.shape}, dtype {raw.dtype})")
    if raw.ndim != 2:
        raise DataError(f"{path}: depth must be a single-channel HxW image, got shape {raw.shape}")
    depth = raw.astype(np.float32)
    depth /= np.float32(depth_scale)
    for code in invalid_codes:  # a few codes: one comparison each beats np.isin's sort
        depth[raw == code] = np.nan
    return depth


def read_numbers_txt(path: Path, what: str, count: int) -> np.ndarray:
    """Read exactly ``count`` whitespace-separated numbers from a text file as float64.

    ``what`` describes the content for error messages (e.g. ``"pose"``). Raises DataError naming
    ``path`` if the file is missing or unreadable, holds a non-number, or has a different count.
    """
    values = _parse_numbers(_read_text(path, what), path, what)
    if values.size != count:
        raise DataError(f"{path}: {what} file must hold {count} numbers, found {values.size}")
    return values


def read_rgb(path: Path) -> np.ndarray:
    """Read a colour image as (H, W, 3) uint8 RGB; DataError naming ``path`` if unreadable."""
    try:
        with Image.open(path) as im:
            return np.array(im.convert("RGB"))
    except FileNotFoundError:
        raise DataError(f"{path}: colour image not found") from None
    except _PIL_ERRORS as e:
        raise DataError(f"{path}: cannot read colour image, the file is corrupt or truncated "
                        f"({type(e).__name__}: {e})") from e


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: {what} file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read {what} file ({e})") from e


def _parse_numbers(text: str, path: Path, what: str) -> np.ndarray:
    tokens = text.split()
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise DataError(f"{path}: {what} file holds {bad!r}, which is not a number") from None


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _stem_key(stem: str) -> tuple:
    """Sort key: numeric stems by value (``2`` before ``10``), others after them by name."""
    return (0, int(stem), stem) if stem.isdigit() else (1, 0, stem)


def _folder_listing(path: Path, limit: int = 12) -> str:
    """A short description of a folder's content for error messages (folders end in '/')."""
    entries = sorted(p.name + ("/" if p.is_dir() else "") for p in path.iterdir())
    if not entries:
        return "nothing (the folder is empty)"
    shown = ", ".join(entries[:limit])
    more = f", ... ({len(entries) - limit} more)" if len(entries) > limit else ""
    return shown + more


def _check_folder(path: str | Path) -> Path:
    path = Path(path).expanduser()
    if not path.exists():
        raise DataError(f"dataset folder {path} does not exist")
    if not path.is_dir():
        raise DataError(f"dataset path {path} is not a folder")
    return path


# --------------------------------------------------------------------------------------------
# Base class
# --------------------------------------------------------------------------------------------

class Dataset(ABC):
    """A lazily read sequence of depth frames (a list-like of :class:`~bftaichi.frame.Frame`).

    ``len(ds)``, ``ds[i]`` (negative ``i`` counts from the end, ``IndexError`` out of range;
    ``ds[a:b:c]`` is :meth:`subset`) and ``for frame in ds`` work as for a list. Files are read when a
    frame is requested, not when the dataset is opened (only the folder listing and intrinsics are).

    Attributes:
        path: the dataset folder.
        name: the folder's name (used in reports).
        format: layout name, a key of :data:`FORMATS`.
        K: (3, 3) float64 pinhole intrinsics shared by all frames, pixels.
        image_size: (W, H) of the depth images, pixels; None while unknown (a layout without the
            size in its intrinsics file learns it from the first frame read).
        gt_mesh_path: ``gt_mesh.ply`` in the folder if present, else None.
        load_rgb: read colour images (``Frame.rgb``, (H, W, 3) uint8; None for a frame without one).
        depth_min_m, depth_max_m: valid depth range, metres; depth outside it is set to 0.
        depth_scale: stored depth units per metre.
    """

    format: ClassVar[str]
    """Layout name (the key in :data:`FORMATS`)."""

    looks_for: ClassVar[str]
    """What :meth:`detect` looks for, shown when no format matches a folder."""

    default_depth_scale: ClassVar[float] = 1000.0
    """Depth units per metre when ``depth_scale`` is not given."""

    def __init__(self, path: str | Path, depth_min_m: float = 0.1, depth_max_m: float = 6.0,
                 load_rgb: bool = False, depth_scale: float | None = None) -> None:
        """Open the dataset folder ``path``: list its frames and read its intrinsics.

        Raises DataError if the folder is missing, holds no frames, or its intrinsics are invalid;
        ConfigError for a non-positive ``depth_scale`` or an empty depth range.
        """
        if depth_scale is None:
            depth_scale = self.default_depth_scale
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise ConfigError(f"depth_scale = {depth_scale} must be a positive number (units per metre)")
        if not (np.isfinite(depth_min_m) and np.isfinite(depth_max_m) and 0 <= depth_min_m < depth_max_m):
            raise ConfigError(f"depth range [{depth_min_m}, {depth_max_m}] m is invalid: "
                              f"need 0 <= depth_min_m < depth_max_m")
        self.path = _check_folder(path)
        self.name = self.path.resolve().name
        self.depth_min_m = float(depth_min_m)
        self.depth_max_m = float(depth_max_m)
        self.depth_scale = float(depth_scale)
        self.load_rgb = bool(load_rgb)
        self.K: np.ndarray = np.eye(3)
        self.image_size: tuple[int, int] | None = None
        self._size_source = ""  # the file that fixed image_size, for error messages
        gt = self.path / "gt_mesh.ply"
        self.gt_mesh_path: Path | None = gt if gt.is_file() else None
        self._names: list[str] = self._scan()
        if not self._names:
            raise DataError(f"{self.path}: no frames found (a {self.format} dataset has {self.looks_for}); "
                            f"the folder contains {_folder_listing(self.path)}")
        self._indices: range = range(len(self._names))

    # --- what a format implements -----------------------------------------------------------

    @classmethod
    @abstractmethod
    def detect(cls, path: Path) -> bool:
        """True if the folder ``path`` looks like this layout (cheap: file names only)."""

    @abstractmethod
    def _scan(self) -> list[str]:
        """List the frames in order and return their names; set ``K`` (and ``image_size`` if the
        layout stores it, with ``_size_source`` naming that file). Runs once, at open."""

    @abstractmethod
    def _read_frame(self, j: int) -> tuple[np.ndarray, Path, np.ndarray, np.ndarray | None]:
        """Read frame ``j`` (position in the full sequence).

        Returns ``(depth_m, depth_path, T_W_C, rgb)``: (H, W) float32 raw depth in metres (invalid
        pixels 0 or NaN; range and finiteness are cleaned by the caller), the depth file (for error
        messages), the checked 4x4 pose, and (H, W, 3) uint8 colour or None (only with load_rgb).
        """

    # --- sequence protocol ------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._indices)

    def __getitem__(self, i):
        """Frame ``i`` of this (possibly sliced) dataset; a slice returns :meth:`subset`."""
        if isinstance(i, slice):
            return self.subset(i)
        if not isinstance(i, numbers.Integral):
            raise TypeError(f"dataset indices must be integers or slices, not {type(i).__name__}")
        n = len(self._indices)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {self.name} ({n} frames)")
        j = self._indices[int(i)]
        depth_raw, depth_path, T_W_C, rgb = self._read_frame(j)
        self._check_size(depth_raw.shape, depth_path)
        if rgb is not None and rgb.shape[:2] != depth_raw.shape:
            raise DataError(f"colour image of frame {self._names[j]} in {self.path} is "
                            f"{rgb.shape[1]}x{rgb.shape[0]} (WxH) but its depth image "
                            f"{depth_path.name} is {depth_raw.shape[1]}x{depth_raw.shape[0]}")
        depth_m = clean_depth(depth_raw, self.depth_min_m, self.depth_max_m)
        return Frame(index=j, name=self._names[j], depth_m=depth_m, K=self.K.copy(), T_W_C=T_W_C, rgb=rgb)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def subset(self, s: slice) -> Dataset:
        """A view of the frames selected by ``s`` (Python slice semantics on this dataset's frames).

        The view shares the files and settings; its frames keep their original ``Frame.index``
        (position in the full sequence), so ``ds.subset(slice(10, None, 5))[0].index == 10``.
        """
        if not isinstance(s, slice):
            raise TypeError(f"subset takes a slice, not {type(s).__name__}")
        view = copy.copy(self)
        view._indices = self._indices[s]
        return view

    @property
    def indices(self) -> list[int]:
        """Original indices (positions in the full sequence) of this dataset's frames."""
        return list(self._indices)

    @property
    def frame_names(self) -> list[str]:
        """Names of this dataset's frames, in order."""
        return [self._names[j] for j in self._indices]

    def __repr__(self) -> str:
        size = f"{self.image_size[0]}x{self.image_size[1]}" if self.image_size else "size unknown"
        return f"<{type(self).__name__} {self.format} {str(self.path)!r}: {len(self)} frames, {size}>"

    # --- helpers ----------------------------------------------------------------------------

    def _check_size(self, shape: tuple[int, ...], depth_path: Path) -> None:
        """Depth images must all have ``image_size``; the first frame read fixes it if unknown."""
        h, w = shape
        if self.image_size is None:
            self.image_size = (w, h)
            self._size_source = f"the first frame read ({depth_path.name})"
        elif (w, h) != tuple(self.image_size):
            W, H = self.image_size
            raise DataError(f"{depth_path}: depth image is {w}x{h} (WxH) but {self._size_source} "
                            f"is {W}x{H}")


# --------------------------------------------------------------------------------------------
# Formats
# --------------------------------------------------------------------------------------------

class SevenScenesDataset(Dataset):
    """Microsoft 7-Scenes sequence folder (see the module docstring for the layout)."""

    format = "7scenes"
    looks_for = "frame-XXXXXX.depth.png + frame-XXXXXX.pose.txt [+ camera-intrinsics.txt]"
    default_depth_scale = 1000.0
    INVALID_CODES = (0, 65535)
    """Raw depth values that mean "no measurement" (Kinect v1 as stored by 7-Scenes)."""
    PUBLISHED_K = (585.0, 585.0, 320.0, 240.0)
    """fx, fy, cx, cy of the 7-Scenes Kinect, for 640x480 images (used without camera-intrinsics.txt)."""
    PUBLISHED_SIZE = (640, 480)

    _DEPTH_RE = re.compile(r"^frame-(\d+)\.depth\.png$")

    @classmethod
    def detect(cls, path: Path) -> bool:
        return any(path.glob("frame-*.depth.png"))

    def _scan(self) -> list[str]:
        numbered = []
        for p in self.path.iterdir():
            m = self._DEPTH_RE.match(p.name)
            if m:
                numbered.append((int(m.group(1)), p.name[: -len(".depth.png")]))
        names = [name for _, name in sorted(numbered)]
        if not names:
            return names
        missing = [n + ".pose.txt" for n in names if not (self.path / f"{n}.pose.txt").is_file()]
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise DataError(f"{self.path / missing[0]}: pose file missing for depth frame "
                            f"{missing[0][: -len('.pose.txt')]} (missing: {', '.join(missing[:3])}{more})")
        k_path = self.path / "camera-intrinsics.txt"
        if k_path.is_file():
            self.K = check_K(read_numbers_txt(k_path, "intrinsics (3x3 K)", 9).reshape(3, 3), str(k_path))
        else:
            fx, fy, cx, cy = self.PUBLISHED_K
            warnings.warn(f"{self.path}: no camera-intrinsics.txt; using the published 7-Scenes "
                          f"intrinsics fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g} (for 640x480 images)",
                          UserWarning, stacklevel=4)
            self.K = intrinsics(fx, fy, cx, cy)
            self.image_size = self.PUBLISHED_SIZE
            self._size_source = "the published 7-Scenes intrinsics (no camera-intrinsics.txt)"
        return names

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / f"{name}.depth.png"
        pose_path = self.path / f"{name}.pose.txt"
        depth = read_depth_png(depth_path, self.depth_scale, self.INVALID_CODES)
        T_W_C = check_pose(read_numbers_txt(pose_path, "pose (4x4 T_W_C)", 16).reshape(4, 4), str(pose_path))
        rgb = None
        color_path = self.path / f"{name}.color.jpg"
        if self.load_rgb and color_path.is_file():
            rgb = read_rgb(color_path)
        return depth, depth_path, T_W_C, rgb


class BFSDFDataset(Dataset):
    """bftaichi's own layout: ``depth/``, ``pose/``, ``intrinsic/intrinsic.txt`` (module docstring)."""

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
        names = sorted((p.stem for p in depth_dir.glob("*.png")), key=_stem_key)
        if not names:
            return names
        missing = [f"{n}.txt" for n in names if not (self.path / "pose" / f"{n}.txt").is_file()]
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise DataError(f"{self.path / 'pose' / missing[0]}: pose file missing for depth frame "
                            f"depth/{missing[0][:-4]}.png (missing: {', '.join(missing[:3])}{more})")
        self.K, self.image_size = self._read_intrinsics(self.path / "intrinsic" / "intrinsic.txt")
        self._size_source = "intrinsic/intrinsic.txt"
        return names

    @staticmethod
    def _read_intrinsics(path: Path) -> tuple[np.ndarray, tuple[int, int]]:
        """Parse ``w h`` / ``fx fy cx cy``; return (K, (W, H))."""
        lines = [line for line in _read_text(path, "intrinsics").splitlines() if line.strip()]
        if len(lines) != 2:
            raise DataError(f"{path}: intrinsics file must have 2 lines, 'w h' then 'fx fy cx cy'; "
                            f"found {len(lines)} non-empty lines")
        size = _parse_numbers(lines[0], path, "intrinsics")
        params = _parse_numbers(lines[1], path, "intrinsics")
        if size.size != 2:
            raise DataError(f"{path}: line 1 must be 'w h' (2 numbers), found {size.size} numbers")
        if params.size != 4:
            raise DataError(f"{path}: line 2 must be 'fx fy cx cy' (4 numbers), found {params.size} numbers")
        if not all(np.isfinite(v) and v >= 1 and float(v).is_integer() for v in size):
            raise DataError(f"{path}: image size 'w h' must be positive integers, got {lines[0].strip()!r}")
        K = check_K(intrinsics(*params), str(path))
        return K, (int(size[0]), int(size[1]))

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / "depth" / f"{name}.png"
        pose_path = self.path / "pose" / f"{name}.txt"
        depth = read_depth_png(depth_path, self.depth_scale)
        T_W_C = check_pose(read_numbers_txt(pose_path, "pose (4x4 T_W_C)", 16).reshape(4, 4), str(pose_path))
        rgb = None
        if self.load_rgb:
            for suffix in self.COLOR_SUFFIXES:
                color_path = self.path / "color" / f"{name}{suffix}"
                if color_path.is_file():
                    rgb = read_rgb(color_path)
                    break
        return depth, depth_path, T_W_C, rgb


# --------------------------------------------------------------------------------------------
# Registry and entry points
# --------------------------------------------------------------------------------------------

FORMATS: dict[str, type[Dataset]] = {
    "7scenes": SevenScenesDataset,
    "bfsdf": BFSDFDataset,
}
"""Dataset layouts by name; ``open_dataset(format=name)`` and :func:`detect_format` use it."""


def detect_format(path: str | Path) -> str:
    """The name of the one layout in :data:`FORMATS` that the folder ``path`` matches.

    Raises DataError if the folder is missing, matches no layout (the message lists what each layout
    looks for and what the folder contains), or matches several (pass ``format`` explicitly).
    """
    path = _check_folder(path)
    matches = [name for name, cls in FORMATS.items() if cls.detect(path)]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        wanted = "; ".join(f"{name}: {cls.looks_for}" for name, cls in FORMATS.items())
        raise DataError(f"{path}: no known dataset layout found (looked for {wanted}); "
                        f"the folder contains {_folder_listing(path)}")
    raise DataError(f"{path}: the folder matches several dataset layouts ({', '.join(matches)}); "
                    f"give the format explicitly")


def open_dataset(path: str | Path, format: str = "auto", depth_min_m: float = 0.1,
                 depth_max_m: float = 6.0, frames: slice | None = None, load_rgb: bool = False,
                 depth_scale: float | None = None) -> Dataset:
    """Open a dataset folder for lazy frame reading.

    Args:
        path: the dataset folder.
        format: a key of :data:`FORMATS`, or ``"auto"`` to detect it (:func:`detect_format`).
        depth_min_m, depth_max_m: valid depth range, metres; other depth is set to 0 per pixel.
        frames: optional slice of the frames to use; ``Frame.index`` keeps the original position.
        load_rgb: also read colour images into ``Frame.rgb``.
        depth_scale: stored depth units per metre; None uses the format's default (1000 = mm for
            ``7scenes`` and ``bfsdf``).

    Raises:
        DataError: missing folder, unknown layout, no frames (or ``frames`` selects none), invalid
            intrinsics, or a depth frame without a pose file.
        ConfigError: unknown ``format`` name, bad ``depth_scale`` or depth range.
    """
    path = _check_folder(path)
    if format == "auto":
        format = detect_format(path)
    if format not in FORMATS:
        raise ConfigError(f"unknown dataset format {format!r}; known formats: auto, {', '.join(FORMATS)}")
    ds = FORMATS[format](path, depth_min_m=depth_min_m, depth_max_m=depth_max_m, load_rgb=load_rgb,
                         depth_scale=depth_scale)
    if frames is not None:
        if not isinstance(frames, slice):
            raise TypeError(f"frames must be a slice or None, not {type(frames).__name__}")
        n = len(ds)
        ds = ds.subset(frames)
        if len(ds) == 0:
            a, b, c = ("" if v is None else str(v) for v in (frames.start, frames.stop, frames.step))
            raise DataError(f"{path}: frames {a}:{b}{':' + c if c else ''} selects none of the {n} frames "
                            f"in the dataset")
    return ds
