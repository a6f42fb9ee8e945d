"""File readers shared by the dataset formats: depth images and arrays, colour and mask
images, number and pose text files, trajectory tables, JSON, plus the folder checks and the
warning helper the loaders use.

Every reader raises :class:`~bftaichi.errors.DataError` naming the offending file (and line) for
a missing, unreadable or malformed file. Depth comes back in metres as float32, not yet
range-checked; poses as checked 4x4 ``T_W_C`` float64 (DESIGN.md section 2).
"""

from __future__ import annotations

import gzip
import json
import math
import numbers
import re
import tokenize
import warnings
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import BftaichiWarning, DataError
from ..geometry import check_K, check_pose


# Everything Pillow raises for a missing, unidentifiable, corrupt or truncated image file
# (UnidentifiedImageError is an OSError; bad chunks raise SyntaxError; short reads OSError/EOFError).
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)


POSE_CONVENTIONS = ("T_W_C", "T_C_W")
"""How pose files may store a pose: camera-to-world (the default everywhere) or world-to-camera."""


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


def read_mask(path: Path) -> np.ndarray:
    """(H, W) bool of a grey mask image: pixel > 50 % (CO3D stores P(foreground) * 255)."""
    return _read_image(path, "mask image", "L")[1] > 127


def read_numbers_txt(path: Path, what: str, count: int) -> np.ndarray:
    """Read exactly ``count`` whitespace-separated numbers from a text file as float64.

    ``what`` describes the content for error messages (e.g. ``"pose"``). Raises DataError naming
    ``path`` if the file is missing or unreadable, holds a non-number, or has a different count.
    """
    values = parse_numbers(read_text(path, what), path, what)
    if values.size != count:
        raise DataError(f"{path}: {what} file must hold {count} numbers, found {values.size}")
    return values


def read_pose_txt(path: Path, convention: str = "T_W_C") -> np.ndarray:
    """A 4x4 pose file (16 numbers) as a checked ``T_W_C`` (``T_C_W`` files are inverted)."""
    return pose_from_values(read_numbers_txt(path, f"pose (4x4 {convention})", 16), str(path), convention)


def read_K_txt(path: Path, count: int = 9) -> np.ndarray:
    """K from a text file holding a 3x3 (9 numbers) or 4x4 (16: the top-left 3x3 is K) matrix."""
    n = int(math.isqrt(count))
    M = read_numbers_txt(path, f"intrinsics ({n}x{n} K)", count).reshape(n, n)
    return check_K(M[:3, :3], str(path))


def read_text(path: Path, what: str) -> str:
    """The text of ``path``; DataError naming it (and ``what`` it holds) if missing or unreadable."""
    try:
        return path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: {what} file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read {what} file ({e})") from e


def parse_numbers(text: str, path: Path, what: str) -> np.ndarray:
    """The whitespace-separated numbers of ``text`` (read from ``path``) as float64; DataError
    naming the first token that is not a number."""
    tokens = text.split()
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not is_number(t))
        raise DataError(f"{path}: {what} file holds {bad!r}, which is not a number") from None


