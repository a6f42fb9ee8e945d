"""Diagnostic plots of a finished run (:func:`write_run_plots`), PNGs in ``<run>/plots/``.

Each plot is drawn from the run folder (``report.json``'s dict, ``mesh.ply``, ``tsdf_mesh.ply``,
``band.npz``) plus what the folder does not hold, the ground-truth mesh; a plot whose inputs are
absent is skipped:

- ``precision_recall.png`` (needs the ground truth): precision and recall against the
  distance threshold, one curve pair per mesh (``mesh.ply``, ``tsdf_mesh.ply``);
- ``fscore.png`` (ground truth): F-score against the threshold, same data;
- ``sigma_histogram.png`` (posterior): posterior sigma of the near-surface band voxels
  (``|mean| <= eval.near_voxels`` voxels, weight > 0) and of the ``mesh.ply`` vertices;
- ``calibration.png`` (posterior and ground truth): observed against Gaussian-expected coverage
  of ``|e| <= k sigma`` over the vertices of ``mesh.ply`` (``report["uncertainty"]``: ``e`` the
  exact distance of the vertex to the true surface, ``sigma`` its vertex sigma);
- ``pcg_residual.png`` (posterior): the MAP PCG relative residual against iteration (of the
  last free-space pass, whose residual the report's ``relative_residual`` is).

"posterior" means a ``run.stages = "full"`` run (a ``"tsdf_only"`` run gets the TSDF curves of the
first two plots and nothing else). The curves use :func:`bftaichi.evaluation.metrics.surface_distances` with
the run's ``eval.n_samples`` and ``eval.seed``, so at the run's ``eval.thresholds_mm`` they are the
report's precision and recall exactly; the calibration uses the vertices and errors of
:func:`bftaichi.evaluation.metrics.vertex_uncertainty`.

Figures are drawn on a bare ``matplotlib.figure.Figure`` (Agg canvas, no pyplot state, so the
caller's backend is left alone) and written atomically.
"""

from __future__ import annotations

import io
import math
import os
from pathlib import Path

import numpy as np

from ..errors import BftaichiError
from ..evaluation.metrics import threshold_curves

__all__ = ["write_run_plots", "PLOTS", "curve_thresholds_mm", "coverage_curve", "save_png"]

#: The run's meshes, in plotting order, with their legend labels.
MESHES = {"mesh.ply": "posterior mean (mesh.ply)",
          "tsdf_mesh.ply": "TSDF bootstrap (tsdf_mesh.ply)"}


def curve_thresholds_mm(voxel_size_m: float, extra_mm=(), n: int = 40) -> np.ndarray:
    """Thresholds for a precision / recall curve, millimetres, ascending: ``n`` log-spaced from
    half a voxel (below that the sample spacing dominates) to 50 voxels (where every run is
    near 1), merged with ``extra_mm`` (the run's ``eval.thresholds_mm``, so the report's values
    lie on the curve)."""
    vs_mm = 1000.0 * float(voxel_size_m)
    grid = np.geomspace(0.5 * vs_mm, 50.0 * vs_mm, int(n))
    return np.unique(np.concatenate([grid, np.asarray(extra_mm, np.float64)]))


def coverage_curve(error: np.ndarray, sigma: np.ndarray, k: np.ndarray):
    """For each sigma multiple ``k``: the coverage a Gaussian error would have,
    ``erf(k / sqrt 2)``, and the observed fraction with ``|error| <= k sigma`` (computed as
    :func:`bftaichi.evaluation.metrics.uncertainty_metrics` computes ``coverage@ksigma``). Returns
    ``(expected, observed)``, float64 arrays like ``k``."""
    from scipy.special import erf

    k = np.asarray(k, np.float64)
    z = np.sort(np.abs(np.asarray(error, np.float64)) /
                np.maximum(np.asarray(sigma, np.float64), np.finfo(np.float64).tiny))
    observed = np.searchsorted(z, k, side="right") / len(z)  # count of z <= k
    return erf(k / math.sqrt(2.0)), observed


# --------------------------------------------------------------------------------------------
# the plots
# --------------------------------------------------------------------------------------------

