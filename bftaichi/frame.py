"""The unit every loader yields and the integrator consumes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .geometry import pose_in_local

__all__ = ["Frame", "clean_depth", "LocalFrames", "local_frames"]


@dataclass(frozen=True)
class Frame:
    """One depth frame.

    Attributes:
        index: position in the (unsliced) sequence.
        name: file stem or label, used in error messages (e.g. ``frame-000012``).
        depth_m: (H, W) float32 depth along the camera z axis, metres; invalid pixels are 0.
        K: (3, 3) float64 pinhole intrinsics.
        T_W_C: (4, 4) float64 camera-to-world pose.
        rgb: optional (H, W, 3) uint8 colour registered to the depth image.
        depth_path: the depth file a recorded frame was read from (None for rendered or
            in-memory frames), for messages and :mod:`bftaichi.plausibility`'s checks.
    """

    index: int
    name: str
    depth_m: np.ndarray
    K: np.ndarray
    T_W_C: np.ndarray
    rgb: np.ndarray | None = None
    depth_path: Path | None = None


def clean_depth(depth_m: np.ndarray, depth_min_m: float, depth_max_m: float) -> np.ndarray:
    """Return float32 depth with every invalid pixel set to 0.

    Invalid (DESIGN.md section 2): 0, NaN, +-inf, negative, or outside ``[depth_min_m, depth_max_m]``.
    Sensor-specific codes (65535 in 7-Scenes) are turned into NaN by the loader before this.
    """
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d >= depth_min_m) & (d <= depth_max_m) & (d > 0)
    return np.where(valid, d, np.float32(0.0)).astype(np.float32, copy=False)


class LocalFrames:
    """A frame source (``len`` and indexing) whose frames come with their pose in the local
    frame of ``origin`` (their ``T_W_C`` field holds ``T_L_C``,
    :func:`bftaichi.geometry.pose_in_local`): what the kernels of a grid built around
    ``origin`` take."""

    def __init__(self, frames, origin):
        self.frames = frames
        self.origin = np.asarray(origin, np.float64)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self._local(self.frames[i])

    def __iter__(self):
        return (self._local(f) for f in self.frames)

    def _local(self, frame: Frame) -> Frame:
        return replace(frame, T_W_C=pose_in_local(frame.T_W_C, self.origin))


def local_frames(frames, origin):
    """``frames`` with local poses (:class:`LocalFrames`); ``frames`` itself when ``origin`` is
    zero."""
    return LocalFrames(frames, origin) if np.any(origin) else frames
