"""kernels.SDFField: @ti.func accessors called from kernels defined here (outside kernels/),
checked against numpy on an analytic sphere band; the import contract of ``kernels``; the
particle example on a fused scene."""

import importlib.util
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

import kernels
from kernels.embed import UNOBSERVED

ROOT = Path(__file__).resolve().parents[1]

VS = 0.02  # voxel size, metres
RADIUS = 0.3
CENTRE = np.array([0.013, -0.007, 0.021])  # off the voxel lattice
BAND_VOXELS = 3.0  # |exact SDF| of the band's voxel centres < 3 voxels
VAR_A, VAR_B = 1e-4, np.array([1e-5, 2e-5, -1e-5])  # var(x) = a + b . x, m^2 (> 0 in the band)
HOLE_X = 0.2  # voxels with centre x > HOLE_X are unobserved


@ti.kernel
def _probe(field: ti.template(), pts: ti.types.ndarray(dtype=ti.f64, ndim=2),
           out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """A user's kernel: every accessor at each point, f64 points (columns sdf, grad xyz, sigma,
    is_observed) and query() plus sdf() of the f32-cast point (columns 6-12)."""
    for i in range(pts.shape[0]):
        p = ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]])
        out[i, 0] = field.sdf(p)
        n = field.grad(p)
        for a in ti.static(range(3)):
            out[i, 1 + a] = n[a]
        out[i, 4] = field.sigma(p)
        out[i, 5] = field.is_observed(p)
        d, nq, s, ok = field.query(p)
        out[i, 6] = d
        for a in ti.static(range(3)):
            out[i, 7 + a] = nq[a]
        out[i, 10] = s
        out[i, 11] = ok
        out[i, 12] = field.sdf(ti.cast(p, ti.f32))


