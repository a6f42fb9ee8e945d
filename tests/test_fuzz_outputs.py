"""Fuzzing what bftaichi reads back: the files of a run, damaged, and users' mesh files.

The property of :mod:`bftaichi.errors`: every reader of a file bftaichi writes (``band.npz``,
``mesh.ply``, ``tsdf_mesh.ply``, ``report.json``, ``config.toml``, ``nbv.json``) and of a
user's mesh either works or raises :class:`~bftaichi.errors.BftaichiError` whose message names
the file; a command exits 2 with ``error: ...`` naming it. Never another exception type, never a
traceback, and what a reader returns passes its own checks (finite vertices, face indices in
range, arrays of agreeing lengths).

The damage: a truncation at any length, or 1 to 4 bit flips at any position (drawn half of the
time among the bytes where a flip changes the structure: a PLY header, the zip headers and
directory of ``band.npz``). Files that parse but disagree with themselves: ``band.npz``
rewritten with one array dropped, retyped, reshaped, or holding NaN / out-of-range / unsorted
values; PLYs (ascii and binary) of random vertices and faces, and random bytes, as user meshes.
One tiny run (tests/robustness_cases.py ``TINY``, with 4 NBV candidates) is made per session;
every example starts from a fresh copy of its files.

Examples per (file, reader), the ``N_*`` constants (derandomized), and their outcomes in a
run of this whole file (``works`` / ``clear error``). Hypothesis derives the draw from each
test's code, so editing a test, or running another selection, draws other examples and moves
the split; recorded before the assertion helpers were renamed::

    file            reader                             examples          works  clear error
    band.npz        Posterior.load                     N_API        150     15          135
    band.npz        bftaichi view OUT --html F --band  N_VIEW        40      1           39
    band.npz        bftaichi nbv OUT                   N_NBV         12      1           11
    mesh.ply        read_mesh_ply                      N_API        150     30          120
    mesh.ply        load_mesh                          N_API        150     42          108
    mesh.ply        bftaichi view --html               N_VIEW        40      1           39
    mesh.ply        bftaichi eval mesh.ply tsdf_mesh   N_EVAL        40      7           33
    tsdf_mesh.ply   read_mesh_ply                      N_API        150     31          119
    tsdf_mesh.ply   load_mesh                          N_API        150     32          118
    tsdf_mesh.ply   bftaichi view --html               N_VIEW        40      5           35
    tsdf_mesh.ply   bftaichi eval mesh.ply tsdf_mesh   N_EVAL        40      5           35
    report.json     read_report                        N_API        150     30          120
    report.json     bftaichi view --html               N_VIEW        40      6           34
    report.json     bftaichi nbv OUT                   N_NBV         12      1           11
    nbv.json        read_ranking                       N_API        150     17          133
    nbv.json        bftaichi view --html               N_VIEW        40      3           37
    config.toml     load_config                        N_API        150     11          139
    config.toml     bftaichi nbv OUT                   N_NBV         12      1           11
    band arrays     Posterior.load (+ extract_mesh)    N_BAND_ARRAYS 150    52           98
    band arrays     bftaichi view --html --band        N_VIEW        40     17           23
    user PLY        load_mesh                          N_USER_PLY   150     86           64
    user PLY        read_mesh_ply                      N_USER_PLY   150     64           86
    user PLY        make_mesh (synthetic.mesh)         N_USER_PLY   150     22          128
    user PLY        bftaichi eval PRED GT, as PRED     N_EVAL        40     15           25
    user PLY        bftaichi eval PRED GT, as GT       N_EVAL        40      9           31

evalviews and the run's plots read only files their own run has just written, through
Posterior.load, read_mesh_ply and load_mesh, fuzzed above. ``python -m pytest
tests/test_fuzz_outputs.py -q --hypothesis-show-statistics`` prints, per test, the share of
examples that "work" and that give a "clear error" (of all test cases, counting the few that
hypothesis discards). The whole file takes about a minute on one core.
"""

from __future__ import annotations

import io
import json
import math
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement

