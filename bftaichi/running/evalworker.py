"""A run's ground-truth evaluation and diagnostic plots in a worker process beside the pipeline.

:class:`~.evaluation.RunEvaluation` measures the meshes against the ground truth on threads,
beside the posterior's solve and the writing of the files; but threads share the interpreter
lock with the pipeline, whose Taichi front end, kernel launches and file writing need it too,
and the plots came after them all. On the default scene (warm, 2026-12-06) the metrics and
the plots cost the run about 1 s: 5.1-5.3 s with both, 4.6-4.8 s without the plots, 4.0-4.2 s
without either. :class:`EvalWorker` runs the same :class:`~.evaluation.RunEvaluation`, and
then :func:`~.plots.write_run_plots`, in one worker process on the core the pipeline leaves
idle: the band is measured as soon as it is solved, the posterior's own plots are drawn while
its mesh is measured, and the other plots while the preview is written. Six alternating warm
runs of the default scene each: 4.98-5.15 s (median 5.02) against 5.17-5.32 s (5.24); the
development suite 93 s against 100 s (docs/measurements.md, "The evaluation in a worker
process").

The values are those of the same functions with the same arguments and seeds: ``report.json``
and the PNGs are the same bytes as when they were computed in the run's own process
(tests/test_evalworker.py). The worker process is spawned (it holds no copy of Taichi's state,
and it does not run the caller's main script: :func:`_without_main`) once per Python process
and reused by later runs, so a suite of runs pays its start-up once; it ignores Ctrl-C (the
run's process stops it) and is terminated at exit.
"""

from __future__ import annotations

import atexit
import itertools
import sys
import threading
import types
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ..errors import BftaichiError

__all__ = ["EvalWorker"]


@dataclass
class BandView:
    """What the evaluation and the plots read of a :class:`~bftaichi.posterior.Posterior`
    (its band's voxels, their mean and variance), without the rest of it."""

    ijk: np.ndarray
    origin: np.ndarray
    voxel_size: float
    weight: np.ndarray
    mean: np.ndarray
    var: np.ndarray

    @property
    def sigma(self) -> np.ndarray:
        """As :attr:`bftaichi.posterior.Posterior.sigma`."""
        return np.sqrt(np.maximum(self.var, 0)).astype(np.float32)

    @classmethod
    def of(cls, post) -> BandView:
        return cls(np.asarray(post.ijk), np.asarray(post.origin, np.float64),
                   float(post.voxel_size), np.asarray(post.weight), np.asarray(post.mean),
                   np.asarray(post.var))


# -- the worker process's side -------------------------------------------------------------------

_RUNS: dict = {}  # run token -> {"evaluation", "gt", "judged"}, in the worker process


def _warm_up(plots: bool) -> None:
    """Worker initializer: leave Ctrl-C to the run's process, and import what the jobs need."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from ..evaluation import metrics  # noqa: F401
    from . import evaluation  # noqa: F401

    if plots:
        import matplotlib.figure  # noqa: F401

        from . import plots as _plots  # noqa: F401


def _mesh(vertices, faces, attributes=None):
    import trimesh

    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False,
                           vertex_attributes=attributes or {})


def _start(token: int, gt_vertices, gt_faces, eval_cfg, voxel_size_m: float, origin) -> None:
    from .evaluation import RunEvaluation

    gt = _mesh(gt_vertices, gt_faces)
    evaluation = RunEvaluation(gt, eval_cfg, voxel_size_m)
    evaluation.start(origin)
    _RUNS[token] = {"evaluation": evaluation, "gt": gt, "judged": None}


def _add_tsdf(token: int, vertices, faces) -> None:
    _RUNS[token]["evaluation"].add_tsdf(_mesh(vertices, faces))


def _add_band(token: int, band: BandView) -> None:
    _RUNS[token]["evaluation"].add_band(band)


def _add_posterior(token: int, band: BandView, vertices, faces, name: str, sigma) -> None:
    _RUNS[token]["evaluation"].add_posterior(band, _mesh(vertices, faces, {name: sigma}))


def _results(token: int) -> dict:
    run = _RUNS[token]
    run["judged"] = run["evaluation"].results()
    return run["judged"]


def _plots(token: int, report: dict, out_dir: str, band: BandView | None, which) -> list:
    from .plots import write_run_plots

    run = _RUNS[token]
    judged = run["judged"] or {}
    return write_run_plots(report, out_dir, post=band, gt=run["gt"],
                           distances=judged.get("distances"),
                           vertex_errors=judged.get("vertex_errors"), which=which)


def _close(token: int) -> None:
    run = _RUNS.pop(token, None)
    if run is not None:
        run["evaluation"].__exit__(None, None, None)


# -- the run's side ------------------------------------------------------------------------------

_pool = None
_worker_pid = None
_pool_lock = threading.Lock()
_tokens = itertools.count()


def _executor(plots: bool):
    """The worker process (one, spawned, started on first use and kept for later runs)."""
    global _pool
    with _pool_lock:
        if _pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            _pool = ProcessPoolExecutor(max_workers=1,
                                        mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_warm_up, initargs=(plots,))
            with _without_main():  # the first job starts the worker process
                _pool.submit(_pid).add_done_callback(_record_pid)
            atexit.register(_shutdown)
        return _pool


@contextmanager
def _without_main():
    """Hide the caller's ``__main__`` from a spawned process. A spawned process imports the
    parent's main script (to find functions defined there); ours needs none of it, and a
    user's script that calls :func:`bftaichi.run` at top level, without ``if __name__ ==
    "__main__":``, would run again in it."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


