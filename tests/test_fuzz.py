"""Fuzzing the input boundary with hypothesis: loaders, the config parser, the TSDF integrator.

The property is the one of :mod:`bftaichi.errors`: whatever a user hands in (any bytes as a
dataset file, any text as a scene file or ``--set``, any depth image, intrinsics and pose),
bftaichi either works (a valid Frame, a valid Config, a finite volume) or raises
:class:`~bftaichi.errors.BftaichiError`: never another exception type, never NaN in the volume.

Every test has explicit, derandomized settings (the same examples on every run, no deadline:
the first Taichi launch compiles). The number of examples per target is the ``N_*`` constant
it uses; ``python -m pytest tests/test_fuzz.py -q --hypothesis-show-statistics`` prints the
examples run, their outcome (hypothesis ``event``: ok / error type) and time per test.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import tempfile
import typing
import warnings
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image

from bftaichi.config import Config, load_config
from bftaichi.formats import open_dataset
from bftaichi.errors import BftaichiError, ConfigError
from bftaichi.stages.integrate import TSDFVolume
from bftaichi.geometry import check_pose, intrinsics, look_at

# Examples per target (pure-Python parsers get many, file-writing targets fewer, the Taichi
# integrator fewest; the whole file runs in well under a minute on one CPU core).
N_LOADER_BYTES = 100  # per (format, file) pair of LOADER_FILES: any bytes / text / mutations
N_DEPTH_PNG = 100  # per format: valid image files of random dtype, shape and values as depth
N_POSE_MATRIX = 150  # per format: random 4x4 matrices (NaN, inf, non-rigid, bad last row)
N_TOML_TEXT = 400  # any text as a scene file
N_OVERRIDE_TEXT = 400  # any text as one --set override
N_CONFIG_VALUES = 400  # random values for every known key of every section
N_TSDF_FRAMES = 120  # random depth / K / pose integrated into one volume

W, H = 8, 6  # fixture image size
FX, FY, CX, CY = 7.0, 6.5, 3.5, 2.5


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])


# --------------------------------------------------------------------------------------------
# Fixture datasets: two frames of each format, written once per session
# --------------------------------------------------------------------------------------------

def _depth_mm(i: int) -> np.ndarray:
    return (1000 + 10 * i + np.arange(W * H).reshape(H, W)).astype(np.uint16)


def _pose(i: int) -> np.ndarray:
    return look_at([1.0 + 0.1 * i, -0.5, 0.8], [0.0, 0.0, 0.0])


def _png(path: Path, a: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(a).save(path)


def _matrix_text(T: np.ndarray) -> str:
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in np.atleast_2d(T)) + "\n"


def _quaternion_xyzw(R: np.ndarray) -> list[float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix (w > 0 branch: the fixture's poses)."""
    w = math.sqrt(max(0.0, 1.0 + np.trace(R))) / 2
    return [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
            (R[1, 0] - R[0, 1]) / (4 * w), w]


def _write_7scenes(root: Path) -> None:
    for i in range(2):
        _png(root / f"frame-{i:06d}.depth.png", _depth_mm(i))
        (root / f"frame-{i:06d}.pose.txt").write_text(_matrix_text(_pose(i)))
    (root / "camera-intrinsics.txt").write_text(_matrix_text(intrinsics(FX, FY, CX, CY)))


def _write_bfsdf(root: Path) -> None:
    for i in range(2):
        _png(root / "depth" / f"{i:06d}.png", _depth_mm(i))
        (root / "pose").mkdir(parents=True, exist_ok=True)
        (root / "pose" / f"{i:06d}.txt").write_text(_matrix_text(_pose(i)))
    (root / "intrinsic").mkdir()
    (root / "intrinsic" / "intrinsic.txt").write_text(f"{W} {H}\n{FX} {FY} {CX} {CY}\n")


def _write_tum(root: Path) -> None:
    depth_rows, gt_rows = ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for i in range(2):
        t = 1000.0 + 0.1 * i
        _png(root / "depth" / f"{t:.6f}.png", (_depth_mm(i).astype(np.uint32) * 5).astype(np.uint16))
        depth_rows.append(f"{t:.6f} depth/{t:.6f}.png")
        T = _pose(i)
        gt_rows.append(" ".join(repr(float(v)) for v in [t, *T[:3, 3], *_quaternion_xyzw(T[:3, :3])]))
    (root / "depth.txt").write_text("\n".join(depth_rows) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_rows) + "\n")
    (root / "camera-intrinsics.txt").write_text(_matrix_text(intrinsics(FX, FY, CX, CY)))


