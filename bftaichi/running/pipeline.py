"""A run: frames -> TSDF bootstrap -> (probabilistic posterior) -> meshes -> metrics -> the
DESIGN.md section 4 outputs.

``run.stages = "full"`` (default) writes ``tsdf_mesh.ply``, ``mesh.ply`` (with per-vertex
``sigma`` and ``sigma_pos``), ``band.npz`` (band voxels: ``ijk, voxel_size, mean, var, cov,
tsdf, weight, origin``), ``report.json`` and
``config.toml``. ``"tsdf_only"`` stops after the bootstrap; its ``band.npz`` then holds every
observed voxel's ``tsdf`` and ``weight``. Meshes are in world coordinates, ``band.npz``'s
``ijk`` in the local grid of ``origin`` (report.json ``origin_m``; see
:mod:`bftaichi.reconstructor`).
"""

from __future__ import annotations

import dataclasses

import os
import platform
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np
import trimesh

from .. import backend
from ..config import Config, parse_slice, save_config
from ..errors import BftaichiError, ConfigError, DataError, NoSurfaceError
from ..frame import clean_depth
from ..io import ensure_out_dir, prepare_out_dir, write_json, write_mesh_ply, write_npz
from ..posterior import mesh_attrs
from ..reconstructor import Reconstructor
from ..version import __version__
from . import folder

__all__ = ["open_frames", "run", "load_gt_mesh"]


def open_frames(cfg: Config):
    """The frame source of a config: a SyntheticDataset or a recorded dataset (lazy)."""
    s = cfg.scene
    if s.source == "synthetic":
        from ..formats.synthetic import SyntheticDataset

        ds = SyntheticDataset(cfg.synthetic, s.depth_min_m, s.depth_max_m)
        if s.frames:
            sl = parse_slice(s.frames, "scene.frames")
            ds = _SlicedSynthetic(ds, sl)
        return ds
    from ..formats import open_dataset

    if not Path(s.data).exists():
        raise DataError(f"scene.data: dataset folder {s.data} does not exist "
                        "(shared data lives in ../shared/data relative to the project root; "
                        "see ../shared/data/README.md)")
    frames = parse_slice(s.frames, "scene.frames") if s.frames else None
    return open_dataset(s.data, format=s.format, depth_min_m=s.depth_min_m,
                        depth_max_m=s.depth_max_m, frames=frames,
                        load_rgb=cfg.tsdf.integrate_rgb, depth_scale=s.depth_scale or None,
                        pose_convention=s.pose_convention)


class _SlicedSynthetic:
    """A slice of a synthetic sequence that keeps the dataset's attributes."""

    def __init__(self, ds, sl: slice | list[int]):
        self._ds = ds
        self._idx = (list(range(len(ds)))[sl] if isinstance(sl, slice)
                     else [range(len(ds))[i] for i in sl])
        if not self._idx:
            raise DataError(f"scene.frames selects no frame of the {len(ds)} synthetic views")
        self.K, self.image_size, self.name = ds.K, ds.image_size, ds.name
        self.gt_mesh, self.gt_mesh_path = ds.gt_mesh, ds.gt_mesh_path
        self.poses = ds.poses[self._idx]

    def __len__(self):
        return len(self._idx)

    def __getitem__(self, i):
        return self._ds[self._idx[i]]

    def __iter__(self):
        return (self._ds[i] for i in self._idx)


def load_gt_mesh(cfg: Config, frames) -> trimesh.Trimesh | None:
    """Ground truth for metrics: the synthetic mesh, ``scene.gt_mesh``, or the dataset's own."""
    from ..evaluation.metrics import load_mesh

    if getattr(frames, "gt_mesh", None) is not None:
        return frames.gt_mesh
    path = cfg.scene.gt_mesh
    if path == "auto" or not path:
        path = getattr(frames, "gt_mesh_path", None)
        if not path:
            return None
    return load_mesh(path, surface=True)


