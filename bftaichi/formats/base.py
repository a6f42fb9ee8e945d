"""The :class:`Dataset` base class: a lazily read, list-like sequence of depth frames.

A format subclasses it (see "Adding a format" in :mod:`bftaichi.formats`); the base class opens
the folder, checks the depth range and scale, serves frames by index or slice, checks each
frame's image size and colour, and cleans its depth with :func:`~bftaichi.frame.clean_depth`.

Any layout may hold a ``gt_mesh.ply`` next to the frames; :attr:`Dataset.gt_mesh_path` points to it.
Without an image size in the intrinsics, the first frame read fixes it, and its principal point
must lie inside it and not fit twice or half its size better (:func:`principal_point_misfit`),
which catches intrinsics written for another resolution.
"""

from __future__ import annotations

import copy
import numbers
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import ConfigError, DataError
from ..frame import Frame, clean_depth
from .readers import check_folder, first_file, folder_listing, read_rgb


def principal_point_misfit(K, width: int, height: int) -> tuple[str, tuple[int, int]] | None:
    """Whether the principal point of ``K`` says the image is not ``width`` x ``height``.

    An exact rule, per axis, with pixel centres at integers (an image of ``n`` pixels spans
    ``[-0.5, n - 0.5]``, centre ``(n - 1) / 2``):

    - ``"outside"``: ``(cx, cy)`` lies outside the image;
    - ``"transposed"``: ``cx`` is nearer the centre of the height than of the width *and*
      ``cy`` nearer the centre of the width than of the height (K is for ``height x width``);
    - ``"scaled"``: on both axes the principal point is nearer the centre of the image twice
      (or half) the size than of this one (K is for another resolution).

    Both axes must agree, so a camera whose principal point is far off centre along one axis
    (a crop, a shifted lens) passes; each rule needs the principal point off centre by a
    quarter of the difference of the sizes on both axes at once. A square image is never
    "transposed". Returns None when the size fits, else ``(kind, (W, H))`` with the size K
    fits (for ``"outside"`` and ``"scaled"``: ``2 c + 1`` rounded, what a centred principal
    point implies).
    """
    cx, cy = float(K[0][2]), float(K[1][2])
    w, h = int(width), int(height)

    def nearer(c, n_alt, n):  # c nearer the centre of n_alt pixels than of n pixels
        return abs(c - (n_alt - 1) / 2) < abs(c - (n - 1) / 2)

    implied = (max(1, round(2 * cx + 1)), max(1, round(2 * cy + 1)))
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        return "outside", implied
    if w != h and nearer(cx, h, w) and nearer(cy, w, h):
        return "transposed", (h, w)
    for f in (2.0, 0.5):
        if nearer(cx, f * w, w) and nearer(cy, f * h, h):
            return "scaled", implied
    return None


def misfit_text(misfit: tuple[str, tuple[int, int]]) -> str:
    """What a :func:`principal_point_misfit` says of the principal point, for messages."""
    kind, (w, h) = misfit
    return {"outside": "lies outside it", "scaled": f"fits an image of about {w}x{h}",
            "transposed": f"fits a {w}x{h} image"}[kind]


class Dataset(ABC):
    """A lazily read sequence of depth frames (a list-like of :class:`~bftaichi.frame.Frame`).

    ``len(ds)``, ``ds[i]`` (negative ``i`` counts from the end, ``IndexError`` out of range;
    ``ds[a:b:c]`` is :meth:`subset`) and ``for frame in ds`` work as for a list. Files are read when a
    frame is requested, not when the dataset is opened (only the folder listing, intrinsics and
    single trajectory files are).

    Attributes:
        path: the dataset folder.
        name: the folder's name (used in reports).
        format: layout name, a key of :data:`~bftaichi.formats.FORMATS`.
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
    """Layout name (the key in :data:`~bftaichi.formats.FORMATS`)."""

    looks_for: ClassVar[str]
    """What :meth:`detect` looks for, shown when no format matches a folder."""

    default_depth_scale: ClassVar[float] = 1000.0
    """Depth units per metre when ``depth_scale`` is not given."""

    options: ClassVar[tuple[str, ...]] = ()
    """Format-specific keyword arguments of ``__init__`` that :func:`~bftaichi.formats.open_dataset`
    passes on."""

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
        self.path = check_folder(path)
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
                            f"the folder contains {folder_listing(self.path)}")
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
                     T_W_C=T_W_C, rgb=rgb, depth_path=depth_path)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def subset(self, s: slice | list[int]) -> Dataset:
        """A view of the frames selected by ``s``: a slice (Python slice semantics on this
        dataset's frames) or a list of positions in it.

        The view shares the files and settings; its frames keep their original ``Frame.index``
        (position in the full sequence), so ``ds.subset(slice(10, None, 5))[0].index == 10``.
        """
        view = copy.copy(self)
        if isinstance(s, slice):
            view._indices = self._indices[s]
        elif isinstance(s, (list, tuple)) and all(isinstance(i, int) for i in s):
            view._indices = [self._indices[i] for i in s]
        else:
            raise TypeError(f"subset takes a slice or a list of positions, not {s!r:.60}")
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
        provided K's principal point lies inside it and fits no other resolution better
        (:func:`principal_point_misfit`; a transposed image is left to
        :mod:`bftaichi.plausibility`, which warns, or refuses with ``run.strict``)."""
        h, w = shape
        if self.image_size is None:
            cx, cy = self.K[0, 2], self.K[1, 2]
            misfit = principal_point_misfit(self.K, w, h)
            if misfit is not None and misfit[0] != "transposed":
                raise DataError(f"{depth_path}: depth image is {w}x{h} (WxH) but the principal point "
                                f"(cx, cy) = ({cx:g}, {cy:g}) of the intrinsics {misfit_text(misfit)}: "
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
        path = first_file(candidates)
        return None if path is None else read_rgb(path)
