"""Geometry judged on views that were not fused (``bftaichi evalviews``): real data has no
ground-truth mesh, but every held-out depth frame is a measurement of the true surface.

1. Split the frames: every ``every``-th frame (0, 2, 4, ... for ``every = 2``) is fused by the
   full pipeline (:func:`bftaichi.run`: TSDF bootstrap and posterior, outputs in ``out_dir``);
   the others are held out (every ``held_out_stride``-th of them is evaluated). With ``block
   = B`` every ``every``-th block of ``B`` consecutive frames is fused instead
   (:func:`split_frames`): a recorded trajectory's pose errors drift, so a held-out frame
   between two fused ones shares most of theirs and flatters the sigma; a block keeps the
   held-out views away in time, as where a map is used later.
2. For each held-out frame, render depth at its pose from each reconstruction:
   - ``bftaichi``: the posterior mean's first ``mu = 0`` crossing through observed band cells
     (:func:`kernels.raycast.raycast_depth`), with the depth's standard deviation ``sigma_z``;
   - ``tsdf``: ray casting of ``tsdf_mesh.ply`` (Embree, :class:`bftaichi.formats.synthetic.DepthRenderer`);
   - ``open3d`` (when Open3D is installed): ray casting of the triangle mesh of Open3D's
     ``VoxelBlockGrid`` fused from the same frames, same voxel size, truncation ``alpha * tau``
     (the bootstrap's) and depth range.
3. Compare with the measured depth ``D`` on the pixels where both have a value:
   ``|z_pred - D|``: mean, median, and the fraction within 1, 2 and 5 cm; *completeness*: the
   fraction of the valid measured pixels for which the method predicts a depth. Each method is
   scored on its own predicted pixels, and again on the pixels every method predicts
   (``methods_common_pixels``; its completeness is their share of the measured pixels): a
   method that predicts more pixels, the hard ones at edges and far away included, is then not
   judged on more. The median comes from a histogram of 0.1 mm bins (the error of a median is
   at most 0.05 mm), so memory does not grow with the frames.
4. Calibration of bftaichi's sigma on real data: the held-out measurement is itself noisy, so
   the residual is normalised by both: ``r = (z_pred - D) / sqrt(sigma_z^2 + sigma_D^2)``,
   ``sigma_D^2 = (a + b (D - z0)^2)^2 + e^2``: the configured depth noise model
   (``[observation]``, without the incidence factor) and the extra per-pixel noise ``e`` the run
   fitted to the *fused* frames (``observation.fit_noise``; both read back from ``band.npz``
   with the posterior; ``e`` = 0 when the fit is off). The held-out frames play no part in
   that fit. Reported: the fraction with ``|r| <= 1, 2, 3`` (ideal 68.3 / 95.4 / 99.7 %) and
   the same for ``sigma_z`` alone.

Every method renders in the run's local frame (``band.npz`` ``origin``): held-out poses, the
TSDF mesh and Open3D's fused frames are moved into it, so a scene far from the world origin is
judged like one near it (Embree and Open3D compute in float32).
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import ConfigError
from ..frame import local_frames
from ..geometry import mesh_in_local, nearest_rigid, pose_in_local

__all__ = ["evaluate_views", "split_frames"]

_BIN_M = 1e-4  # histogram bin of |error| for the median, metres
_MAX_ERR_M = 2.0  # errors beyond this fall in the last bin (counted in the mean exactly)


def split_frames(frames, every: int, block: int = 1):
    """``(fused, held_out)``: a view of the frame source at the positions ``i`` with ``(i //
    block) % every == 0`` (datasets split with ``subset``, synthetic sequences by index) and
    the other positions. ``block = 1``: positions 0, every, 2 every, ... fused, the frames
    between held out; ``block = B``: blocks of ``B`` consecutive frames, one fused and ``every
    - 1`` held out in turn, so a held-out frame lies up to ``B (every - 1)`` frames from the
    fused ones."""
    if every < 2:
        raise ConfigError(f"every = {every}: need at least 2 (one fused frame per held-out one)")
    _check_block(block)
    n = len(frames)
    if n <= block:
        raise ConfigError(f"{n} frames: too few to hold any out with every = {every} and "
                          f"block = {block}")
    fused = [i for i in range(n) if (i // block) % every == 0]
    held = [i for i in range(n) if (i // block) % every]
    pick = slice(0, None, every) if block == 1 else fused
    if hasattr(frames, "subset"):
        return frames.subset(pick), held
    from ..running.pipeline import _SlicedSynthetic

    return _SlicedSynthetic(frames, pick), held


def _check_block(block) -> None:
    if not (isinstance(block, int) and block >= 1):
        raise ConfigError(f"block = {block!r}: must be an integer >= 1 (frames per block)")


#: Floor of the mean's slope along a held-out ray when its SDF sigma is turned into a depth
#: sigma (kernels.raycast.raycast_depth): at most 3.3x the SDF sigma at grazing views.
SLOPE_MIN = 0.3


class _Scores:
    """Streaming depth-error statistics of one method."""

    def __init__(self):
        self.hist = np.zeros(int(_MAX_ERR_M / _BIN_M) + 1, np.int64)
        self.sum = 0.0
        self.n = 0
        self.measured = 0
        self.within = {1: 0, 2: 0, 5: 0}

    def add(self, pred: np.ndarray, measured: np.ndarray) -> np.ndarray:
        valid = measured > 0
        both = valid & (pred > 0)
        err = np.abs(pred[both].astype(np.float64) - measured[both])
        self.measured += int(valid.sum())
        self.n += len(err)
        self.sum += float(err.sum())
        self.hist += np.bincount(np.minimum((err / _BIN_M).astype(np.int64), len(self.hist) - 1),
                                 minlength=len(self.hist))
        for cm in self.within:
            self.within[cm] += int(np.count_nonzero(err <= cm / 100.0))
        return both

    def summary(self) -> dict:
        if self.n == 0:
            return {"pixels": 0, "completeness": 0.0}
        c = np.cumsum(self.hist)
        median_bin = int(np.searchsorted(c, 0.5 * self.n))
        out = {"pixels": self.n, "mean_abs_m": self.sum / self.n,
               "median_abs_m": (median_bin + 0.5) * _BIN_M,
               "completeness": self.n / self.measured if self.measured else 0.0}
        for cm, k in self.within.items():
            out[f"within_{cm}cm"] = k / self.n
        return out


def _open3d_mesh(frames, cfg: Config):
    """Open3D's VoxelBlockGrid mesh of ``frames`` (trimesh), or None without Open3D."""
    try:
        import open3d as o3d
        import open3d.core as o3c
    except ImportError:
        return None
    import trimesh

    vs = cfg.tsdf.voxel_size_m
    trunc_voxels = cfg.tsdf.bootstrap_trunc_m / vs
    dev = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)), voxel_size=vs, block_resolution=8, block_count=100_000,
        device=dev)
    for f in frames:
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(f.depth_m, np.float32)))
        K = o3c.Tensor(f.K, o3c.float64)
        ext = o3c.Tensor(np.linalg.inv(f.T_W_C), o3c.float64)
        blocks = vbg.compute_unique_block_coordinates(depth, K, ext, 1.0, cfg.scene.depth_max_m,
                                                      trunc_voxels)
        vbg.integrate(blocks, depth, K, ext, 1.0, cfg.scene.depth_max_m, trunc_voxels)
    mesh = vbg.extract_triangle_mesh().to_legacy()
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=False)


