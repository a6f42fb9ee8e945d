"""Closed-loop active scanning on a synthetic scene (``bftaichi scan``).

Every policy starts from the same ``nbv.initial_views`` candidate views (a draw seeded by
``run.seed``; the whole scan is repeated for ``nbv.initial_seeds`` draws, seeds ``run.seed`` +
0, 1, ...) and then adds ``nbv.steps`` views, one at a time, from the same candidate set
(:func:`bftaichi.planning.nbv.make_candidates` around ``synthetic.look_at`` at ``synthetic.cam_radius_m``
unless ``nbv.target`` / ``nbv.radius_m`` say otherwise). After each view:

1. the chosen view's noisy depth is rendered from the true mesh (the scene's noise model; view
   ``c`` always draws its noise from ``default_rng([synthetic.seed, c])``, so every policy sees
   the same frame for the same view);
2. it is fused: the TSDF volume is integrated incrementally, the coverage grid marks what the
   frame saw, and the posterior is rebuilt (band and observations of all views so far), its
   PCG warm-started from the previous mean;
3. ``mesh.ply``'s metrics against the ground truth are recorded: recall (surface coverage) at
   5, 2 and 10 mm, F at 10 mm, completeness, accuracy, and for ``bayes`` the calibration of its
   vertex sigma. Summaries (:func:`runs_summary`): the area under recall@5mm and F@10mm
   against views and the views needed to reach 90 % and 95 % recall@5mm, as mean and std over
   the runs.

Policies: ``bayes`` (:class:`bftaichi.planning.nbv.Planner` utility: expected variance reduction),
``coverage`` (the classic volumetric heuristic: the distinct unseen cells a view's rays cross
before the predicted surface), ``frontier`` (frontier-based exploration, Yamauchi 1997: the
distinct frontier cells, unseen with a seen face neighbour, the rays cross before the predicted
surface; :meth:`~bftaichi.planning.nbv.CoverageGrid.count_frontier`), ``entropy`` (Isler et
al. 2016's *average entropy*: the mean occupancy entropy of every cell the rays cross before
the predicted surface, unseen cells at p = 0.5, seen ones at p = 0.12;
:meth:`~bftaichi.planning.nbv.CoverageGrid.average_entropy`), ``farthest`` (the candidate
farthest from every used view), and ``random`` (seeded; the mean over ``nbv.random_seeds``
seeds). Only ``bayes`` needs the
variance, so only its runs solve the probes.
"""

from __future__ import annotations

import functools
import os
import time
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import ConfigError

__all__ = ["POLICIES", "scan", "curve_summary", "runs_summary"]

POLICIES = ("bayes", "coverage", "frontier", "entropy", "farthest", "random")
F_KEY = "fscore@10mm"
R5, R2 = "recall@5mm", "recall@2mm"
#: surface coverage, the usual measure of active reconstruction (Isler et al. 2016, Delmerico
#: et al. 2018): the fraction of the true surface within 5 / 2 / 10 mm of the mesh
RECALL_KEYS = (R5, R2, "recall@10mm")
#: the vertex calibration of the bayes posterior's sigma (bftaichi.evaluation.metrics)
CALIBRATION_KEYS = ("coverage@1sigma", "coverage@2sigma", "coverage@3sigma", "nll_vs_constant",
                    "spearman")


