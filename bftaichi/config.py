"""Run configuration: typed dataclasses, one per TOML section of a scene file.

A run is a scene file plus overrides. Precedence (highest first):

1. ``--set section.key=value`` on the command line (value parsed as a TOML value; a bare word is a
   string, so ``--set synthetic.mesh=sphere`` works without quotes);
2. the scene file (``scenes/*.toml``);
3. the defaults below. The defaults *are* the built-in default scene (a tabletop seen by a
   Kinect-like camera), so ``bftaichi run`` with no scene file needs nothing from disk.

Unknown sections or keys, wrong types and out-of-range values raise :class:`ConfigError` naming
the key. Relative paths in a scene file are resolved against the scene file's folder; ``$VARS``
and ``~`` are expanded. The resolved configuration is saved as ``config.toml`` next to the outputs.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import os
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

from .checks import (MAX_SEED, check_choice, check_finite, check_range, coerce as _coerce,
                     parse_override, parse_slice)
from .errors import ConfigError, DataError
from .geometry import check_field_of_view, intrinsics
from .stages.band import BandConfig
from .stages.integrate import TSDFConfig
from .stages.observe import ObservationConfig
from .stages.prior import PriorConfig
from .stages.solve import SolverConfig
from .running.settings import RunConfig
from .stages.surface import MeshConfig

__all__ = [
    "Config",
    "SceneConfig",
    "SyntheticConfig",
    "TSDFConfig",
    "MeshConfig",
    "EvalConfig",
    "BandConfig",
    "ObservationConfig",
    "PriorConfig",
    "SolverConfig",
    "RunConfig",
    "NBVConfig",
    "load_config",
]

MAX_DEPTH_M = 1000.0
"""The farthest depth a scene may keep (``scene.depth_max_m``): beyond the range of any depth
camera or lidar range image; larger values are a unit mistake."""


@dataclass
class SceneConfig:
    """``[scene]``: where the frames come from."""

    name: str = "default"
    """Scene name, used for the default output folder ``out/<name>`` and in reports."""

    source: str = "synthetic"
    """``synthetic`` (render frames from a mesh, section ``[synthetic]``, with ground truth) or
    ``dataset`` (read recorded frames from ``data``)."""

    data: str = ""
    """Dataset folder for ``source = "dataset"``; relative paths are relative to the scene file."""

    format: str = "auto"
    """Dataset layout: ``auto`` (detect), ``7scenes`` (also 3DMatch and ``seq-XX/`` folders),
    ``bfsdf``, ``tum``, ``replica`` (NICE-SLAM export), ``scannet`` (SensReader export), ``co3d``,
    ``redwood`` (Open3D ``.log``) or ``folder`` (generic); see :mod:`bftaichi.formats`."""

    frames: str = ""
    """Python-style slice of the frames to use, e.g. ``"0:100:2"``; empty = all frames."""

    gt_mesh: str = ""
    """Optional ground-truth mesh for metrics on a dataset (``synth`` writes ``gt_mesh.ply``;
    ``auto`` finds that file in the dataset folder). Synthetic scenes always have one."""

    depth_min_m: float = 0.1
    """Depth below this (metres) is invalid and dropped per pixel (sensor near limit)."""

    depth_max_m: float = 6.0
    """Depth above this (metres) is invalid and dropped per pixel. 6 m keeps Kinect-class sensors'
    far, noisy returns out of the map."""

    depth_scale: float = 0.0
    """Stored depth units per metre; 0 = the format's own (1000 for millimetre PNGs, 5000 for
    ``tum``, 6553.5 for ``replica``, 1 for ``.npy`` depth of the ``folder`` format)."""

    pose_convention: str = "T_W_C"
    """What the ``folder`` format's pose files hold: ``T_W_C`` (camera-to-world) or ``T_C_W``
    (world-to-camera, inverted on load). The other formats have a fixed convention."""

    def check(self) -> None:
        check_choice("scene.source", self.source, ("synthetic", "dataset"))
        from .formats import FORMATS, POSE_CONVENTIONS

        check_choice("scene.format", self.format, ("auto", *FORMATS))
        check_range("scene.depth_scale", self.depth_scale, 0.0)
        check_choice("scene.pose_convention", self.pose_convention, POSE_CONVENTIONS)
        if self.pose_convention != "T_W_C" and self.format not in ("auto", "folder"):
            raise ConfigError(f"scene.pose_convention = {self.pose_convention!r} applies to the folder "
                              f"format only; scene.format = {self.format!r} has T_W_C poses")
        check_range("scene.depth_min_m", self.depth_min_m, 0.0)
        check_range("scene.depth_max_m", self.depth_max_m, self.depth_min_m, MAX_DEPTH_M,
                    lo_open=True)
        if self.source == "dataset" and not self.data:
            raise ConfigError("scene.data is empty but scene.source = 'dataset': give the dataset folder")
        if self.frames:
            parse_slice(self.frames, "scene.frames")


PRIMITIVES = ("sphere", "box", "cylinder", "torus", "bowl", "tabletop", "clutter", "shelf")
"""The built-in meshes ``synthetic.mesh`` names (:mod:`bftaichi.formats.synthetic` builds them);
any other value is a mesh file path."""


@dataclass
class SyntheticConfig:
    """``[synthetic]``: a scene rendered from a mesh, with ground truth."""

    mesh: str = "tabletop"
    """Built-in primitive (``sphere``, ``box``, ``cylinder``, ``torus``, ``tabletop``) or a mesh
    file path (OBJ/PLY/STL/OFF/GLB, anything trimesh reads)."""

    mesh_up: str = "z"
    """Which axis of the mesh file points up; ``y`` rotates a y-up mesh (e.g. the Stanford bunny)
    so that +y becomes +z. The world is z-up."""

    mesh_scale: float = 1.0
    """Uniform scale applied to the mesh (after ``mesh_up``)."""

    center_mesh: bool = False
    """Translate a mesh file so its bounding-box centre is at the origin (primitives are already
    placed around the origin)."""

    radius_m: float = 0.3
    """Size of ``sphere``/``cylinder`` primitives (radius) and ``torus`` major radius, metres;
    ``box`` has half-extent ``radius_m`` (the tabletop has fixed, documented dimensions)."""

    trajectory: str = "ring"
    """Camera path: ``ring`` (the paper's: a horizontal circle at ``cam_height_m``), ``sphere`` or
    ``hemisphere`` (Fibonacci points), ``spiral`` (rising from ``cam_height_m`` to
    ``cam_height_end_m`` over ``turns``)."""

    n_views: int = 24
    """Number of camera poses."""

    cam_radius_m: float = 1.2
    """Distance of the cameras from the look-at point (ring/spiral: horizontal radius)."""

    cam_height_m: float = 0.7
    """Camera height above the look-at point for ``ring`` and start of ``spiral``, metres."""

    cam_height_end_m: float = 1.0
    """Final camera height of ``spiral``, metres."""

    turns: float = 2.0
    """Number of revolutions of ``spiral``."""

    min_elevation_deg: float = 10.0
    """Lowest elevation of ``hemisphere`` views (0 = horizon); keeps cameras above a table."""

    look_at: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    """World point every camera looks at (z-up world)."""

    width: int = 320
    """Image width, pixels."""

    height: int = 240
    """Image height, pixels."""

    fx: float = 262.5
    """Focal length x, pixels (Kinect v1 at 320x240)."""

    fy: float = 262.5
    """Focal length y, pixels."""

    cx: float = 159.5
    """Principal point x, pixels (OpenCV convention: pixel centres at integers)."""

    cy: float = 119.5
    """Principal point y, pixels."""

    noise: str = "kinect"
    """Depth noise model: ``none``, ``gaussian`` (``sigma_m``), or ``kinect`` (axial
    ``sigma_z(z) = depth_a_m + depth_b * (z - depth_z0_m)^2``)."""

    sigma_m: float = 0.002
    """Standard deviation of the ``gaussian`` model, metres."""

    depth_a_m: float = 0.0012
    """``kinect`` axial noise ``sigma_z(z) = a + b (z - z0)^2`` (Nguyen et al. 2012): constant
    term ``a``, metres. The same names as the model the posterior assumes, ``[observation]``."""

    depth_b: float = 0.0019
    """``kinect`` noise quadratic term ``b``, 1/metre."""

    depth_z0_m: float = 0.4
    """``kinect`` noise reference depth ``z0``, metres."""

    quantization_m: float = 0.001
    """Depth quantisation step, metres (0 = none). 0.001 mimics depth stored in millimetres."""

    dropout: float = 0.0
    """Fraction of valid pixels dropped at random (set to invalid)."""

    seed: int = 0
    """Seed (>= 0) of the noise and dropout; frame ``i`` draws from ``default_rng([seed, i])``, so a
    frame is the same whatever order frames are requested in."""

    def depth_sigma_m(self, z):
        """The depth noise the frames get at depth ``z`` (metres, float or array; the same
        shape back): ``sigma_m`` (``gaussian``), ``depth_a_m + depth_b (z - depth_z0_m)^2``
        (``kinect``), 0 (``none``)."""
        if self.noise == "kinect":
            return self.depth_a_m + self.depth_b * (z - self.depth_z0_m) ** 2
        return (self.sigma_m if self.noise == "gaussian" else 0.0) + 0.0 * z

    def check(self) -> None:
        check_choice("synthetic.mesh_up", self.mesh_up, ("z", "y"))
        check_range("synthetic.mesh_scale", self.mesh_scale, 0.0, lo_open=True)
        check_range("synthetic.radius_m", self.radius_m, 0.0, lo_open=True)
        check_choice("synthetic.trajectory", self.trajectory, ("ring", "sphere", "hemisphere", "spiral"))
        check_range("synthetic.n_views", self.n_views, 1, 100000)
        check_range("synthetic.cam_radius_m", self.cam_radius_m, 0.0, lo_open=True)
        check_range("synthetic.turns", self.turns, 0.0)
        check_range("synthetic.min_elevation_deg", self.min_elevation_deg, -90.0, 89.0)
        if len(self.look_at) != 3:
            raise ConfigError(f"synthetic.look_at must have 3 numbers, got {self.look_at!r}")
        check_range("synthetic.width", self.width, 2, 16384)
        check_range("synthetic.height", self.height, 2, 16384)
        for key in ("fx", "fy"):
            check_range(f"synthetic.{key}", getattr(self, key), 0.0, lo_open=True)
        check_range("synthetic.cx", self.cx, 0.0, self.width - 1)
        check_range("synthetic.cy", self.cy, 0.0, self.height - 1)
        try:
            check_field_of_view(intrinsics(self.fx, self.fy, self.cx, self.cy),
                                (self.height, self.width), "synthetic.fx / synthetic.fy")
        except DataError as e:
            raise ConfigError(str(e)) from None
        check_choice("synthetic.noise", self.noise, ("none", "gaussian", "kinect"))
        check_range("synthetic.sigma_m", self.sigma_m, 0.0)
        check_range("synthetic.depth_a_m", self.depth_a_m, 0.0)
        check_range("synthetic.depth_b", self.depth_b, 0.0)
        check_range("synthetic.quantization_m", self.quantization_m, 0.0, 1.0)
        check_range("synthetic.dropout", self.dropout, 0.0, 0.99)
        check_range("synthetic.seed", self.seed, 0, MAX_SEED)


@dataclass
class EvalConfig:
    """``[eval]``: geometry metrics against a ground-truth mesh (DESIGN.md section 6)."""

    thresholds_mm: list[float] = field(default_factory=lambda: [5.0, 10.0, 20.0, 50.0])
    """Distance thresholds of precision / recall / F-score, millimetres."""

    n_samples: int = 200000
    """Points sampled (area-weighted) on each surface; more = finer, slower."""

    seed: int = 0
    """Seed of the surface sampling, so metrics are reproducible."""

    near_voxels: float = 1.0
    """Uncertainty metrics (coverage, Spearman, AUSE) are taken over the observed band voxels
    whose true signed distance is at most this many voxels: the voxels that place the surface."""

    vertex_sigma: str = "sigma"
    """The vertex property of ``mesh.ply`` that report.json's ``uncertainty`` judges against
    the exact vertex errors: ``sigma`` (the posterior std of the SDF at the vertex) or
    ``sigma_pos`` (``sigma / |grad mean|``, the std of the zero crossing of the posterior's
    samples along the normal). Over the development suite ``sigma`` is the calibrated one
    (``python tools/suite.py --set eval.vertex_sigma=sigma_pos``; docs/measurements.md)."""

    def check(self) -> None:
        check_range("eval.near_voxels", self.near_voxels, 0.0, 100.0, lo_open=True)
        check_choice("eval.vertex_sigma", self.vertex_sigma, ("sigma", "sigma_pos"))
        if not self.thresholds_mm:
            raise ConfigError("eval.thresholds_mm is empty")
        for t in self.thresholds_mm:
            check_range("eval.thresholds_mm", float(t), 0.0, lo_open=True)
        check_range("eval.n_samples", self.n_samples, 100, 50_000_000)
        check_range("eval.seed", self.seed, 0, MAX_SEED)


@dataclass
class NBVConfig:
    """``[nbv]``: next-best-view planning (DESIGN.md 3.8) and the closed-loop ``bftaichi scan``.

    Candidates look at ``target`` from ``radius_m``; each is scored by the expected reduction of
    the posterior variance its depth image would bring (:mod:`bftaichi.planning.nbv`)."""

    enabled: bool = False
    """``bftaichi run`` ranks the candidates at the end of the run and writes ``nbv.json``."""

    candidates: str = "hemisphere"
    """``sphere`` / ``hemisphere`` (Fibonacci points between ``min_elevation_deg`` and
    ``max_elevation_deg``; ``hemisphere`` starts at 10 deg above the horizon unless
    ``min_elevation_deg`` says otherwise), ``ring`` (a horizontal circle at ``height_m``),
    ``rings`` (one circle per height of ``heights_m``, the candidates split evenly, alternate
    rings turned by half a step: where a robot's camera can reach) or ``file``
    (``poses_file``)."""

    n_candidates: int = 48
    """Number of generated candidate views."""

    radius_m: float = 0.0
    """Distance of the candidates from ``target``, metres; 0 = ``radius_scale`` times the radius
    of the band's bounding sphere (``bftaichi scan``: the scene's ``synthetic.cam_radius_m``)."""

    radius_scale: float = 3.0
    """See ``radius_m``."""

    min_elevation_deg: float = -90.0
    """Lowest candidate elevation above the target, degrees (``hemisphere``: at least 10)."""

    max_elevation_deg: float = 80.0
    """Highest candidate elevation, degrees (straight down views are rarely reachable)."""

    height_m: float = 0.0
    """Height of the ``ring`` above the target, metres."""

    heights_m: list[float] = field(default_factory=list)
    """Heights of the ``rings`` above the target, metres."""

    target: list[float] = field(default_factory=list)
    """World point the candidates look at; empty = the centre of the band's bounding box
    (``bftaichi scan``: ``synthetic.look_at``)."""

    poses_file: str = ""
    """``candidates = "file"``: a text file with one 4x4 ``T_W_C`` per line (16 numbers, row
    major) or a folder of ``*.txt`` files holding one 4x4 matrix each."""

    stride: int = 0
    """Pixel stride of a candidate's predicted depth image and hypothetical observations;
    0 = ``observation.stride``. A larger stride is faster; the information is scaled by
    ``(stride / observation.stride)^2`` so utilities stay comparable."""

    rerank: int = 0
    """0 (default): every candidate is scored at the full ``stride``. ``k > 0``: all of them are
    first screened at twice the stride (four times fewer rays), and only the ``k`` best of the
    screen are scored again at the full stride and ranked first (the other candidates keep the
    screen's utility, with ``stride`` saying so). Ranks 48 candidates 2.1-2.9x faster at
    ``k = 4``, but picks other views: the shelf scene's mean recall over a scan fell from
    0.775 to 0.761 (docs/measurements.md, "Screening the candidates")."""

    eps_voxels: float = 1.0
    """``Omega_eps``: the utility sums over voxels with ``|mu| <= eps_voxels * voxel``."""

    coverage_cells: int = 96
    """Cells along the longest side of the coverage grid (seen / unknown space) over the region
    of interest; the cell is never smaller than a voxel."""

    miss_as_free: bool = True
    """A pixel without depth marks its ray as seen free space (up to ``scene.depth_max_m``):
    right for synthetic scenes and for sensors whose missing returns are sky or far range;
    set false for sensors with many dropouts on near surfaces."""

    roi_scale: float = 1.5
    """Region of interest: a cube around the band's bounding box centre whose side is this times
    the box's longest side (``bftaichi scan``: around ``target``, side ``2 * radius / roi_scale``
    capped by the scene)."""

    steps: int = 12
    """``bftaichi scan``: views added after the initial ones."""

    initial_views: int = 2
    """``bftaichi scan``: views every policy starts from (the same for every policy)."""

    random_seeds: int = 3
    """``bftaichi scan``: the ``random`` policy's result is the mean over this many seeds."""

    initial_seeds: int = 3
    """``bftaichi scan``: the scan is repeated from this many draws of the initial views
    (seeds ``run.seed`` + 0, 1, ...); summaries give the mean and std over them."""

    def check(self) -> None:
        check_choice("nbv.candidates", self.candidates,
                     ("sphere", "hemisphere", "ring", "rings", "file"))
        if self.candidates == "rings" and not 0 < len(self.heights_m) <= self.n_candidates:
            raise ConfigError("nbv.candidates = 'rings' needs nbv.heights_m: 1 to "
                              f"nbv.n_candidates heights, got {self.heights_m}")
        check_range("nbv.n_candidates", self.n_candidates, 1, 100_000)
        check_range("nbv.radius_m", self.radius_m, 0.0)
        check_range("nbv.radius_scale", self.radius_scale, 0.1, 1000.0)
        check_range("nbv.min_elevation_deg", self.min_elevation_deg, -90.0, 90.0)
        check_range("nbv.max_elevation_deg", self.max_elevation_deg, -90.0, 90.0)
        if self.min_elevation_deg > self.max_elevation_deg:
            raise ConfigError(f"nbv.min_elevation_deg = {self.min_elevation_deg} is above "
                              f"nbv.max_elevation_deg = {self.max_elevation_deg}")
        if self.target and len(self.target) != 3:
            raise ConfigError(f"nbv.target must be empty or [x, y, z], got {self.target}")
        if self.candidates == "file" and not self.poses_file:
            raise ConfigError("nbv.candidates = 'file' needs nbv.poses_file")
        if self.candidates == "file" and not Path(self.poses_file).expanduser().exists():
            raise ConfigError(f"nbv.poses_file = {self.poses_file!r} does not exist")
        check_range("nbv.stride", self.stride, 0, 64)
        check_range("nbv.rerank", self.rerank, 0, 100_000)
        check_range("nbv.eps_voxels", self.eps_voxels, 0.0, 100.0, lo_open=True)
        check_range("nbv.coverage_cells", self.coverage_cells, 8, 512)
        check_range("nbv.roi_scale", self.roi_scale, 0.1, 100.0)
        check_range("nbv.steps", self.steps, 1, 1000)
        check_range("nbv.initial_views", self.initial_views, 1, 1000)
        check_range("nbv.random_seeds", self.random_seeds, 1, 100)
        check_range("nbv.initial_seeds", self.initial_seeds, 1, 100)


@dataclass
class Config:
    """The whole configuration of a run; one attribute per TOML section."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    tsdf: TSDFConfig = field(default_factory=TSDFConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    band: BandConfig = field(default_factory=BandConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    nbv: NBVConfig = field(default_factory=NBVConfig)
    run: RunConfig = field(default_factory=RunConfig)

    def check(self) -> "Config":
        """Validate every section; raise ConfigError naming the first bad key."""
        for f in dataclasses.fields(self):
            check_finite(f.name, getattr(self, f.name))
            getattr(self, f.name).check()
        if self.mesh.min_weight > self.tsdf.max_weight:  # weights never exceed the cap
            raise ConfigError(f"mesh.min_weight = {self.mesh.min_weight} is above tsdf.max_weight "
                              f"= {self.tsdf.max_weight}: no voxel could ever be meshed")
        return self

    @classmethod
    def from_toml(cls, path: str | os.PathLike, overrides: typing.Sequence[str] = ()) -> "Config":
        """Load a scene file, apply ``section.key=value`` overrides, resolve paths, validate."""
        return load_config(path, overrides)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _field_types(obj) -> dict[str, typing.Any]:
    return typing.get_type_hints(type(obj))


RENAMED = {
    "synthetic.kinect_a": "renamed to synthetic.depth_a_m (metres)",
    "synthetic.kinect_b": "renamed to synthetic.depth_b (1/metre)",
    "synthetic.kinect_z0": "renamed to synthetic.depth_z0_m (metres)",
    "run.memory_budget": "split into run.memory_fraction (0 to 1 of the available RAM) and "
                         "run.memory_budget_gib (GiB)",
    "prior.outer": "removed: the outer-band anchor measured worse than none; the free-space "
                   "constraint prior.free covers the voxels it was for",
}
"""Keys of earlier versions: ``section.key`` -> what became of it (the error a user sees)."""


def _unknown(kind: str, name: str, known: typing.Iterable[str]) -> ConfigError:
    known = sorted(known)
    close = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigError(f"unknown {kind} {name!r}{hint}; known: {', '.join(known)}")


def _set(cfg: Config, section: str, key: str, value) -> None:
    sections = {f.name for f in dataclasses.fields(cfg)}
    if section not in sections:
        raise _unknown("section", section, sections)
    sub = getattr(cfg, section)
    types = _field_types(sub)
    if f"{section}.{key}" in RENAMED:
        raise ConfigError(f"{section}.{key} was {RENAMED[f'{section}.{key}']}")
    if key not in types:
        raise _unknown(f"key in [{section}]", key, types)
    setattr(sub, key, _coerce(f"{section}.{key}", value, types[key]))


def apply_dict(cfg: Config, data: dict, origin: str = "") -> Config:
    """Apply a nested ``{section: {key: value}}`` mapping (a parsed scene file) to ``cfg``."""
    where = f" in {origin}" if origin else ""
    for section, table in data.items():
        if not isinstance(table, dict):
            raise ConfigError(f"top-level key {section!r}{where} must be a [section] table")
        for key, value in table.items():
            try:
                _set(cfg, section, key, value)
            except ConfigError as e:
                raise ConfigError(f"{e}{where}") from None
    return cfg


def _resolve_path(p: str, base: Path) -> str:
    if not p or p in ("auto",):
        return p
    expanded = os.path.expanduser(os.path.expandvars(p))
    path = Path(expanded)
    if not path.is_absolute():
        path = base / path
    return str(path.resolve()) if path.exists() else str(path)


def resolve_paths(cfg: Config, base: Path) -> Config:
    """Make data / mesh paths absolute against ``base`` (the scene file's folder)."""
    cfg.scene.data = _resolve_path(cfg.scene.data, base)
    cfg.scene.gt_mesh = _resolve_path(cfg.scene.gt_mesh, base)
    cfg.nbv.poses_file = _resolve_path(cfg.nbv.poses_file, base)
    if cfg.synthetic.mesh not in PRIMITIVES:
        cfg.synthetic.mesh = _resolve_path(cfg.synthetic.mesh, base)
    return cfg


def load_config(path: str | os.PathLike | None = None, overrides: typing.Sequence[str] = ()) -> Config:
    """Defaults, then the scene file ``path`` (if any), then ``overrides``; validated.

    Raises ConfigError for a missing or malformed scene file, unknown keys and bad values; a
    bad value of the scene file itself (not of an override) is reported with the file's name.
    """
    cfg = Config()
    base = Path.cwd()
    from_file = None
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"scene file {path} does not exist")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"scene file {path} is not valid TOML: {e}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(f"scene file {path} cannot be read: {e}") from None
        apply_dict(cfg, data, origin=str(path))
        resolve_paths(cfg, path.resolve().parent)
        from_file = copy.deepcopy(cfg)
    sections = {f.name for f in dataclasses.fields(cfg)}
    for text in overrides:
        section, key, value = parse_override(text)
        if (section in sections and _field_types(getattr(cfg, section)).get(key) is str
                and not isinstance(value, str)):
            # A text field takes the text as written: --set scene.frames=100, scene.name=2024.
            value = text.split("=", 1)[1].strip()
        _set(cfg, section, key, value)
    resolve_paths(cfg, Path.cwd())
    try:
        return cfg.check()
    except ConfigError as e:
        if from_file is not None and _check_error(from_file) == str(e):
            raise ConfigError(f"{e} in {path}") from None  # the file's value, not an override's
        raise


def _check_error(cfg: Config) -> str | None:
    """The message of ``cfg.check()``'s ConfigError, or None if it passes."""
    try:
        cfg.check()
    except ConfigError as e:
        return str(e)
    return None


def save_config(cfg: Config, path: str | os.PathLike) -> None:
    """Write the resolved configuration as TOML (atomically)."""
    import tomli_w

    from .io import atomic_write_bytes

    atomic_write_bytes(path, tomli_w.dumps(cfg.to_dict()).encode())
