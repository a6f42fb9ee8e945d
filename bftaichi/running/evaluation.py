"""A run's ground-truth evaluation, computed beside the pipeline instead of after it.

:func:`bftaichi.running.pipeline.run` judges its meshes against the ground truth (DESIGN.md
section 6): surface distances of both meshes, the vertex sigma's calibration against the exact
vertex errors, and the band's. Most of that needs only the ground truth and the TSDF mesh, which
exist long before the posterior is solved, and the posterior keeps one of the two cores busy
only part of the time (a warm default run: 2.6 s of wall time, 3.1 s of CPU time). So
:class:`RunEvaluation` prepares the ground truth (sampled and indexed for the distances and for
the band's signed distance) and measures the TSDF mesh on worker threads while the posterior is
solved, and measures the posterior's mesh and band on two threads (and imports the plotting
library) while the run writes its files. The k-d tree queries and NumPy release the GIL.
Measured (``python tools/bench_startup.py --repeats 3 --ab`` of a temporary switch, warm runs
of the default scene, medians): preparing the ground truth only after the posterior instead,
6.21 s against 5.73 s; importing matplotlib beside the posterior (its Taichi front end needs
the GIL too), 5.84 s against 5.61 s (docs/measurements.md, "Start-up: what a warm run spends
outside the model").

The values are those of the functions it calls, with the same arguments and seeds (the same
bytes in report.json and the plots); only the order in which they are computed changes. Every
job works on arrays and meshes of its own, never on an object the main thread touches (trimesh
caches are not thread-safe).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

__all__ = ["RunEvaluation"]

#: The band's signed distance is prepared beside the posterior only up to this many samples of
#: the ground truth (every voxel / 4: ~60 MB with its k-d tree; the default scene's 0.25 M):
#: beyond, it would add to the solve's peak memory, so it waits until the posterior is solved.
AHEAD_SAMPLES = 1_000_000


def _own_mesh(mesh):
    """A private copy of ``mesh``'s vertices and faces (no attributes, no caches shared)."""
    import trimesh

    return trimesh.Trimesh(vertices=np.array(mesh.vertices, np.float64),
                           faces=np.array(mesh.faces), process=False)


class RunEvaluation:
    """The metrics of one run against its ground-truth mesh ``gt`` (world coordinates),
    configured by ``eval_cfg`` (``[eval]``). (:class:`~.evalworker.EvalWorker` runs it in
    a worker process, whose start-up imports the plotting library.)

    Call in order: :meth:`start` once the grid's origin is known, :meth:`add_tsdf`,
    :meth:`add_posterior` (full runs), then :meth:`results`. Use as a context manager: leaving
    it cancels what has not started and waits for the rest, so a failed run leaves no thread
    behind. An exception in a job is raised by :meth:`results`.
    """

    def __init__(self, gt, eval_cfg, voxel_size_m: float):
        self.gt, self.cfg, self.voxel_size_m = gt, eval_cfg, float(voxel_size_m)
        self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="bftaichi-eval")
        self._prepared = self._tsdf = self._post = self._band = None
        self._origin = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._pool.shutdown(wait=True, cancel_futures=True)

    def start(self, origin) -> None:
        """Prepare the ground truth in the grid's local frame at ``origin`` (world metres)."""
        self._origin = np.asarray(origin, np.float64).copy()
        self._prepared = self._pool.submit(self._prepare, self._origin)

    def _prepare(self, origin):
        from ..evaluation.metrics import SampledSurface, band_sdf
        from ..geometry import mesh_in_local

        gt_local = mesh_in_local(self.gt, origin)
        target = SampledSurface(gt_local, self.cfg.n_samples, self.cfg.seed)
        target.index()
        sdf = None  # a large ground truth's band SDF waits for the posterior to free its memory
        if self.gt.area / (self.voxel_size_m / 4) ** 2 <= AHEAD_SAMPLES:
            sdf = band_sdf(self.gt, origin, self.voxel_size_m, self.cfg.seed)
        return gt_local, target, sdf

    def add_tsdf(self, mesh) -> None:
        """Measure the TSDF mesh (local frame) against the ground truth."""
        own = _own_mesh(mesh)
        self._tsdf = self._pool.submit(lambda: self._prepared.result()[1].distances(own))

    def add_band(self, post) -> None:
        """Measure the posterior's band against the ground truth (as soon as it is solved,
        before its mesh is extracted); :meth:`add_posterior` does it if this was not called."""
        self._band = self._pool.submit(self._judge_band, post)

    def add_posterior(self, post, post_mesh) -> None:
        """Measure the posterior's mesh (local frame, with its vertex ``eval.vertex_sigma``
        attribute) and band against the ground truth: the distances on one thread, the band
        and the vertex errors on the other."""
        if self._band is None:
            self.add_band(post)
        own = _own_mesh(post_mesh)  # the distances' (one thread per object)
        vertices = np.array(post_mesh.vertices, np.float64)  # the vertex errors'
        sigma = np.array(post_mesh.vertex_attributes[self.cfg.vertex_sigma], np.float64)
        distances = self._pool.submit(lambda: self._prepared.result()[1].distances(own))
        self._post = (distances, self._pool.submit(self._judge_vertices, vertices, sigma))

    def _judge_band(self, post):
        from ..evaluation.metrics import band_sdf, band_uncertainty

        _, _, sdf = self._prepared.result()
        if sdf is None or not np.array_equal(np.asarray(post.origin, np.float64), self._origin):
            sdf = band_sdf(self.gt, post.origin, self.voxel_size_m, self.cfg.seed)
        return band_uncertainty(post, self.gt, self.cfg.near_voxels, self.cfg.seed, sdf)

    def _judge_vertices(self, vertices, sigma):
        from ..evaluation.metrics import uncertainty_metrics, vertex_errors

        gt_local = self._prepared.result()[0]
        errors = uncertainty = None
        if len(sigma) >= 2:  # vertex_uncertainty's rule, with the errors kept for the plots
            errors = vertex_errors(vertices, gt_local)
            uncertainty = uncertainty_metrics(errors, sigma, np.zeros_like(errors))
        return errors, uncertainty

    def results(self) -> dict:
        """``{"distances": {name: (d_pg, d_gp) or None}, "uncertainty", "band_uncertainty",
        "vertex_errors"}`` (the last three None for a TSDF-only run; ``vertex_errors`` (V,) the
        exact errors of the posterior mesh's vertices, metres)."""
        out = {"distances": {"tsdf_mesh.ply": self._tsdf.result()}, "uncertainty": None,
               "band_uncertainty": None, "vertex_errors": None}
        if self._post is not None:
            out["distances"]["mesh.ply"] = self._post[0].result()
            out["vertex_errors"], out["uncertainty"] = self._post[1].result()
            out["band_uncertainty"] = self._band.result()
        return out