def evaluate_views(cfg: Config, out_dir, *, every: int = 2, held_out_stride: int = 1,
                   block: int = 1, open3d: bool = True, overwrite: bool = False,
                   progress: bool = True) -> dict:
    """Fuse every ``every``-th frame (or block of ``block`` frames, :func:`split_frames`) of
    ``cfg``'s scene into ``out_dir`` and score the held-out frames (module docstring); write
    ``evalviews.json`` there and return its content. Holds the folder's writer lock throughout
    (bftaichi.running.folder)."""
    from ..io import ensure_out_dir
    from ..running.folder import hold

    cfg.check()
    _check_block(block)  # before the folder is made
    with hold(ensure_out_dir(out_dir)):
        return _evaluate_views(cfg, out_dir, every, held_out_stride, block, open3d, overwrite,
                               progress)


def _evaluate_views(cfg: Config, out_dir, every: int, held_out_stride: int, block: int,
                    open3d: bool, overwrite: bool, progress: bool) -> dict:
    from kernels.raycast import raycast_depth

    from .. import backend
    from ..io import write_json
    from ..running.pipeline import _progress, open_frames, run
    from ..posterior import Posterior
    from ..formats.synthetic import DepthRenderer

    if cfg.run.stages != "full":
        raise ConfigError("evalviews compares the posterior with the TSDF: run.stages must be "
                          "'full'")
    if held_out_stride < 1:
        raise ConfigError(f"held_out_stride = {held_out_stride}: must be >= 1")
    frames = open_frames(cfg)
    fused, held = split_frames(frames, every, block)
    held = held[::held_out_stride]
    cfg = copy.deepcopy(cfg)
    cfg.nbv.enabled = False
    t0 = time.perf_counter()
    report = run(cfg, out_dir, overwrite=overwrite, progress=progress, frames=fused)
    t_fuse = time.perf_counter() - t0
    backend.init(cfg.run.arch)
    out = Path(out_dir)
    post = Posterior.load(out / "band.npz")
    keys, table = post.band.block_keys, post.band.block_table
    observed = post.band.observed.astype(np.uint8)
    from .metrics import load_mesh

    origin = post.origin  # the run's local frame (module docstring)
    renderers = {"tsdf": DepthRenderer(mesh_in_local(load_mesh(out / "tsdf_mesh.ply"), origin))}
    t1 = time.perf_counter()
    o3d_mesh = _open3d_mesh(local_frames(fused, origin), cfg) if open3d else None
    t_o3d = time.perf_counter() - t1
    if o3d_mesh is not None and len(o3d_mesh.faces):
        renderers["open3d"] = DepthRenderer(o3d_mesh)
    scores = {m: _Scores() for m in ("bftaichi", *renderers)}
    common = {m: _Scores() for m in scores}  # on the pixels every method predicts
    o, extra = post.observation, post.sigma_extra_m  # the solve's noise model, from band.npz
    cover = {"normalised": np.zeros(3, np.int64), "sigma_z_only": np.zeros(3, np.int64), "n": 0,
             "nll_sum": 0.0, "r2_sum": 0.0}
    sigma_z_sum = 0.0
    vs = post.voxel_size
    t2 = time.perf_counter()
    for i in _progress(held, len(held), "held-out views", progress):
        f = frames[i]
        h, w = f.depth_m.shape
        D = f.depth_m
        T_L_C = pose_in_local(f.T_W_C, origin)
        z, sz = raycast_depth(keys, table, post.mean, observed, vs, f.K, T_L_C, w, h,
                              cfg.scene.depth_min_m, cfg.scene.depth_max_m, var=post.var,
                              slope_min=SLOPE_MIN)
        both = scores["bftaichi"].add(z, D)
        r = z[both].astype(np.float64) - D[both]
        s_pred = sz[both].astype(np.float64)
        s_meas = np.hypot(o.axial_sigma_m(D[both].astype(np.float64)), extra)
        k = np.arange(1, 4)[:, None]
        s_tot = np.sqrt(s_pred ** 2 + s_meas ** 2)
        cover["normalised"] += (np.abs(r)[None] <= k * s_tot).sum(1)
        cover["nll_sum"] += float(np.sum(np.log(s_tot) + 0.5 * (r / s_tot) ** 2))
        cover["r2_sum"] += float(np.sum(r * r))
        cover["sigma_z_only"] += (np.abs(r)[None] <= k * s_pred).sum(1)
        cover["n"] += len(r)
        sigma_z_sum += float(s_pred.sum())
        T = nearest_rigid(T_L_C)
        pred = {"bftaichi": z}
        for name, renderer in renderers.items():
            pred[name] = renderer.render(f.K, T, w, h)
            scores[name].add(pred[name], D)
        all_predict = np.logical_and.reduce([p > 0 for p in pred.values()])
        for name, p in pred.items():
            common[name].add(np.where(all_predict, p, 0), D)
    t_eval = time.perf_counter() - t2
    n = max(cover["n"], 1)
    result = {
        "source": report["source"], "voxel_size_m": vs, "trunc_m": cfg.tsdf.trunc_m,
        "bootstrap_trunc_m": cfg.tsdf.bootstrap_trunc_m,
        "frames": len(frames), "fused": len(fused), "held_out_evaluated": len(held),
        "every": every, "block": block, "held_out_stride": held_out_stride,
        "methods": {m: s.summary() for m, s in scores.items()},
        "methods_common_pixels": {m: s.summary() for m, s in common.items()},
        "calibration": {
            "pixels": cover["n"],
            "coverage_normalised": (cover["normalised"] / n).tolist(),
            "coverage_sigma_z_only": (cover["sigma_z_only"] / n).tolist(),
            "mean_sigma_z_m": sigma_z_sum / n,
            # mean Gaussian NLL of r under N(0, sigma_z^2 + sigma_D^2) minus that under the best
            # constant sigma, sqrt(mean r^2) (below 0: the per-pixel sigma is informative)
            "nll_vs_constant": (cover["nll_sum"] / n
                                - (0.5 * math.log(max(cover["r2_sum"] / n, 1e-30)) + 0.5)),
            "sigma_extra_m": extra,
            "what": "|z_pred - D| <= k sqrt(sigma_z^2 + sigma_D^2), k = 1, 2, 3 (and with "
                    "sigma_z alone); sigma_D^2 = (a + b (D - z0)^2)^2 + e^2, the [observation] "
                    "model and e = sigma_extra_m fitted to the fused frames"},
        "open3d": ("not installed" if open3d and o3d_mesh is None else
                   "skipped" if not open3d else "VoxelBlockGrid, same voxel, truncation and "
                   "depth range"),
        "seconds": {"fuse": round(t_fuse, 2), "open3d": round(t_o3d, 2),
                    "evaluate": round(t_eval, 2)},
    }
    write_json(out / "evalviews.json", result)
    return result


