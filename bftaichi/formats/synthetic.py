"""Synthetic depth scenes with ground truth, rendered from a mesh.

A synthetic scene is a mesh (a built-in primitive or a mesh file), a camera trajectory around it,
a pinhole camera and a depth-noise model, all set by :class:`~bftaichi.config.SyntheticConfig`.
:class:`SyntheticDataset` renders its frames lazily and behaves like the recorded-data loaders
(DESIGN.md section 5): each item is a :class:`~bftaichi.frame.Frame` with depth in metres (0 =
invalid), ``T_W_C`` and ``K``. :func:`write_7scenes` stores any synthetic scene on disk in the
7-Scenes layout plus ``gt_mesh.ply`` so other tools can read it.

Conventions (DESIGN.md section 2): metres; the world is z-up; OpenCV cameras (x right, y down,
z forward); poses are ``T_W_C``; pixel ``(u, v)`` integer coordinates are pixel centres.

Built-in meshes (:data:`PRIMITIVES`), all centred around the origin except the tabletop:

- ``sphere``: radius ``radius_m`` (icosphere, 6 subdivisions: 81920 faces; faceting error
  below 1e-4 * radius, 0.02 mm at 0.3 m).
- ``box``: a cube of half extent ``radius_m`` (edges along the world axes).
- ``cylinder``: radius ``radius_m``, height ``2 * radius_m``, axis along z, 256 sections.
- ``torus``: major radius ``radius_m``, minor radius ``radius_m / 3``, lying in the xy plane.
- ``bowl``: a concave bowl, open at the top: rim radius ``radius_m``, height ``0.6 radius_m``,
  a flat floor of radius ``radius_m / 2``, walls ``0.08 radius_m`` thick (a quarter-ellipse
  profile revolved about z, watertight); its inside is seen only from above the rim.
- ``tabletop``: fixed dimensions, independent of ``radius_m``. A table slab, box
  1.0 x 1.0 x 0.04 m with its top face at z = 0 (x, y in [-0.5, 0.5]), and resting on it (lowest
  point at z = 0 exactly), without touching each other. Faces that no camera above the table can
  see (the slab's underside, the box and cylinder bottoms resting on it) are left out of the
  ground truth, so completeness measures what a scan could reach:

  ======================  ==================================  ============================
  object                  size (m)                            centre (x, y)
  ======================  ==================================  ============================
  sphere                  radius 0.1                          (-0.22, 0.18)
  box (turned 30 deg)     0.20 x 0.15 x 0.12 (x, y, z)        (0.20, 0.20)
  upright cylinder        radius 0.06, height 0.20            (-0.20, -0.20)
  torus lying flat        major 0.08, minor 0.03              (0.20, -0.18)
  ======================  ==================================  ============================

The default camera looks at the origin, the centre of the table top.

- ``clutter``: fixed dimensions, independent of ``radius_m``: a table 0.5 x 0.5 x 0.03 m (top
  at z = 0) with six objects packed on it so that they hide each other from most views (for
  active scanning), without touching: a tall box 0.06 x 0.06 x 0.20 m at the centre, cylinders
  (radius 0.04, height 0.14 at (0.09, 0.03); radius 0.025, height 0.10 at (0.11, -0.10)), a
  sphere (radius 0.05 at (-0.08, 0.06)), a box 0.10 x 0.05 x 0.08 turned 20 deg at
  (0.02, -0.10) and a torus lying flat (0.05 / 0.018 at (-0.11, -0.09)). As for the tabletop,
  the faces resting on the table and its underside are left out.
- ``shelf``: fixed dimensions: an open bookshelf 0.53 m wide, 0.25 m deep and 0.515 m high
  standing on the floor (z = 0) with a back panel on its +y side, three boards (z = 0, 0.25,
  0.5) and five objects on the two lower ones (a box, a cylinder and a sphere below; a torus
  and a box turned 30 deg on the middle board), seen from the front (-y) between the boards.
"""

from __future__ import annotations

import dataclasses
import io
import math
import threading
from pathlib import Path
from typing import Iterator

import numpy as np
import trimesh

from ..config import PRIMITIVES, SyntheticConfig
from ..errors import ConfigError, DataError
from ..evaluation.metrics import check_mesh_file
from ..frame import Frame, clean_depth
from ..geometry import check_K, check_pose, intrinsics, look_at, pixel_rays
from ..io import atomic_write_bytes, ensure_out_dir, write_json, write_mesh_ply