def _write_folder(root: Path) -> None:
    _png(root / "depth" / "000000.png", _depth_mm(0))
    np.save(root / "depth" / "000001.npy", _depth_mm(1).astype(np.float32) / 1000)
    (root / "poses.txt").write_text("".join(_matrix_text(_pose(i).reshape(1, 16)) for i in range(2)))
    (root / "intrinsics.json").write_text(json.dumps({"fx": FX, "fy": FY, "cx": CX, "cy": CY,
                                                      "width": W, "height": H}))


def _write_redwood(root: Path) -> None:
    blocks = []
    for i in range(2):
        _png(root / "depth" / f"{i:06d}.png", _depth_mm(i))
        blocks.append(f"{i} {i} {i + 1}\n" + _matrix_text(_pose(i)))
    (root / "traj.log").write_text("".join(blocks))
    K = intrinsics(FX, FY, CX, CY)
    (root / "camera_intrinsic.json").write_text(json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": K.T.ravel().tolist()}))


def _write_replica(root: Path) -> None:
    for i in range(2):
        _png(root / "results" / f"depth{i:06d}.png", _depth_mm(i))
    (root / "traj.txt").write_text("".join(_matrix_text(_pose(i).reshape(1, 16)) for i in range(2)))
    (root / "cam_params.json").write_text(json.dumps(
        {"camera": {"w": W, "h": H, "fx": FX, "fy": FY, "cx": CX, "cy": CY, "scale": 1000.0}}))


WRITERS = {"7scenes": _write_7scenes, "bfsdf": _write_bfsdf, "tum": _write_tum,
           "folder": _write_folder, "redwood": _write_redwood, "replica": _write_replica}

#: (format, file) pairs whose content is fuzzed: every depth image, pose and intrinsics file kind.
LOADER_FILES = [
    ("7scenes", "frame-000000.depth.png"), ("7scenes", "frame-000001.pose.txt"),
    ("7scenes", "camera-intrinsics.txt"),
    ("bfsdf", "depth/000000.png"), ("bfsdf", "pose/000001.txt"), ("bfsdf", "intrinsic/intrinsic.txt"),
    ("tum", "groundtruth.txt"), ("tum", "depth.txt"), ("tum", "camera-intrinsics.txt"),
    ("folder", "poses.txt"), ("folder", "intrinsics.json"), ("folder", "depth/000001.npy"),
    ("redwood", "traj.log"), ("redwood", "camera_intrinsic.json"),
    ("replica", "traj.txt"), ("replica", "cam_params.json"),
]

#: Where each format keeps frame 0's depth image and frame 0's 4x4 pose (None: not a 4x4 file).
DEPTH_FILE = {"7scenes": "frame-000000.depth.png", "bfsdf": "depth/000000.png",
              "folder": "depth/000000.png", "redwood": "depth/000000.png",
              "replica": "results/depth000000.png"}


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> dict[str, Path]:
    """One valid two-frame dataset per format (the fuzz tests copy it and damage one file)."""
    base = tmp_path_factory.mktemp("fuzz-templates")
    roots = {}
    for fmt, write in WRITERS.items():
        roots[fmt] = base / fmt
        roots[fmt].mkdir()
        write(roots[fmt])
        assert len(_read_all(roots[fmt], fmt)) == 2, fmt  # the undamaged fixture loads
    return roots


def _read_all(root: Path, fmt: str) -> list:
    """Open ``root`` and read every frame; check each Frame. BftaichiError propagates."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = open_dataset(root, format=fmt)
        frames = list(ds)
    for f in frames:
        assert f.depth_m.dtype == np.float32 and f.depth_m.ndim == 2
        assert (f.depth_m.shape[1], f.depth_m.shape[0]) == tuple(ds.image_size)
        assert np.all(np.isfinite(f.depth_m)) and np.all(f.depth_m >= 0)
        assert f.K.shape == (3, 3) and np.all(np.isfinite(f.K)) and f.K[0, 0] > 0 and f.K[1, 1] > 0
        assert f.T_W_C.shape == (4, 4) and f.T_W_C.dtype == np.float64
        check_pose(f.T_W_C, f.name)  # finite and rigid (a DataError here fails the test)
    return frames


def _outcome(fn) -> str:
    """Run ``fn``; return "ok" or the BftaichiError subclass name (any other exception escapes)."""
    try:
        fn()
    except BftaichiError as e:
        return type(e).__name__
    return "ok"


def _load_with(templates, fmt: str, files: dict[str, bytes]) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / fmt
        shutil.copytree(templates[fmt], root)
        for rel, data in files.items():
            (root / rel).write_bytes(data)
        outcome = _outcome(lambda: _read_all(root, fmt))
    event(f"{fmt}: {outcome}")
    return outcome


# --------------------------------------------------------------------------------------------
# Loaders: any bytes
# --------------------------------------------------------------------------------------------

_NUMBER_WORDS = ["nan", "-nan", "inf", "-inf", "1e309", "-0", "0", "1", "0x10", "1_0", "١",
                 "1e-320", "9" * 40, "", " ", "\n", "#", "null", "[]", "{}", "true", '"1"', "1,"]


@st.composite
def _mutated(draw, original: bytes) -> bytes:
    """``original`` with a few edits: truncated, bytes replaced, tokens swapped for odd numbers."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["truncate", "byte", "token", "insert"]))
        if kind == "truncate":
            data = data[: draw(st.integers(0, len(data)))]
        elif kind == "byte" and data:
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        elif kind == "token":
            tokens = bytes(data).split(b" ")
            if tokens:
                k = draw(st.integers(0, len(tokens) - 1))
                tokens[k] = draw(st.sampled_from(_NUMBER_WORDS)).encode()
                data = bytearray(b" ".join(tokens))
        else:
            at = draw(st.integers(0, len(data)))
            data[at:at] = draw(st.binary(max_size=16))
    return bytes(data)


_MAGIC = [b"\x89PNG\r\n\x1a\n", b"\x93NUMPY\x01\x00", b"PK\x03\x04", b"\x1f\x8b", b"II*\x00",
          b"\xff\xd8\xff", b"\x80\x04"]  # PNG, npy, zip (npz), gzip, TIFF, JPEG, pickle


def _any_bytes(original: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(max_size=300),
        st.tuples(st.sampled_from(_MAGIC), st.binary(max_size=100)).map(b"".join),
        st.text(max_size=200).map(lambda s: s.encode("utf-8", "surrogatepass")),
        st.lists(st.sampled_from(_NUMBER_WORDS), max_size=20).map(lambda t: " ".join(t).encode()),
        _mutated(original),
    )


@pytest.mark.parametrize("fmt, rel", LOADER_FILES, ids=[f"{f}:{r}" for f, r in LOADER_FILES])
@_settings(N_LOADER_BYTES)
@given(data=st.data())
def test_any_bytes_in_a_dataset_file_load_or_raise_bftaichi_error(templates, fmt, rel, data):
    payload = data.draw(_any_bytes((templates[fmt] / rel).read_bytes()), label="file content")
    # frames that pass every check, or a DataError naming the file (anything else escapes and
    # fails: a traceback from deep inside is what this guards against)
    assert _load_with(templates, fmt, {rel: payload}) in ("ok", "DataError")


# --------------------------------------------------------------------------------------------
# Loaders: valid image files of any dtype / shape / values as depth
# --------------------------------------------------------------------------------------------

_IMAGE_DTYPES = [np.uint8, np.uint16, np.int16, np.int32, np.float32, np.bool_]


@st.composite
def _image_file(draw) -> bytes:
    """Bytes of a valid image of random content: PNG, or TIFF for the signed 32-bit integer and
    float modes Pillow cannot write as PNG (the loaders open files by content, not name)."""
    dtype = np.dtype(draw(st.sampled_from(_IMAGE_DTYPES)))
    h, w = draw(st.one_of(st.just((H, W)), st.tuples(st.integers(1, 12), st.integers(1, 12))))
    channels = draw(st.sampled_from([None, None, 2, 3, 4])) if dtype == np.uint8 else None
    shape = (h, w) if channels is None else (h, w, channels)
    a = draw(hnp.arrays(dtype, shape, elements=hnp.from_dtype(dtype, allow_nan=True,
                                                              allow_infinity=True)))
    fmt = "PNG" if dtype in (np.uint8, np.uint16, np.bool_) else "TIFF"
    buf = tempfile.SpooledTemporaryFile()
    Image.fromarray(a).save(buf, format=fmt)
    buf.seek(0)
    return buf.read()


@pytest.mark.parametrize("fmt", sorted(DEPTH_FILE))
@_settings(N_DEPTH_PNG)
@given(image=_image_file())
def test_any_valid_image_as_depth_loads_or_raises_bftaichi_error(templates, fmt, image):
    _load_with(templates, fmt, {DEPTH_FILE[fmt]: image})


# --------------------------------------------------------------------------------------------
# Loaders: random 4x4 matrices as poses
# --------------------------------------------------------------------------------------------

_any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def _rotation(draw) -> np.ndarray:
    q = np.array(draw(st.tuples(*[st.floats(-1, 1)] * 4)))
    n = np.linalg.norm(q)
    if n < 1e-3:
        return np.eye(3)
    x, y, z, w = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@st.composite
def _rigid(draw, max_translation_m: float = 3.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = draw(_rotation())
    T[:3, 3] = draw(st.tuples(*[st.floats(-max_translation_m, max_translation_m)] * 3))
    return T


@st.composite
def _matrix(draw) -> np.ndarray:
    """A 4x4 matrix: rigid, or rigid and damaged (NaN/inf entry, scaled, reflected, bad last
    row, tiny perturbation), or all random floats."""
    kind = draw(st.sampled_from(["rigid", "entry", "scale", "reflect", "last_row", "perturb",
                                 "random"]))
    if kind == "random":
        return np.array(draw(st.lists(_any_float, min_size=16, max_size=16))).reshape(4, 4)
    T = draw(_rigid(max_translation_m=1e3))
    if kind == "entry":
        T[draw(st.integers(0, 3)), draw(st.integers(0, 3))] = draw(_any_float)
    elif kind == "scale":
        T[:3, :3] *= draw(st.floats(0, 10))
    elif kind == "reflect":
        T[:3, 0] *= -1
    elif kind == "last_row":
        T[3] = draw(st.lists(_any_float, min_size=4, max_size=4))
    elif kind == "perturb":
        T[:3, :3] += draw(hnp.arrays(np.float64, (3, 3), elements=st.floats(-2e-3, 2e-3)))
    event(f"pose kind: {kind}")
    return T


def _pose_files(fmt: str, T: np.ndarray) -> dict[str, bytes]:
    """The files of ``fmt`` that hold frame 1's pose, rewritten with the matrix ``T``."""
    if fmt == "7scenes":
        return {"frame-000001.pose.txt": _matrix_text(T).encode()}
    if fmt == "bfsdf":
        return {"pose/000001.txt": _matrix_text(T).encode()}
    if fmt in ("folder", "replica"):
        rows = [_pose(0).reshape(1, 16), T.reshape(1, 16)]
        if fmt == "folder":
            return {"poses.txt": "".join(_matrix_text(r) for r in rows).encode()}
        return {"traj.txt": "".join(_matrix_text(r) for r in rows).encode()}
    assert fmt == "redwood"
    text = "0 0 1\n" + _matrix_text(_pose(0)) + "1 1 2\n" + _matrix_text(T)
    return {"traj.log": text.encode()}


@pytest.mark.parametrize("fmt", ["7scenes", "bfsdf", "folder", "replica", "redwood"])
@_settings(N_POSE_MATRIX)
@given(T=_matrix())
def test_any_matrix_as_pose_loads_as_a_rigid_pose_or_raises(templates, fmt, T):
    outcome = _load_with(templates, fmt, _pose_files(fmt, T))
    if outcome == "ok":  # accepted: it was a rigid transform (within check_pose's tolerance)
        assert np.all(np.isfinite(T)) and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6)
        assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-2


@st.composite
def _tum_pose_row(draw) -> list[float]:
    t = draw(st.tuples(*[st.one_of(st.floats(-10, 10), _any_float)] * 3))
    q = draw(st.one_of(st.tuples(*[st.floats(-1, 1)] * 4), st.tuples(*[_any_float] * 4)))
    if draw(st.booleans()):
        n = math.sqrt(sum(v * v for v in q)) if all(math.isfinite(v) for v in q) else 0
        if 1e-6 < n < 1e150:
            q = tuple(v / n for v in q)
    return [*t, *q]


@_settings(N_POSE_MATRIX)
@given(row=_tum_pose_row())
def test_any_quaternion_pose_in_tum_groundtruth_loads_or_raises(templates, row):
    first = (templates["tum"] / "groundtruth.txt").read_text().splitlines()[:2]
    text = "\n".join(first + [" ".join(repr(v) for v in [1000.1, *row])]) + "\n"
    _load_with(templates, "tum", {"groundtruth.txt": text.encode()})


# --------------------------------------------------------------------------------------------
# Config parser
# --------------------------------------------------------------------------------------------

def _section_fields() -> dict[str, dict[str, typing.Any]]:
    """{section: {key: type}} of every known key (from the dataclasses, so new keys are fuzzed)."""
    out = {}
    for f in dataclasses.fields(Config):
        section_type = typing.get_type_hints(Config)[f.name]
        out[f.name] = typing.get_type_hints(section_type)
    return out


SECTIONS = _section_fields()
KEYS = [(s, k) for s, keys in SECTIONS.items() for k in keys]


def _load_config_outcome(path=None, overrides=()) -> str:
    """load_config's outcome, "ok" or "ConfigError" (anything else fails the test); an accepted
    Config has a finite value in every float field (NaN would reach the kernels)."""
    try:
        cfg = load_config(path, overrides)
    except ConfigError:
        event("ConfigError")
        return "ConfigError"
    assert isinstance(cfg, Config)
    for section, keys in SECTIONS.items():
        for key, typ in keys.items():
            value = getattr(getattr(cfg, section), key)
            if typ is float or typ == list[float]:
                assert all(math.isfinite(v) for v in np.atleast_1d(value)), f"{section}.{key} = {value}"
    event("ok")
    return "ok"


_SCENE_TEXT = (Path(__file__).resolve().parents[1] / "scenes" / "bunny.toml").read_bytes()
_text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=300)


