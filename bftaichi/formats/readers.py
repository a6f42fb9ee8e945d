"""Recorded RGB-D sequences on disk, read lazily as :class:`~bftaichi.frame.Frame` objects.

Opening a dataset lists its frames and reads the intrinsics (and the one trajectory file of the
layouts that keep all poses in one file); a frame's depth image, pose and (optionally) colour image
are read and checked only when that frame is requested, so a corrupt frame 7 does not stop frames
0-6 from loading. Every user error (missing or unreadable file, malformed text, inconsistent sizes,
a pose that is not a rigid transform) raises :class:`~bftaichi.errors.DataError` with a message that
names the offending file (and line, or frame).

Conventions (DESIGN.md section 2): depth is returned in metres as float32 along the camera z axis;
invalid pixels (0, the sensor's "no return" codes, NaN, inf, negative, or outside
``[depth_min_m, depth_max_m]``) are set to 0 by :func:`bftaichi.frame.clean_depth`. Cameras are
OpenCV pinhole (x right, y down, z forward, integer pixel coordinates at pixel centres),
``K = [[fx,0,cx],[0,fy,cy],[0,0,1]]`` (float64), and poses are ``T_W_C`` (4x4 float64
camera-to-world, metres: ``p_W = T_W_C @ p_C``). Every loader converts its format's conventions to
these; each class docstring says what it converts.

Layouts (DESIGN.md section 5)
-----------------------------
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

``bfsdf`` (this project's own layout, written e.g. by ``bftaichi synth``)::

    depth/000000.png         uint16 (or 8-bit) depth, depth_scale units per metre (default 1000)
    pose/000000.txt          4x4 T_W_C (camera-to-world), metres, 16 numbers
    color/000000.png|jpg     optional 8-bit RGB, read only with load_rgb
    intrinsic/intrinsic.txt  line 1 "w h" (image size, pixels), line 2 "fx fy cx cy" (pixels)
    gt_mesh.ply              optional ground-truth mesh (metres, world frame)

Frames are ordered by file stem (numerically when the stems are numbers). All depth images must
have the size given in ``intrinsic/intrinsic.txt``.

``tum`` (TUM RGB-D benchmark sequence, :class:`TUMDataset`)::

    depth.txt                "timestamp depth/<timestamp>.png" per line; '#' lines are comments
    depth/*.png              uint16 depth, 5000 units per metre; 0 = no measurement
    groundtruth.txt          "timestamp tx ty tz qx qy qz qw": T_W_C (translation, unit
                             quaternion x y z w), each depth frame takes the pose nearest in time
                             (within tolerance_s, default 0.02 s; frames without are skipped)
    rgb.txt, rgb/*.png       optional colour, associated the same way
    camera-intrinsics.txt    optional 3x3 K; otherwise the Freiburg 1/2/3 preset (640x480) named
                             by ``intrinsics`` or by the folder name (rgbd_dataset_freiburg2_...)

``replica`` (Replica as exported by NICE-SLAM, :class:`ReplicaDataset`)::

    results/depth000000.png  uint16 depth, 6553.5 units per metre
    results/frame000000.jpg  optional colour
    traj.txt                 one row-major 4x4 T_W_C (OpenCV camera) per line, in frame order
    cam_params.json          optional {"camera": {"w","h","fx","fy","cx","cy","scale"}}; otherwise
                             NICE-SLAM's camera 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5

``scannet`` (a ScanNet scene exported by its SensReader, :class:`ScanNetDataset`)::

    depth/0.png ...          uint16 depth in millimetres
    pose/0.txt ...           4x4 T_W_C; all inf/NaN = tracking lost: the frame is skipped
    color/0.jpg ...          optional colour (must be resized to the depth size to be used)
    intrinsic/intrinsic_depth.txt   4x4 whose top-left 3x3 is the depth camera's K
                             (intrinsic_color.txt is the colour camera's and is not used)

``co3d`` (one CO3D category folder or sequence, :class:`CO3DDataset`)::

    frame_annotations.jgz    gzip JSON list of frame annotations (or frame_annotations.json):
                             image size, depth PNG path + scale_adjustment (+ depth mask), fg
                             mask, PyTorch3D NDC camera; paths relative to the CO3D root (the
                             folder's parent) or to the folder itself

``redwood`` (Redwood / Open3D RGB-D sequences, :class:`RedwoodDataset`)::

    depth/*.png              uint16 depth in millimetres, frames in file-name order
    color/*.jpg|png          optional colour, same order
    *.log                    Open3D trajectory: per frame a line "id id frame", then 4 lines of a
                             4x4 T_W_C
    camera_intrinsic.json    optional Open3D PinholeCameraIntrinsic (width, height,
                             intrinsic_matrix: 9 values column-major); otherwise PrimeSense
                             (525, 525, 319.5, 239.5, 640x480)

``folder`` (anything else, :class:`FolderDataset`)::

    depth/*.png | *.npy      PNG: depth_scale units per metre (default 1000); .npy: float metres
                             (unless depth_scale is given)
    poses.txt or pose/*.txt  one row-major 4x4 (16 numbers) or 3x4 (12) per line, in depth-stem
                             order; or one 4x4 file per depth stem; T_W_C, or T_C_W with
                             pose_convention="T_C_W" (then inverted)
    intrinsics.json          {"fx","fy","cx","cy"[,"width","height"]} or {"K": [[...]] [, ...]}
    color/<stem>.png|jpg     optional colour

Any layout may hold a ``gt_mesh.ply`` next to the frames; :attr:`Dataset.gt_mesh_path` points to it.
Without an image size in the intrinsics, the first frame read fixes it, and its principal point
must lie near the image centre (within :data:`PRINCIPAL_POINT_TOLERANCE` of the width/height),
which catches intrinsics written for another resolution.

Adding a format
---------------
Subclass :class:`Dataset`: set ``format``, ``looks_for`` and ``default_depth_scale`` (and
``options``, the keyword arguments of your ``__init__`` beyond the base ones), implement
``detect`` (does a folder look like this layout?), ``_scan`` (list the frames, set ``K`` and, if
known, ``image_size`` with :meth:`Dataset._set_image_size`) and ``_read_frame`` (read one frame's
raw depth in metres, pose and colour, with the helpers :func:`read_depth_png`,
:func:`read_numbers_txt`, :func:`read_pose_txt` and :func:`read_rgb`), then add one line to
:data:`FORMATS`.
"""