def _record_pid(job) -> None:
    global _worker_pid
    if job.exception() is None:
        _worker_pid = job.result()


def _pid() -> int:
    import os

    return os.getpid()


def _shutdown() -> None:
    """Stop the worker process: every run has waited for its jobs, so it is idle; it is
    terminated rather than asked to exit, since its interpreter's teardown (matplotlib, scipy,
    trimesh) took 0.2-0.3 s that the run's process would wait for."""
    import multiprocessing

    global _pool, _worker_pid
    with _pool_lock:
        pool, _pool = _pool, None
        pid, _worker_pid = _worker_pid, None
    if pool is None:
        return
    if pid is None:  # not started yet (or failed to): let it exit the usual way
        pool.shutdown(wait=True, cancel_futures=True)
        return
    pool.shutdown(wait=False, cancel_futures=True)
    for child in multiprocessing.active_children():
        if child.pid == pid:
            child.terminate()
            child.join(5)


class EvalWorker:
    """:class:`~.evaluation.RunEvaluation`'s calls (:meth:`start`, :meth:`add_tsdf`,
    :meth:`add_posterior`, :meth:`results`, the same arguments and results), run in the worker
    process, plus :meth:`plots` / :meth:`wait_plots` (:func:`~.plots.write_run_plots` with the
    run's own distances and vertex errors). Each call only queues its job; :meth:`results` and
    :meth:`wait_plots` wait. Use as a context manager: leaving it drops the run's state in the
    worker. A job's exception is raised by the call that waits for it; a worker process that
    died raises BftaichiError (and the next run starts another)."""

    def __init__(self, gt, eval_cfg, voxel_size_m: float, plots: bool = False):
        self._pool = _executor(plots)
        self._token = next(_tokens)
        self._gt = (np.asarray(gt.vertices, np.float64), np.asarray(gt.faces))
        self._cfg, self._voxel_size_m = eval_cfg, float(voxel_size_m)
        self._jobs: list = []
        self._plot_jobs: list = []
        self._plotted: set = set()
        self._band = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        try:
            self._submit(_close, self._token).result()
        except Exception:  # noqa: BLE001  (a broken worker: nothing of this run is left in it)
            pass

    def _submit(self, fn, *args):
        from concurrent.futures.process import BrokenProcessPool

        try:
            job = self._pool.submit(fn, *args)
        except (BrokenProcessPool, RuntimeError) as e:
            _shutdown()
            raise BftaichiError(f"the evaluation worker process is gone ({e}); run again") \
                from None
        self._jobs.append(job)
        return job

    def _wait(self, job):
        from concurrent.futures.process import BrokenProcessPool

        try:
            return job.result()
        except BrokenProcessPool as e:
            _shutdown()
            raise BftaichiError(f"the evaluation worker process ended unexpectedly ({e}); "
                                "run again, or set run.plots=false and drop the ground truth "
                                "to run without it") from None

    def start(self, origin) -> None:
        self._submit(_start, self._token, *self._gt, self._cfg, self._voxel_size_m,
                     np.asarray(origin, np.float64).copy())

    def add_tsdf(self, mesh) -> None:
        self._submit(_add_tsdf, self._token, np.asarray(mesh.vertices, np.float64),
                     np.asarray(mesh.faces))

    def add_band(self, post) -> None:
        self._band = BandView.of(post)
        self._submit(_add_band, self._token, self._band)

    def add_posterior(self, post, post_mesh) -> None:
        name = self._cfg.vertex_sigma
        self._submit(_add_posterior, self._token, self._band or BandView.of(post),
                     np.asarray(post_mesh.vertices, np.float64), np.asarray(post_mesh.faces),
                     name, np.asarray(post_mesh.vertex_attributes[name]))

    def results(self) -> dict:
        job = self._submit(_results, self._token)
        for earlier in self._jobs[:-1]:  # their exceptions first, in order
            self._wait(earlier)
        return self._wait(job)

    def plots(self, report: dict, out_dir, post=None, which=None) -> None:
        """Start writing the run's plots ``which`` (names of :data:`~.plots.PLOTS`; default:
        those not started yet) into ``out_dir``, as :func:`~.plots.write_run_plots` with the
        run's ground truth, distances and vertex errors; :meth:`wait_plots` waits for all.
        Those that need no ground truth (the posterior's sigma histogram and PCG residual) can
        start as soon as ``mesh.ply`` is written, with a ``report`` that holds what they read
        (``scene``, ``tsdf``, ``config``, ``solver``)."""
        from .plots import PLOTS

        which = tuple(p for p in (PLOTS if which is None else which) if p not in self._plotted)
        self._plotted.update(which)
        band = None if post is None else (self._band or BandView.of(post))
        self._plot_jobs.append(self._submit(_plots, self._token, report, str(out_dir), band,
                                            which))

    def wait_plots(self) -> None:
        for job in self._plot_jobs:
            self._wait(job)