def _figure(figsize=(6.4, 4.4), margins=(0.75, 0.2, 0.55, 0.4)):
    """A figure with one axes at fixed ``margins`` (left, right, bottom, top; inches): the run's
    plots have fixed labels, so :func:`save_png` need not measure them (``tight_layout`` draws
    every text once more: the five plots of the default run took 1.75-1.82 s without it
    against 1.94-2.04 s with it, three alternating calls of :func:`write_run_plots` each)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=110)
    left, right, bottom, top = margins
    w, h = figsize
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h)
    return fig, fig.add_subplot()


def save_png(fig, path: str | os.PathLike, tight: bool = True) -> Path:
    """Write matplotlib figure ``fig`` to ``path`` as PNG, atomically (rendered into memory,
    then :func:`bftaichi.io.atomic_write_bytes`), laid out by ``tight_layout`` unless ``tight``
    is False (a figure with fixed margins); return the path."""
    from ..io import atomic_write_bytes

    path = Path(path)
    if tight:
        fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())
    return path


def _plot_precision_recall(curves: dict, report: dict, path: Path) -> Path:
    fig, ax = _figure()
    for i, (name, c) in enumerate(curves.items()):
        color = f"C{i}"
        ax.plot(c["threshold_mm"], c["precision"], color=color, label=f"precision, {MESHES[name]}")
        ax.plot(c["threshold_mm"], c["recall"], color=color, ls="--",
                label=f"recall, {MESHES[name]}")
        _mark_report(ax, report["metrics"].get(name, {}), ("precision", "recall"), color)
    lowest = min(min(c["precision"][0], c["recall"][0]) for c in curves.values())
    _threshold_axes(ax, report, "precision / recall", lowest,
                    f"{report['scene']}: precision and recall vs threshold")
    return save_png(fig, path, tight=False)


def _plot_fscore(curves: dict, report: dict, path: Path) -> Path:
    fig, ax = _figure()
    for i, (name, c) in enumerate(curves.items()):
        ax.plot(c["threshold_mm"], c["fscore"], color=f"C{i}", label=MESHES[name])
        _mark_report(ax, report["metrics"].get(name, {}), ("fscore",), f"C{i}")
    lowest = min(c["fscore"][0] for c in curves.values())
    _threshold_axes(ax, report, "F-score", lowest, f"{report['scene']}: F-score vs threshold")
    return save_png(fig, path, tight=False)


def _mark_report(ax, metrics: dict, kinds, color) -> None:
    """Dots at the report's own thresholds (they lie on the curves)."""
    for kind in kinds:
        pts = [(float(k.split("@")[1][:-2]), v) for k, v in metrics.items()
               if k.startswith(f"{kind}@")]
        if pts:
            ax.plot(*zip(*pts), ls="none", marker="o", ms=4, color=color)


def _threshold_axes(ax, report: dict, ylabel: str, lowest: float, title: str) -> None:
    """Log threshold axis with the voxel size marked; y from the lowest value (rounded down to
    0.1, some room below) to 1."""
    bottom = max(0.0, math.floor(10 * (lowest - 0.05)) / 10)
    vs_mm = 1000.0 * report["tsdf"]["voxel_size_m"]
    ax.axvline(vs_mm, color="0.6", lw=0.8, ls=":")
    ax.text(vs_mm, bottom + 0.01 * (1 - bottom), " 1 voxel", color="0.4", fontsize=8)
    ax.set(xscale="log", xlabel="distance threshold [mm]", ylabel=ylabel,
           ylim=(bottom, 1 + 0.02 * (1 - bottom)), title=title)
    _plain_log_ticks(ax)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, title="dots: report.json thresholds", title_fontsize=8)


