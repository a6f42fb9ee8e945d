"""Dataset formats: recorded RGB-D sequences on disk, read lazily as
:class:`~bftaichi.frame.Frame` objects.

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

Modules: :mod:`~bftaichi.formats.base` (the :class:`Dataset` base class),
:mod:`~bftaichi.formats.readers` (the file readers the formats share), and one module per format
whose docstring gives its layout (DESIGN.md section 5): ``7scenes``
(:mod:`~bftaichi.formats.sevenscenes`), ``bfsdf``, ``tum``, ``replica``, ``scannet``, ``co3d``,
``redwood`` and ``folder`` (the generic folder); :mod:`~bftaichi.formats.synthetic` renders
synthetic scenes with ground truth. This module holds the registry :data:`FORMATS`,
:func:`detect_format` and :func:`open_dataset`.

Adding a format
---------------
In a new module, subclass :class:`Dataset`: set ``format``, ``looks_for`` and
``default_depth_scale`` (and ``options``, the keyword arguments of your ``__init__`` beyond the
base ones), implement ``detect`` (does a folder look like this layout?), ``_scan`` (list the
frames, set ``K`` and, if known, ``image_size`` with :meth:`Dataset._set_image_size`) and
``_read_frame`` (read one frame's raw depth in metres, pose and colour, with the helpers of
:mod:`~bftaichi.formats.readers`: ``read_depth_png``, ``read_numbers_txt``, ``read_pose_txt``,
``read_rgb`` and the others), then import the class here and add one line to :data:`FORMATS`.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError, DataError
from .base import Dataset
from .bfsdf import BFSDFDataset
from .co3d import CO3DDataset, pytorch3d_to_opencv
from .folder import FolderDataset
from .readers import POSE_CONVENTIONS, check_folder, folder_listing
from .redwood import RedwoodDataset
from .replica import ReplicaDataset
from .scannet import ScanNetDataset
from .sevenscenes import SevenScenesDataset
from .tum import TUMDataset

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
    "POSE_CONVENTIONS",
    "detect_format",
    "open_dataset",
    "pytorch3d_to_opencv",
]


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
    path = check_folder(path)
    matches = [name for name, cls in FORMATS.items() if cls.detect(path)]
    if len(matches) == 1:
        return matches[0]
    wanted = "; ".join(f"{name}: {cls.looks_for}" for name, cls in FORMATS.items())
    if not matches:
        raise DataError(f"{path}: no known dataset layout found (looked for {wanted}); "
                        f"the folder contains {folder_listing(path)}")
    raise DataError(f"{path}: the folder matches several dataset layouts ({', '.join(matches)}); "
                    f"give the format explicitly (each looks for {wanted}); the folder contains "
                    f"{folder_listing(path)}")


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
    path = check_folder(path)
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