class _Scene:
    """The synthetic scene: true mesh, renderer, camera, candidates and initial views."""

    def __init__(self, cfg: Config):
        from .nbv import make_candidates
        from ..formats.synthetic import DepthRenderer, intrinsics_of, make_mesh

        sc = cfg.synthetic
        self.cfg = cfg
        self.gt = make_mesh(sc)
        self.renderer = DepthRenderer(self.gt)
        self.K = intrinsics_of(sc)
        self.size = (int(sc.width), int(sc.height))
        self.target = np.asarray(cfg.nbv.target or sc.look_at, np.float64)
        self.radius = cfg.nbv.radius_m or float(sc.cam_radius_m)
        self.poses = make_candidates(cfg, self.target, self.radius)
        n = len(self.poses)
        if cfg.nbv.initial_views + cfg.nbv.steps > n:
            raise ConfigError(f"nbv.initial_views + nbv.steps = "
                              f"{cfg.nbv.initial_views + cfg.nbv.steps} views, but there are "
                              f"only {n} candidates (nbv.n_candidates)")
        self.initial = self.initial_views(0)
        self._frames = {}

    def initial_views(self, draw: int) -> list[int]:
        """The initial views of draw ``draw`` (seeded by ``run.seed + draw``)."""
        rng = np.random.default_rng(self.cfg.run.seed + draw)
        return [int(i) for i in rng.choice(len(self.poses), self.cfg.nbv.initial_views,
                                           replace=False)]

    def frame(self, c: int):
        from ..frame import Frame, clean_depth
        from ..formats.synthetic import add_noise

        if c not in self._frames:
            sc, s = self.cfg.synthetic, self.cfg.scene
            depth = self.renderer.render(self.K, self.poses[c], *self.size)
            noisy = add_noise(depth, sc, np.random.default_rng([sc.seed, c]))
            self._frames[c] = Frame(index=c, name=f"candidate-{c:03d}",
                                    depth_m=clean_depth(noisy, s.depth_min_m, s.depth_max_m),
                                    K=self.K.copy(), T_W_C=self.poses[c].copy(), rgb=None)
        return self._frames[c]


def _run_policy(scene: _Scene, policy: str, seed: int, roi, thresholds, progress,
                initial: list[int], draw: int = 0) -> dict:
    """One closed loop from the views ``initial``: the views chosen and the metrics after each
    (for ``bayes``, whose posterior has a variance, also the calibration of its vertex sigma)."""
    from ..evaluation.metrics import geometry_metrics, vertex_uncertainty
    from ..geometry import mesh_in_local
    from ..reconstructor import Reconstructor
    from .nbv import Planner, coverage_grid

    cfg = scene.cfg
    recon = Reconstructor(cfg)
    coverage = coverage_grid(cfg, *roi, cfg.tsdf.voxel_size_m)
    rng = np.random.default_rng([cfg.run.seed, seed])
    used, steps = [], []

    def add(c):
        f = scene.frame(c)
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
        coverage.mark(f.depth_m, f.K, f.T_W_C, stride=cfg.observation.stride)
        used.append(c)

    for c in initial:
        add(c)
    for step in range(cfg.nbv.steps + 1):
        t0 = time.perf_counter()
        post = recon.solve(variance=policy == "bayes")
        seconds_fuse = round(time.perf_counter() - t0, 3)
        mesh = post.extract_mesh(local=True)  # metrics in the local frame, as a run's
        gt = mesh_in_local(scene.gt, post.origin)
        m = geometry_metrics(mesh, gt, thresholds, cfg.eval.n_samples, cfg.eval.seed)
        record = {"views": len(used), "view": used[-1], F_KEY: m[F_KEY],
                  **{k: m[k] for k in RECALL_KEYS},
                  "completeness_mm": 1000.0 * m["completeness_m"],
                  "accuracy_mm": 1000.0 * m["accuracy_m"], "chamfer_m2": m["chamfer_l2"],
                  "map_converged": post.solver["converged"], "seconds_fuse": seconds_fuse}
        if policy == "bayes" and len(mesh.faces):
            u = vertex_uncertainty(mesh, gt)
            record["calibration"] = {k: u[k] for k in CALIBRATION_KEYS if k in u}
        if step == cfg.nbv.steps:
            steps.append(record)
            break
        t1 = time.perf_counter()
        free = [c for c in range(len(scene.poses)) if c not in used]
        if policy == "random":
            choice = int(rng.choice(free))
        elif policy == "farthest":
            eyes = scene.poses[:, :3, 3]
            d = np.linalg.norm(eyes[free][:, None] - eyes[used][None], axis=2).min(axis=1)
            choice = free[int(np.argmax(d))]
        else:
            planner = Planner(post, cfg, scene.K, scene.size, coverage)
            if policy == "bayes":  # the best of the ranking (nbv.rerank: after a screen)
                choice = free[planner.rank(scene.poses[free])[0]["index"]]
            else:
                score = {"coverage": coverage.count_unknown,
                         "entropy": coverage.average_entropy}.get(policy)
                if policy == "frontier":  # the frontier once per step, not per candidate
                    score = functools.partial(coverage.count_frontier,
                                              not_frontier=coverage.grid.not_frontier())
                scores = [score(planner.predict_depth(scene.poses[c]), scene.K, scene.poses[c],
                                planner.stride, planner.depth_range[1]) for c in free]
                choice = free[int(np.argmax(scores))]  # ties: the lowest candidate index
        record["seconds_choose"] = round(time.perf_counter() - t1, 3)
        steps.append(record)
        add(choice)
        if progress:
            progress(policy, seed, record)
    return {"policy": policy, "seed": seed, "initial_draw": draw, "views": used, "steps": steps}


