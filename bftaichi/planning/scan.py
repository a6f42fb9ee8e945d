"""Closed-loop active scanning on a synthetic scene (``bftaichi scan``).

Every policy starts from the same ``nbv.initial_views`` candidate views (seeded by
``run.seed``) and then adds ``nbv.steps`` views, one at a time, from the same candidate set
(:func:`bftaichi.planning.nbv.make_candidates` around ``synthetic.look_at`` at ``synthetic.cam_radius_m``
unless ``nbv.target`` / ``nbv.radius_m`` say otherwise). After each view:

1. the chosen view's noisy depth is rendered from the true mesh (the scene's noise model; view
   ``c`` always draws its noise from ``default_rng([synthetic.seed, c])``, so every policy sees
   the same frame for the same view);
2. it is fused: the TSDF volume is integrated incrementally, the coverage grid marks what the
   frame saw, and the posterior is rebuilt (band and observations of all views so far), its
   PCG warm-started from the previous mean;
3. ``mesh.ply``'s metrics against the ground truth are recorded (F at 10 mm among them).

Policies: ``bayes`` (:class:`bftaichi.planning.nbv.Planner` utility: expected variance reduction),
``coverage`` (the classic volumetric heuristic: the distinct unseen cells a view's rays cross
before the predicted surface), ``farthest`` (the candidate farthest from every used view), and
``random`` (seeded; the mean over ``nbv.random_seeds`` seeds). Only ``bayes`` needs the
variance, so only its runs solve the probes.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..config import Config
from ..errors import ConfigError

__all__ = ["POLICIES", "scan", "curve_summary"]

POLICIES = ("bayes", "coverage", "farthest", "random")
F_KEY = "fscore@10mm"


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
        rng = np.random.default_rng(cfg.run.seed)
        self.initial = [int(i) for i in rng.choice(n, cfg.nbv.initial_views, replace=False)]
        self._frames = {}

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


def _run_policy(scene: _Scene, policy: str, seed: int, roi, thresholds, progress) -> dict:
    """One closed loop: the views chosen and the metrics after each."""
    from ..evaluation.metrics import geometry_metrics
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

    for c in scene.initial:
        add(c)
    for step in range(cfg.nbv.steps + 1):
        t0 = time.perf_counter()
        post = recon.solve(variance=policy == "bayes")
        mesh = post.extract_mesh(local=True)  # metrics in the local frame, as a run's
        m = geometry_metrics(mesh, mesh_in_local(scene.gt, post.origin), thresholds,
                             cfg.eval.n_samples, cfg.eval.seed)
        record = {"views": len(used), "view": used[-1], F_KEY: m[F_KEY],
                  "recall@10mm": m["recall@10mm"],
                  "completeness_mm": 1000.0 * m["completeness_m"],
                  "accuracy_mm": 1000.0 * m["accuracy_m"], "chamfer_m2": m["chamfer_l2"],
                  "map_converged": post.solver["converged"],
                  "seconds_fuse": round(time.perf_counter() - t0, 3)}
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
            if policy == "bayes":
                scores = [planner.utility(scene.poses[c])["utility"] for c in free]
            else:  # coverage
                scores = [coverage.count_unknown(planner.predict_depth(scene.poses[c]), scene.K,
                                                 scene.poses[c], planner.stride,
                                                 planner.depth_range[1]) for c in free]
            choice = free[int(np.argmax(scores))]  # ties: the lowest candidate index
        record["seconds_choose"] = round(time.perf_counter() - t1, 3)
        steps.append(record)
        add(choice)
        if progress:
            progress(policy, seed, record)
    return {"policy": policy, "seed": seed, "views": used, "steps": steps}


def curve_summary(steps: list, threshold: float = 0.9) -> dict:
    """Area under F@10mm against views (trapezoid, divided by the views spanned: the mean F over
    the scan) and the first view count with F@10mm >= ``threshold`` (None if never)."""
    views = np.array([s["views"] for s in steps], np.float64)
    f = np.array([s[F_KEY] for s in steps], np.float64)
    span = views[-1] - views[0]
    auc = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(views)) / span) if span else float(f[0])
    reach = next((int(v) for v, x in zip(views, f) if x >= threshold), None)
    return {"auc_f10": auc, "views_to_f10_0.9": reach, "final_f10": float(f[-1]),
            "final_completeness_mm": float(steps[-1]["completeness_mm"])}


def _mean_runs(runs: list) -> list:
    """Step-wise mean of several runs' metrics (the random policy)."""
    out = []
    for k in range(len(runs[0]["steps"])):
        rows = [r["steps"][k] for r in runs]
        out.append({"views": rows[0]["views"],
                    **{key: float(np.mean([r[key] for r in rows]))
                       for key in (F_KEY, "completeness_mm", "accuracy_mm", "chamfer_m2")}})
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
    thresholds = sorted(set(cfg.eval.thresholds_mm) | {10.0})
    # the region of interest, from the initial views' band (the same for every policy)
    recon = Reconstructor(cfg)
    for c in scene.initial:
        f = scene.frame(c)
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name, keep=False)
    roi = region_of_interest(recon.voxels["ijk"], cfg.tsdf.voxel_size_m, cfg.nbv.roi_scale,
                             scene.target, recon.origin)
    results = {}
    for policy in policies:
        seeds = range(cfg.nbv.random_seeds) if policy == "random" else [0]
        runs = [_run_policy(scene, policy, s, roi, thresholds, progress) for s in seeds]
        steps = runs[0]["steps"] if len(runs) == 1 else _mean_runs(runs)
        results[policy] = {"summary": curve_summary(steps), "steps": steps, "runs": runs}
    report = {
        "scene": cfg.scene.name,
        "candidates": len(scene.poses),
        "initial_views": scene.initial,
        "steps": cfg.nbv.steps,
        "target": scene.target.tolist(),
        "radius_m": scene.radius,
        "roi": [roi[0].tolist(), roi[1].tolist()],
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
    """F@10mm and completeness against the number of views, one curve per policy (PNG,
    written atomically)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_write_bytes

    fig, (ax_f, ax_c) = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    for policy, res in report["policies"].items():
        views = [s["views"] for s in res["steps"]]
        label = policy + (f" (mean of {len(res['runs'])})" if len(res["runs"]) > 1 else "")
        ax_f.plot(views, [s[F_KEY] for s in res["steps"]], marker="o", ms=3, label=label)
        ax_c.plot(views, [s["completeness_mm"] for s in res["steps"]], marker="o", ms=3,
                  label=label)
    ax_f.set(xlabel="views", ylabel="F-score at 10 mm", title=f"{report['scene']}: F@10mm")
    ax_c.set(xlabel="views", ylabel="completeness (mm, lower is better)",
             title=f"{report['scene']}: completeness")
    for ax in (ax_f, ax_c):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