def format_result(r: dict) -> str:
    """Markdown table of one :func:`evaluate_views` result."""
    lines = [f"held-out views of {r['source']}: {r['fused']} fused, {r['held_out_evaluated']} "
             f"evaluated, voxel {r['voxel_size_m'] * 100:g} cm",
             "| method | median abs (mm) | mean abs (mm) | within 1 / 2 / 5 cm | completeness | "
             "median / mean on the pixels all predict (mm) |",
             "|---|---|---|---|---|---|"]
    common = r.get("methods_common_pixels", {})
    for m, s in r["methods"].items():
        if not s["pixels"]:
            lines.append(f"| {m} | - | - | - | 0 | - |")
            continue
        c = common.get(m, {})
        both = (f"{1000 * c['median_abs_m']:.2f} / {1000 * c['mean_abs_m']:.2f}"
                if c.get("pixels") else "-")
        lines.append(f"| {m} | {1000 * s['median_abs_m']:.2f} | {1000 * s['mean_abs_m']:.2f} | "
                     f"{s['within_1cm']:.3f} / {s['within_2cm']:.3f} / {s['within_5cm']:.3f} | "
                     f"{s['completeness']:.3f} | {both} |")
    c = r["calibration"]
    cn, cs = c["coverage_normalised"], c["coverage_sigma_z_only"]
    lines.append(f"bftaichi sigma on real data ({c['pixels']:,} pixels, mean sigma_z "
                 f"{1000 * c['mean_sigma_z_m']:.2f} mm, extra noise fitted to the fused frames "
                 f"{1000 * c.get('sigma_extra_m', 0.0):.1f} mm): |r| <= 1 / 2 / 3 of "
                 f"sqrt(sigma_z^2 + sigma_D^2): {100 * cn[0]:.1f} / {100 * cn[1]:.1f} / "
                 f"{100 * cn[2]:.1f} %; of "
                 f"sigma_z alone: {100 * cs[0]:.1f} / {100 * cs[1]:.1f} / {100 * cs[2]:.1f} %; "
                 f"NLL minus the best constant sigma's {c['nll_vs_constant']:+.2f} nats")
    return "\n".join(lines)