@_settings(N_TOML_TEXT)
@given(data=st.one_of(_text.map(str.encode), st.binary(max_size=300), _mutated(_SCENE_TEXT)))
def test_any_text_as_a_scene_file_gives_config_or_config_error(data):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.toml"
        path.write_bytes(data)
        assert _load_config_outcome(path) in ("ok", "ConfigError")


_key_text = st.one_of(st.sampled_from([f"{s}.{k}" for s, k in KEYS]), _text)


@_settings(N_OVERRIDE_TEXT)
@given(text=st.one_of(_text,
                      st.tuples(_key_text, st.sampled_from(["=", " = ", "=="]), _text).map("".join),
                      st.tuples(_key_text, st.sampled_from(_NUMBER_WORDS)).map("=".join)))
def test_any_override_gives_config_or_config_error(text):
    assert _load_config_outcome(None, [text]) in ("ok", "ConfigError")


_toml_str = st.one_of(
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=20),
    st.sampled_from(["", "auto", "sphere", "dataset", "synthetic", "0:10:2", "folder", "T_C_W",
                     "file", "none", "all", "pixel", "cpu", "tsdf_only", "y", "spiral"]))
_toml_scalar = st.one_of(
    st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    _toml_str, st.sampled_from([0, 1, 2, 6, 26, -1, 0.5, 1e-4, 1e9, 100000, 16385]),
)
_toml_value = st.one_of(_toml_scalar, st.lists(_toml_scalar, max_size=5),
                        st.lists(st.lists(_toml_scalar, max_size=2), max_size=2),
                        st.dictionaries(st.text(max_size=3), _toml_scalar, max_size=2))
