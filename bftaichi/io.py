"""Output files: atomic writes and the PLY / NPZ / JSON formats of DESIGN.md section 4.

Every file is written to a temporary file in the destination folder and then renamed over the
target (``os.replace`` is atomic on POSIX), so an interrupted run never leaves a half-written file.
"""

from __future__ import annotations

import io
import json
import os
import stat
import tempfile
from pathlib import Path

import numpy as np

from .errors import BftaichiError, DataError

__all__ = ["atomic_write_bytes", "writable_target", "to_json", "write_json", "write_npz",
           "write_mesh_ply", "read_mesh_ply", "prepare_out_dir", "ensure_out_dir"]


_UMASK = os.umask(0)
os.umask(_UMASK)  # read once: temp files are created 0600, outputs get the usual 0666 & ~umask


def writable_target(path: str | os.PathLike) -> Path:
    """The file a write to ``path`` replaces: ``path`` itself, or the file a symlink at ``path``
    points to (the write goes through the link, which stays). BftaichiError if that is not a
    regular file (a device, FIFO, socket or folder): those are never replaced."""
    path = Path(path)
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    try:
        st = os.stat(target)
    except FileNotFoundError:
        return target
    except OSError as e:
        raise BftaichiError(f"cannot write {path}: {e.strerror or e}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a device" if
                stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "a FIFO" if
                stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else
                "not a regular file")
        via = f" (the link {path} points to {target})" if target != path else ""
        raise BftaichiError(f"cannot write {path}: it is {kind}{via}; bftaichi only replaces "
                            "regular files, choose a file name")
    return target


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temp file in the same folder + rename (permissions as
    a plain ``open`` would give). A symlink is written through; a device, FIFO, socket or
    folder at ``path`` is refused (:func:`writable_target`)."""
    path = writable_target(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise BftaichiError(f"cannot write {path}: {e.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError):
            raise BftaichiError(f"cannot write {path}: {e.strerror or e}") from None
        raise


def _finite_or_null(o):
    """``o`` with numpy scalars and arrays as Python numbers and lists, and every NaN / inf
    float as None (dict keys and other values unchanged)."""
    if isinstance(o, float):  # also np.float64
        return o if np.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite_or_null(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_null(v) for v in o]
    if isinstance(o, np.ndarray):
        return _finite_or_null(o.tolist())
    if isinstance(o, np.generic):
        return _finite_or_null(o.item())
    return o


def to_json(obj, indent: int | None = 2) -> str:
    """``obj`` as strict JSON (RFC 8259) text: numpy scalars and arrays as numbers and lists,
    paths as strings, and NaN / inf as ``null``. JSON has no non-finite numbers (Python's
    ``json`` would write ``NaN`` / ``Infinity``, which other parsers reject); in bftaichi's
    files and ``--json`` output a null number means "not defined" (e.g. the distances of a
    mesh without surface)."""

    def default(o):
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o)}")

    return json.dumps(_finite_or_null(obj), indent=indent, default=default, allow_nan=False)


def write_json(path: str | os.PathLike, obj) -> None:
    """:func:`to_json` of ``obj`` (2-space indent), written atomically."""
    atomic_write_bytes(path, (to_json(obj) + "\n").encode())


#: A member of ``write_npz`` whose first STORE_PROBE bytes deflate to more than STORE_RATIO of
#: their size is stored uncompressed: a float field of the posterior (mean, var, cov) deflates
#: to 0.91-0.92 of its size, at ~20 ns a byte.
STORE_PROBE = 1 << 20
STORE_RATIO = 0.85


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """An ``.npz`` (a zip of ``.npy`` members, as ``np.savez`` writes and ``np.load`` reads)
    built in memory, then an atomic write; the entries carry a fixed timestamp, so the same
    arrays give the same bytes. Deflate level 1: about 1.5x faster than savez_compressed's
    default level for a file 2 % larger. A member that deflates little (its first STORE_PROBE
    bytes to more than STORE_RATIO) is stored as is: writing a 1 cm band of 3.46 M voxels took
    0.8-0.9 s instead of 2.1 s, for a file 7 % larger (docs/measurements.md)."""
    import zipfile
    import zlib

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, value in arrays.items():
            data = io.BytesIO()
            np.lib.format.write_array(data, np.asanyarray(value), allow_pickle=False)
            data = data.getbuffer()
            head = bytes(data[:STORE_PROBE])
            deflate = zlib.compressobj(1, zlib.DEFLATED, -15)
            small = len(deflate.compress(head) + deflate.flush()) <= STORE_RATIO * len(head)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o600 << 16  # rw-------, as ZipFile.open gives a name
            zf.writestr(info, data, compresslevel=1,
                        compress_type=zipfile.ZIP_DEFLATED if small else zipfile.ZIP_STORED)
    atomic_write_bytes(path, buf.getvalue())


def write_mesh_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                   vertex_attrs: dict[str, np.ndarray] | None = None,
                   vertex_colors: np.ndarray | None = None, origin=None) -> None:
    """Binary little-endian PLY: vertex ``x y z`` + extra float32 attributes (e.g. ``sigma``)
    + optional ``red green blue`` (uint8), and ``vertex_indices`` faces (int32).

    ``vertices`` (n, 3) are in the local frame of ``origin`` ((3,) float64 metres, world
    position of the local frame; None or zeros: the world frame itself). The file always
    holds world coordinates: with a zero origin ``x y z`` are ``float`` (float32, the
    vertices as given); with a non-zero one they are ``double`` (float64) ``origin +
    vertices``, since float32 cannot hold georeferenced coordinates (its ulp is 0.5 m at
    5,000 km). :func:`read_mesh_ply` and common PLY readers (trimesh, Open3D, plyfile) read
    both."""
    from plyfile import PlyData, PlyElement

    world = origin is not None and bool(np.any(origin))
    if world:
        vertices = (np.asarray(origin, np.float64).reshape(3)
                    + np.asarray(vertices, dtype=np.float64).reshape(-1, 3))
    else:
        vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    vertex_attrs = vertex_attrs or {}
    xyz = "f8" if world else "f4"
    dtype = [("x", xyz), ("y", xyz), ("z", xyz)]
    dtype += [(name, "f4") for name in vertex_attrs]
    if vertex_colors is not None:
        dtype += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vert = np.empty(len(vertices), dtype=dtype)
    vert["x"], vert["y"], vert["z"] = vertices.T
    for name, values in vertex_attrs.items():
        vert[name] = np.asarray(values, dtype=np.float32).reshape(-1)
    if vertex_colors is not None:
        c = np.asarray(vertex_colors, dtype=np.uint8).reshape(-1, 3)
        vert["red"], vert["green"], vert["blue"] = c.T
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    ply = PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")],
                  text=False, byte_order="<")
    # plyfile's header; the data as the packed arrays plyfile writes (it writes list
    # properties one row at a time in Python: ~5 s for a million faces)
    packed = np.empty(len(faces), dtype=[("n", "u1"), ("vertex_indices", "<i4", (3,))])
    packed["n"], packed["vertex_indices"] = 3, faces
    atomic_write_bytes(path, b"".join([ply.header.encode("ascii"), b"\n",
                                       vert.astype(vert.dtype.newbyteorder("<")).tobytes(),
                                       packed.tobytes()]))


def read_mesh_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Read a PLY written by :func:`write_mesh_ply`: (vertices, faces, extra vertex properties).
    Vertices are world coordinates: float32 when the file stores ``float`` x y z, float64 when
    it stores ``double`` (a mesh of a scene far from the world origin).
    Raises DataError naming the file if it is not such a mesh: unreadable, truncated or with
    bytes after its data (a damaged element count), no vertex ``x y z``, faces that are not
    triangles or index outside ``0..V-1``, NaN or inf in the vertices or their float
    properties."""
    from plyfile import PlyData

    path = Path(path)
    try:
        with open(path, "rb") as f:
            try:  # triangles (what write_mesh_ply writes): plyfile's vectorised path
                ply = PlyData.read(f, known_list_len={"face": {"vertex_indices": 3}})
            except Exception:  # noqa: BLE001 - other lists or a damaged file: the general reader
                f.seek(0)
                ply = PlyData.read(f)
            trailing = 0 if ply.text else os.fstat(f.fileno()).st_size - f.tell()
    except FileNotFoundError:
        raise DataError(f"mesh file {path} does not exist") from None
    # plyfile's parse errors, and numpy's and the OS's on a damaged or truncated file
    except Exception as e:  # noqa: BLE001 - re-raised as DataError naming the file
        raise DataError(f"{path}: cannot read the PLY mesh, the file is damaged or truncated "
                        f"({type(e).__name__}: {e})") from None
    if trailing:
        raise DataError(f"{path}: {trailing} bytes after the PLY data: the header's element "
                        "counts do not match the file (damaged or truncated header)")
    return _ply_mesh_arrays(ply, path)


