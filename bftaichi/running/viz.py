"""See a run: a meshcat scene of its outputs, as a self-contained HTML page or a live viewer.

The scene (:func:`build_scene`, from the files of an output folder, DESIGN.md section 4):

- ``bftaichi/mesh``: ``mesh.ply`` coloured by its vertex ``sigma`` (colour map ``viridis``
  between the 2nd and 98th percentile, written into the page as a legend in millimetres).
  ``sigma`` is the posterior std of the SDF at the vertex; the mesh's vertices are where the
  mean is 0, so a vertex's distance to the true surface is the SDF's error there, and
  ``sigma`` is what the development suite finds calibrated against those distances.
  ``sigma_pos`` (``sigma / |grad mean|``, the spread of the zero crossings of the posterior's
  samples) is not: the mean's gradient at a vertex is noisy (median magnitude 1.1-1.4 on the
  suite's cases, a tenth of the vertices above 2-5), and dividing by it made the vertices
  overconfident (``python tools/suite.py --set eval.vertex_sigma=sigma_pos``: within 3 sigma
  on 0 of 43 cases against 36, docs/measurements.md). A ``mesh.ply`` without ``sigma`` is
  coloured by ``sigma_pos``, and the legend says which one is shown;
- ``bftaichi/tsdf_mesh``: the TSDF baseline ``tsdf_mesh.ply`` in grey, hidden at first (tick it
  in the viewer's *Open Controls* > *Scene* tree to show it);
- ``bftaichi/cameras``: a frustum per input frame (from ``report.json``'s ``frames`` poses);
- ``bftaichi/nbv``: with ``nbv.json``, the candidate frustums coloured by utility (dark =
  low, yellow = high) and the best view in red, drawn larger;
- ``bftaichi/band`` (``band=True``): band voxels near the surface as points coloured by their
  marginal sigma (SDF std, ``sqrt(var)``).

Meshes above ``max_faces`` are decimated (quadric decimation, ``fast-simplification``) before
they are sent, and the colour value of a decimated vertex is that of the nearest original vertex.

meshcat-python 0.3.2 notes, all handled here: its ``Visualizer()`` starts a server subprocess
(ports 6000/7000 and up) and ``static_html()`` asks that server for the page. The static page
needs no server here: :class:`_Recorder` is a meshcat window that keeps the encoded commands
and builds the page itself (meshcat's own ``create_command`` and viewer bundle), so writing
``preview.html`` never starts a process. Only :func:`serve` (``bftaichi view``) starts the
server, and it kills it (and waits for it) however the command ends: return, error, Ctrl-C,
SIGTERM or SIGHUP; if the command is killed outright, the server gets SIGKILL from the kernel
(``PR_SET_PDEATHSIG``). Arrays go to meshcat as
3xN float32, faces as uint32. Float32 cannot hold world coordinates far from the origin, so the
scene is shown in the run's local frame: world minus ``origin_m`` of report.json (or
``origin`` of band.npz; zeros for a scene near the world origin, where nothing moves).
"""

from __future__ import annotations

import contextlib
import html
import time
from pathlib import Path

import numpy as np

from ..errors import DataError

__all__ = ["build_scene", "preview_html", "write_preview", "serve", "screenshot"]

CHROMIUM = "/usr/bin/chromium"
#: Flags for a headless Chromium that renders WebGL on the CPU and talks to no network service.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--no-first-run")

MAX_FACES = 200_000


class _Recorder:
    """A meshcat window that records commands (``umsgpack`` bytes, as the server stores them)
    instead of sending them, and renders them into a static page."""

    def __init__(self):
        self.commands: list[bytes] = []

    def send(self, command) -> None:
        import umsgpack

        self.commands.append(umsgpack.packb(command.lower()))


def _colormap(values, lo: float, hi: float, name: str = "viridis") -> np.ndarray:
    """(n, 3) float32 RGB in [0, 1] of ``values`` mapped from [lo, hi]."""
    from matplotlib import colormaps

    t = np.clip((np.asarray(values, np.float64) - lo) / max(hi - lo, 1e-30), 0.0, 1.0)
    return colormaps[name](t)[:, :3].astype(np.float32)