def _plain_log_ticks(ax, subs=(2.0, 5.0)) -> None:
    """Tick labels 5, 10, 20 on a log x axis, not 5x10^0; labelled minor ticks at ``subs``."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_locator(LogLocator(subs=subs))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}"))


def _plot_sigma_histogram(post, vertex_sigma, report: dict, path: Path) -> Path:
    near_voxels = float(report["config"]["eval"]["near_voxels"])
    near = (post.weight > 0) & (np.abs(post.mean) <= near_voxels * post.voxel_size)
    series = {f"band voxels, |mean| <= {near_voxels:g} voxel ({np.count_nonzero(near)})":
              post.sigma[near]}
    if vertex_sigma is not None and len(vertex_sigma):
        series[f"mesh.ply vertices ({len(vertex_sigma)})"] = vertex_sigma
    series = {k: 1000.0 * np.asarray(v, np.float64) for k, v in series.items()}
    series = {k: v[np.isfinite(v) & (v > 0)] for k, v in series.items()}
    series = {k: v for k, v in series.items() if len(v)}
    fig, ax = _figure()
    if series:
        lo = min(v.min() for v in series.values())
        hi = max(v.max() for v in series.values())
        bins = np.geomspace(lo, hi * (1 + 1e-9), 41) if hi > lo else 10
        for i, (label, v) in enumerate(series.items()):
            ax.hist(v, bins=bins, weights=np.full(len(v), 1.0 / len(v)), histtype="step",
                    lw=1.5, color=f"C{i}", label=f"{label}, median {np.median(v):.2f} mm")
        ax.set_xscale("log")
        _plain_log_ticks(ax, subs=(1.5, 2.0, 3.0, 5.0, 7.0))
        ax.set_ylim(0, 1.3 * ax.get_ylim()[1])  # headroom for the legend
        ax.legend(fontsize=8, loc="upper left")
    ax.set(xlabel="posterior sigma [mm]", ylabel="fraction per bin",
           title=f"{report['scene']}: posterior sigma near the surface")
    ax.grid(alpha=0.3, which="both")
    return save_png(fig, path, tight=False)


def _plot_calibration(error, sigma, report: dict, path: Path) -> Path:
    k = np.linspace(0.0, 4.0, 161)
    expected, observed = coverage_curve(error, sigma, k)
    fig, ax = _figure((5.2, 5.0), margins=(0.75, 0.25, 0.55, 0.6))
    ax.plot([0, 1], [0, 1], color="0.5", lw=1, ls="--", label="calibrated (Gaussian)")
    ax.plot(expected, observed, color="C0", label=f"posterior ({len(error)} vertices)")
    e3, o3 = coverage_curve(error, sigma, np.array([1.0, 2.0, 3.0]))
    ax.plot(e3, o3, ls="none", marker="o", ms=4, color="C0")
    for kk, x, y in zip((1, 2, 3), e3, o3):
        ax.annotate(f"{kk}", (x, y), textcoords="offset points", xytext=(-10, 4), fontsize=8,
                    color="C0")
    ax.text(0.98, 0.02, "coverage at 1 / 2 / 3 sigma (dots):\n"
            + " / ".join(f"{100 * y:.1f}" for y in o3) + " % observed\n"
            "68.3 / 95.4 / 99.7 % Gaussian\n\n"
            "above the diagonal: sigma conservative\nbelow: overconfident",
            transform=ax.transAxes, ha="right", va="bottom", fontsize=8, color="0.3")
    ax.set(xlabel="expected coverage erf(k / sqrt 2) [fraction]",
           ylabel="observed fraction with |error| <= k sigma",
           xlim=(0, 1), ylim=(0, 1.01), aspect="equal")
    ax.set_title(f"{report['scene']}: vertex sigma calibration\n(mesh.ply vertices, error = "
                 "exact distance to the true surface)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    return save_png(fig, path, tight=False)


def _plot_pcg_residual(solver: dict, report: dict, path: Path) -> Path:
    history = np.asarray(solver["residual_history"], np.float64)
    fig, ax = _figure()
    solves = solver.get("solves", 1 + (solver.get("free_space") or {}).get("passes", 0))
    label = f"converged={solver['converged']} after {solver['iterations']} iterations"
    if solves > 1:  # the history is the last solve's (bftaichi.stages.solve.solve_map)
        label += f"\nin {solves} solves (reweighting, free-space passes); the last shown"
    ax.semilogy(np.arange(len(history)), history, color="C0", lw=1.2, label=label)
    tol = report["config"]["solver"]["tol"]
    ax.axhline(tol, color="C3", lw=0.8, ls="--", label=f"solver.tol = {tol:g}")
    ax.set(xlabel="PCG iteration", ylabel="relative residual ||b - Q x|| / ||b||",
           title=f"{report['scene']}: MAP solve (PCG) convergence")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_png(fig, path, tight=False)


#: The plots :func:`write_run_plots` writes, in its order (``plots/<name>.png``).
PLOTS = ("precision_recall", "fscore", "sigma_histogram", "calibration", "pcg_residual")


def write_run_plots(report: dict, out_dir: str | os.PathLike, post=None, gt=None,
                    distances: dict | None = None,
                    vertex_errors: np.ndarray | None = None, which=PLOTS) -> list[Path]:
    """Write the diagnostic PNGs of the run in ``out_dir`` into ``out_dir / "plots"``; return
    their paths, in the order of the module's list (plots whose inputs are absent are skipped).

    Args:
        report: the run's report (the dict :func:`bftaichi.run` returns, or its report.json).
        out_dir: the run folder (holding ``tsdf_mesh.ply`` and, for a full run, ``mesh.ply``
            and ``band.npz``).
        post: the run's :class:`bftaichi.posterior.Posterior` (saves reloading it); default:
            loaded from ``band.npz`` when the run solved one. Ignored for a tsdf_only run.
        gt: ground-truth ``trimesh.Trimesh`` (metres, world frame), for the precision / recall,
            F-score and calibration plots; None skips them.
        distances: ``{mesh name: surface_distances(...)}`` the run already computed for its
            metrics (same ``eval.n_samples`` and seed); default: computed here.
        vertex_errors: the exact errors of ``mesh.ply``'s vertices the run already computed
            for its ``uncertainty`` (:func:`~bftaichi.evaluation.metrics.vertex_errors`, in
            the vertices' order); default: computed here from ``gt``.
        which: the names (:data:`PLOTS`) of the plots to write, e.g. those without the ground
            truth while it is still being measured; default all.

    Raises:
        BftaichiError naming the missing files when ``out_dir`` does not hold the run, or when
        ``report`` is not a run's report.
    """
    from ..io import ensure_out_dir, read_mesh_ply
    from ..evaluation.metrics import load_mesh, surface_distances
    from ..evaluation.metrics import vertex_errors as exact_errors

    out = Path(out_dir)
    if not isinstance(report, dict) or not {"scene", "tsdf", "config", "solver"} <= set(report):
        raise BftaichiError("write_run_plots: report must be a run's report dict (report.json), "
                            "with scene, tsdf, solver and config")
    solved = report["solver"] is not None
    names = [n for n in MESHES if solved or n != "mesh.ply"]
    want = set(which)
    if want - set(PLOTS):
        raise BftaichiError(f"write_run_plots: no plot {', '.join(sorted(want - set(PLOTS)))} "
                            f"(choose from {', '.join(PLOTS)})")
    missing = [n for n in names if not (out / n).is_file()]
    if missing:
        raise BftaichiError(f"{out}: missing {', '.join(missing)}: not the folder of this run")
    if solved and post is None and "sigma_histogram" in want:
        from ..posterior import Posterior

        post = Posterior.load(out / "band.npz")
    plots = ensure_out_dir(out / "plots")
    ev = report["config"]["eval"]
    written = []
    if gt is not None and {"precision_recall", "fscore"} & want:
        thresholds = curve_thresholds_mm(report["tsdf"]["voxel_size_m"], ev["thresholds_mm"])
        curves = {}
        for name in names:
            d = (distances[name] if distances and name in distances else
                 surface_distances(load_mesh(out / name), gt, int(ev["n_samples"]),
                                   int(ev["seed"])))
            if d is not None:
                curves[name] = threshold_curves(*d, thresholds)
        if curves and "precision_recall" in want:
            written.append(_plot_precision_recall(curves, report, plots / "precision_recall.png"))
        if curves and "fscore" in want:
            written.append(_plot_fscore(curves, report, plots / "fscore.png"))
    if solved and {"sigma_histogram", "calibration", "pcg_residual"} & want:
        _, _, attrs = read_mesh_ply(out / "mesh.ply")
        if "sigma_histogram" in want:
            written.append(_plot_sigma_histogram(post, attrs.get("sigma"), report,
                                                 plots / "sigma_histogram.png"))
        pairs = None
        if ("calibration" in want and gt is not None and attrs.get("sigma") is not None
                and len(attrs["sigma"]) >= 2):
            if vertex_errors is None or len(vertex_errors) != len(attrs["sigma"]):
                v, _, _ = read_mesh_ply(out / "mesh.ply")
                vertex_errors = exact_errors(v, gt)
            pairs = np.asarray(vertex_errors, np.float64), np.asarray(attrs["sigma"], np.float64)
        if pairs is not None:
            written.append(_plot_calibration(*pairs, report, plots / "calibration.png"))
        if "pcg_residual" in want and report["solver"]["map"].get("residual_history"):
            written.append(_plot_pcg_residual(report["solver"]["map"], report,
                                              plots / "pcg_residual.png"))
    return written
