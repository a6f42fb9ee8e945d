"""Camera geometry and input checks shared by datasets, synthetic scenes and the integrator.

Conventions (DESIGN.md section 2): metres; OpenCV pinhole camera (x right, y down, z forward);
``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; poses are ``T_W_C`` (camera-to-world, 4x4), so a
camera point maps to the world as ``p_W = T_W_C @ p_C``.
"""

from __future__ import annotations

import numpy as np

from kernels.layout import BLOCK, MAP_BLOCKS

from .errors import DataError

__all__ = ["intrinsics", "look_at", "pixel_rays", "check_K", "check_pose", "check_depth",
           "MAP_VOXELS", "LOCAL_ORIGIN_VOXELS", "local_origin", "pose_in_local", "points_in_local",
           "points_in_world", "mesh_in_local"]

#: Voxels per axis of the TSDF's block map (:data:`kernels.layout.MAP_BLOCKS` blocks of 8): the
#: grid holds ``MAP_VOXELS * voxel_size`` metres per axis (81.92 m at 1 cm voxels, 409.6 m at
#: 5 cm), centred on its origin.
MAP_VOXELS = MAP_BLOCKS * BLOCK

#: A first camera farther than this many voxels from the world origin along some axis moves the
#: grid to a local origin next to it (:func:`local_origin`): a quarter of the map's half-range,
#: 10.24 m at 1 cm voxels, 51.2 m at 5 cm. A scene near the world origin keeps the world as its
#: grid (and its outputs, byte for byte) with three quarters of the half-range to spare.
LOCAL_ORIGIN_VOXELS = MAP_VOXELS // 8


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


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(3, height * width) float64 ``K^-1 [u, v, 1]`` of every pixel centre, row by row, z = 1.

    For a pinhole ``K`` whose last row is exactly (0, 0, 1) by the diagonal's reciprocals,
    ``(u - cx) * (1 / fx)``: the bits ``np.linalg.solve(K, .)`` gives (its triangular solve
    multiplies by them; docs/experiments/render_rays.py), ~15x faster; otherwise solved."""
    u, v = (a.ravel() for a in np.meshgrid(np.arange(width, dtype=np.float64),
                                           np.arange(height, dtype=np.float64)))
    if np.array_equal(K[2], [0.0, 0.0, 1.0]):
        return np.stack([(u - K[0, 2]) * (1.0 / K[0, 0]), (v - K[1, 2]) * (1.0 / K[1, 1]),
                         np.ones(u.size)])
    rays = np.linalg.solve(K, np.stack([u, v, np.ones(u.size)]))
    return rays / rays[2]


MAX_FIELD_OF_VIEW_DEG = 170.0
"""The widest field of view (per axis) a pinhole camera is taken to have: wider is a focal
length in the wrong unit (a fisheye must be undistorted to a narrower pinhole first)."""


def check_field_of_view(K, image_size_hw, where: str) -> None:
    """DataError unless the pinhole ``K`` sees at most :data:`MAX_FIELD_OF_VIEW_DEG` across an
    image of ``(H, W)`` pixels on each axis (e.g. fx = 1 for a 640-pixel-wide image: 179.8°)."""
    K = np.asarray(K, dtype=np.float64)
    h, w = image_size_hw
    # the angle between the rays through the image's two edges on each axis
    fov = [np.degrees(np.arctan((n - c) / f) + np.arctan(c / f))
           for f, c, n in ((K[0, 0], K[0, 2], w), (K[1, 1], K[1, 2], h))]
    if max(fov) > MAX_FIELD_OF_VIEW_DEG:
        raise DataError(f"{where}: the intrinsics (fx={K[0, 0]:g}, fy={K[1, 1]:g}) give a "
                        f"{max(fov):.1f} degree field of view across the {w}x{h} image (at most "
                        f"{MAX_FIELD_OF_VIEW_DEG:g}): the focal lengths must be in pixels")


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


# -- the local frame ---------------------------------------------------------------------------
# The sparse TSDF holds MAP_VOXELS voxels per axis around its grid's origin, and every kernel
# computes in float32 (ulp 0.5 m at 5,000 km): a georeferenced scene (UTM) or a long trajectory
# is built in a *local* frame L, the world translated by ``origin`` (float64, metres):
# ``p_W = origin + p_L``. Poses move into it in float64 before anything is cast to float32.


def local_origin(camera_centre, voxel_size_m: float) -> np.ndarray:
    """The origin (3,) float64, metres, world frame) of the grid of a scene whose first camera
    is at ``camera_centre``: zeros when the camera is within :data:`LOCAL_ORIGIN_VOXELS` voxels
    of the world origin along every axis, else the integer multiple of the block edge
    (``8 voxel_size_m``) nearest the camera, so the local voxel lattice is the world's."""
    c = np.asarray(camera_centre, np.float64).reshape(3)
    if np.abs(c).max() <= LOCAL_ORIGIN_VOXELS * voxel_size_m:
        return np.zeros(3)
    block_m = BLOCK * voxel_size_m
    return np.round(c / block_m) * block_m


def pose_in_local(T_W_C, origin) -> np.ndarray:
    """``T_L_C`` (4, 4) float64: the pose ``T_W_C`` in the local frame of ``origin`` (its
    translation minus ``origin``, in float64). ``T_W_C`` itself when ``origin`` is zero."""
    if not np.any(origin):
        return T_W_C
    T = np.array(T_W_C, np.float64)
    T[:3, 3] -= origin
    return T


def nearest_rigid(T) -> np.ndarray:
    """A (4, 4) float64 copy of pose ``T`` whose rotation is the nearest orthonormal matrix
    (``U V^T`` of its SVD). Recorded poses are rigid to ~1e-4; the mesh renderer
    (:class:`bftaichi.formats.synthetic.DepthRenderer`) wants 1e-6."""
    T = np.array(T, np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T


def points_in_local(points_W, origin) -> np.ndarray:
    """World points (..., 3) in the local frame of ``origin`` (float64); ``points_W`` itself
    when ``origin`` is zero."""
    if not np.any(origin):
        return points_W
    return np.asarray(points_W, np.float64) - origin


def points_in_world(points_L, origin) -> np.ndarray:
    """Local points (..., 3) (e.g. float32 mesh vertices) in the world frame, float64:
    ``origin + points_L``; ``points_L`` itself when ``origin`` is zero."""
    if not np.any(origin):
        return points_L
    return origin + np.asarray(points_L, np.float64)


def mesh_in_local(mesh, origin):
    """A ``trimesh.Trimesh`` in world coordinates moved into the local frame of ``origin`` (a
    new mesh with the same faces); ``mesh`` itself when ``origin`` is zero."""
    if not np.any(origin):
        return mesh
    import trimesh

    return trimesh.Trimesh(points_in_local(mesh.vertices, origin), mesh.faces, process=False)