__all__ = [
    "PRIMITIVES",
    "make_mesh",
    "trajectory",
    "intrinsics_of",
    "DepthRenderer",
    "add_noise",
    "SyntheticDataset",
    "write_7scenes",
]

"""Names of the built-in meshes; any other ``synthetic.mesh`` value is a mesh file path."""

# Tessellation: faceting error (sagitta) well below 1 mm at radius 0.3 m.
_ICOSPHERE_SUBDIVISIONS = 6  # max sagitta 7.1e-5 * r (2.1e-5 m at r = 0.3 m)
_CYLINDER_SECTIONS = 256  # sagitta r * (1 - cos(pi / 256)) = 7.5e-5 * r
_TORUS_MAJOR_SECTIONS = 256
_TORUS_MINOR_SECTIONS = 64  # sagitta of the tube 1.2e-3 * minor radius

# Tabletop layout (metres), see the module docstring.
_TABLE_EXTENTS = (1.0, 1.0, 0.04)
_TABLE_OBJECTS = {
    "sphere": {"radius": 0.1, "xy": (-0.22, 0.18)},
    "box": {"extents": (0.20, 0.15, 0.12), "yaw_deg": 30.0, "xy": (0.20, 0.20)},
    "cylinder": {"radius": 0.06, "height": 0.20, "xy": (-0.20, -0.20)},
    "torus": {"major": 0.08, "minor": 0.03, "xy": (0.20, -0.18)},
}


# --------------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------------

def _sphere(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=_ICOSPHERE_SUBDIVISIONS, radius=radius)


def _cylinder(radius: float, height: float) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, height=height, sections=_CYLINDER_SECTIONS)


def _torus(major: float, minor: float) -> trimesh.Trimesh:
    return trimesh.creation.torus(major, minor, major_sections=_TORUS_MAJOR_SECTIONS,
                                  minor_sections=_TORUS_MINOR_SECTIONS)


def _rest_on_table(mesh: trimesh.Trimesh, xy: tuple[float, float]) -> trimesh.Trimesh:
    """Move ``mesh`` so its bounding-box centre is above ``xy`` and its lowest vertex at z = 0."""
    lo, hi = mesh.bounds
    shift = np.array([xy[0] - 0.5 * (lo[0] + hi[0]), xy[1] - 0.5 * (lo[1] + hi[1]), -lo[2]])
    mesh.apply_translation(shift)
    return mesh