_typed = {int: st.integers(-10, 10**6), bool: st.booleans(), str: _toml_str, float: st.floats(allow_nan=True, allow_infinity=True),
    list[float]: st.lists(st.floats(-10, 100), max_size=5)}


@st.composite
def _entry(draw) -> tuple[str, str, typing.Any]:
    """(section, key, value): mostly a value of the key's own type, else anything."""
    section, key = draw(st.sampled_from(KEYS))
    typed = _typed[SECTIONS[section][key]]
    return section, key, draw(st.one_of(typed, typed, typed, _toml_value))


@_settings(N_CONFIG_VALUES)
@given(entries=st.lists(_entry(), min_size=1, max_size=4))
def test_random_values_for_every_key_give_config_or_config_error(entries):
    data: dict[str, dict] = {}
    for section, key, value in entries:
        data.setdefault(section, {})[key] = value
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.toml"
        path.write_text(tomli_w.dumps(data))
        assert _load_config_outcome(path) in ("ok", "ConfigError")


def test_every_key_round_trips_its_default_through_an_override():
    """Sanity of the fuzzing above: the default of every key, given back as ``--set``, loads."""
    cfg = Config()
    for section, key in KEYS:
        value = getattr(getattr(cfg, section), key)
        text = tomli_w.dumps({"v": value}).split("=", 1)[1].strip()
        assert getattr(getattr(load_config(None, [f"{section}.{key}={text}"]), section), key) == value