class _Timer:
    """Seconds per stage; ``current`` is the stage running (or the last one started)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.current = "start"
        self.rss = None  # a resources.PeakRSS: peak memory per stage too

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        self.current = stage
        try:
            with (self.rss(stage) if self.rss is not None else nullcontext()):
                yield
        finally:
            self.seconds[stage] = round(self.seconds.get(stage, 0.0) + time.perf_counter() - t0, 4)


#: Everything a run writes into its folder (files and the plots/ folder).
RUN_OUTPUTS = ("tsdf_mesh.ply", "mesh.ply", "band.npz", "report.json", "config.toml",
               "preview.html", "nbv.json", "evalviews.json", "plots", "fusion_state.npz")


class SolverError(BftaichiError):
    """A solve did not converge and ``run.strict`` asks not to write its result."""


def _record_failure(out: Path, stage: str, error: BaseException) -> None:
    """Record a run that did not complete: ``report.json`` with ``status`` ``failed`` /
    ``interrupted`` and the stage when the folder holds no run, else ``failed_run.json`` next
    to the previous run's files (the next complete run removes it)."""
    from .signals import describe_interrupt

    interrupted = isinstance(error, KeyboardInterrupt)
    record = {"status": "interrupted" if interrupted else "failed", "stage": stage,
              "error": describe_interrupt(error) if interrupted else
              f"{type(error).__name__}: {error}"}
    previous = (out / "report.json").exists()
    try:
        write_json(out / ("failed_run.json" if previous else "report.json"), record)
    except BftaichiError:
        pass  # the folder cannot be written (disk full, ...): nothing more to keep