from __future__ import annotations

import copy
import gzip
import json
import math
import numbers
import re
import tokenize
import warnings
import zipfile
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
from PIL import Image

from ..errors import ConfigError, DataError
from ..frame import Frame, clean_depth
from ..geometry import check_K, check_pose, intrinsics

__all__ = [
    "Dataset",
    "SevenScenesDataset",
    "BFSDFDataset",
    "TUMDataset",
    "ReplicaDataset",
    "ScanNetDataset",
    "CO3DDataset",
    "RedwoodDataset",
    "FolderDataset",
    "FORMATS",
    "PRINCIPAL_POINT_TOLERANCE",
    "detect_format",
    "open_dataset",
    "pytorch3d_to_opencv",
    "read_depth_npy",
    "read_depth_png",
    "read_float16_png",
    "read_numbers_txt",
    "read_pose_txt",
    "read_rgb",
]

# Everything Pillow raises for a missing, unidentifiable, corrupt or truncated image file
# (UnidentifiedImageError is an OSError; bad chunks raise SyntaxError; short reads OSError/EOFError).
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)

PRINCIPAL_POINT_TOLERANCE = 0.2
"""How far (fraction of the width / height) the principal point may be from the image centre when
the intrinsics do not give the image size. Real cameras are within a few percent; intrinsics for
twice or half the resolution are 25 % or 50 % off."""

POSE_CONVENTIONS = ("T_W_C", "T_C_W")
"""How pose files may store a pose: camera-to-world (the default everywhere) or world-to-camera."""


# --------------------------------------------------------------------------------------------
# File readers shared by all formats
# --------------------------------------------------------------------------------------------

def _read_image(path: Path, what: str, mode: str | None = None) -> tuple[str, np.ndarray]:
    """Pillow mode and pixel array of an image file (converted to ``mode`` if given).

    Raises DataError naming ``path`` (and ``what``, e.g. "depth image") if it is missing or corrupt.
    """
    try:
        with Image.open(path) as im:
            if mode is not None:
                im = im.convert(mode)
            im.load()
            return im.mode, np.array(im)
    except FileNotFoundError:
        raise DataError(f"{path}: {what} not found") from None
    except _PIL_ERRORS as e:
        raise DataError(f"{path}: cannot read {what}, the file is corrupt or truncated "
                        f"({type(e).__name__}: {e})") from e


def _read_depth_raw(path: Path) -> tuple[str, np.ndarray]:
    """Pillow mode and (H, W) integer array of a single-channel 16-bit or 8-bit depth image."""
    mode, raw = _read_image(path, "depth image")
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
    return mode, raw


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
    _, raw = _read_depth_raw(path)
    depth = raw.astype(np.float32)
    depth /= np.float32(depth_scale)
    for code in invalid_codes:  # a few codes: one comparison each beats np.isin's sort
        depth[raw == code] = np.nan
    return depth


def read_float16_png(path: Path) -> np.ndarray:
    """(H, W) float32 of a 16-bit PNG whose pixels are float16 bit patterns (CO3D depth)."""
    mode, raw = _read_depth_raw(path)
    if mode == "L":
        raise DataError(f"{path}: depth must be a 16-bit PNG holding float16 values, got an 8-bit image")
    return raw.astype(np.uint16).view(np.float16).astype(np.float32)