from bftaichi.cli import main
from bftaichi.config import SyntheticConfig, load_config
from bftaichi.errors import BftaichiError
from bftaichi.evaluation.metrics import load_mesh
from bftaichi.formats.synthetic import make_mesh
from bftaichi.io import read_mesh_ply, write_json, write_npz
from bftaichi.planning.nbv import read_ranking
from bftaichi.posterior import Posterior
from bftaichi.running.report import read_report
from robustness_cases import sets

N_API = 150  # a library reader (milliseconds per example)
N_VIEW = 40  # bftaichi view --html (builds the page: ~20 ms)
N_EVAL = 40  # bftaichi eval (500 samples per surface)
N_NBV = 12  # bftaichi nbv (renders the frames and ranks 4 views: ~0.3 s)
N_BAND_ARRAYS = 150  # band.npz rewritten with inconsistent arrays
N_USER_PLY = 150  # generated PLY files and random bytes as a user's mesh
N_JSON = 100  # random nested values with NaN / inf through write_json

OUTPUTS = ("band.npz", "mesh.ply", "tsdf_mesh.ply", "report.json", "config.toml", "nbv.json")


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow, HealthCheck.data_too_large])


# --------------------------------------------------------------------------------------------
# The run, and fresh copies of its files
# --------------------------------------------------------------------------------------------

class Quiet(dict):
    """A dict that hypothesis prints by its size (a failing example lists the fixtures)."""

    def __repr__(self) -> str:
        return f"<{len(self)} entries: {', '.join(self)}>"


@pytest.fixture(scope="session")
def run_files(tmp_path_factory) -> Quiet:
    """The bytes of each output of one tiny run with NBV (made once per session)."""
    out = tmp_path_factory.mktemp("fuzz-outputs") / "run"
    assert main(["run", "-q", "--out", str(out),
                 *sets("nbv.enabled=true", "nbv.n_candidates=4")]) == 0
    return Quiet({name: (out / name).read_bytes() for name in OUTPUTS})


class Work:
    """A folder holding a copy of the run; :meth:`damage` restores every file and writes one
    damaged file (commands like ``nbv`` rewrite report.json and nbv.json)."""

    def __init__(self, root: Path, files: dict[str, bytes]):
        self.root, self.files = root, files
        self.out = root / "run"

    def __repr__(self) -> str:
        return f"Work({self.root})"

    def damage(self, name: str | None = None, data: bytes = b"") -> Path:
        if self.out.exists():
            shutil.rmtree(self.out)
        self.out.mkdir(parents=True)
        for n, original in self.files.items():
            (self.out / n).write_bytes(data if n == name else original)
        return self.out / (name or "")


@pytest.fixture
def work(tmp_path, run_files) -> Work:
    return Work(tmp_path, run_files)


def _structure(name: str, data: bytes) -> list[int]:
    """Byte positions where a flip changes a file's structure rather than one stored value."""
    if name.endswith(".ply"):
        return list(range(data.index(b"end_header\n") + len(b"end_header\n")))
    if name.endswith(".npz"):
        positions = list(range(data.index(b"PK\x01\x02"), len(data)))  # central directory
        for info in zipfile.ZipFile(io.BytesIO(data)).infolist():  # each member's local header
            positions += range(info.header_offset, info.header_offset + 30 + len(info.filename)
                               + 20)
        return positions
    return list(range(len(data)))  # text: every byte is structure


def damage(name: str, data: bytes) -> st.SearchStrategy[tuple]:
    """A damage to ``data``: ``("truncate", length)`` at any length, or ``("flip", [(byte,
    bit), ...])`` of 1-4 bits anywhere (half of the positions drawn among the structural
    bytes of :func:`_structure`). :func:`apply` makes the damaged bytes."""
    n = len(data)
    position = st.one_of(st.integers(0, n - 1), st.sampled_from(_structure(name, data)))
    return st.one_of(st.tuples(st.just("truncate"), position),
                     st.tuples(st.just("flip"), st.lists(st.tuples(position, st.integers(0, 7)),
                                                         min_size=1, max_size=4)))


def apply(data: bytes, damage_: tuple) -> bytes:
    kind, how = damage_
    if kind == "truncate":
        return data[:how]
    out = bytearray(data)
    for pos, bit in how:
        out[pos] ^= 1 << bit
    return bytes(out)


