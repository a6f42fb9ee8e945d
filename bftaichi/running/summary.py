"""What the commands print at the end: a run's summary (``run``, ``fuse``, ``update``), a
ranking of next-best views (``nbv``), a scan (``scan``)."""

from __future__ import annotations

import json
from pathlib import Path

import click

#: Metrics of the default (compact) summary; --verbose shows every metric.
_SUMMARY_KEYS = ("chamfer_l2", "accuracy_m", "completeness_m")


def print_summary(out: Path, report: dict, verbose: bool = False) -> None:
    """One screen about the run just made in ``out``, from the report it returned (what it
    wrote as report.json; not read back)."""
    from ..evaluation.metrics import format_table

    c, s = report["counts"], report["seconds"]
    click.echo(f"scene {report['scene']}: {c['frames']} frames, {c['pixels_used']:,} depth pixels, "
               f"{c['observed_voxels']:,} observed voxels in {c['blocks']:,} blocks")
    fps = c["frames"] / s["tsdf"] if s.get("tsdf") else float("nan")
    click.echo(f"time: total {s['total']:.2f} s (TSDF {s['tsdf']:.2f} s = {fps:.0f} frames/s, "
               f"mesh {s['mesh']:.2f} s, reading frames {s['read_frames']:.2f} s)")
    if verbose:
        click.echo("seconds per stage: " + ", ".join(f"{k} {v:.2f}" for k, v in s.items()))
    click.echo(f"tsdf_mesh.ply: {c['tsdf_mesh_vertices']:,} vertices, {c['tsdf_mesh_faces']:,} faces")
    if report.get("solver"):
        m, v = report["solver"]["map"], report["solver"]["variance"]
        state = "converged" if m["converged"] else "NOT CONVERGED"
        click.echo(f"mesh.ply: {c['mesh_vertices']:,} vertices, {c['mesh_faces']:,} faces; "
                   f"band {c['band_voxels']:,} voxels; MAP PCG {state} in {m['iterations']} "
                   f"iterations (relative residual {m['relative_residual']:.1e}); "
                   f"variance from {v['n_probes']} probes"
                   + (" and as many perturbations" if "perturbation" in v else "")
                   + f" ({s['posterior']:.2f} s)")
        fit = report["solver"]["observations"].get("noise_fit") or {}
        if fit.get("sigma_extra_m"):
            L = fit.get("frames_sharing_noise") or 1.0
            click.echo(f"noise fit: {1000 * fit['sigma_extra_m']:.1f} mm of depth noise per frame "
                       "beyond the sensor model"
                       + (f"; frames in a row share it, ~{L:.0f} per error, and sigma counts "
                          "such a run as one frame" if L > 1 else ""))
        if verbose:
            sub = report["solver"]["seconds"]
            click.echo("posterior seconds: " + ", ".join(f"{k} {x:.2f}" for k, x in sub.items()))
            obs = report["solver"]["observations"]
            click.echo("observations: " + ", ".join(f"{k} {x:,}" for k, x in obs.items()
                                                    if isinstance(x, int)))
        if not m["converged"]:
            click.echo("warning: the MAP solve did not converge; mesh.ply is written but flagged "
                       "in report.json (raise solver.maxiter or check the scene)", err=True)
        fs = m.get("free_space") or {}
        if fs.get("settled") is False:
            click.echo(f"warning: the free-space constraint still found free voxels below half a "
                       f"voxel after {fs['passes']} passes; some may be left inside the surface "
                       "(report.json: solver.map.free_space)", err=True)
    if c["empty_frames"]:
        click.echo(f"warning: {c['empty_frames']} of {c['frames']} frames observed no voxel; if that "
                   "is unexpected, check that poses are T_W_C (camera-to-world), not T_C_W, and the "
                   "depth scale", err=True)
    if report["metrics"]:
        click.echo("metrics vs ground truth:")
        keys = None
        if not verbose:
            keys = [k for k in next(iter(report["metrics"].values()))
                    if k in _SUMMARY_KEYS or k.startswith("fscore@")]
        click.echo(format_table(report["metrics"], keys))
        u = report.get("uncertainty")
        if u:
            click.echo(f"vertex sigma vs true error ({u['n']:,} vertices of mesh.ply): "
                       f"coverage of |e| <= 1/2/3 sigma {u['coverage@1sigma']:.1%} / "
                       f"{u['coverage@2sigma']:.1%} / {u['coverage@3sigma']:.1%} (Gaussian "
                       f"68.3 / 95.4 / 99.7 %), NLL minus the best constant sigma's "
                       f"{u['nll_vs_constant']:+.2f} nats (below 0: informative), "
                       f"Spearman {u['spearman']:.2f}")
    else:
        click.echo("no ground-truth mesh: geometry metrics skipped")
    if report.get("nbv"):
        b = report["nbv"]["best"]
        eye = ", ".join(f"{x:.3f}" for x in (row[3] for row in b["pose"][:3]))
        click.echo(f"next-best view: candidate {b['index']} of {report['nbv']['n_candidates']} "
                   f"at ({eye}), utility {b['utility']:.3e} m^2 (nbv.json)")
    if (out / "preview.html").exists():
        mb = (out / "preview.html").stat().st_size / 1e6
        click.echo(f"preview.html ({mb:.1f} MB): open it in a browser, or `bftaichi view {out}`")
    click.echo(f"outputs in {out}/")


def print_ranking(result: dict, top: int = 5) -> None:
    import numpy as np

    st = result["settings"]
    click.echo(f"{len(result['candidates'])} candidates at {st['radius_m']:.3f} m around "
               f"({', '.join(f'{v:.3f}' for v in st['target'])}); seen cells {st['seen_cells']:,} "
               f"of {st['cell_m'] * 1000:.1f} mm")
    click.echo("rank  index  utility [m^2]  known      unknown    frontier cells  hits  camera at")
    for c in result["candidates"][:top]:
        eye = np.asarray(c["pose"])[:3, 3]
        click.echo(f"{c['rank']:4d}  {c['index']:5d}  {c['utility']:.3e}      {c['known']:.3e}  "
                   f"{c['unknown']:.3e}  {c['frontier_cells']:13,d}  {c['hit_fraction']:4.0%}  "
                   f"({', '.join(f'{v:.3f}' for v in eye)})")


def print_scan_summary(out: Path) -> None:
    """One screen about a scan, built from ``out/scan.json``."""
    report = json.loads((out / "scan.json").read_text())
    click.echo(f"scan of {report['scene']}: {report['candidates']} candidates, {report['steps']} "
               f"steps from {len(report['initial_draws'])} draws of the initial views "
               f"({report['seconds']:.0f} s); mean ± std over the runs")
    click.echo("policy                 AUC recall@5mm   views to 95 % (reached)  final recall@5mm"
               "  AUC F@10mm  final comp. (mm)")
    for policy, res in report["policies"].items():
        s, sd, n = res["summary"], res["summary"]["std"], res["summary"]["n_runs"]
        reach, got = s["views_to_recall5_0.95"], s["reached"]["views_to_recall5_0.95"]
        click.echo(f"{policy + f' ({n} runs)':22s} {s['auc_recall5']:.4f} ± {sd['auc_recall5']:.4f}"
                   f"   {f'{reach:.1f}' if reach else 'never':>6} ({got:4.0%})            "
                   f"{s['final_recall5']:.3f}     {s['auc_f10']:.4f}      "
                   f"{s['final_completeness_mm']:.2f}")
    click.echo(f"outputs in {out}/ (scan.json, scan.png)")