def _drop_bottom(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Remove the flat, downward-facing faces at the mesh's lowest z (a face resting on the table,
    or the slab's underside): no camera above the table can see them, so keeping them in the
    ground truth would only cap every method's recall."""
    n = mesh.face_normals
    c = mesh.triangles_center
    bottom = (n[:, 2] < -0.999) & (c[:, 2] < mesh.bounds[0, 2] + 1e-9)
    return trimesh.Trimesh(mesh.vertices, mesh.faces[~bottom], process=False)


def _tabletop() -> trimesh.Trimesh:
    """The tabletop scene of the module docstring, as one concatenated mesh (5 separate parts),
    without the faces that rest on the table or face the floor (see :func:`_drop_bottom`)."""
    slab = trimesh.creation.box(extents=_TABLE_EXTENTS)
    slab.apply_translation([0.0, 0.0, -0.5 * _TABLE_EXTENTS[2]])  # top face at z = 0
    o = _TABLE_OBJECTS
    box = trimesh.creation.box(extents=o["box"]["extents"])
    box.apply_transform(trimesh.transformations.rotation_matrix(
        math.radians(o["box"]["yaw_deg"]), [0.0, 0.0, 1.0]))
    parts = [
        slab,
        _rest_on_table(_sphere(o["sphere"]["radius"]), o["sphere"]["xy"]),
        _rest_on_table(box, o["box"]["xy"]),
        _rest_on_table(_cylinder(o["cylinder"]["radius"], o["cylinder"]["height"]),
                       o["cylinder"]["xy"]),
        _rest_on_table(_torus(o["torus"]["major"], o["torus"]["minor"]), o["torus"]["xy"]),
    ]
    return trimesh.util.concatenate([_drop_bottom(p) for p in parts])


#: The cluttered table (module docstring): (kind, size, centre (x, y), yaw in degrees).
_CLUTTER = (
    ("box", (0.06, 0.06, 0.20), (0.00, 0.00), 0.0),
    ("cylinder", (0.04, 0.14), (0.09, 0.03), 0.0),
    ("sphere", (0.05,), (-0.08, 0.06), 0.0),
    ("box", (0.10, 0.05, 0.08), (0.02, -0.10), 20.0),
    ("torus", (0.05, 0.018), (-0.11, -0.09), 0.0),
    ("cylinder", (0.025, 0.10), (0.11, -0.10), 0.0),
)
_CLUTTER_TABLE = (0.5, 0.5, 0.03)


def _clutter() -> trimesh.Trimesh:
    """The cluttered table of the module docstring: six objects packed on a small table so that
    they hide each other, without touching; the faces resting on the table and the table's
    underside are left out of the ground truth (:func:`_drop_bottom`)."""
    slab = trimesh.creation.box(extents=_CLUTTER_TABLE)
    slab.apply_translation([0.0, 0.0, -0.5 * _CLUTTER_TABLE[2]])
    parts = [slab]
    for kind, size, xy, yaw in _CLUTTER:
        parts.append(_rest_on_table(_object(kind, size, yaw), xy))
    return trimesh.util.concatenate([_drop_bottom(p) for p in parts])


#: The shelf (module docstring): panels as (extents, centre), objects as in _CLUTTER plus the
#: height of the board they stand on.
_SHELF_PANELS = (
    ((0.50, 0.25, 0.015), (0.0, 0.0, 0.0075)),      # bottom board, on the floor
    ((0.50, 0.25, 0.015), (0.0, 0.0, 0.2575)),      # middle board
    ((0.50, 0.25, 0.015), (0.0, 0.0, 0.5075)),      # top
    ((0.015, 0.25, 0.515), (-0.2575, 0.0, 0.2575)),  # sides
    ((0.015, 0.25, 0.515), (0.2575, 0.0, 0.2575)),
    ((0.53, 0.015, 0.515), (0.0, 0.1325, 0.2575)),  # back
)
_SHELF_OBJECTS = (
    ("box", (0.08, 0.06, 0.12), (-0.12, -0.02), 0.0, 0.015),
    ("cylinder", (0.035, 0.15), (0.04, 0.04), 0.0, 0.015),
    ("sphere", (0.045,), (0.15, -0.06), 0.0, 0.015),
    ("torus", (0.05, 0.018), (-0.11, 0.0), 0.0, 0.265),
    ("box", (0.06, 0.10, 0.14), (0.10, 0.02), 30.0, 0.265),
)


def _object(kind: str, size, yaw: float) -> trimesh.Trimesh:
    m = {"box": lambda: trimesh.creation.box(extents=size), "cylinder": lambda: _cylinder(*size),
         "sphere": lambda: _sphere(*size), "torus": lambda: _torus(*size)}[kind]()
    if yaw:
        m.apply_transform(trimesh.transformations.rotation_matrix(math.radians(yaw),
                                                                  [0.0, 0.0, 1.0]))
    return m


def _shelf() -> trimesh.Trimesh:
    """The shelf of the module docstring: an open bookshelf with a back panel standing on the
    floor at z = 0, and five objects on its two lower boards. The faces where panels meet,
    those on the floor and those resting on a board are left out of the ground truth (no view
    can see them)."""
    parts = []
    boxes = [(np.asarray(c) - 0.5 * np.asarray(e), np.asarray(c) + 0.5 * np.asarray(e))
             for e, c in _SHELF_PANELS]
    for k, (extents, centre) in enumerate(_SHELF_PANELS):
        panel = trimesh.creation.box(extents=extents)
        panel.apply_translation(centre)
        panel = panel.subdivide_to_size(0.01)
        # the faces where panels meet are hidden: drop triangles inside another panel's box
        c = panel.triangles_center
        hidden = c[:, 2] < 1e-9  # on the floor
        for j, (lo, hi) in enumerate(boxes):
            if j != k:
                hidden |= np.all((c >= lo - 1e-9) & (c <= hi + 1e-9), axis=1)
        parts.append(trimesh.Trimesh(panel.vertices, panel.faces[~hidden], process=False))
    for kind, size, xy, yaw, base in _SHELF_OBJECTS:
        m = _rest_on_table(_object(kind, size, yaw), xy)
        m.apply_translation([0.0, 0.0, base])
        parts.append(_drop_bottom(m))
    return trimesh.util.concatenate(parts)


def _primitive(name: str, radius_m: float) -> trimesh.Trimesh:
    if name == "sphere":
        return _sphere(radius_m)
    if name == "box":
        return trimesh.creation.box(extents=[2.0 * radius_m] * 3)
    if name == "cylinder":
        return _cylinder(radius_m, 2.0 * radius_m)
    if name == "torus":
        return _torus(radius_m, radius_m / 3.0)
    if name == "bowl":
        return _bowl(radius_m)
    if name == "clutter":
        return _clutter()
    if name == "shelf":
        return _shelf()
    return _tabletop()


def _bowl(radius_m: float, sections: int = 128) -> trimesh.Trimesh:
    """A bowl of rim radius R = ``radius_m`` (module docstring): the profile revolved about z,
    closed (watertight), its bounding box centred at the origin."""
    R, t, h = radius_m, 0.08 * radius_m, 0.6 * radius_m
    a = np.linspace(0.0, 0.5 * np.pi, 33)
    outer = np.stack([0.5 * R + 0.5 * R * np.sin(a), h * (1.0 - np.cos(a))], 1)  # base to rim
    inner = np.stack([0.5 * R - t + 0.5 * R * np.sin(a), t + (h - t) * (1.0 - np.cos(a))],
                     1)[::-1]  # rim to the floor
    profile = np.concatenate([[[0.0, 0.0]], outer, inner, [[0.0, t]]])
    mesh = trimesh.creation.revolve(profile, sections=sections)
    mesh.apply_translation([0.0, 0.0, -0.5 * h])
    return mesh


def _load_mesh_file(path: Path) -> trimesh.Trimesh:
    """Read a mesh file with trimesh; a Scene is concatenated (with its transforms) into one mesh."""
    if not path.is_file():
        raise DataError(f"mesh file {path} does not exist (synthetic.mesh is neither a file nor "
                        f"one of the built-in meshes {', '.join(PRIMITIVES)})")
    try:
        loaded = trimesh.load(str(path))
    except Exception as e:  # noqa: BLE001 - trimesh's many format readers raise many error types
        raise DataError(f"mesh file {path} cannot be read: {type(e).__name__}: {e}") from None
    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            raise DataError(f"mesh file {path} contains no geometry")
        try:
            loaded = loaded.to_mesh()
        except Exception as e:  # noqa: BLE001 - trimesh's concatenation of damaged geometry
            raise DataError(f"mesh file {path} cannot be read: {type(e).__name__}: {e}") from None
    return check_mesh_file(loaded, path, surface=True)


def make_mesh(cfg: SyntheticConfig) -> trimesh.Trimesh:
    """The ground-truth mesh of a synthetic scene (world frame, z-up, metres).

    ``cfg.mesh`` is one of :data:`PRIMITIVES` (sized by ``cfg.radius_m``, see the module docstring;
    ``mesh_up``, ``mesh_scale`` and ``center_mesh`` do not apply to them) or a mesh file path. A
    mesh file is rotated by ``cfg.mesh_up`` (``y``: +y becomes +z, a +90 deg turn about x), then
    scaled by ``cfg.mesh_scale``, then, with ``cfg.center_mesh``, translated so its bounding-box
    centre is at the origin.

    Raises:
        DataError: the file is missing or unreadable, or its mesh fails
            :func:`~bftaichi.evaluation.metrics.check_mesh_file` with ``surface`` (names the path).
    """
    if cfg.mesh in PRIMITIVES:
        return _primitive(cfg.mesh, float(cfg.radius_m))
    path = Path(cfg.mesh).expanduser()
    mesh = _load_mesh_file(path)
    if cfg.mesh_up == "y":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]))
    if cfg.mesh_scale != 1.0:
        mesh.apply_scale(float(cfg.mesh_scale))
    if cfg.center_mesh:
        mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def trajectory(cfg: SyntheticConfig, target=None) -> np.ndarray:
    """Camera poses ``T_W_C`` (n_views, 4, 4) float64 that all look at ``target`` with up = +z.

    ``target`` defaults to ``cfg.look_at`` (world point, metres). Paths (deterministic):

    - ``ring``: ``n_views`` cameras evenly spaced (first at azimuth 0, i.e. on +x) on a horizontal
      circle of radius ``cam_radius_m``, ``cam_height_m`` above the target. The paper's
      controlled scene is 12 views, radius 1.5 m, height 0.6 m.
    - ``sphere``: a Fibonacci lattice at distance ``cam_radius_m`` from the target (evenly spread
      over the whole sphere, top to bottom).
    - ``hemisphere``: a Fibonacci lattice on the spherical cap of elevations
      ``>= min_elevation_deg`` (even in area), distance ``cam_radius_m``.
    - ``spiral``: heights rising linearly from ``cam_height_m`` to ``cam_height_end_m`` above the
      target over ``turns`` revolutions, horizontal radius ``cam_radius_m``.
    """
    target = np.asarray(cfg.look_at if target is None else target, dtype=np.float64).reshape(3)
    n = int(cfg.n_views)
    k = np.arange(n, dtype=np.float64)
    r = float(cfg.cam_radius_m)
    if cfg.trajectory == "ring":
        az = 2.0 * np.pi * k / n
        offsets = np.stack([r * np.cos(az), r * np.sin(az), np.full(n, float(cfg.cam_height_m))], 1)
    elif cfg.trajectory in ("sphere", "hemisphere"):
        # Fibonacci lattice: z (= sin elevation) evenly spaced over the cap -> equal areas,
        # azimuth advancing by the golden angle.
        z_min = -1.0 if cfg.trajectory == "sphere" else math.sin(math.radians(cfg.min_elevation_deg))
        z = 1.0 - (k + 0.5) / n * (1.0 - z_min)
        az = k * np.pi * (3.0 - math.sqrt(5.0))
        rho = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
        offsets = r * np.stack([rho * np.cos(az), rho * np.sin(az), z], 1)
    elif cfg.trajectory == "spiral":
        t = k / (n - 1) if n > 1 else np.zeros(1)
        az = 2.0 * np.pi * float(cfg.turns) * t
        h = cfg.cam_height_m + (cfg.cam_height_end_m - cfg.cam_height_m) * t
        offsets = np.stack([r * np.cos(az), r * np.sin(az), h], 1)
    else:
        raise ConfigError(f"synthetic.trajectory = {cfg.trajectory!r} is not one of "
                          "ring, sphere, hemisphere, spiral")
    return np.stack([look_at(target + o, target, up=(0.0, 0.0, 1.0)) for o in offsets])


