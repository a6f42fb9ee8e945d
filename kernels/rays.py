"""Ray geometry shared by the ray casting (:mod:`kernels.raycast`) and the next-best-view
coverage grid (:mod:`kernels.coverage`): the per-view parameter vector, the ray of a pixel in
grid coordinates, the clip to a box, and the checks of cameras and images at the boundary.

Pixel ``(u, v)`` (integers at pixel centres) has the camera
ray ``K^-1 (u, v, 1)``, whose z component is 1: the ray parameter is the camera depth ``z``
(metres along the camera z axis, not along the ray). In a world-aligned grid of cells with edge
``s`` metres whose cell 0 starts at the world point ``origin``, the ray point at depth ``z`` has
grid coordinate ``g(z) = o + z m`` with ``m = R_WC K^-1 (u, v, 1) / s`` and
``o = (t_WC - origin) / s`` (:func:`ray_params`, :func:`ray_grid`); it lies in cell
``floor(g)``. A step of ``l`` grid units along the ray is ``l / |m|`` of camera depth.

All functions here are pure reads (deterministic).
"""

import math

import numpy as np
import taichi as ti

P_M = 0  # 9: m-matrix M = R_WC K^-1 / s, row-major: ray direction m = M (u, v, 1), grid units
P_O = 9  # 3: o = (t_WC - origin) / s, the camera centre in grid coordinates
N_RAY_PARAMS = 12  # slots of the ray geometry; a user of the vector may append its own
NO_FACE = 1e300  # "no face ahead" depth of an axis the ray does not move along


# -- ray geometry -----------------------------------------------------------------------------

@ti.func
def ray_grid(prm: ti.template(), u: ti.i32, v: ti.i32):
    """Ray direction ``m = M (u, v, 1)`` (float64, grid units per metre of camera depth)."""
    p = ti.Vector([ti.cast(u, ti.f64), ti.cast(v, ti.f64), 1.0])
    return ti.Vector([prm[P_M + 3 * r] * p[0] + prm[P_M + 3 * r + 1] * p[1] + prm[P_M + 3 * r + 2]
                      for r in ti.static(range(3))])


@ti.func
def ray_origin(prm: ti.template()):
    """Camera centre ``o`` in grid coordinates (float64)."""
    return ti.Vector([prm[P_O], prm[P_O + 1], prm[P_O + 2]])


@ti.func
def clip_to_box(o, m, lo, hi, z_in: ti.f64, z_out: ti.f64):
    """The part ``(z_in', z_out')`` of the depth interval [z_in, z_out] where the ray
    ``g(z) = o + z m`` is inside the grid box ``lo <= g <= hi`` (slab test); empty when
    ``z_in' >= z_out'``."""
    for a in ti.static(range(3)):
        if m[a] != 0:
            t0 = (lo[a] - o[a]) / m[a]
            t1 = (hi[a] - o[a]) / m[a]
            z_in = ti.max(z_in, ti.min(t0, t1))
            z_out = ti.min(z_out, ti.max(t0, t1))
        elif o[a] < lo[a] or o[a] >= hi[a]:
            z_out = -NO_FACE  # parallel to the slab and outside it
    return z_in, z_out


# -- Python side: validation at the boundary --------------------------------------------------

def check_positive(name: str, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} = {value} must be a positive finite number")
    return value


def check_stride(stride) -> int:
    if isinstance(stride, bool) or int(stride) != stride or stride < 1:
        raise ValueError(f"stride = {stride} must be a positive integer")
    return int(stride)


def check_camera(K, T_W_C) -> tuple[np.ndarray, np.ndarray]:
    """Check an OpenCV pinhole K (3, 3) and a rigid T_W_C (4, 4); return both as float64."""
    K = np.asarray(K, np.float64)
    T = np.asarray(T_W_C, np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or K[1, 0] != 0 or \
            not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                         f"got {K.tolist()}")
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_W_C must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]) or \
            np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise ValueError("T_W_C must be a rigid transform (rotation R_WC, last row 0 0 0 1)")
    return K, T


def ray_params(K: np.ndarray, T_W_C: np.ndarray, origin, cell: float,
               n_params: int = N_RAY_PARAMS) -> np.ndarray:
    """The float64 parameter vector (n_params,) of the ray geometry: M = R_WC K^-1 / cell,
    o = (t_WC - origin) / cell (module docstring); slots from N_RAY_PARAMS on are 0."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    K_inv = np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])
    prm = np.zeros(n_params, np.float64)
    prm[P_M:P_M + 9] = (T_W_C[:3, :3] @ K_inv / cell).ravel()
    prm[P_O:P_O + 3] = (T_W_C[:3, 3] - np.asarray(origin, np.float64)) / cell
    return prm


def depth_image(name: str, image) -> np.ndarray:
    """(H, W) float32 depth image, metres, with every invalid pixel (NaN, inf, <= 0) set to 0."""
    image = np.asarray(image)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"{name} must be a non-empty (H, W) image, got shape {image.shape}")
    if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, got dtype {image.dtype}")
    image = image.astype(np.float32)
    return np.where(np.isfinite(image) & (image > 0), image, np.float32(0))