@ti.kernel
def _query(scene: ti.template(), pts: ti.types.ndarray(dtype=ti.f32, ndim=2),
           out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    """sdf and observed of query() at f32 points, for any scene with a query(p) accessor."""
    for i in range(pts.shape[0]):
        d, n, s, ok = scene.query(ti.Vector([pts[i, 0], pts[i, 1], pts[i, 2]]))
        out[i, 0] = d
        out[i, 1] = ok


def query(scene, pts) -> tuple[np.ndarray, np.ndarray]:
    out = np.zeros((len(pts), 2), np.float32)
    _query(scene, np.ascontiguousarray(pts, np.float32), out)
    return out[:, 0], out[:, 1] == 1


def probe(field, pts) -> np.ndarray:
    out = np.zeros((len(pts), 13), np.float32)
    _probe(field, np.ascontiguousarray(pts, np.float64), out)
    return out


def _sphere_band():
    r = int(math.ceil((RADIUS + BAND_VOXELS * VS) / VS)) + 2
    g = np.stack(np.meshgrid(*[np.arange(-r, r)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = (g + 0.5) * VS
    sdf = np.linalg.norm(centres - CENTRE, axis=1) - RADIUS
    keep = np.abs(sdf) < BAND_VOXELS * VS
    ijk, centres = g[keep].astype(np.int32), centres[keep]
    var = VAR_A + centres @ VAR_B
    observed = centres[:, 0] <= HOLE_X
    return ijk, sdf[keep].astype(np.float32), var.astype(np.float32), observed


def _observed_ref(ijk, observed, pts) -> np.ndarray:
    """numpy reference of is_observed: all 8 corners of the cell are observed band voxels."""
    known = {tuple(v) for v in ijk[observed]}
    c0 = np.floor(pts / VS - 0.5).astype(np.int64)
    corners = [(ci, cj, ck) for ci in (0, 1) for cj in (0, 1) for ck in (0, 1)]
    return np.array([all(tuple(c + o) in known for o in corners) for c in c0])


@pytest.fixture(scope="module")
def sphere():
    ijk, mean, var, observed = _sphere_band()
    return ijk, mean, var, observed, kernels.SDFField(ijk, mean, var, observed, VS)


def _shell_points(n, lo_vox, hi_vox, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return CENTRE + d * (RADIUS + rng.uniform(lo_vox, hi_vox, (n, 1)) * VS), d


def test_accessors_match_the_analytic_sphere(sphere):
    ijk, mean, var, observed, field = sphere
    pts, normal = _shell_points(4000, -2.0, 2.0)  # every cell corner within 2.9 voxels: in band
    out = probe(field, pts)
    ok = out[:, 5] == 1
    np.testing.assert_array_equal(ok, _observed_ref(ijk, observed, pts))
    assert 0.6 < ok.mean() < 0.95  # the hole (x > HOLE_X) is unobserved, the rest observed
    exact = np.linalg.norm(pts - CENTRE, axis=1) - RADIUS
    assert np.abs(out[ok, 0] - exact[ok]).max() < 0.05 * VS
    cos = np.clip(np.sum(out[ok, 1:4] * normal[ok], axis=1), -1, 1)
    angle = np.degrees(np.arccos(cos))
    # the trilinear interpolant's own slope: off by ~ (voxel / 2) / radius = 1.9 deg at most
    assert angle.max() < 4.0 and np.median(angle) < 2.0, (angle.max(), np.median(angle))
    # ... and grad is its analytic gradient: central differences of sdf() inside the cell
    eps = 1e-4
    frac = pts / VS - 0.5 - np.floor(pts / VS - 0.5)
    inner = ok & (np.minimum(frac, 1 - frac).min(axis=1) > 2 * eps / VS)
    fd = np.stack([probe(field, pts + eps * e)[:, 0] - probe(field, pts - eps * e)[:, 0]
                   for e in np.eye(3)], axis=1)[inner]
    fd /= np.linalg.norm(fd, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.sum(fd * out[inner, 1:4], axis=1), -1, 1))).max() < 0.2
    np.testing.assert_allclose(out[ok, 4], np.sqrt(VAR_A + pts[ok] @ VAR_B), rtol=1e-4)
    # unobserved: documented fallbacks
    assert (out[~ok, 0] == UNOBSERVED).all() and (out[~ok, 4] == UNOBSERVED).all()
    assert (out[~ok, 1:4] == 0).all()
    # query() is the same numbers as the single accessors; f32 points agree with f64 points
    np.testing.assert_array_equal(out[:, 6:12], out[:, 0:6])
    assert np.abs(out[ok, 12] - out[ok, 0]).max() < 1e-6


def test_is_observed_outside_the_band(sphere):
    *_, field = sphere
    far_out, _ = _shell_points(500, 4.0, 20.0, seed=1)  # a corner beyond 3 voxels: not in band
    far_in, _ = _shell_points(500, -20.0, -4.0, seed=2)
    pts = np.concatenate([far_out, far_in, [[10.0, 0.0, 0.0], [-1e7, 3e8, 0.0],
                                            [np.nan, 0.0, 0.0]]])
    out = probe(field, pts)
    assert (out[:, 5] == 0).all() and (out[:, 0] == UNOBSERVED).all()


def test_update_and_validation(sphere):
    ijk, mean, var, observed, _ = sphere
    field = kernels.SDFField(ijk, mean, var, observed, VS)
    pts, _ = _shell_points(200, -1.0, 1.0, seed=3)
    before = probe(field, pts)
    field.update(mean + 0.01, 4 * var, np.ones(len(ijk), bool))
    after = probe(field, pts)
    ok = before[:, 5] == 1
    assert (after[:, 5] == 1).all()  # the hole is observed now
    np.testing.assert_allclose(after[ok, 0], before[ok, 0] + 0.01, atol=1e-6)
    np.testing.assert_allclose(after[ok, 4], 2 * before[ok, 4], rtol=1e-5)
    with pytest.raises(ValueError, match="mean"):
        field.update(mean[:-1], var, observed)
    with pytest.raises(TypeError, match="observed"):
        field.update(mean, var, observed.astype(np.float32))
    with pytest.raises(ValueError, match="var"):
        field.update(mean, -var, observed)
    field.destroy()
    with pytest.raises(RuntimeError, match="new SDFField"):
        field.update(mean, var, observed)
    with pytest.raises(ValueError, match="duplicate"):
        kernels.SDFField(np.concatenate([ijk, ijk[:1]]), *(np.append(a, a[0]) for a in
                                                           (mean, var, observed)), VS)
    with pytest.raises(ValueError, match="voxel_size"):
        kernels.SDFField(ijk, mean, var, observed, 0.0)


def test_import_kernels_neither_imports_bftaichi_nor_initialises_taichi():
    code = ("import sys, numpy as np\n"
            "import kernels, kernels.embed\n"
            "from taichi.lang import impl\n"
            "assert 'bftaichi' not in sys.modules, 'bftaichi imported'\n"
            "assert impl.get_runtime().prog is None, 'ti.init called'\n"
            "try:\n"
            "    kernels.SDFField(np.zeros((1, 3), np.int32), np.zeros(1, np.float32),\n"
            "                     np.zeros(1, np.float32), np.ones(1, bool), 0.01)\n"
            "except RuntimeError as e:\n"
            "    assert 'ti.init' in str(e)\n"
            "else:\n"
            "    raise AssertionError('SDFField built without ti.init')\n"
            "assert impl.get_runtime().prog is None\n"
            "print('ok')\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr


def _example():
    spec = importlib.util.spec_from_file_location("particles_collide",
                                                  ROOT / "examples" / "particles_collide.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_example_particles_stay_outside_the_surface(tmp_path):
    ex = _example()
    res = ex.main(n_particles=400, steps=150, out=tmp_path)
    assert (tmp_path / "band.npz").exists() and (tmp_path / "particles.npz").exists()
    vs = res["field"].voxel_size
    for key, scene in (("positions", res["field"]), ("positions_analytic", ex.TabletopSDF())):
        x = res[key]
        assert x.shape == (400, 3) and np.isfinite(x).all()
        # after 0.6 s every particle has landed (the drop takes <= 0.34 s): at least 90 % lie
        # on the table (top at z = 0) or an object; a few may bounce or slide off an edge
        assert np.mean((x[:, 2] > -0.05) & (x[:, 2] < 0.25)) > 0.9, key
        d, ok = query(scene, x)
        assert ok.mean() > 0.8, key  # they rest inside the (fused) band ...
        assert d[ok].min() >= -0.25 * vs, key  # ... and not inside the surface
    for name in ("fuse", "step_fused", "step_analytic"):
        assert res["seconds"][name] > 0


def test_bench_embed_prints_both_times_and_the_ratio():
    res = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_embed.py"), "--particles",
                          "200", "--steps", "4", "--repeats", "1"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "200 particles, 4 steps" in res.stdout and "ratio fused / analytic" in res.stdout
    assert all(f"  {name} " in res.stdout for name in ("fused", "analytic"))


def test_a_kernel_error_still_names_its_file_line_and_code():
    """bftaichi.init shortens Taichi's per-node source labels (bftaichi.backend
    ._lean_source_positions, a start-up cost): a user's broken kernel must still be reported at
    its file and line, with the offending line."""
    @ti.kernel
    def broken(out: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(out.shape[0]):
            out[i] = undefined_name_in_kernel  # noqa: F821

    with pytest.raises(Exception) as err:
        broken(np.zeros(3, np.float32))
    msg = str(err.value)
    source = Path(__file__).read_text().splitlines()
    line = 1 + next(i for i, text in enumerate(source) if "= undefined_name_in_kernel" in text)
    assert Path(__file__).name in msg and f"line {line}" in msg, msg
    assert "out[i] = undefined_name_in_kernel" in msg, msg


@pytest.mark.parametrize("setting, expected", [(None, "False"), ("full", "True")])
def test_init_compiles_without_taichis_advanced_passes_unless_asked(setting, expected):
    """bftaichi.init turns Taichi's advanced IR passes off (half of a cold run's compilation,
    no run time bought: bftaichi.backend._advanced_optimization); BFTAICHI_TAICHI_OPT=full
    brings them back."""
    env = {k: v for k, v in os.environ.items() if k != "BFTAICHI_TAICHI_OPT"}
    if setting is not None:
        env["BFTAICHI_TAICHI_OPT"] = setting
    code = ("import bftaichi, taichi as ti\n"
            "bftaichi.init()\n"
            "print(ti.lang.impl.current_cfg().advanced_optimization)\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, env=env)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == expected


def _count_inspect_calls(tmp_path, name: str, source: str, wrapped: str, body: str) -> tuple:
    """Run ``body`` in a fresh Python with ``tmp_path / name.py`` (``source``) importable and
    every call of ``inspect.<wrapped>`` recorded in ``calls`` (its argument's ``__name__``); the
    body prints one line, returned split at its first space."""
    (tmp_path / f"{name}.py").write_text(source)
    code = ("import inspect, sys\n"
            f"sys.path.insert(0, {str(tmp_path)!r})\n"
            "calls = []\n"
            f"original = inspect.{wrapped}\n"
            "def counted(obj):\n"
            "    calls.append(getattr(obj, '__name__', ''))\n"
            "    return original(obj)\n"
            f"inspect.{wrapped} = counted\n" + body)
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    return tuple(res.stdout.strip().splitlines()[-1].split(maxsplit=1))


def test_importing_taichi_after_bftaichi_does_not_scan_every_module_per_decorator(tmp_path):
    """bftaichi.backend._skip_frozen_frame_scans: Taichi's ``@ti.func`` asks inspect whether it
    sits in a class, which for a module-level function scanned all of ``sys.modules`` (~0.3 s
    of each process's start). After ``import bftaichi`` importing Taichi and the kernels scans
    none, and a ``@ti.data_oriented`` class's ``@ti.func`` method still works."""
    scans, doubled = _count_inspect_calls(
        tmp_path, "oriented",
        "import taichi as ti\n\n"
        "@ti.data_oriented\n"
        "class Doubler:\n"
        "    @ti.func\n"
        "    def twice(self, x):\n"
        "        return 2 * x\n\n"
        "    @ti.kernel\n"
        "    def run(self, a: ti.types.ndarray(dtype=ti.f32, ndim=1)):\n"
        "        for i in range(a.shape[0]):\n"
        "            a[i] = self.twice(a[i])\n",
        "ismodule",
        "import bftaichi, taichi as ti, numpy as np\n"
        "import kernels.dataterm, kernels.compact, kernels.raycast\n"
        "import oriented\n"
        "bftaichi.init()\n"
        "a = np.arange(3, dtype=np.float32)\n"
        "oriented.Doubler().run(a)\n"
        "print(len(calls), a.tolist())\n")
    assert doubled.strip() == "[0.0, 2.0, 4.0]"
    # a scan of sys.modules asks ismodule of each of its ~1,600 modules; a file inspect has
    # not seen yet (here oriented.py) costs one scan, each decorator at a module's top level
    # cost two (652,302 calls here without the fix, 3,928 with it)
    assert int(scans) < 20_000, scans


def test_taichi_reads_a_functions_source_once_per_process(tmp_path):
    """bftaichi.backend._remembered_source_lines: Taichi's front end read a ``@ti.func``'s
    source lines again for every kernel that calls it (471 reads of 86 functions in a warm
    ``bftaichi run``); after bftaichi.init two kernels calling one function read it once, and
    both still compute with it."""
    reads, values = _count_inspect_calls(
        tmp_path, "twokernels",
        "import taichi as ti\n\n"
        "@ti.func\n"
        "def square(x):\n"
        "    return x * x\n\n"
        "@ti.kernel\n"
        "def first(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):\n"
        "    for i in range(a.shape[0]):\n"
        "        a[i] = square(a[i])\n\n"
        "@ti.kernel\n"
        "def second(a: ti.types.ndarray(dtype=ti.f32, ndim=1)):\n"
        "    for i in range(a.shape[0]):\n"
        "        a[i] = square(a[i]) + 1\n",
        "getsourcelines",
        "import bftaichi, numpy as np\n"
        "bftaichi.init()\n"
        "import twokernels\n"
        "a = np.array([1, 2, 3], np.float32)\n"
        "twokernels.first(a)\n"
        "twokernels.second(a)\n"
        "print(calls.count('square'), a.tolist())\n")
    assert values.strip() == "[2.0, 17.0, 82.0]"
    assert reads == "1", (reads, values)
