"""The meshcat preview (bftaichi/viz.py, `bftaichi view`), checked in a real browser.

Headless Chromium (Debian's ``chromium``; .ci/run installs it) loads the page and takes a
screenshot; :func:`drawn` says whether the WebGL canvas shows the sigma-coloured mesh. A page
with the same viewer but no scene must fail that check (the test can fail). Outside CI the
browser tests skip when Chromium is missing; in CI (``CI`` set) they fail instead.
"""

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bftaichi.errors import DataError
from bftaichi.running import viz
from bftaichi.cli import main
from bftaichi.running.viz import LEGEND, _colormap, _decimate, _page, _Recorder, preview_html
from conftest import TINY_SCENE_SETS

CHROMIUM = Path(viz.CHROMIUM)
needs_browser = pytest.mark.skipif(not CHROMIUM.exists() and not os.environ.get("CI"),
                                   reason="Debian's chromium is not installed")


def screenshot(url: str, tmp_path: Path, name: str = "shot.png") -> np.ndarray:
    """(H, W, 3) uint8 screenshot of ``url`` by headless Chromium (bftaichi.running.viz.screenshot)."""
    return np.asarray(Image.open(viz.screenshot(url, tmp_path / name)).convert("RGB"))


def drawn(img: np.ndarray) -> float:
    """Fraction of the screenshot's pixels that show the mesh: near a colour of the sigma
    colour map (viridis) and far from the viewer's blue background gradient."""
    cmap = (_colormap(np.linspace(0, 1, 64), 0, 1) * 255).astype(np.float64)
    px = img.reshape(-1, 3).astype(np.float64)
    d = np.min(np.linalg.norm(px[:, None, :] - cmap[None, :, :], axis=2), axis=1)
    blue_bg = (px[:, 2] > px[:, 0] + 50) & (px[:, 2] > 100)  # sky and floor of the viewer
    return float(np.mean((d < 40) & ~blue_bg))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("viz") / "run"
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    assert main(["run", "-q", "--out", str(out), *sets, "--set", "nbv.enabled=true",
                 "--set", "nbv.n_candidates=6"]) == 0
    return out


def test_run_writes_a_self_contained_preview(tiny_run):
    page = (tiny_run / "preview.html").read_text()
    assert "MeshCat.Viewer" in page and LEGEND["sigma"] in page
    assert "http://" not in page.split("<script>")[0]  # nothing fetched from a server
    assert page.count("handle_command_bytearray") >= 4  # mesh, TSDF mesh, cameras, NBV, ...
    m = re.search(r'<span>([0-9.e+-]+)</span><span>([0-9.e+-]+)</span>', page)
    lo, hi = float(m.group(1)), float(m.group(2))
    assert 0 < lo < hi < 100  # a sigma range in millimetres
    # the colours are the vertex sigma's (the calibrated property), not sigma_pos's
    from bftaichi.io import read_mesh_ply

    sigma = read_mesh_ply(tiny_run / "mesh.ply")[2]["sigma"]
    np.testing.assert_allclose([lo, hi], 1000 * np.percentile(sigma, [2, 98]), rtol=5e-3)


def test_the_same_outputs_give_the_same_page(tiny_run, tmp_path):
    """meshcat names its objects by uuid1 (time and host): the page numbers them, so a
    preview is as reproducible as the run; it reads band.npz only to draw the band."""
    page = preview_html(tiny_run)
    assert preview_html(tiny_run) == page == (tiny_run / "preview.html").read_text()
    copy = tmp_path / tiny_run.name  # the page's title is the folder's name
    shutil.copytree(tiny_run, copy)
    (copy / "band.npz").write_bytes(b"damaged")
    assert preview_html(copy) == page  # band.npz not read (report.json has the origin)
    with pytest.raises(DataError, match="band.npz"):
        preview_html(copy, band=True)


@needs_browser
def test_preview_draws_in_a_real_browser(tiny_run, tmp_path):
    img = screenshot((tiny_run / "preview.html").as_uri(), tmp_path)
    assert img.std() > 10
    assert drawn(img) > 0.002  # the mesh is on screen
    # the same viewer with an empty scene (axes hidden, as in the preview) is not "drawn":
    # the check can fail
    import meshcat

    rec = _Recorder()
    meshcat.Visualizer(window=rec)["/Axes"].set_property("visible", False)
    blank = tmp_path / "blank.html"
    blank.write_text(_page(rec.commands, None, "blank"))
    assert drawn(screenshot(blank.as_uri(), tmp_path, "blank.png")) < 0.0005


def meshcat_servers() -> set:
    """PIDs of running meshcat server processes (from /proc)."""
    pids = set()
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if b"meshcat.servers.zmqserver" in (p / "cmdline").read_bytes():
                    pids.add(int(p.name))
            except OSError:
                pass
    return pids


@needs_browser
def test_view_serves_the_live_viewer_and_leaves_no_process(tiny_run, tmp_path):
    before = meshcat_servers()
    proc = subprocess.Popen([sys.executable, "-m", "bftaichi.cli", "view", str(tiny_run),
                             "--timeout", "30"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        line = proc.stdout.readline()
        url = re.search(r"(http://\S+)", line).group(1)
        assert meshcat_servers() - before  # the server runs while serving
        assert drawn(screenshot(url, tmp_path, "live.png")) > 0.002
        proc.terminate()  # like closing the terminal: the command must still clean up
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    deadline = time.monotonic() + 5
    while meshcat_servers() - before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not meshcat_servers() - before


def test_view_timeout_html_and_errors(tiny_run, tmp_path, capsys):
    before = meshcat_servers()
    assert main(["view", str(tiny_run), "--timeout", "0.5"]) == 0
    assert "http://127.0.0.1" in capsys.readouterr().out
    assert meshcat_servers() == before  # the server is gone when the command returns
    page = tmp_path / "p.html"
    assert main(["view", str(tiny_run), "--html", str(page), "--band"]) == 0
    assert page.stat().st_size > 100_000 and "wrote" in capsys.readouterr().out
    assert main(["view", str(tmp_path / "missing")]) == 2
    assert "not a folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--html", str(page)]) == 2
    assert "neither mesh.ply nor tsdf_mesh.ply" in capsys.readouterr().err
    assert meshcat_servers() == before


def test_large_meshes_are_decimated_and_keep_sigma():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces
    sigma = sphere.vertices[:, 2].copy()  # varies over the surface
    v, f, s = _decimate(sphere.vertices, sphere.faces, sigma, 2000)
    assert len(f) <= 2000 and len(s) == len(v)
    assert np.corrcoef(s, v[:, 2])[0, 1] > 0.99  # each vertex keeps its neighbourhood's sigma
    same = _decimate(sphere.vertices, sphere.faces, sigma, 10**6)
    assert same[1] is sphere.faces


def test_preview_of_a_tsdf_only_run(tmp_path):
    out = tmp_path / "t"
    sets = [a for s in TINY_SCENE_SETS for a in ("--set", s)]
    assert main(["run", "-q", "--out", str(out), *sets, "--set", "run.stages=tsdf_only"]) == 0
    page = preview_html(out)
    assert "posterior sigma" not in page and page.count("handle_command_bytearray") >= 2
