"""The unit every loader yields and the integrator consumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Frame", "clean_depth"]


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
    """

    index: int
    name: str
    depth_m: np.ndarray
    K: np.ndarray
    T_W_C: np.ndarray
    rgb: np.ndarray | None = None


def clean_depth(depth_m: np.ndarray, depth_min_m: float, depth_max_m: float) -> np.ndarray:
    """Return float32 depth with every invalid pixel set to 0.

    Invalid (DESIGN.md section 2): 0, NaN, +-inf, negative, or outside ``[depth_min_m, depth_max_m]``.
    Sensor-specific codes (65535 in 7-Scenes) are turned into NaN by the loader before this.
    """
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d >= depth_min_m) & (d <= depth_max_m) & (d > 0)
    return np.where(valid, d, np.float32(0.0)).astype(np.float32, copy=False)