def _ply_mesh_arrays(ply, path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`read_mesh_ply`'s arrays of a parsed PLY, checked (DataError naming ``path``)."""
    if "vertex" not in ply:
        raise DataError(f"{path}: no 'vertex' element, not a mesh")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    missing = [a for a in ("x", "y", "z") if a not in names or v.dtype[a].kind not in "fiu"]
    if missing:
        raise DataError(f"{path}: the vertices lack the number propert"
                        f"{'y' if len(missing) == 1 else 'ies'} {' '.join(missing)}")
    xyz = np.float64 if v.dtype["x"].itemsize == 8 else np.float32
    vertices = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(xyz)
    extra = {n: np.asarray(v[n]) for n in v.dtype.names if n not in ("x", "y", "z")}
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise DataError(f"{path}: {int(bad.sum())} vertices have NaN or infinite coordinates "
                        f"(the first: vertex {int(np.flatnonzero(bad)[0])})")
    for name, values in extra.items():
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            raise DataError(f"{path}: vertex property {name} holds NaN or inf")
    faces = np.zeros((0, 3), np.int32)
    if "face" in ply and len(ply["face"].data):
        if "vertex_indices" not in (ply["face"].data.dtype.names or ()):
            raise DataError(f"{path}: the faces lack the property vertex_indices")
        idx = ply["face"].data["vertex_indices"]  # (M, 3), or rows of objects (general path)
        if idx.dtype == object:
            sizes = np.array([np.size(row) for row in idx])
            if (sizes != 3).any():
                k = int(np.flatnonzero(sizes != 3)[0])
                raise DataError(f"{path}: face {k} has {sizes[k]} vertex indices; only "
                                "triangle meshes are read")
            idx = np.stack(idx)
        idx = np.asarray(idx)
        if idx.ndim != 2 or idx.shape[1] != 3 or idx.dtype.kind not in "iu":
            raise DataError(f"{path}: face vertex_indices must be lists of 3 integers, got "
                            f"{idx.dtype} of shape {idx.shape}")
        lo, hi = int(idx.min()), int(idx.max())
        if lo < 0 or hi >= len(vertices):
            raise DataError(f"{path}: face vertex indices span {lo}..{hi} but the mesh has "
                            f"{len(vertices)} vertices")
        faces = idx.astype(np.int32)
    return vertices, faces, extra


RUN_MARKERS = ("report.json", "tsdf_mesh.ply", "mesh.ply", "band.npz")


def ensure_out_dir(out: str | os.PathLike) -> Path:
    """Create folder ``out`` (and parents) and check it is writable; BftaichiError names it."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BftaichiError(f"output folder {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BftaichiError(f"cannot create output folder {out}: {e.strerror or e}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise BftaichiError(f"output folder {out} is not writable")
    return out


def prepare_out_dir(out: str | os.PathLike, overwrite: bool = False,
                    marker: str | None = None) -> Path:
    """:func:`ensure_out_dir`, and refuse a folder that already holds a run's outputs (or the
    file ``marker``, for commands that write other outputs) unless ``overwrite``. Raises
    BftaichiError naming the folder."""
    out = ensure_out_dir(out)
    existing = [m for m in ((marker,) if marker else RUN_MARKERS) if (out / m).exists()]
    if existing and not overwrite:
        raise BftaichiError(
            f"output folder {out} already holds a run ({', '.join(existing)}); "
            "pass --overwrite to replace it or choose another --out")
    return out
