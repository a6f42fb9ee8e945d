"""Camera geometry and input checks shared by datasets, synthetic scenes and the integrator.

Conventions (DESIGN.md section 2): metres; OpenCV pinhole camera (x right, y down, z forward);
``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; poses are ``T_W_C`` (camera-to-world, 4x4), so a
camera point maps to the world as ``p_W = T_W_C @ p_C``.
"""

from __future__ import annotations

import numpy as np

from .errors import DataError

__all__ = ["intrinsics", "look_at", "check_K", "check_pose", "check_depth"]


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3x3 pinhole matrix K (float64)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_W_C`` (4x4 float64) of an OpenCV camera at ``eye`` looking at ``target``.

    The camera z axis points from ``eye`` to ``target``; the image y axis (down) is the projection
    of ``-up``. When the view direction is parallel to ``up``, world +y (or +x) is used instead.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    norm = np.linalg.norm(z)
    if norm == 0:
        raise ValueError("look_at: eye and target coincide")
    z /= norm
    for candidate in (up, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        x = np.cross(-candidate, z)  # x = y x z with y (image down) ~ -up
        if np.linalg.norm(x) > 1e-6:
            break
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def check_K(K, where: str) -> np.ndarray:
    """Validate a 3x3 pinhole matrix; return it as float64. ``where`` names the file or frame."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise DataError(f"{where}: intrinsics must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise DataError(f"{where}: intrinsics contain NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"{where}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0 or K[0, 1] != 0:
        raise DataError(f"{where}: intrinsics are not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    return K


def check_pose(T, where: str, tol: float = 1e-3) -> np.ndarray:
    """Validate a 4x4 rigid transform ``T_W_C``; return it as float64.

    Rejects NaN/inf, a last row other than ``0 0 0 1``, and a rotation that is not orthonormal with
    determinant +1 (within ``tol``; recorded poses are often stored with 6-7 digits).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DataError(f"{where}: pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise DataError(f"{where}: pose contains NaN or inf")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{where}: pose last row must be 0 0 0 1, got {T[3].tolist()}")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise DataError(f"{where}: pose rotation is not orthonormal (|R^T R - I| = {err:.2g}, "
                        f"det = {np.linalg.det(R):.3f})")
    return T


def check_depth(depth, where: str, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Validate a depth image in metres: 2-D, real-valued, and ``shape`` (H, W) if given."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise DataError(f"{where}: depth must be a single-channel HxW image, got shape {depth.shape}")
    if not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise DataError(f"{where}: depth has unsupported dtype {depth.dtype}")
    if shape is not None and depth.shape != tuple(shape):
        raise DataError(f"{where}: depth is {depth.shape[1]}x{depth.shape[0]} (WxH) but the "
                        f"intrinsics are for {shape[1]}x{shape[0]}")
    return depth