def damaged_file(work: "Work", name: str, data) -> Path:
    """Restore the run in ``work`` and damage its file ``name`` as hypothesis draws."""
    original = work.files[name]
    return work.damage(name, apply(original, data.draw(damage(name, original), label=name)))


# --------------------------------------------------------------------------------------------
# Outcomes
# --------------------------------------------------------------------------------------------

def _assert_ok_or_clear(fn, path: Path) -> str:
    """Call ``fn``: "works", or "clear error" for a BftaichiError naming ``path`` (any other
    exception escapes and fails the test)."""
    try:
        fn()
    except BftaichiError as e:
        assert str(path) in str(e), f"the error does not name {path}: {e}"
        event(f"clear error ({type(e).__name__})")
        return "clear error"
    event("works")
    return "works"


def _assert_cli_ok_or_clear(argv: list, path: Path, capsys, names_file: bool = True) -> str:
    """Run ``bftaichi argv`` in-process: exit 0 ("works") or exit 2 with ``error: ...`` naming
    ``path`` ("clear error"; ``names_file=False``: any clear error). No traceback either way."""
    capsys.readouterr()
    rc = main([str(a) for a in argv])  # an exception other than BftaichiError escapes main
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if rc == 0:
        event("works")
        return "works"
    assert rc == 2, f"exit code {rc}: {err}"
    assert err.startswith("error: "), err
    if names_file:
        assert str(path) in err, f"the error does not name {path}: {err}"
    event("clear error")
    return "clear error"


def _check_mesh_arrays(vertices, faces):
    """What a mesh reader returns when it works: finite vertices, triangles indexing them."""
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    assert vertices.ndim == 2 and vertices.shape[1] == 3 and np.isfinite(vertices).all()
    assert faces.ndim == 2 and faces.shape[1] == 3
    assert faces.size == 0 or (faces.min() >= 0 and faces.max() < len(vertices))


def _read_ply(path: Path):
    v, f, extra = read_mesh_ply(path)
    _check_mesh_arrays(v, f)
    assert all(len(a) == len(v) for a in extra.values())


def _load_mesh(path: Path):
    mesh = load_mesh(path)
    _check_mesh_arrays(mesh.vertices, mesh.faces)
    assert len(mesh.faces) and math.isfinite(mesh.area)


def _load_posterior(path: Path):
    post = Posterior.load(path)
    n = len(post.ijk)
    assert post.mean.shape == post.var.shape == post.tsdf.shape == post.weight.shape == (n,)
    assert np.isfinite(post.mean).all() and np.isfinite(post.var).all()
    assert post.voxel_size > 0 and math.isfinite(post.voxel_size)
    mesh = post.extract_mesh()  # what the checks at the boundary must make safe
    _check_mesh_arrays(mesh.vertices, mesh.faces)


API_READERS = {
    "band.npz": {"Posterior.load": _load_posterior},
    "mesh.ply": {"read_mesh_ply": _read_ply, "load_mesh": _load_mesh},
    "tsdf_mesh.ply": {"read_mesh_ply": _read_ply, "load_mesh": _load_mesh},
    "report.json": {"read_report": read_report},
    "nbv.json": {"read_ranking": read_ranking},
    "config.toml": {"load_config": load_config},
}
API_CASES = [(f, r) for f, readers in API_READERS.items() for r in readers]


# --------------------------------------------------------------------------------------------
# Damaged run files
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, reader", API_CASES, ids=[f"{f}:{r}" for f, r in API_CASES])
@_settings(N_API)
@given(data=st.data())
def test_a_damaged_output_reads_or_gives_a_clear_error(work, name, reader, data):
    path = damaged_file(work, name, data)
    _assert_ok_or_clear(lambda: API_READERS[name][reader](path), path)


VIEW_FILES = ("band.npz", "mesh.ply", "tsdf_mesh.ply", "report.json", "nbv.json")


@pytest.mark.parametrize("name", VIEW_FILES)
@_settings(N_VIEW)
@given(data=st.data())
def test_view_of_a_damaged_run_writes_the_page_or_gives_a_clear_error(work, capsys, name,
                                                                      data):
    path = damaged_file(work, name, data)
    page = work.root / "page.html"
    argv = ["view", work.out, "--html", page, "--band"]
    if _assert_cli_ok_or_clear(argv, path, capsys) == "works":
        assert "MeshCat.Viewer" in page.read_text()