def _auc(views: np.ndarray, y: np.ndarray) -> float:
    """Area under ``y`` against views (trapezoid) divided by the views spanned: the mean of
    ``y`` over the scan."""
    span = views[-1] - views[0]
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(views)) / span) if span else float(y[0])


def _reach(views: np.ndarray, y: np.ndarray, level: float) -> int | None:
    """The first view count with ``y >= level`` (None if never)."""
    return next((int(v) for v, x in zip(views, y) if x >= level), None)


def curve_summary(steps: list, threshold: float = 0.9) -> dict:
    """One scan's summary: the area under F@10mm and under recall@5mm against views (each
    divided by the views spanned: the mean over the scan), the first view count with F@10mm >=
    ``threshold`` and with recall@5mm >= 0.9 and >= 0.95 (None if never), and the final values."""
    views = np.array([s["views"] for s in steps], np.float64)
    f = np.array([s[F_KEY] for s in steps], np.float64)
    out = {"auc_f10": _auc(views, f), "views_to_f10_0.9": _reach(views, f, threshold),
           "final_f10": float(f[-1]),
           "final_completeness_mm": float(steps[-1]["completeness_mm"])}
    if all(R5 in s for s in steps):
        r5 = np.array([s[R5] for s in steps], np.float64)
        out.update({"auc_recall5": _auc(views, r5), "views_to_recall5_0.9": _reach(views, r5, 0.9),
                    "views_to_recall5_0.95": _reach(views, r5, 0.95),
                    "final_recall5": float(r5[-1]), "final_recall2": float(steps[-1][R2])})
    return out


def runs_summary(runs: list) -> dict:
    """The mean of :func:`curve_summary` over ``runs`` (draws of the initial views, and seeds of
    ``random``), with the std of each figure under ``std``. A views-to-reach figure is the mean
    over the runs that reached the level, and ``reached`` gives the fraction that did."""
    per_run = [curve_summary(r["steps"]) for r in runs]
    out, std, reached = {}, {}, {}
    for key in per_run[0]:
        values = [s[key] for s in per_run if s[key] is not None]
        if key.startswith("views_to_"):
            reached[key] = len(values) / len(per_run)
        out[key] = float(np.mean(values)) if values else None
        std[key] = float(np.std(values)) if values else None
    return {**out, "std": std, "reached": reached, "n_runs": len(per_run)}


def _mean_runs(runs: list) -> list:
    """Step-wise mean of several runs' metrics."""
    out = []
    for k in range(len(runs[0]["steps"])):
        rows = [r["steps"][k] for r in runs]
        out.append({"views": rows[0]["views"],
                    **{key: float(np.mean([r[key] for r in rows]))
                       for key in (F_KEY, *RECALL_KEYS, "completeness_mm", "accuracy_mm",
                                   "chamfer_m2")}})
    return out


def scan(cfg: Config, out_dir, policies=POLICIES, *, overwrite: bool = False,
         progress=None) -> dict:
    """Run the closed loop for each policy on the synthetic scene of ``cfg``; write
    ``scan.json`` and ``scan.png`` into ``out_dir``; return the scan.json content.

    ``progress(policy, seed, record)`` is called after every step (for a progress display)."""
    from ..io import ensure_out_dir, prepare_out_dir
    from ..running.folder import hold, staged

    cfg.check()
    if cfg.scene.source != "synthetic":
        raise ConfigError("bftaichi scan renders new views from the true mesh, so it needs "
                          "scene.source = 'synthetic'")
    bad = [p for p in policies if p not in POLICIES]
    if bad or not policies:
        raise ConfigError(f"unknown policy {', '.join(bad) or '(none given)'}: choose from "
                          f"{', '.join(POLICIES)}")
    t_start = time.perf_counter()
    scene = _Scene(cfg)
    out = ensure_out_dir(out_dir)
    with hold(out):  # one writer; scan.json and scan.png replaced together
        prepare_out_dir(out, overwrite=overwrite, marker="scan.json")
        with staged(out) as staging:
            return _scan(cfg, scene, policies, staging, progress, t_start)