def read_depth_npy(path: Path, depth_scale: float = 1.0) -> np.ndarray:
    """(H, W) float32 depth in metres from a ``.npy`` array of ``depth_scale`` units per metre."""
    try:
        a = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DataError(f"{path}: depth array not found") from None
    except (OSError, ValueError, EOFError, SyntaxError, tokenize.TokenError, zipfile.BadZipFile) as e:
        # numpy parses the header with ast/tokenize (a corrupt one raises SyntaxError or
        # TokenError) and opens anything starting with the zip magic as an .npz (BadZipFile)
        raise DataError(f"{path}: cannot read depth array, the file is corrupt "
                        f"({type(e).__name__}: {e})") from e
    if not isinstance(a, np.ndarray):  # np.load opens a zip (.npz) archive whatever the name
        a.close()
        raise DataError(f"{path}: depth must be a .npy array, but the file is an .npz archive")
    if a.ndim != 2 or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise DataError(f"{path}: depth must be a real-valued HxW array, got shape {a.shape} "
                        f"dtype {a.dtype}")
    depth = a.astype(np.float32)
    depth /= np.float32(depth_scale)
    return depth


def read_rgb(path: Path) -> np.ndarray:
    """Read a colour image as (H, W, 3) uint8 RGB; DataError naming ``path`` if unreadable."""
    return _read_image(path, "colour image", "RGB")[1]


def _read_mask(path: Path) -> np.ndarray:
    """(H, W) bool of a grey mask image: pixel > 50 % (CO3D stores P(foreground) * 255)."""
    return _read_image(path, "mask image", "L")[1] > 127


def read_numbers_txt(path: Path, what: str, count: int) -> np.ndarray:
    """Read exactly ``count`` whitespace-separated numbers from a text file as float64.

    ``what`` describes the content for error messages (e.g. ``"pose"``). Raises DataError naming
    ``path`` if the file is missing or unreadable, holds a non-number, or has a different count.
    """
    values = _parse_numbers(_read_text(path, what), path, what)
    if values.size != count:
        raise DataError(f"{path}: {what} file must hold {count} numbers, found {values.size}")
    return values


def read_pose_txt(path: Path, convention: str = "T_W_C") -> np.ndarray:
    """A 4x4 pose file (16 numbers) as a checked ``T_W_C`` (``T_C_W`` files are inverted)."""
    return _pose_from_values(read_numbers_txt(path, f"pose (4x4 {convention})", 16), str(path), convention)


def _read_K_txt(path: Path, count: int = 9) -> np.ndarray:
    """K from a text file holding a 3x3 (9 numbers) or 4x4 (16: the top-left 3x3 is K) matrix."""
    n = int(math.isqrt(count))
    M = read_numbers_txt(path, f"intrinsics ({n}x{n} K)", count).reshape(n, n)
    return check_K(M[:3, :3], str(path))


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


def _read_rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """The non-empty lines of a text table that do not start with '#', as (line number, tokens)."""
    rows = []
    for lineno, line in enumerate(_read_text(path, what).splitlines(), start=1):
        tokens = line.split()
        if tokens and not tokens[0].startswith("#"):
            rows.append((lineno, tokens))
    return rows


def _row_numbers(tokens: list[str], path: Path, lineno: int, what: str,
                 counts: tuple[int, ...]) -> np.ndarray:
    """The numbers of one table row; DataError naming the file and line unless there are
    ``counts`` of them (one of) and all are numbers."""
    values = _parse_numbers(" ".join(tokens), path, f"{what} (line {lineno})")
    if values.size not in counts:
        wanted = " or ".join(str(c) for c in counts)
        raise DataError(f"{path}: line {lineno}: a {what} row must hold {wanted} numbers, "
                        f"found {values.size}")
    return values


def _read_pose_rows(path: Path, counts: tuple[int, ...] = (16,)) -> list[tuple[int, np.ndarray]]:
    """(line number, numbers) of a trajectory file with one row-major 4x4 (16) or 3x4 (12) pose
    per line; the poses are checked later, per frame, by :func:`_pose_from_values`."""
    return [(lineno, _row_numbers(tokens, path, lineno, "pose", counts))
            for lineno, tokens in _read_rows(path, "trajectory")]


def _pose_from_values(values: np.ndarray, where: str, convention: str = "T_W_C") -> np.ndarray:
    """A checked 4x4 ``T_W_C`` from 16 (4x4) or 12 (3x4, last row implied) row-major numbers.

    ``convention`` says what the numbers are: ``T_W_C`` or ``T_C_W`` (inverted here)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    T = np.eye(4)
    T[: values.size // 4] = values.reshape(-1, 4)
    T = check_pose(T, where)
    return _invert_rigid(T) if convention == "T_C_W" else T


def _invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: ``[R t]^-1 = [R^T, -R^T t]``."""
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


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