def intrinsics_of(cfg: SyntheticConfig) -> np.ndarray:
    """The 3x3 float64 pinhole matrix K of the synthetic camera (``fx, fy, cx, cy``, pixels)."""
    return intrinsics(cfg.fx, cfg.fy, cfg.cx, cfg.cy)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------

_EMBREE = threading.Lock()  # reader threads' renders take turns; picklable renderers (Ray)


class DepthRenderer:
    """Ray-cast depth images of one triangle mesh (Embree via trimesh, float64 hit depths).

    The Embree scene is built once (on the first render) and reused for every view. Embree finds
    the first triangle along each ray in float32; the depth is then the exact float64
    intersection of the ray with that triangle's plane, so flat faces give constant depth to
    ~1e-12 m.
    """

    def __init__(self, mesh: trimesh.Trimesh):
        """``mesh``: a non-empty triangle mesh in world coordinates (metres). It must not be
        modified while this renderer is in use."""
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise DataError("DepthRenderer needs a non-empty trimesh.Trimesh")
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.mesh = mesh
        self._intersector = RayMeshIntersector(mesh)
        tri = np.asarray(mesh.triangles, dtype=np.float64)  # (F, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        self._plane_normal = np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 0)
        self._plane_point = tri[:, 0].copy()

    def render(self, K: np.ndarray, T_W_C: np.ndarray, width: int, height: int) -> np.ndarray:
        """Depth image (height, width) float32 along the camera z axis, metres; 0 where no hit.

        One ray per pixel centre: pixel ``(u, v)`` (integers) has camera direction
        ``K^-1 [u, v, 1]`` (z component 1, so the ray parameter of a hit is its depth), rotated to
        the world by ``T_W_C[:3, :3]`` and starting at the camera centre ``T_W_C[:3, 3]``.
        """
        K = check_K(K, "DepthRenderer.render")
        T_W_C = check_pose(T_W_C, "DepthRenderer.render", tol=1e-6)
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise DataError(f"DepthRenderer.render: image size {width}x{height} is empty")
        dirs_C = pixel_rays(K, width, height)
        dirs_W = (T_W_C[:3, :3] @ dirs_C).T  # (H*W, 3), camera-z component 1
        origin = T_W_C[:3, 3]
        origins = np.broadcast_to(origin, dirs_W.shape)
        with _EMBREE:  # the scene is built lazily, by whichever thread renders first
            tri = self._intersector.intersects_first(origins, dirs_W)
        depth = np.zeros(width * height, dtype=np.float64)
        hit = np.flatnonzero(tri >= 0)
        if hit.size:
            n = self._plane_normal[tri[hit]]
            d = dirs_W[hit]
            denom = np.einsum("ij,ij->i", n, d)
            num = np.einsum("ij,ij->i", n, self._plane_point[tri[hit]] - origin)
            ok = np.abs(denom) > 1e-12 * np.linalg.norm(d, axis=1)
            t = np.zeros(hit.size)
            t[ok] = num[ok] / denom[ok]
            depth[hit] = np.where(t > 0, t, 0.0)
        return depth.reshape(height, width).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------------