# --------------------------------------------------------------------------------------------
# TSDF integrator
# --------------------------------------------------------------------------------------------

_special_depth = st.sampled_from([0.0, -0.0, -1.0, float("nan"), float("inf"), float("-inf"),
                                  1e30, -1e30, 1e-30, 0.5, 1.0, 2.0, 5.99, 6.0, 6.01, 100.0])


@st.composite
def _depth_image(draw) -> np.ndarray:
    h, w = draw(st.integers(1, 24)), draw(st.integers(1, 32))
    dtype = draw(st.sampled_from([np.float32, np.float64, np.uint16, np.int32]))
    if dtype in (np.uint16, np.int32):
        return draw(hnp.arrays(dtype, (h, w)))
    base = draw(st.floats(0.2, 5.0))
    noise = draw(hnp.arrays(np.float64, (h, w), elements=st.floats(-0.3, 0.3)))
    depth = (base + noise).astype(dtype)
    # sprinkle special values
    for _ in range(draw(st.integers(0, 8))):
        depth[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = draw(_special_depth)
    if draw(st.booleans()):
        elements = st.one_of(_special_depth, hnp.from_dtype(np.dtype(dtype)))
        depth = draw(hnp.arrays(dtype, (h, w), elements=elements))
    return depth


@st.composite
def _camera(draw, shape) -> np.ndarray:
    h, w = shape
    if draw(st.integers(0, 9)) == 0:  # sometimes an arbitrary matrix
        return np.array(draw(st.lists(_any_float, min_size=9, max_size=9))).reshape(3, 3)
    f = draw(st.one_of(st.floats(1.0, 200.0), st.floats(1.0, 200.0), st.floats(1e-6, 1e6),
                       st.sampled_from([0.0, -5.0])))
    fy = f * draw(st.floats(0.5, 2.0))
    cx = draw(st.one_of(st.just(0.5 * (w - 1)), st.floats(-100, 100)))
    cy = draw(st.one_of(st.just(0.5 * (h - 1)), st.floats(-100, 100)))
    return intrinsics(f, fy, cx, cy)


@pytest.fixture(scope="module")
def volume():
    """One small volume for all examples (allocating Taichi fields is slow): 5 cm voxels."""
    return TSDFVolume(voxel_size_m=0.05, trunc_m=0.1)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # 1e300 -> inf: dropped
@_settings(N_TSDF_FRAMES)
@given(data=st.data())
def test_random_frames_integrate_or_raise_and_the_volume_stays_finite(volume, data):
    depth = data.draw(_depth_image(), label="depth")
    K = data.draw(_camera(depth.shape), label="K")
    T = data.draw(st.one_of(_rigid(), _rigid(), _matrix()), label="T_W_C")
    outcome = _outcome(lambda: volume.integrate(depth, K, T, name="fuzz"))
    event(f"integrate: {outcome}")
    v = volume.export()
    assert v["tsdf"].dtype == np.float32 and v["weight"].dtype == np.float32
    assert np.all(np.isfinite(v["tsdf"])) and np.all(np.isfinite(v["weight"]))
    assert np.all(v["weight"] > 0)  # export lists observed voxels only
    assert np.all(np.abs(v["tsdf"]) <= volume.trunc_m * (1 + 1e-6))


def test_the_fuzzed_volume_still_integrates_a_plain_frame(volume):
    """After the fuzzing above (same module-scoped volume), a plane 1 m ahead still updates voxels
    and the volume stays finite: the rejected and odd frames left it usable. The camera sits at
    the volume's origin, which the first fuzzed frame chose (its grid is local to that frame,
    bftaichi.geometry.local_origin; a frame farther than the map reaches is refused)."""
    T = np.eye(4)
    T[:3, 3] = volume.origin
    updates = volume.integrate(np.full((24, 32), 1.0, np.float32), intrinsics(30, 30, 15.5, 11.5),
                               T, name="plane")
    v = volume.export()
    assert updates > 0 and len(v["ijk"]) > 0
    assert np.all(np.isfinite(v["tsdf"])) and np.all(v["weight"] > 0)