def _read_json(path: Path, what: str):
    """Parsed JSON of ``path`` (gzip-compressed when the name ends in ``.jgz`` or ``.gz``)."""
    try:
        if path.suffix in (".jgz", ".gz"):
            with gzip.open(path, "rt") as f:
                return json.load(f)
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: {what} file not found") from None
    except (OSError, EOFError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: cannot read {what} file ({type(e).__name__}: {e})") from e


def _json_numbers(d, keys: tuple[str, ...], path: Path, what: str) -> list[float]:
    """The numeric values of ``keys`` in the JSON object ``d``; DataError naming the missing key."""
    if not isinstance(d, dict):
        raise DataError(f"{path}: {what} must be a JSON object, got {type(d).__name__}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise DataError(f"{path}: {what} lacks {', '.join(repr(k) for k in missing)} "
                        f"(needs {', '.join(keys)})")
    bad = [k for k in keys if not isinstance(d[k], numbers.Real) or isinstance(d[k], bool)]
    if bad:
        raise DataError(f"{path}: {what} {bad[0]!r} = {d[bad[0]]!r} is not a number")
    return [float(d[k]) for k in keys]


def _nearest(sorted_times: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index into ``sorted_times`` of the nearest time to each query, and the absolute gap."""
    hi = np.clip(np.searchsorted(sorted_times, queries), 1, max(len(sorted_times) - 1, 1))
    lo = hi - 1
    hi = np.minimum(hi, len(sorted_times) - 1)
    pick = np.where(np.abs(sorted_times[hi] - queries) < np.abs(sorted_times[lo] - queries), hi, lo)
    return pick, np.abs(sorted_times[pick] - queries)


def _stem_key(stem: str) -> tuple:
    """Sort key: numeric stems by value (``2`` before ``10``), others after them by name."""
    return (0, int(stem), stem) if stem.isdigit() else (1, 0, stem)


def _first_file(candidates) -> Path | None:
    """The first of ``candidates`` (paths) that is a file, else None."""
    return next((p for p in candidates if p.is_file()), None)


def _require_files(paths: list[Path], what: str, owners: list[str]) -> None:
    """DataError naming the first missing file of ``paths`` (``what`` of frame ``owners[i]``)."""
    missing = [(p, o) for p, o in zip(paths, owners) if not p.is_file()]
    if missing:
        names = [p.name for p, _ in missing]
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        raise DataError(f"{missing[0][0]}: {what} missing for depth frame {missing[0][1]} "
                        f"(missing: {', '.join(names[:3])}{more})")


def _check_pose_count(trajectory: Path, n_poses: int, n_depth: int, depth_folder: str) -> None:
    """A trajectory file pairs its k-th pose with the k-th depth image: the counts must agree."""
    if n_poses != n_depth:
        raise DataError(f"{trajectory}: {n_poses} poses for {n_depth} depth images in {depth_folder} "
                        f"(one pose per frame, in frame order, is needed)")


def _warn(message: str) -> None:
    # _warn <- _scan (or a helper of it) <- Dataset.__init__ <- ... : 5 reaches open_dataset's caller
    # for most formats; the message names the folder either way.
    warnings.warn(message, UserWarning, stacklevel=5)


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
    frame is requested, not when the dataset is opened (only the folder listing, intrinsics and
    single trajectory files are).

    Attributes:
        path: the dataset folder.
        name: the folder's name (used in reports).
        format: layout name, a key of :data:`FORMATS`.
        K: (3, 3) float64 pinhole intrinsics shared by all frames, pixels (CO3D: the first
            frame's; each ``Frame.K`` is its own).
        image_size: (W, H) of the depth images, pixels; None while unknown (a layout without the
            size in its intrinsics file learns it from the first frame read).
        gt_mesh_path: ``gt_mesh.ply`` in the folder if present, else None.
        load_rgb: read colour images (``Frame.rgb``, (H, W, 3) uint8; None for a frame without one).
        depth_min_m, depth_max_m: valid depth range, metres; depth outside it is set to 0.
        depth_scale: stored depth units per metre.
        skipped: frames of the recording left out at open (TUM: no pose within the time tolerance;
            ScanNet: tracking lost); each format warns once when it skips any.
    """

    format: ClassVar[str]
    """Layout name (the key in :data:`FORMATS`)."""

    looks_for: ClassVar[str]
    """What :meth:`detect` looks for, shown when no format matches a folder."""

    default_depth_scale: ClassVar[float] = 1000.0
    """Depth units per metre when ``depth_scale`` is not given."""

    options: ClassVar[tuple[str, ...]] = ()
    """Format-specific keyword arguments of ``__init__`` that :func:`open_dataset` passes on."""

    def __init__(self, path: str | Path, depth_min_m: float = 0.1, depth_max_m: float = 6.0,
                 load_rgb: bool = False, depth_scale: float | None = None) -> None:
        """Open the dataset folder ``path``: list its frames and read its intrinsics.

        Raises DataError if the folder is missing, holds no frames, or its intrinsics are invalid;
        ConfigError for a non-positive ``depth_scale`` or an empty depth range.
        """
        self._depth_scale_given = depth_scale is not None
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
        self.skipped = 0
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
        layout stores it, with :meth:`_set_image_size`). Runs once, at open."""

    @abstractmethod
    def _read_frame(self, j: int) -> tuple[np.ndarray, Path, np.ndarray, np.ndarray | None]:
        """Read frame ``j`` (position in the full sequence).

        Returns ``(depth_m, depth_path, T_W_C, rgb)``: (H, W) float32 raw depth in metres (invalid
        pixels 0 or NaN; range and finiteness are cleaned by the caller), the depth file (for error
        messages), the checked 4x4 pose, and (H, W, 3) uint8 colour or None (only with load_rgb).
        """

    def _frame_K(self, j: int) -> np.ndarray:
        """Intrinsics of frame ``j``: ``K`` unless the layout stores them per frame."""
        return self.K

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
        return Frame(index=j, name=self._names[j], depth_m=depth_m, K=self._frame_K(j).copy(),
                     T_W_C=T_W_C, rgb=rgb)

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

    def _set_image_size(self, width, height, source: str) -> None:
        """Fix ``image_size`` from the intrinsics file ``source``; DataError unless positive integers."""
        if not all(isinstance(v, numbers.Real) and np.isfinite(v) and v >= 1 and float(v).is_integer()
                   for v in (width, height)):
            raise DataError(f"{source}: image size (width, height) must be positive integers, "
                            f"got ({width}, {height})")
        self.image_size = (int(width), int(height))
        self._size_source = source

    def _check_size(self, shape: tuple[int, ...], depth_path: Path) -> None:
        """Depth images must all have ``image_size``; the first frame read fixes it if unknown,
        provided the principal point is near its centre (:data:`PRINCIPAL_POINT_TOLERANCE`)."""
        h, w = shape
        if self.image_size is None:
            cx, cy = self.K[0, 2], self.K[1, 2]
            tol = PRINCIPAL_POINT_TOLERANCE
            if abs(cx - 0.5 * (w - 1)) > tol * w or abs(cy - 0.5 * (h - 1)) > tol * h:
                raise DataError(f"{depth_path}: depth image is {w}x{h} (WxH) but the principal point "
                                f"(cx, cy) = ({cx:g}, {cy:g}) of the intrinsics is far from its centre: "
                                f"the intrinsics are for another image size")
            self.image_size = (w, h)
            self._size_source = f"the first frame read ({depth_path.name})"
        elif (w, h) != tuple(self.image_size):
            W, H = self.image_size
            raise DataError(f"{depth_path}: depth image is {w}x{h} (WxH) but {self._size_source} "
                            f"is {W}x{H}")

    def _colour(self, candidates) -> np.ndarray | None:
        """The first existing of ``candidates`` read as RGB with ``load_rgb``, else None."""
        if not self.load_rgb:
            return None
        path = _first_file(candidates)
        return None if path is None else read_rgb(path)


# --------------------------------------------------------------------------------------------
# Formats
# --------------------------------------------------------------------------------------------

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
    looks_for = ("frame-XXXXXX.depth.png + frame-XXXXXX.pose.txt [+ camera-intrinsics.txt], "
                 "or seq-XX/ folders of them")
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
            numbered = sorted((int(m.group(1)), p.name[: -len(".depth.png")])
                              for p in folder.iterdir() if (m := self._DEPTH_RE.match(p.name)))
            names += [prefix + name for _, name in numbered]
        if not names:
            return names
        _require_files([self.path / f"{n}.pose.txt" for n in names], "pose file", names)
        k_paths = [p for p in dict.fromkeys(f / "camera-intrinsics.txt" for f in [self.path, *sequences])
                   if p.is_file()]
        if k_paths:
            self.K = _read_K_txt(k_paths[0])
            for other in k_paths[1:]:
                if not np.allclose(_read_K_txt(other), self.K, rtol=1e-9, atol=0):
                    raise DataError(f"{other}: intrinsics differ from {k_paths[0]}; the sequences of "
                                    f"one dataset must share one camera")
        else:
            fx, fy, cx, cy = self.PUBLISHED_K
            _warn(f"{self.path}: no camera-intrinsics.txt; using the published 7-Scenes "
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
        names = sorted((p.stem for p in depth_dir.glob("*.png")), key=_stem_key)
        if not names:
            return names
        _require_files([self.path / "pose" / f"{n}.txt" for n in names], "pose file",
                       [f"depth/{n}.png" for n in names])
        k_path = self.path / "intrinsic" / "intrinsic.txt"
        self.K, size = self._read_intrinsics(k_path)
        self._set_image_size(*size, "intrinsic/intrinsic.txt")
        return names

    @staticmethod
    def _read_intrinsics(path: Path) -> tuple[np.ndarray, tuple[float, float]]:
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
        return K, (float(size[0]), float(size[1]))

    def _read_frame(self, j: int):
        name = self._names[j]
        depth_path = self.path / "depth" / f"{name}.png"
        depth = read_depth_png(depth_path, self.depth_scale)
        T_W_C = read_pose_txt(self.path / "pose" / f"{name}.txt")
        rgb = self._colour(self.path / "color" / f"{name}{s}" for s in self.COLOR_SUFFIXES)
        return depth, depth_path, T_W_C, rgb


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
        for lineno, tokens in _read_rows(list_path, "file list"):
            if len(tokens) != 2 or not _is_number(tokens[0]):
                raise DataError(f"{list_path}: line {lineno}: expected 'timestamp path', "
                                f"got {' '.join(tokens)!r}")
            rows.append((float(tokens[0]), tokens[0], tokens[1]))
        return rows

    def _scan(self) -> list[str]:
        depth_rows = self._timed_files(self.path / "depth.txt")
        self._gt_path = self.path / "groundtruth.txt"
        gt = sorted(((_row_numbers(tokens, self._gt_path, lineno, "groundtruth", (8,)), lineno)
                     for lineno, tokens in _read_rows(self._gt_path, "ground truth")),
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
            _warn(f"{self.path}: skipped {self.skipped} of {len(depth_rows)} depth frames without a "
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
            self.K = _read_K_txt(k_path)
            return
        if preset is None:
            m = self._FOLDER_RE.search(self.name)
            if m:
                preset = f"fr{m.group(1)}"
            else:
                preset = "fr1"
                _warn(f"{self.path}: neither intrinsics=, camera-intrinsics.txt nor a 'freiburgN' "
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


class ReplicaDataset(Dataset):
    """Replica as exported by NICE-SLAM (``Replica/room0``: ``results/``, ``traj.txt``).

    Conventions: ``results/depthNNNNNN.png`` uint16 with 6553.5 units per metre (NICE-SLAM's
    ``png_depth_scale``); ``traj.txt`` one row-major 4x4 ``T_W_C`` per line, frame ``k`` the
    ``k``-th line. Those poses already use OpenCV camera axes; NICE-SLAM flips the y and z axes
    itself because it renders with OpenGL axes, and bftaichi does not. Intrinsics: NICE-SLAM's
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
        numbered = sorted((int(m.group(1)), m.group(1)) for p in results.glob("depth*.png")
                          if (m := self._DEPTH_RE.match(p.name)))
        self._numbers = [digits for _, digits in numbered]
        if not numbered:
            return []
        self._traj_path = self.path / "traj.txt"
        self._poses = _read_pose_rows(self._traj_path)
        _check_pose_count(self._traj_path, len(self._poses), len(numbered), "results/")
        cam_path = self.path / "cam_params.json"
        if cam_path.is_file():
            cam = _read_json(cam_path, "camera parameters")
            w, h, fx, fy, cx, cy = _json_numbers(cam.get("camera") if isinstance(cam, dict) else cam,
                                                 ("w", "h", "fx", "fy", "cx", "cy"), cam_path, '"camera"')
            self.K = check_K(intrinsics(fx, fy, cx, cy), str(cam_path))
            self._set_image_size(w, h, str(cam_path))
            if not self._depth_scale_given and "scale" in cam["camera"]:
                self.depth_scale = _json_numbers(cam["camera"], ("scale",), cam_path, '"camera"')[0]
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
        T_W_C = _pose_from_values(values, f"{self._traj_path}: line {lineno} (frame {self._names[j]})")
        rgb = self._colour(self.path / "results" / f"frame{digits}{s}" for s in (".jpg", ".png"))
        return depth, depth_path, T_W_C, rgb


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
        names = sorted((p.stem for p in (self.path / "depth").glob("*.png")), key=_stem_key)
        if not names:
            return names
        pose_paths = [self.path / "pose" / f"{n}.txt" for n in names]
        _require_files(pose_paths, "pose file", [f"depth/{n}.png" for n in names])
        lost = [self._tracking_lost(p) for p in pose_paths]
        kept = [n for n, bad in zip(names, lost) if not bad]
        self.skipped = len(names) - len(kept)
        if self.skipped:
            _warn(f"{self.path}: skipped {self.skipped} of {len(names)} frames whose pose is inf/NaN "
                  f"(ScanNet's mark for lost tracking)")
        self.K = _read_K_txt(self.path / "intrinsic" / "intrinsic_depth.txt", 16)
        return kept

    @staticmethod
    def _tracking_lost(pose_path: Path) -> bool:
        """True for a pose file of 16 numbers with an inf or NaN (a malformed file is not "lost":
        reading that frame reports it)."""
        try:
            values = _parse_numbers(pose_path.read_text(), pose_path, "pose")
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
    return K, _invert_rigid(check_pose(T_C_W, where))


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
        self._ann_path = _first_file(self.path / name for name in self.ANNOTATION_FILES)
        entries = _read_json(self._ann_path, "frame annotations")
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
        return _first_file(candidates) or candidates[0]

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
            mask = _read_mask(mask_path)
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


class RedwoodDataset(Dataset):
    """Redwood / Open3D RGB-D sequence: ``depth/``, ``color/`` and an Open3D ``.log`` trajectory.

    Conventions: ``depth/*.png`` uint16 millimetres, ordered by file name (numerically for numeric
    stems), colour the same order in ``color/``; the ``.log`` (Open3D's trajectory format, the
    only ``*.log`` in the folder) holds per frame a line "id id frame" and 4 lines of a 4x4
    ``T_W_C`` (OpenCV axes), the ``k``-th block for the ``k``-th depth image. Intrinsics: an Open3D
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
        depth_files = sorted((self.path / "depth").glob("*.png"), key=lambda p: _stem_key(p.stem))
        self._files = [p.name for p in depth_files]
        if not depth_files:
            return []
        colour_dir = self.path / "color"
        colours = sorted((p for p in colour_dir.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg")),
                         key=lambda p: _stem_key(p.stem)) if colour_dir.is_dir() else []
        self._colours = colours if len(colours) == len(depth_files) else []
        logs = sorted(self.path.glob("*.log"))
        if len(logs) > 1:
            raise DataError(f"{self.path}: several trajectories ({', '.join(p.name for p in logs)}); "
                            f"keep one .log file")
        self._log_path = logs[0]
        self._poses = self._read_log(self._log_path)
        _check_pose_count(self._log_path, len(self._poses), len(depth_files), "depth/")
        k_path = self.path / "camera_intrinsic.json"
        if k_path.is_file():
            cam = _read_json(k_path, "camera intrinsics")
            w, h = _json_numbers(cam, ("width", "height"), k_path, "camera intrinsics")
            M = cam.get("intrinsic_matrix")
            if not (isinstance(M, list) and len(M) == 9 and all(_is_real(v) for v in M)):
                raise DataError(f"{k_path}: intrinsic_matrix must be 9 numbers (column-major 3x3)")
            self.K = check_K(np.array(M, dtype=np.float64).reshape(3, 3).T, str(k_path))
            self._set_image_size(w, h, str(k_path))
        else:
            _warn(f"{self.path}: no camera_intrinsic.json; using Open3D's PrimeSense default "
                  f"intrinsics {self.PRIMESENSE_K} (640x480)")
            self.K = intrinsics(*self.PRIMESENSE_K)
            self._set_image_size(*self.PRIMESENSE_SIZE, "the PrimeSense default intrinsics")
        return [p.stem for p in depth_files]

    @staticmethod
    def _read_log(path: Path) -> list[tuple[int, np.ndarray]]:
        """(line number of the header, 16 numbers) per block of an Open3D .log trajectory."""
        rows = _read_rows(path, "trajectory")
        if len(rows) % 5:
            raise DataError(f"{path}: an Open3D .log has 5 lines per frame ('id id frame' and 4 rows "
                            f"of 4x4); found {len(rows)} lines")
        poses = []
        for b in range(0, len(rows), 5):
            lineno, header = rows[b]
            _row_numbers(header, path, lineno, "frame header ('id id frame')", (3,))
            values = [_row_numbers(tokens, path, n, "pose", (4,)) for n, tokens in rows[b + 1: b + 5]]
            poses.append((lineno, np.concatenate(values)))
        return poses

    def _read_frame(self, j: int):
        depth_path = self.path / "depth" / self._files[j]
        depth = read_depth_png(depth_path, self.depth_scale)
        lineno, values = self._poses[j]
        T_W_C = _pose_from_values(values, f"{self._log_path}: lines {lineno}-{lineno + 4} "
                                          f"(frame {self._names[j]})")
        return depth, depth_path, T_W_C, self._colour(self._colours[j: j + 1])


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


class FolderDataset(Dataset):
    """A generic folder: ``depth/``, poses (``poses.txt`` or ``pose/``), ``intrinsics.json``.

    Conventions: ``depth/<stem>.png`` integer depth with ``depth_scale`` units per metre (default
    1000, millimetres) or ``depth/<stem>.npy`` float depth in metres (divided by ``depth_scale``
    only if it is given); frames ordered by stem (numerically for numeric stems). Poses:
    ``poses.txt`` (one pose per line, in frame order: 16 numbers, a row-major 4x4, or 12, the top
    3x4) or else ``pose/<stem>.txt`` (a 4x4 each). ``pose_convention`` says what they are:
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
        names = sorted(files, key=_stem_key)
        self._files = [files[n] for n in names]
        if not names:
            return names
        poses_txt = self.path / "poses.txt"
        if poses_txt.is_file():
            self._pose_rows = _read_pose_rows(poses_txt, (12, 16))
            _check_pose_count(poses_txt, len(self._pose_rows), len(names), "depth/")
            self._poses_txt = poses_txt
        else:
            self._pose_rows = None
            _require_files([self.path / "pose" / f"{n}.txt" for n in names], "pose file",
                           [f"depth/{f.name}" for f in self._files])
        self._read_intrinsics(self.path / "intrinsics.json")
        return names

    def _read_intrinsics(self, path: Path) -> None:
        d = _read_json(path, "intrinsics")
        if isinstance(d, dict) and "K" in d:
            try:
                K = np.array(d["K"], dtype=np.float64)
            except (TypeError, ValueError):
                raise DataError(f"{path}: \"K\" must be a 3x3 list of numbers") from None
            self.K = check_K(K, str(path))
        else:
            self.K = check_K(intrinsics(*_json_numbers(d, ("fx", "fy", "cx", "cy"), path, "intrinsics")),
                             str(path))
        if "width" in d or "height" in d:
            self._set_image_size(*_json_numbers(d, ("width", "height"), path, "intrinsics"), str(path))

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
            T_W_C = _pose_from_values(values, f"{self._poses_txt}: line {lineno} (frame {self._names[j]})",
                                      self.pose_convention)
        rgb = self._colour(self.path / "color" / f"{self._names[j]}{s}" for s in (".png", ".jpg"))
        return depth, depth_path, T_W_C, rgb


# --------------------------------------------------------------------------------------------
# Registry and entry points
# --------------------------------------------------------------------------------------------

FORMATS: dict[str, type[Dataset]] = {
    "7scenes": SevenScenesDataset,
    "bfsdf": BFSDFDataset,
    "tum": TUMDataset,
    "replica": ReplicaDataset,
    "scannet": ScanNetDataset,
    "co3d": CO3DDataset,
    "redwood": RedwoodDataset,
    "folder": FolderDataset,
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
    wanted = "; ".join(f"{name}: {cls.looks_for}" for name, cls in FORMATS.items())
    if not matches:
        raise DataError(f"{path}: no known dataset layout found (looked for {wanted}); "
                        f"the folder contains {_folder_listing(path)}")
    raise DataError(f"{path}: the folder matches several dataset layouts ({', '.join(matches)}); "
                    f"give the format explicitly (each looks for {wanted}); the folder contains "
                    f"{_folder_listing(path)}")


def open_dataset(path: str | Path, format: str = "auto", depth_min_m: float = 0.1,
                 depth_max_m: float = 6.0, frames: slice | None = None, load_rgb: bool = False,
                 depth_scale: float | None = None, pose_convention: str = "T_W_C",
                 **options) -> Dataset:
    """Open a dataset folder for lazy frame reading.

    Args:
        path: the dataset folder.
        format: a key of :data:`FORMATS`, or ``"auto"`` to detect it (:func:`detect_format`).
        depth_min_m, depth_max_m: valid depth range, metres; other depth is set to 0 per pixel.
        frames: optional slice of the frames to use; ``Frame.index`` keeps the original position.
        load_rgb: also read colour images into ``Frame.rgb``.
        depth_scale: stored depth units per metre; None or 0 (``scene.depth_scale``'s default) uses
            the format's default (1000 = mm for most, 5000 for ``tum``, 6553.5 for ``replica``).
        pose_convention: ``T_W_C`` or ``T_C_W``, for the ``folder`` format; every other format has
            a fixed convention, so anything but ``T_W_C`` is a ConfigError for them.
        options: format-specific keyword arguments (each class's ``options``: ``intrinsics`` and
            ``tolerance_s`` for ``tum``, ``sequence``, ``use_masks`` and ``use_depth_masks`` for
            ``co3d``).

    Raises:
        DataError: missing folder, unknown layout, no frames (or ``frames`` selects none), invalid
            intrinsics, or a depth frame without a pose file.
        ConfigError: unknown ``format`` name or option, bad ``depth_scale`` or depth range.
    """
    path = _check_folder(path)
    if format == "auto":
        format = detect_format(path)
    if format not in FORMATS:
        raise ConfigError(f"unknown dataset format {format!r}; known formats: auto, {', '.join(FORMATS)}")
    cls = FORMATS[format]
    if "pose_convention" in cls.options:
        options["pose_convention"] = pose_convention
    elif pose_convention != "T_W_C":
        raise ConfigError(f"pose_convention = {pose_convention!r}: the {format} format's poses are "
                          f"always T_W_C (only the folder format takes T_C_W)")
    unknown = sorted(set(options) - set(cls.options))
    if unknown:
        takes = ", ".join(cls.options) if cls.options else "none"
        raise ConfigError(f"the {format} format has no option {', '.join(unknown)} (its options: {takes})")
    ds = cls(path, depth_min_m=depth_min_m, depth_max_m=depth_max_m, load_rgb=load_rgb,
             depth_scale=depth_scale or None, **options)
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