@pytest.mark.parametrize("name", ("mesh.ply", "tsdf_mesh.ply"))
@_settings(N_EVAL)
@given(data=st.data())
def test_eval_of_a_damaged_mesh_gives_metrics_or_a_clear_error(work, capsys, name, data):
    path = damaged_file(work, name, data)
    _assert_cli_ok_or_clear(["eval", work.out / "mesh.ply", work.out / "tsdf_mesh.ply",
                             "--samples", "500", "--json"], path, capsys)


@pytest.mark.parametrize("name", ("band.npz", "config.toml", "report.json"))
@_settings(N_NBV)
@given(data=st.data())
def test_nbv_of_a_damaged_run_ranks_or_gives_a_clear_error(work, capsys, name, data):
    path = damaged_file(work, name, data)
    names_file = True
    if name == "config.toml":
        # a flip that leaves a valid configuration (another number, another mesh name) is
        # not detectable; what the run then lacks (a mesh file, ...) is a clear error of its own
        try:
            load_config(path)
            names_file = False
        except BftaichiError:
            pass
    if _assert_cli_ok_or_clear(["nbv", work.out, "-q"], path, capsys, names_file) == "works":
        ranking = read_ranking(work.out / "nbv.json")
        assert len(ranking["candidates"]) >= 1


# --------------------------------------------------------------------------------------------
# band.npz that parses but is inconsistent
# --------------------------------------------------------------------------------------------