def add_noise(depth_m: np.ndarray, cfg: SyntheticConfig, rng: np.random.Generator) -> np.ndarray:
    """Sensor model applied to a clean depth image (H, W) in metres; returns float32 (H, W).

    Steps, in order:

    1. noise (``cfg.noise``): ``none``; ``gaussian``, ``z + N(0, sigma_m^2)``; ``kinect``, axial
       ``z + N(0, sigma_z(z)^2)`` with ``sigma_z(z) = depth_a_m + depth_b * (z - depth_z0_m)^2``
       (Nguyen et al. 2012);
    2. quantisation to the nearest multiple of ``quantization_m`` (0 = off);
    3. dropout: each valid pixel is set to 0 with probability ``dropout``.

    Pixels that were 0 or non-finite (no hit) are 0 in the result; noisy depth <= 0 becomes 0.
    One standard normal and one uniform are drawn per pixel from ``rng`` (whatever the model), so
    the result depends only on the input, the config and the generator's state.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise DataError(f"add_noise: depth must be an (H, W) image, got shape {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    z = np.where(valid, depth, 0.0)
    gauss = rng.standard_normal(depth.shape)
    uniform = rng.random(depth.shape)
    if cfg.noise == "gaussian":
        z = z + cfg.sigma_m * gauss
    elif cfg.noise == "kinect":
        z = z + cfg.depth_sigma_m(z) * gauss
    elif cfg.noise != "none":
        raise ConfigError(f"synthetic.noise = {cfg.noise!r} is not one of none, gaussian, kinect")
    if cfg.quantization_m > 0:
        z = np.round(z / cfg.quantization_m) * cfg.quantization_m
    keep = valid & (z > 0) & (uniform >= cfg.dropout)
    return np.where(keep, z, 0.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------

class SyntheticDataset:
    """Frames rendered lazily from ``cfg`` (a :class:`~bftaichi.config.SyntheticConfig`).

    Frame ``i`` is the mesh rendered at ``poses[i]``, passed through :func:`add_noise` with the
    generator ``np.random.default_rng([cfg.seed, i])`` and then through
    :func:`bftaichi.frame.clean_depth` with ``[depth_min_m, depth_max_m]``. It is identical
    however many times and in whatever order it is requested.

    Attributes:
        cfg: the configuration (validated).
        K: (3, 3) float64 intrinsics. image_size: (width, height) pixels.
        poses: (n, 4, 4) float64 ``T_W_C``. gt_mesh: ground-truth trimesh (world, metres).
        name: ``"synthetic:<cfg.mesh>"``. gt_mesh_path: None (the mesh lives in memory).
    """

    CACHE_BYTES = 256 * 2 ** 20
    """Rendered frames kept in memory (the first ones, up to this many bytes of depth)."""

    def __init__(self, cfg: SyntheticConfig, depth_min_m: float = 0.1, depth_max_m: float = 6.0):
        cfg.check()
        if cfg.seed < 0:
            raise ConfigError(f"synthetic.seed = {cfg.seed} must be >= 0")
        if not (0 <= depth_min_m < depth_max_m):
            raise ConfigError(f"depth limits [{depth_min_m}, {depth_max_m}] m are not an interval "
                              "0 <= depth_min_m < depth_max_m")
        self.cfg = cfg
        self.depth_min_m = float(depth_min_m)
        self.depth_max_m = float(depth_max_m)
        self.K = intrinsics_of(cfg)
        self.image_size = (int(cfg.width), int(cfg.height))
        self.poses = trajectory(cfg)
        self.gt_mesh = make_mesh(cfg)
        self.gt_mesh_path = None
        self.name = f"synthetic:{cfg.mesh}"
        self._renderer = DepthRenderer(self.gt_mesh)
        # a run reads every frame several times (memory estimate, checks, TSDF, observation,
        # misfit and noise-fit passes): keep the rendered frames up to CACHE_BYTES
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.poses)

    def _index(self, i: int) -> int:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        j = int(i) + n if i < 0 else int(i)
        if not 0 <= j < n:
            raise IndexError(f"{self.name}: frame {i} is out of range (0..{n - 1})")
        return j

    def _render(self, i: int) -> np.ndarray:
        width, height = self.image_size
        return self._renderer.render(self.K, self.poses[i], width, height)

    def clean_depth(self, i: int) -> np.ndarray:
        """Noise-free depth of view ``i``: (H, W) float32 metres, 0 where no surface or outside
        ``[depth_min_m, depth_max_m]``."""
        i = self._index(i)
        return clean_depth(self._render(i), self.depth_min_m, self.depth_max_m)

    def __getitem__(self, i: int) -> Frame:
        i = self._index(i)
        depth = self._cache.get(i)
        if depth is None:
            rng = np.random.default_rng([self.cfg.seed, i])
            depth = clean_depth(add_noise(self._render(i), self.cfg, rng), self.depth_min_m,
                                self.depth_max_m)
            if (len(self._cache) + 1) * depth.nbytes <= self.CACHE_BYTES:
                self._cache[i] = depth
        return Frame(index=i, name=f"frame-{i:06d}", depth_m=depth.copy(),
                     K=self.K.copy(), T_W_C=self.poses[i].copy(), rgb=None)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------

def _matrix_text(M: np.ndarray) -> bytes:
    """Rows of whitespace-separated numbers, 15 significant digits."""
    return "".join(" ".join(f"{x:.15g}" for x in row) + "\n" for row in np.asarray(M)).encode()


def _png16(depth_m: np.ndarray) -> bytes:
    """uint16 millimetre PNG of a depth image in metres (0 = invalid; beyond 65.534 m -> 0)."""
    from PIL import Image

    mm = np.rint(np.nan_to_num(np.asarray(depth_m, np.float64), nan=0.0, posinf=0.0) * 1000.0)
    mm = np.where((mm > 0) & (mm < 65535), mm, 0).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(mm).save(buf, format="PNG")
    return buf.getvalue()


def write_7scenes(dataset: SyntheticDataset, out_dir, progress: bool = False) -> Path:
    """Write ``dataset`` to ``out_dir`` in the 7-Scenes layout; return the folder.

    Files (each written atomically):

    - ``frame-000000.depth.png`` (6-digit frame number): uint16 depth in millimetres (rounded), 0 = invalid;
    - ``frame-000000.pose.txt``: 4x4 ``T_W_C`` (metres, OpenCV camera), 15 significant digits;
    - ``camera-intrinsics.txt``: 3x3 K;
    - ``gt_mesh.ply``: the ground-truth mesh (binary PLY, :func:`bftaichi.io.write_mesh_ply`);
    - ``scene.json``: width, height, n_frames, depth limits and the SyntheticConfig (provenance).

    ``progress`` shows a tqdm bar. Raises BftaichiError naming ``out_dir`` if it cannot be created.
    """
    from tqdm import tqdm

    out = ensure_out_dir(out_dir)
    width, height = dataset.image_size
    atomic_write_bytes(out / "camera-intrinsics.txt", _matrix_text(dataset.K))
    for i in tqdm(range(len(dataset)), desc=f"writing {out}", unit="frame", disable=not progress):
        frame = dataset[i]
        atomic_write_bytes(out / f"{frame.name}.depth.png", _png16(frame.depth_m))
        atomic_write_bytes(out / f"{frame.name}.pose.txt", _matrix_text(frame.T_W_C))
    mesh = dataset.gt_mesh
    write_mesh_ply(out / "gt_mesh.ply", mesh.vertices, mesh.faces)
    cfg = getattr(dataset, "cfg", None)
    write_json(out / "scene.json", {
        "format": "7scenes",
        "name": dataset.name,
        "width": int(width),
        "height": int(height),
        "n_frames": len(dataset),
        "depth_scale": 1000.0,
        "depth_min_m": getattr(dataset, "depth_min_m", None),
        "depth_max_m": getattr(dataset, "depth_max_m", None),
        "synthetic": dataclasses.asdict(cfg) if cfg is not None else None,
    })
    return out