def _decimate(vertices, faces, attr, max_faces: int):
    """Quadric decimation to at most ``max_faces``; ``attr`` (per vertex) follows the nearest
    original vertex."""
    if len(faces) <= max_faces:
        return vertices, faces, attr
    import trimesh
    from scipy.spatial import cKDTree

    small = trimesh.Trimesh(vertices, faces, process=False).simplify_quadric_decimation(
        face_count=max_faces)
    v = np.asarray(small.vertices)
    if attr is not None:
        attr = np.asarray(attr)[cKDTree(vertices).query(v, k=1)[1]]
    return v, np.asarray(small.faces), attr


def _translation(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def _frustums(poses, K, size, depth_m: float, colors) -> tuple[np.ndarray, np.ndarray]:
    """Line segments (3, 16 n) and colours (3, 16 n) of camera frustums: the 4 corner rays to
    ``depth_m`` and the far rectangle, per pose (world frame)."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], np.float64)
    rays = np.linalg.solve(K, corners.T).T * depth_m  # camera frame, z = depth_m
    segs = []
    for T in poses:
        c = T[:3, 3]
        far = (T[:3, :3] @ rays.T).T + c
        for k in range(4):
            segs += [c, far[k], far[k], far[(k + 1) % 4]]
    pts = np.asarray(segs, np.float32).T
    col = np.repeat(np.asarray(colors, np.float32), 16, axis=0).T
    return pts, col


def _load_outputs(out: Path, band: bool = True) -> dict:
    """The outputs of a run folder, read while no commit replaces them (``band``: see
    :func:`_read_outputs`)."""
    from .folder import reading

    with reading(out):
        return _read_outputs(out, band)


def _read_outputs(out: Path, band: bool = True) -> dict:
    """Each output file through its checking reader (a damaged one: DataError naming it).
    ``band`` False: band.npz is read only when report.json has no ``origin_m`` (the scene
    without the band's points needs nothing else of it; at 1 cm it is ~90 MB to inflate)."""
    from ..io import read_mesh_ply
    from ..planning.nbv import read_ranking
    from ..posterior import read_band
    from .report import read_report

    out = Path(out)
    if not out.is_dir():
        raise DataError(f"{out} is not a folder of run outputs")
    report = out / "report.json"
    data = {"report": read_report(report) if report.exists() else None, "band": None}
    readers = {"nbv": (out / "nbv.json", read_ranking),
               "mesh.ply": (out / "mesh.ply", read_mesh_ply),
               "tsdf_mesh.ply": (out / "tsdf_mesh.ply", read_mesh_ply)}
    if band or "origin_m" not in (data["report"] or {}):
        readers["band"] = (out / "band.npz", read_band)
    data.update({name: read(p) if p.exists() else None for name, (p, read) in readers.items()})
    if data["mesh.ply"] is None and data["tsdf_mesh.ply"] is None:
        raise DataError(f"{out} holds neither mesh.ply nor tsdf_mesh.ply: nothing to show")
    report, arrays = data["report"] or {}, data["band"] or {}
    data["origin"] = np.asarray(report.get("origin_m", arrays.get("origin", np.zeros(3))),
                                np.float64)
    for name in ("mesh.ply", "tsdf_mesh.ply"):  # world -> the local frame (module docstring)
        if data[name] is not None and np.any(data["origin"]):
            v, f, extra = data[name]
            data[name] = ((v - data["origin"]).astype(np.float32), f, extra)
    return data


def _local_poses(poses, origin) -> np.ndarray:
    """World poses (n, 4, 4) in the local frame the scene is shown in (float64)."""
    poses = np.array(poses, np.float64).reshape(-1, 4, 4)
    poses[:, :3, 3] -= origin
    return poses


def build_scene(vis, out_dir, *, max_faces: int = MAX_FACES, band: bool = False) -> dict:
    """Send the scene of a run's outputs in ``out_dir`` to the meshcat visualizer ``vis``;
    return the legend (``sigma_mm``: colour range, or None; ``sigma_name``: the vertex
    property shown, ``sigma`` or, for a mesh.ply without it, ``sigma_pos``) and what was drawn."""
    import meshcat.geometry as g

    d = _load_outputs(Path(out_dir), band=band)
    root = vis["bftaichi"]
    info = {"sigma_mm": None, "sigma_name": None, "drawn": []}
    scale, centre = 1.0, None
    if d["mesh.ply"] is not None:
        v, f, attrs = d["mesh.ply"]
        name = next((n for n in ("sigma", "sigma_pos") if n in attrs), None)
        v, f, sigma = _decimate(v, f, attrs.get(name), max_faces)
        color = None
        if sigma is not None and len(sigma):
            lo, hi = (float(x) for x in np.percentile(sigma, [2, 98]))
            color = _colormap(sigma, lo, hi)
            info["sigma_mm"], info["sigma_name"] = (1000 * lo, 1000 * hi), name
        root["mesh"].set_object(g.TriangularMeshGeometry(v, f, color=color),
                                g.MeshLambertMaterial(color=0xffffff, vertexColors=color is not None))
        info["drawn"].append(f"mesh.ply ({len(f):,} faces)")
        if len(v):
            scale, centre = float(np.ptp(v, axis=0).max()), 0.5 * (v.min(axis=0) + v.max(axis=0))
    if d["tsdf_mesh.ply"] is not None:
        v, f, _ = d["tsdf_mesh.ply"]
        v, f, _ = _decimate(v, f, None, max_faces)
        root["tsdf_mesh"].set_object(g.TriangularMeshGeometry(v, f),
                                     g.MeshLambertMaterial(color=0xb0b0b0))
        if d["mesh.ply"] is not None:
            root["tsdf_mesh"].set_property("visible", False)
        elif len(v):
            scale, centre = float(np.ptp(v, axis=0).max()), 0.5 * (v.min(axis=0) + v.max(axis=0))
        info["drawn"].append(f"tsdf_mesh.ply ({len(f):,} faces)")
    report = d["report"] or {}
    cams = report.get("cameras")
    if cams and cams.get("poses"):
        poses = _local_poses(cams["poses"], d["origin"])
        pts, col = _frustums(poses, np.asarray(cams["K"]), cams["image_size"], 0.15 * scale,
                             [(0.2, 0.4, 1.0)] * len(poses))
        root["cameras"].set_object(g.LineSegments(g.PointsGeometry(pts, col),
                                                  g.LineBasicMaterial(vertexColors=True)))
        info["drawn"].append(f"{len(poses)} camera frustums")
    if d["nbv"] is not None and cams:
        cand = d["nbv"]["candidates"]
        poses = _local_poses([c["pose"] for c in cand], d["origin"])
        u = np.array([c["utility"] for c in cand])
        col = _colormap(u, float(u.min()), float(u.max()), "plasma")
        best = int(np.argmin([c["rank"] for c in cand]))
        col[best] = (1.0, 0.0, 0.0)
        pts, cols = _frustums(poses, np.asarray(cams["K"]), cams["image_size"], 0.1 * scale, col)
        root["nbv"]["candidates"].set_object(
            g.LineSegments(g.PointsGeometry(pts, cols), g.LineBasicMaterial(vertexColors=True)))
        pts, cols = _frustums(poses[best:best + 1], np.asarray(cams["K"]), cams["image_size"],
                              0.25 * scale, [(1.0, 0.0, 0.0)])
        root["nbv"]["best"].set_object(
            g.LineSegments(g.PointsGeometry(pts, cols), g.LineBasicMaterial(vertexColors=True)))
        info["drawn"].append(f"{len(cand)} NBV candidates (best: {cand[best]['index']})")
    if centre is not None:
        # frame the result: the orbit target at its centre, the camera 2 extents away, from
        # above and to the side (meshcat's camera sits in a y-up frame: world z is its y)
        vis["/Cameras/default"].set_transform(_translation(centre))
        dist = 2.0 * scale
        vis["/Cameras/default/rotated/<object>"].set_property(
            "position", [0.7 * dist, 0.6 * dist, 0.9 * dist])
        vis["/Axes"].set_property("visible", False)
    if band and d["band"] is not None and "var" in d["band"]:
        b = d["band"]
        vs = float(b["voxel_size"])
        near = (np.abs(b["mean"]) <= vs) & (b["weight"] > 0)
        pts = ((b["ijk"][near] + 0.5) * vs).astype(np.float32).T
        sig = np.sqrt(np.maximum(b["var"][near], 0))
        lo, hi = (float(x) for x in np.percentile(sig, [2, 98])) if len(sig) else (0.0, 1.0)
        root["band"].set_object(g.PointCloud(pts, _colormap(sig, lo, hi).T, size=vs))
        info["drawn"].append(f"{pts.shape[1]:,} band voxels")
    return info


_PAGE = """<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>bftaichi: {title}</title>
<style>
body {{ margin: 0; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#legend {{ position: absolute; left: 12px; bottom: 12px; padding: 8px 10px;
  background: rgba(255, 255, 255, 0.85); font: 13px sans-serif; border-radius: 4px; }}
#legend .bar {{ width: 220px; height: 12px; margin: 4px 0;
  background: linear-gradient(to right, {gradient}); }}
#legend .ends {{ display: flex; justify-content: space-between; }}
</style></head>
<body>
<div id="meshcat-pane"></div>
{legend}
<script>
{viewer_js}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
{commands}
</script>
</body>
</html>
"""


def preview_html(out_dir, *, max_faces: int = MAX_FACES, band: bool = False,
                 title: str | None = None) -> str:
    """The self-contained page (meshcat's viewer bundle and the scene inline) of a run's
    outputs in ``out_dir``, titled ``title`` (default: the folder's name). Starts no
    process."""
    import meshcat

    rec = _Recorder()
    with _numbered_uuids():
        info = build_scene(meshcat.Visualizer(window=rec), out_dir, max_faces=max_faces,
                           band=band)
    return _page(rec.commands, info["sigma_mm"], title or Path(out_dir).name, info["sigma_name"])


@contextlib.contextmanager
def _numbered_uuids():
    """meshcat names each geometry and material ``uuid.uuid1()`` (the time and the host), so
    a page of the same outputs differed byte for byte run after run; a static page numbers
    them instead (unique within the page, as three.js needs)."""
    import itertools
    import uuid

    import meshcat.geometry

    numbers = itertools.count(1)

    class Numbered:
        @staticmethod
        def uuid1():
            return uuid.UUID(int=next(numbers))

    meshcat.geometry.uuid = Numbered
    try:
        yield
    finally:
        meshcat.geometry.uuid = uuid


#: Legend titles of the vertex property the mesh is coloured by.
LEGEND = {"sigma_pos": "posterior sigma of the surface position along the normal (mm)",
          "sigma": "posterior sigma of the SDF at the vertex (mm)"}


def _page(commands: list, sigma_mm, title: str, sigma_name: str = "sigma") -> str:
    """The static page of recorded meshcat ``commands`` with the legend of ``sigma_name``
    (:data:`LEGEND`; mm range ``sigma_mm``, or None for no legend)."""
    import os

    from meshcat.servers.zmqserver import VIEWER_ROOT, create_command

    legend = ""
    if sigma_mm is not None:
        lo, hi = sigma_mm
        legend = (f'<div id="legend">{LEGEND[sigma_name]}<div class="bar"></div>'
                  f'<div class="ends"><span>{lo:.3g}</span><span>{hi:.3g}</span></div>'
                  f'<div>layers (TSDF mesh: hidden, cameras, NBV views): Open Controls &gt; '
                  f'Scene</div></div>')
    stops = _colormap(np.linspace(0, 1, 9), 0, 1)
    gradient = ", ".join(f"rgb({int(255 * r)}, {int(255 * gg)}, {int(255 * b)})"
                         for r, gg, b in stops)
    with open(os.path.join(VIEWER_ROOT, "main.min.js"), encoding="utf-8") as f:
        viewer_js = f.read()
    return _PAGE.format(title=html.escape(title), gradient=gradient, legend=legend,
                        viewer_js=viewer_js, commands="".join(create_command(c) for c in commands))


def write_preview(out_dir, path=None, **kwargs) -> Path:
    """Write :func:`preview_html` of ``out_dir`` to ``path`` (default ``out_dir/preview.html``),
    atomically; return the path."""
    from ..io import atomic_write_bytes

    path = Path(path) if path else Path(out_dir) / "preview.html"
    atomic_write_bytes(path, preview_html(out_dir, **kwargs).encode("utf-8"))
    return path


class _ZmqWindow:
    """A meshcat window talking to a running server (meshcat's ``ViewerWindow.send``, without
    its printing)."""

    def __init__(self, zmq_url: str):
        import zmq

        self.context = zmq.Context.instance()
        self.socket = self.context.socket(zmq.REQ)
        self.socket.connect(zmq_url)

    def send(self, command) -> None:
        import umsgpack

        data = command.lower()
        self.socket.send_multipart([data["type"].encode("utf-8"), data["path"].encode("utf-8"),
                                    umsgpack.packb(data)])
        self.socket.recv()

    def close(self) -> None:
        self.socket.close(linger=0)


def _die_with_parent() -> None:
    """In the server child, before exec: ask Linux to kill it when its parent dies, even by
    SIGKILL (prctl PR_SET_PDEATHSIG); elsewhere a no-op."""
    import ctypes
    import signal
    import sys

    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass


def _start_server():
    """meshcat's server as a child process (meshcat's own command line, as its
    ``start_zmq_server_as_subprocess`` runs it, plus :func:`_die_with_parent`); returns
    ``(proc, zmq_url, web_url)``."""
    import os
    import subprocess
    import sys

    import meshcat
    from meshcat.servers.zmqserver import match_web_url, match_zmq_url

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [os.path.dirname(os.path.dirname(meshcat.__file__))] + sys.path)
    proc = subprocess.Popen([sys.executable, "-u", "-m", "meshcat.servers.zmqserver"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            start_new_session=True, preexec_fn=_die_with_parent)
    line = ""
    while "zmq_url" not in line:
        line = proc.stdout.readline().decode("utf-8", "replace").strip()
        if proc.poll() is not None:
            err = proc.stderr.read().decode("utf-8", "replace")
            raise DataError(f"the meshcat server did not start (exit code {proc.returncode}): "
                            f"{err[-500:]}")
    zmq_url = match_zmq_url(line)
    web_url = match_web_url(proc.stdout.readline().decode("utf-8", "replace").strip())
    return proc, zmq_url, web_url


def serve(out_dir, *, timeout_s: float | None = None, max_faces: int = MAX_FACES,
          band: bool = False, on_url=print) -> None:
    """Serve the live meshcat viewer of ``out_dir``: start meshcat's server, send the scene,
    report its URL through ``on_url``, and wait until Ctrl-C, SIGTERM, SIGHUP or ``timeout_s``
    seconds. The server process is killed and reaped however this ends, and Linux kills it
    if this process itself is killed."""
    import signal
    import threading

    import meshcat

    _load_outputs(Path(out_dir))  # bad folder: an error before any process starts

    def stop(signum, frame):  # SIGTERM / SIGHUP end the wait like Ctrl-C, through `finally`
        raise KeyboardInterrupt

    handlers = {}
    if threading.current_thread() is threading.main_thread():
        handlers = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGHUP)}
    proc, zmq_url, web_url = _start_server()
    window = None
    try:
        window = _ZmqWindow(zmq_url)
        build_scene(meshcat.Visualizer(window=window), out_dir, max_faces=max_faces, band=band)
        on_url(web_url)
        t0 = time.monotonic()
        while timeout_s is None or time.monotonic() - t0 < timeout_s:
            time.sleep(0.1)
            if proc.poll() is not None:
                raise DataError(f"the meshcat server stopped (exit code {proc.returncode})")
    finally:
        if window is not None:
            window.close()
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream:
                stream.close()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)


def screenshot(url: str, png_path, size=(800, 600), wait_ms: int = 20000,
               chromium: str = CHROMIUM) -> Path:
    """Screenshot ``url`` (e.g. ``Path("preview.html").as_uri()``) with headless Chromium
    (Debian's ``chromium``) into ``png_path``, after up to ``wait_ms`` of virtual time for the
    page's scripts, with a fresh throw-away profile. Raises DataError if Chromium is missing or
    writes no image."""
    import shutil
    import subprocess
    import tempfile

    if not Path(chromium).exists() and shutil.which(chromium) is None:
        raise DataError(f"{chromium} not found: install Debian's chromium package")
    png_path = Path(png_path)
    with tempfile.TemporaryDirectory(prefix="bftaichi-chromium-") as profile:
        cmd = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
               f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={wait_ms}",
               f"--screenshot={png_path}", url]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    if not png_path.exists():
        raise DataError(f"chromium wrote no screenshot of {url}: {proc.stderr[-1000:]}")
    return png_path