@st.composite
def _inconsistent_band(draw, arrays: dict) -> dict:
    """The arrays of a band.npz with 1-2 of them dropped, retyped, reshaped or spoiled."""
    arrays = dict(arrays)
    for _ in range(draw(st.integers(1, 2))):
        key = draw(st.sampled_from(sorted(arrays)))
        a = arrays[key]
        kind = draw(st.sampled_from(["drop", "dtype", "shape", "nan", "value", "swap", "text"]))
        if kind == "drop":
            del arrays[key]
        elif kind == "dtype":
            dtype = np.dtype(draw(st.sampled_from(
                [np.float64, np.float16, np.int32, np.int64, np.uint8, np.bool_, np.complex64,
                 "U4"])))
            arrays[key] = a.astype(dtype) if a.dtype.kind != "U" else np.zeros(a.shape, dtype)
        elif kind == "shape":
            arrays[key] = draw(st.sampled_from([
                a.reshape(-1), a[:-1] if a.ndim else a.reshape(1), a[..., None], a.T,
                np.zeros((0,) + a.shape[1:], a.dtype), np.stack([a, a])]))
        elif kind == "nan" and a.size and a.dtype.kind == "f":
            b = a.copy().reshape(-1)
            b[draw(st.integers(0, b.size - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
            arrays[key] = b.reshape(a.shape)
        elif kind == "value" and a.size and a.dtype.kind in "fiu":
            b = a.copy().reshape(-1)
            value = draw(st.sampled_from([0, -1, 2**23, -2**23, 2**31 - 1, 1e30, -1e-3, 1e-30]))
            if b.dtype.kind in "iu":  # what the integer type holds
                value = int(np.clip(value, np.iinfo(b.dtype).min, np.iinfo(b.dtype).max))
            b[draw(st.integers(0, b.size - 1))] = value
            arrays[key] = b.reshape(a.shape)
        elif kind == "swap" and a.ndim and len(a) > 1:  # two rows swapped: unsorted ijk
            i, j = draw(st.integers(0, len(a) - 1)), draw(st.integers(0, len(a) - 1))
            b = a.copy()
            b[[i, j]] = b[[j, i]]
            arrays[key] = b
        elif kind == "text":
            arrays[key] = np.array(draw(st.sampled_from(
                ["", "{}", "[1]", '{"stride": -1}', '{"stride": "x"}', '{"nope": 1}', "nan",
                 json.dumps({"stride": 1.5})])))
    return arrays


@pytest.fixture(scope="module")
def band_arrays(run_files) -> Quiet:
    with np.load(io.BytesIO(run_files["band.npz"])) as z:
        return Quiet({k: z[k] for k in z.files})


@_settings(N_BAND_ARRAYS)
@given(data=st.data())
def test_an_inconsistent_band_loads_or_gives_a_clear_error(band_arrays, work, data):
    path = work.damage("band.npz", b"")
    write_npz(path, **data.draw(_inconsistent_band(band_arrays), label="arrays"))
    _assert_ok_or_clear(lambda: _load_posterior(path), path)


@_settings(N_VIEW)
@given(data=st.data())
def test_view_of_an_inconsistent_band_gives_a_page_or_a_clear_error(band_arrays, work, capsys,
                                                                     data):
    path = work.damage("band.npz", b"")
    write_npz(path, **data.draw(_inconsistent_band(band_arrays), label="arrays"))
    argv = ["view", work.out, "--html", work.root / "page.html", "--band"]
    _assert_cli_ok_or_clear(argv, path, capsys)


# --------------------------------------------------------------------------------------------
# Users' meshes: generated PLYs (ascii, binary) and random bytes
# --------------------------------------------------------------------------------------------

#: What a generated PLY may get wrong (0-2 of them per file; none: a valid triangle mesh).
PLY_SPOILERS = ("coordinate", "index", "face size", "no faces", "no vertices", "property name")


@st.composite
def _ply_bytes(draw) -> bytes:
    """A PLY file of 3-8 random vertices and 1-8 triangles, ascii or either binary byte order,
    float32 / float64 / int32 coordinates and 8-32 bit indices, with 0-2 of
    :data:`PLY_SPOILERS`: a NaN / inf / huge coordinate, an index out of range, a face of
    0-2 or 4-5 vertices, no face element, no vertices, a vertex property other than z."""
    spoil = draw(st.sets(st.sampled_from(PLY_SPOILERS), max_size=2))
    n = 0 if "no vertices" in spoil else draw(st.integers(3, 8))
    vdtype = draw(st.sampled_from(["f4", "f8", "i4"]))
    coords = np.array(draw(st.lists(st.tuples(*[st.floats(-2, 2)] * 3), min_size=n,
                                    max_size=n)), np.float64).reshape(n, 3)
    if vdtype == "i4":
        coords = np.round(coords * 1000)  # millimetres
    if "coordinate" in spoil and n:
        coords[draw(st.integers(0, n - 1)), draw(st.integers(0, 2))] = draw(st.sampled_from(
            [np.nan, np.inf, -np.inf, 1e38, 1e300] if vdtype != "i4" else [2**31 - 1]))
    if vdtype == "f4":  # float32 overflows to inf
        coords = np.where(np.abs(coords) > 3e38, np.copysign(np.inf, coords), coords)
    xyz = ("x", "y", "w") if "property name" in spoil else ("x", "y", "z")
    vert = np.empty(n, dtype=[(a, vdtype) for a in xyz])
    for k, a in enumerate(xyz):
        vert[a] = coords[:, k]
    elements = [PlyElement.describe(vert, "vertex")]
    faces = draw(st.lists(st.lists(st.integers(0, max(n - 1, 0)), min_size=3, max_size=3),
                          min_size=1, max_size=8))
    k = draw(st.integers(0, len(faces) - 1))
    if "index" in spoil:
        faces[k][draw(st.integers(0, 2))] = draw(st.sampled_from([-1, -2, n, n + 1, 2**31 - 1]))
    if "face size" in spoil:
        faces[k] = (faces[k] + [0, 0])[:draw(st.sampled_from([0, 1, 2, 4, 5]))]
    if "no faces" not in spoil:
        idx_type = draw(st.sampled_from(["i4", "u4", "u1", "i2"]))
        lo, hi = np.iinfo(idx_type).min, np.iinfo(idx_type).max
        face = np.empty(len(faces), dtype=[("vertex_indices", "O")])
        face["vertex_indices"] = [np.clip(np.array(f, np.int64), lo, hi).astype(idx_type)
                                  for f in faces]
        elements.append(PlyElement.describe(face, "face", val_types={"vertex_indices": idx_type}))
    kind = draw(st.sampled_from(["ascii", "<", ">"]))
    buf = io.BytesIO()
    PlyData(elements, text=kind == "ascii", byte_order="=" if kind == "ascii" else kind).write(buf)
    return buf.getvalue()


_user_mesh = st.one_of(
    _ply_bytes(), _ply_bytes(), _ply_bytes(),
    st.binary(max_size=200),
    st.tuples(st.sampled_from([b"ply\n", b"ply\nformat ascii 1.0\n",
                               b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"]),
              st.binary(max_size=200)).map(b"".join))


def _make_mesh(path: Path):
    mesh = make_mesh(SyntheticConfig(mesh=str(path)))
    _check_mesh_arrays(mesh.vertices, mesh.faces)


USER_READERS = {"load_mesh": _load_mesh, "read_mesh_ply": _read_ply, "make_mesh": _make_mesh}


@pytest.mark.parametrize("reader", sorted(USER_READERS))
@_settings(N_USER_PLY)
@given(content=_user_mesh)
def test_a_users_mesh_file_reads_or_gives_a_clear_error(tmp_path, reader, content):
    path = tmp_path / "user.ply"
    path.write_bytes(content)
    _assert_ok_or_clear(lambda: USER_READERS[reader](path), path)


@pytest.mark.parametrize("role", ("PRED", "GT"))
@_settings(N_EVAL)
@given(content=_user_mesh)
def test_eval_of_a_users_mesh_gives_metrics_or_a_clear_error(work, capsys, role, content):
    good = work.damage() / "tsdf_mesh.ply"
    path = work.root / "user.ply"
    path.write_bytes(content)
    pred, gt = (path, good) if role == "PRED" else (good, path)
    _assert_cli_ok_or_clear(["eval", pred, gt, "--samples", "300", "--json"], path, capsys)


# --------------------------------------------------------------------------------------------
# JSON written by bftaichi is JSON: non-finite numbers become null
# --------------------------------------------------------------------------------------------

def _strict_json(text: str):
    """json.loads that refuses the NaN / Infinity extensions of Python's json module."""
    def refuse(constant):
        raise AssertionError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


_json_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                         st.floats(width=32).map(np.float32), st.integers(-10**6, 10**6),
                         st.sampled_from([np.float64(np.nan), np.float32(np.inf), np.int64(3)]))
_json_value = st.recursive(st.one_of(_json_number, st.booleans(), st.none(), st.text(max_size=5)),
                           lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                   st.dictionaries(st.text(max_size=4), inner,
                                                                   max_size=4)),
                           max_leaves=12)


def _same_json(written, original) -> bool:
    """``written`` (parsed) is ``original`` with every non-finite float as None."""
    if isinstance(original, dict):
        return (isinstance(written, dict) and written.keys() == original.keys()
                and all(_same_json(written[k], original[k]) for k in original))
    if isinstance(original, (list, tuple)):
        return (isinstance(written, list) and len(written) == len(original)
                and all(_same_json(w, o) for w, o in zip(written, original)))
    if isinstance(original, (float, np.floating)):
        return written is None if not math.isfinite(original) else written == float(original)
    if isinstance(original, np.integer):
        return written == int(original)
    return written == original


@_settings(N_JSON)
@given(value=_json_value)
def test_write_json_writes_strict_json_with_null_for_non_finite_numbers(tmp_path, value):
    write_json(tmp_path / "x.json", {"v": value})
    assert _same_json(_strict_json((tmp_path / "x.json").read_text()), {"v": value})


def test_eval_json_of_a_degenerate_mesh_is_valid_json(tmp_path, run_files, capsys):
    """A zero-area prediction has no distances: the JSON gives null, not Infinity."""
    gt = tmp_path / "gt.ply"
    gt.write_bytes(run_files["tsdf_mesh.ply"])
    flat = tmp_path / "flat.ply"
    flat.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 0\n0 0 0\n0 0 0\n3 0 1 2\n")
    capsys.readouterr()
    assert main(["eval", str(flat), str(gt), "--samples", "300", "--json"]) == 0
    m = _strict_json(capsys.readouterr().out)
    assert m["chamfer_l2"] is None and m["accuracy_m"] is None and m["completeness_m"] is None
    assert m["fscore@10mm"] == 0.0 and m["n_pred_faces"] == 1