def _progress(iterable, total: int, desc: str, enabled: bool, unit: str = "frame"):
    """A tqdm bar on stderr; off when ``enabled`` is False, and by itself (``disable=None``)
    when stderr is not a terminal (CI, pipes)."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=None if enabled else True,
                leave=False)


READERS = 2
"""Frames read ahead, each by its own thread. Pillow decodes a PNG without the GIL, so with two
the TSDF pass (2 ms of kernel against ~5 ms of decoding a frame at 2 cm) waits less: the TSDF
pass with its waits 4.9-5.1 -> 4.2-4.7 s on 500 redkitchen frames (docs/measurements.md)."""


class _FrameReader:
    """Iterate over frames in order while the next :data:`READERS` frames are read in
    background threads. Taichi holds the GIL while a kernel runs
    (docs/experiments/kernel_gil.py), so the threads read between kernels and while the loop
    waits for them; a reader process beside the kernels saved nothing (docs/measurements.md,
    "Taichi kernels hold the GIL"). Accumulates the seconds spent waiting."""

    def __init__(self, progress: bool):
        self.progress = progress
        self.wait_s = 0.0

    def __call__(self, frames, desc: str):
        n = len(frames)
        with ThreadPoolExecutor(max_workers=READERS) as reader:
            pending = deque(reader.submit(frames.__getitem__, i) for i in range(min(READERS, n)))
            for i in _progress(range(n), n, desc, self.progress):
                t0 = time.perf_counter()
                frame = pending.popleft().result()
                self.wait_s += time.perf_counter() - t0
                if i + READERS < n:
                    pending.append(reader.submit(frames.__getitem__, i + READERS))
                yield frame


def run(cfg: Config, out_dir: str | os.PathLike, *, overwrite: bool = False,
        progress: bool = True, frames=None, update=None) -> dict:
    """Run the pipeline of ``cfg`` and write its outputs into ``out_dir``; return the report.

    ``frames``: a frame source to use instead of the one ``cfg.scene`` describes (a dataset
    or a subset of one, with ``len`` and indexing), e.g. the fused half of a held-out-view
    evaluation. ``update``: a :class:`bftaichi.running.state.UpdatePlan`, whose saved TSDF
    (with its moved frames re-fused) replaces integrating every frame (``bftaichi update``).

    Raises BftaichiError subclasses for bad input (naming the file, frame or key) and
    NoSurfaceError when no voxel was observed (then no mesh is written).
    """
    cfg.check()
    if cfg.nbv.enabled and cfg.run.stages != "full":
        raise ConfigError("nbv.enabled = true needs the posterior: run.stages must be 'full', "
                          f"not {cfg.run.stages!r}")
    timer = _Timer()
    t_start = time.perf_counter()
    with timer("load"):  # before touching the output folder: bad data leaves nothing behind
        frames = open_frames(cfg) if frames is None else frames
        gt = load_gt_mesh(cfg, frames)
    from .resources import PeakRSS, check_memory

    with timer("memory_check"):  # before the output folder: a refused run writes nothing
        memory = check_memory(cfg, frames)  # may choose run.chunk_m to fit the budget
    if memory.get("chunk_m_chosen"):
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(
            cfg.run, chunk_m=memory["chunk_m_chosen"]))
    from ..plausibility import check_inputs

    with timer("checks"):  # also starts Taichi, and sets cfg.run.arch to the backend that runs
        checks = check_inputs(cfg, frames)  # warns; with run.strict, a refusal writes nothing
    timer.rss = PeakRSS()
    out = ensure_out_dir(out_dir)
    with folder.hold(out):  # one writer at a time; the check below cannot race
        prepare_out_dir(out, overwrite=overwrite)
        staging = folder.Staging(out)
        try:
            report = _run_stages(cfg, frames, gt, staging.dir, timer, t_start, progress, memory,
                                 checks, update)
            timer.current = "commit"
            staging.commit(remove=RUN_OUTPUTS + ("failed_run.json",))
        except BaseException as e:
            staging.discard()
            _record_failure(out, timer.current, e)
            raise
    return report


def _run_stages(cfg: Config, frames, gt, out: Path, timer, t_start: float, progress: bool,
                memory: dict, checks, update=None):
    """The stages of :func:`run`, writing into the staging folder ``out``; ``checks``: what
    :func:`~bftaichi.plausibility.check_inputs` found. With a ground truth, its metrics are
    computed beside the stages, in a worker process (:class:`~.evalworker.EvalWorker`)."""
    if gt is None:
        return _stages(cfg, frames, None, out, timer, t_start, progress, memory, checks, update)
    from .evalworker import EvalWorker

    with EvalWorker(gt, cfg.eval, cfg.tsdf.voxel_size_m, plots=cfg.run.plots) as evaluation:
        return _stages(cfg, frames, gt, out, timer, t_start, progress, memory, checks, update,
                       evaluation)


def _stages(cfg: Config, frames, gt, out: Path, timer, t_start: float, progress: bool,
            memory: dict, checks, update=None, evaluation=None):
    """:func:`_run_stages`' body (``evaluation``: an EvalWorker to start, or None)."""
    with timer("init"):
        backend.init(cfg.run.arch)
    recon = Reconstructor(cfg)
    reader = _FrameReader(progress)
    cameras = {"K": None, "image_size": None, "poses": []}  # for the preview
    names, poses = [], []  # what fusion_state.npz keeps
    with timer("tsdf"):
        if update is not None:  # bftaichi update: the saved sums, the moved frames re-fused
            s = cfg.scene
            update.apply(recon, frames.frames,
                         lambda d: clean_depth(d, s.depth_min_m, s.depth_max_m))
            first = frames[update.moved[0]]
            cameras.update(K=np.asarray(first.K).tolist(),
                           image_size=[first.depth_m.shape[1], first.depth_m.shape[0]],
                           poses=update.new.tolist())
            names, poses = update.names, list(update.new)
        for frame in (reader(frames, "integrate") if update is None else ()):  # step 1; the
            recon.integrate(frame.depth_m, frame.K, frame.T_W_C, rgb=frame.rgb,  # posterior
                            name=frame.name, keep=False)  # re-reads the frames
            if cameras["K"] is None:
                cameras["K"] = np.asarray(frame.K).tolist()
                cameras["image_size"] = [frame.depth_m.shape[1], frame.depth_m.shape[0]]
            cameras["poses"].append(np.asarray(frame.T_W_C).tolist())
            names.append(frame.name)
            poses.append(np.asarray(frame.T_W_C, np.float64))
    timer.seconds["tsdf"] = round(timer.seconds["tsdf"] - reader.wait_s, 4)
    state_bytes = None
    if cfg.run.keep_state:
        from .state import STATE_FILE, save_state

        with timer("state"):
            state_bytes = save_state(out / STATE_FILE, recon.tsdf, names, poses)
    stats = recon.tsdf.stats()
    with timer("export"):
        voxels = recon.voxels
    if len(voxels["ijk"]) == 0:
        raise NoSurfaceError(
            f"{cfg.scene.data or getattr(frames, 'name', 'the scene')}: "
            f"no surface was observed in {stats['frames']} frames ({stats['pixels']} valid depth "
            "pixels): check the depth range (scene.depth_min_m / depth_max_m), the depth scale, and "
            "that poses are T_W_C (camera-to-world), not T_C_W. No mesh was written.")
    # Meshes and metrics in the grid's local frame (float32-exact; distances do not depend on
    # the frame); the files and report.json in world coordinates (recon.origin added back).
    with timer("mesh"):
        mesh = recon.tsdf_mesh(local=True)
    if len(mesh.faces) == 0:
        raise NoSurfaceError(
            f"{len(voxels['ijk'])} voxels were observed but no cell has all 8 corners with weight >= "
            f"mesh.min_weight = {cfg.mesh.min_weight}, so there is no surface to mesh; lower "
            "mesh.min_weight or add frames. No mesh was written.")
    if evaluation is not None:  # the ground truth and the TSDF mesh, beside the posterior
        evaluation.start(recon.origin)
        evaluation.add_tsdf(mesh)
    post = post_mesh = None
    if cfg.run.stages == "full":
        wait0 = reader.wait_s
        with timer("posterior"):
            post = recon.solve(frames, frame_iter=reader)  # steps 2-6
        timer.seconds["posterior"] = round(timer.seconds["posterior"] - (reader.wait_s - wait0), 4)
        if evaluation is not None:  # the band against the truth, while its mesh is extracted
            evaluation.add_band(post)
        if cfg.run.strict and not post.solver["converged"]:
            m = post.solver
            raise SolverError(
                f"the MAP solve did not converge ({m.get('reason', 'stopped')}; "
                f"{m['iterations']} iterations, relative residual {m['relative_residual']:.2e} "
                f"> solver.tol = {cfg.solver.tol:g}); run.strict refuses to write its mesh: "
                "raise solver.maxiter, check the scene, or run without --strict (the mesh is "
                "then written and flagged in report.json)")
        with timer("mesh"):
            post_mesh = post.extract_mesh(local=True)  # step 7
    timer.seconds["read_frames"] = round(reader.wait_s, 4)  # time spent waiting for frames
    if evaluation is not None and post is not None:
        evaluation.add_posterior(post, post_mesh)  # measured while the files are written
    with timer("write"):
        colors = mesh.visual.vertex_colors[:, :3] if cfg.tsdf.integrate_rgb else None
        write_mesh_ply(out / "tsdf_mesh.ply", mesh.vertices, mesh.faces, vertex_colors=colors,
                       origin=recon.origin)
        vs32 = np.float32(cfg.tsdf.voxel_size_m)
        if post is None:
            write_npz(out / "band.npz", ijk=voxels["ijk"], voxel_size=vs32, tsdf=voxels["tsdf"],
                      weight=voxels["weight"], origin=recon.origin)
        else:
            post_colors = None
            if colors is not None and len(post_mesh.vertices):
                from ..stages.surface import sample_field

                # the TSDF's per-voxel colour at the posterior surface (nearest observed voxels)
                rgb = sample_field(voxels["ijk"], voxels["rgb"], voxels["weight"] > 0,
                                   cfg.tsdf.voxel_size_m, post_mesh.vertices)
                post_colors = np.clip(np.nan_to_num(rgb), 0, 255).astype(np.uint8)
            write_mesh_ply(out / "mesh.ply", post_mesh.vertices, post_mesh.faces,
                           vertex_attrs=mesh_attrs(post_mesh),
                           vertex_colors=post_colors, origin=recon.origin)
            write_npz(out / "band.npz", **post.band_arrays())
        save_config(cfg, out / "config.toml")
    tsdf_info = {"voxel_size_m": cfg.tsdf.voxel_size_m,
                 "bootstrap_trunc_m": cfg.tsdf.bootstrap_trunc_m}
    if cfg.run.plots and evaluation is not None and post is not None:
        # the posterior's own plots (what they read of the report), while the worker still
        # measures it against the truth
        evaluation.plots({"scene": cfg.scene.name, "config": cfg.to_dict(), "tsdf": tsdf_info,
                          "solver": {"map": post.solver}}, out, post,
                         which=("sigma_histogram", "pcg_residual"))
    metrics, distances, judged = {}, {}, {}
    if evaluation is not None:
        from ..evaluation.metrics import metrics_from_distances

        with timer("metrics"):
            judged = evaluation.results()
            for name, m in (("tsdf_mesh.ply", mesh), ("mesh.ply", post_mesh)):
                if m is not None:
                    distances[name] = judged["distances"][name]
                    metrics[name] = metrics_from_distances(distances[name],
                                                           cfg.eval.thresholds_mm, len(m.faces))
    uncertainty, band_unc = judged.get("uncertainty"), judged.get("band_uncertainty")
    report = {
        "status": "complete",
        "bftaichi_version": __version__,
        "scene": cfg.scene.name,
        "source": getattr(frames, "name", cfg.scene.data),
        "stages_run": ["tsdf", "mesh"] + (["posterior"] if post else [])
        + (["metrics"] if metrics else []),
        "seconds": {**timer.seconds, "total": round(time.perf_counter() - t_start, 4)},
        "counts": {
            "frames": stats["frames"],
            "empty_frames": stats["empty_frames"],
            "pixels_used": stats["pixels"],
            "observed_voxels": int(len(voxels["ijk"])),
            "blocks": stats["blocks"],
            "activation_stride": stats["activation_stride"],
            "out_of_range_samples": stats["out_of_range_samples"],
            "tsdf_mesh_vertices": int(len(mesh.vertices)),
            "tsdf_mesh_faces": int(len(mesh.faces)),
            **({"band_voxels": int(len(post.ijk)), "mesh_vertices": int(len(post_mesh.vertices)),
                "mesh_faces": int(len(post_mesh.faces))} if post else {}),
        },
        "solver": ({"map": post.solver, "variance": post.variance,
                    "observations": post.observations, "seconds": post.seconds}
                   if post else None),
        "flags": ([] if post is None else
                  (["map_not_converged"] if not post.solver["converged"] else [])
                  + ([f"{post.variance['n_not_converged']}_probes_not_converged"]
                     if post.variance.get("n_not_converged") else [])),
        "tsdf": tsdf_info,
        # world position of the local grid (band.npz ijk); meshes, cameras and NBV poses are
        # world coordinates
        "origin_m": recon.origin.tolist(),
        "metrics": metrics,
        "uncertainty": uncertainty,
        "band_uncertainty": band_unc,
        "cameras": cameras,
        **({"fusion_state": {"file": "fusion_state.npz", "bytes": state_bytes}}
           if state_bytes is not None else {}),
        **({"update": update.summary()} if update is not None else {}),
        "has_ground_truth": gt is not None,
        "memory": {"estimate": memory, "peak_rss": timer.rss.to_dict() if timer.rss else None},
        "machine": {"python": platform.python_version(), "arch": checks.arch,
                    "arch_requested": checks.arch_requested, "cpus": os.cpu_count()},
        "warnings": checks.warnings(),
        "checks": checks.measured,
        "config": cfg.to_dict(),
    }
    if post is not None and cfg.nbv.enabled:
        from ..planning.nbv import nbv_summary, rank_run

        with timer("nbv"):
            bar = (lambda it: _progress(it, len(it), "nbv", progress, "view"))
            report["nbv"] = nbv_summary(rank_run(post, cfg, frames, out, progress=bar))
        report["seconds"]["nbv"] = timer.seconds["nbv"]
        report["seconds"]["total"] = round(time.perf_counter() - t_start, 4)
    write_json(out / "report.json", report)
    if cfg.run.plots and evaluation is not None:  # in the worker, beside the preview
        evaluation.plots(report, out, post)
    elif cfg.run.plots:
        from .plots import write_run_plots

        with timer("plots"):
            write_run_plots(report, out, post=post, gt=gt, distances=distances,
                            vertex_errors=judged.get("vertex_errors"))
        report["seconds"]["plots"] = timer.seconds["plots"]
    if cfg.run.preview:
        from .viz import write_preview

        with timer("preview"):
            write_preview(out, title=out.parent.name)  # out: the staging folder in OUT
        report["seconds"]["preview"] = timer.seconds["preview"]
    if cfg.run.plots and evaluation is not None:
        with timer("plots"):  # what is left of them once the preview is written
            evaluation.wait_plots()
        report["seconds"]["plots"] = timer.seconds["plots"]
    if cfg.run.plots or cfg.run.preview:
        report["seconds"]["total"] = round(time.perf_counter() - t_start, 4)
        write_json(out / "report.json", report)
    return report

