"""Which points of a true surface a capture observed (the development suite's split of the
Chamfer distance, tools/suite.py: docs/measurements.md, "Where the suite's Chamfer distance
comes from")."""

from __future__ import annotations

import numpy as np

from ..errors import BftaichiError

__all__ = ["seen_points"]


def seen_points(points: np.ndarray, frames, sigma_m, tol: float = 3.0,
                slack_m: float = 0.001) -> np.ndarray:
    """(n,) bool: the world ``points`` (n, 3) that at least one of ``frames`` observed. A point
    is observed by a frame (``depth_m`` (H, W) metres, 0 invalid; ``K``; ``T_W_C``) when it lies
    in front of the camera, projects to a pixel (nearest) with a valid depth, and that depth is
    within ``tol * sigma_m(depth) + slack_m`` of the point's own camera depth: nothing hid it.
    ``sigma_m``: the frames' axial depth noise (metres) as a function of depth (arrays).
    Vectorised per frame (numpy); deterministic."""
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise BftaichiError(f"points must have shape (n, 3), got {points.shape}")
    seen = np.zeros(len(points), bool)
    for i in range(len(frames)):
        f = frames[i]
        D = np.asarray(f.depth_m, np.float64)
        T = np.asarray(f.T_W_C, np.float64)
        K = np.asarray(f.K, np.float64)
        p_c = (points - T[:3, 3]) @ T[:3, :3]  # world -> camera: R^T (p - t)
        z = p_c[:, 2]
        front = np.flatnonzero(z > 1e-9)
        u = np.round(K[0, 0] * p_c[front, 0] / z[front] + K[0, 2]).astype(np.int64)
        v = np.round(K[1, 1] * p_c[front, 1] / z[front] + K[1, 2]).astype(np.int64)
        keep = (u >= 0) & (u < D.shape[1]) & (v >= 0) & (v < D.shape[0])
        idx, u, v = front[keep], u[keep], v[keep]
        d = D[v, u]
        valid = d > 0
        idx, d = idx[valid], d[valid]
        seen[idx[np.abs(d - z[idx]) <= tol * np.asarray(sigma_m(d)) + slack_m]] = True
    return seen