def _scan(cfg: Config, scene, policies, out: Path, progress, t_start: float) -> dict:
    """:func:`scan`'s loop, writing into ``out`` (the staging folder)."""
    from .. import backend
    from ..io import write_json
    from ..reconstructor import Reconstructor
    from .nbv import region_of_interest

    backend.init(cfg.run.arch)
    thresholds = sorted(set(cfg.eval.thresholds_mm) | {2.0, 5.0, 10.0})
    runs = {policy: [] for policy in policies}
    rois = []
    for draw in range(cfg.nbv.initial_seeds):
        initial = scene.initial_views(draw)
        # the region of interest, from the initial views' band (the same for every policy)
        recon = Reconstructor(cfg)
        for c in initial:
            f = scene.frame(c)
            recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name, keep=False)
        roi = region_of_interest(recon.voxels["ijk"], cfg.tsdf.voxel_size_m, cfg.nbv.roi_scale,
                                 scene.target, recon.origin)
        rois.append([roi[0].tolist(), roi[1].tolist()])
        for policy in policies:
            seeds = range(cfg.nbv.random_seeds) if policy == "random" else [0]
            runs[policy] += [_run_policy(scene, policy, s, roi, thresholds, progress, initial,
                                         draw) for s in seeds]
    results = {policy: {"summary": runs_summary(r),
                        "steps": r[0]["steps"] if len(r) == 1 else _mean_runs(r), "runs": r}
               for policy, r in runs.items()}
    report = {
        "scene": cfg.scene.name,
        "candidates": len(scene.poses),
        "initial_views": scene.initial,
        "initial_draws": [scene.initial_views(d) for d in range(cfg.nbv.initial_seeds)],
        "steps": cfg.nbv.steps,
        "target": scene.target.tolist(),
        "radius_m": scene.radius,
        "roi": rois[0],
        "rois": rois,
        "candidate_poses": scene.poses.tolist(),
        "policies": results,
        "seconds": round(time.perf_counter() - t_start, 2),
        "machine": {"cpus": os.cpu_count()},
        "config": cfg.to_dict(),
    }
    write_json(out / "scan.json", report)
    plot_scan(report, out / "scan.png")
    return report


def plot_scan(report: dict, path) -> None:
    """Recall at 5 and 2 mm, F@10mm and completeness against the number of views, one curve
    per policy (the mean over its runs; PNG, written atomically)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_write_bytes

    fig, (ax_r, ax_f, ax_c) = plt.subplots(1, 3, figsize=(15, 4), dpi=110)
    for policy, res in report["policies"].items():
        views = [s["views"] for s in res["steps"]]
        label = policy + (f" (mean of {len(res['runs'])})" if len(res["runs"]) > 1 else "")
        line, = ax_r.plot(views, [s.get(R5, np.nan) for s in res["steps"]], marker="o", ms=3,
                          label=f"{label}, 5 mm")
        ax_r.plot(views, [s.get(R2, np.nan) for s in res["steps"]], ls="--",
                  color=line.get_color(), label=f"{label}, 2 mm")
        ax_f.plot(views, [s[F_KEY] for s in res["steps"]], marker="o", ms=3, label=label)
        ax_c.plot(views, [s["completeness_mm"] for s in res["steps"]], marker="o", ms=3,
                  label=label)
    ax_r.set(xlabel="views", ylabel="recall (surface coverage)",
             title=f"{report['scene']}: recall at 5 mm (solid), 2 mm (dashed)")
    ax_f.set(xlabel="views", ylabel="F-score at 10 mm", title=f"{report['scene']}: F@10mm")
    ax_c.set(xlabel="views", ylabel="completeness (mm, lower is better)",
             title=f"{report['scene']}: completeness")
    for ax in (ax_r, ax_f, ax_c):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