def is_number(token: str) -> bool:
    """True if ``float(token)`` parses."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """The non-empty lines of a text table that do not start with '#', as (line number, tokens)."""
    rows = []
    for lineno, line in enumerate(read_text(path, what).splitlines(), start=1):
        tokens = line.split()
        if tokens and not tokens[0].startswith("#"):
            rows.append((lineno, tokens))
    return rows


def row_numbers(tokens: list[str], path: Path, lineno: int, what: str,
                 counts: tuple[int, ...]) -> np.ndarray:
    """The numbers of one table row; DataError naming the file and line unless there are
    ``counts`` of them (one of) and all are numbers."""
    values = parse_numbers(" ".join(tokens), path, f"{what} (line {lineno})")
    if values.size not in counts:
        wanted = " or ".join(str(c) for c in counts)
        raise DataError(f"{path}: line {lineno}: a {what} row must hold {wanted} numbers, "
                        f"found {values.size}")
    return values


def read_pose_rows(path: Path, counts: tuple[int, ...] = (16,)) -> list[tuple[int, np.ndarray]]:
    """(line number, numbers) of a trajectory file with one row-major 4x4 (16) or 3x4 (12) pose
    per line; the poses are checked later, per frame, by :func:`pose_from_values`."""
    return [(lineno, row_numbers(tokens, path, lineno, "pose", counts))
            for lineno, tokens in read_rows(path, "trajectory")]


def pose_from_values(values: np.ndarray, where: str, convention: str = "T_W_C") -> np.ndarray:
    """A checked 4x4 ``T_W_C`` from 16 (4x4) or 12 (3x4, last row implied) row-major numbers.

    ``convention`` says what the numbers are: ``T_W_C`` or ``T_C_W`` (inverted here)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    T = np.eye(4)
    T[: values.size // 4] = values.reshape(-1, 4)
    T = check_pose(T, where)
    return invert_rigid(T) if convention == "T_C_W" else T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: ``[R t]^-1 = [R^T, -R^T t]``."""
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


def read_json(path: Path, what: str):
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


def json_numbers(d, keys: tuple[str, ...], path: Path, what: str) -> list[float]:
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


def json_matrix(value, shape: tuple[int, ...], path: Path, what: str) -> np.ndarray:
    """``value`` (nested JSON lists) as a float64 array of ``shape`` (-1: any length); DataError
    naming ``path`` and ``what`` unless it is one, of numbers (values not checked here)."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):  # ragged lists, text, objects
        a = None
    if a is None or a.ndim != len(shape) or any(want not in (-1, got)
                                                for want, got in zip(shape, a.shape)):
        dims = "x".join("n" if d == -1 else str(d) for d in shape)
        raise DataError(f"{path}: {what} must be a {dims} array of numbers, got "
                        f"{str(value)[:80]}")
    return a


def stem_key(stem: str) -> tuple:
    """Sort key: numeric stems by value (``2`` before ``10``), others after them by name."""
    return (0, int(stem), stem) if stem.isdigit() else (1, 0, stem)


def first_file(candidates) -> Path | None:
    """The first of ``candidates`` (paths) that is a file, else None."""
    return next((p for p in candidates if p.is_file()), None)


def require_files(paths: list[Path], what: str, owners: list[str]) -> None:
    """DataError naming the first missing file of ``paths`` (``what`` of frame ``owners[i]``)."""
    missing = [(p, o) for p, o in zip(paths, owners) if not p.is_file()]
    if missing:
        names = [p.name for p, _ in missing]
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        raise DataError(f"{missing[0][0]}: {what} missing for depth frame {missing[0][1]} "
                        f"(missing: {', '.join(names[:3])}{more})")


_NUMBERED = re.compile(r"^(.*?)(\d+)$")


def frame_number(stem: str) -> tuple[str, int] | None:
    """``(prefix, number)`` of a file stem that ends in digits (``frame-000010`` and ``frame-10``
    -> ``("frame-", 10)``, ``depth10`` -> ``("depth", 10)``, ``000010`` -> ``("", 10)``); None
    for a stem without a number."""
    m = _NUMBERED.match(stem)
    return (m.group(1), int(m.group(2))) if m else None


def sort_frames(files, stem=lambda p: p.stem) -> list[Path]:
    """``files`` in frame order: numbered stems by (prefix, number), so ``2`` comes before
    ``10``; then the others by name. Two files with the same prefix and number
    (``frame-10`` and ``frame-000010``) are a DataError naming both: two copies of one frame
    would be fused twice."""
    keyed = sorted(((frame_number(stem(p)), p.name, p) for p in files),
                   key=lambda t: (t[0] is None, t[0] or ("", 0), t[1]))
    for (a, _, pa), (b, _, pb) in zip(keyed, keyed[1:]):
        if a is not None and a == b:
            raise DataError(f"{pa} and {pb} have the same frame number {a[1]}: two copies of "
                            "one frame? keep one of them")
    return [p for _, _, p in keyed]


def poses_by_frame_number(trajectory: Path, entries: list, numbers: list, images: list[Path]) -> list:
    """The pose of each image from a one-file trajectory.

    ``entries``: ``(frame number, pose record)`` in file order; ``numbers``: each image's frame
    number (None if its name has none). When there are as many poses as images (a whole
    sequence, or a trajectory cut to the images), the i-th image takes the i-th pose. Otherwise
    each image takes the pose of its frame number, so a partial copy (the first N images) or a
    subsampled one (every k-th image) of a sequence with its full trajectory loads, with one
    warning giving both counts. DataError names an image without a pose."""
    if len(entries) == len(images):
        return [record for _, record in entries]
    by_number = {}
    for n, record in entries:
        if n in by_number:
            raise DataError(f"{trajectory}: two poses for frame number {n}")
        by_number[n] = record
    for n, image in zip(numbers, images):
        if n is None:
            raise DataError(f"{trajectory}: {len(entries)} poses for {len(images)} depth images, and "
                            f"{image.name} has no frame number in its name to take its pose by")
        if n not in by_number:
            known = sorted(by_number)
            span = f"frames {known[0]}-{known[-1]}" if known else "no frames"
            raise DataError(f"{image}: no pose for frame number {n} in {trajectory} "
                            f"({len(entries)} poses, {span})")
    warn(f"{trajectory}: {len(entries)} poses for {len(images)} depth images in "
         f"{images[0].parent}: each image takes the pose of the frame number in its name "
         "(a partial or subsampled copy of the sequence)")
    return [by_number[n] for n in numbers]


def warn(message: str) -> None:
    """A BftaichiWarning about a dataset, attributed to the code that opened it."""
    # warn <- _scan (or a helper of it) <- Dataset.__init__ <- ... : 5 reaches open_dataset's caller
    # for most formats; the message names the folder either way.
    warnings.warn(message, BftaichiWarning, stacklevel=5)


def folder_listing(path: Path, limit: int = 12) -> str:
    """A short description of a folder's content for error messages (folders end in '/')."""
    entries = sorted(p.name + ("/" if p.is_dir() else "") for p in path.iterdir())
    if not entries:
        return "nothing (the folder is empty)"
    shown = ", ".join(entries[:limit])
    more = f", ... ({len(entries) - limit} more)" if len(entries) > limit else ""
    return shown + more


def check_folder(path: str | Path) -> Path:
    """``path`` as a Path (``~`` expanded); DataError unless it is an existing folder."""
    path = Path(path).expanduser()
    if not path.exists():
        raise DataError(f"dataset folder {path} does not exist")
    if not path.is_dir():
        raise DataError(f"dataset path {path} is not a folder")
    return path
