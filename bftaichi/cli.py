"""The ``bftaichi`` command line. Commands stay thin: parse, call the library, print.

Errors the user can fix (bad file, key or value) print ``error: ...`` and exit with code 2;
Ctrl-C exits with 130. No traceback unless ``BFTAICHI_DEBUG=1``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import click

from .errors import BftaichiError

ARCH = click.Choice(["cpu", "cuda", "vulkan", "metal", "gpu"])


def _overrides(arch: str | None, sets: tuple[str, ...]) -> list[str]:
    out = list(sets)
    if arch:
        out.append(f"run.arch={arch}")
    return out


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="bftaichi")
def cli():
    """bftaichi: probabilistic signed-distance fusion (BayesFusion-SDF) on the CPU.

    Give it depth frames with poses and intrinsics; get a mesh, metrics against ground truth
    and (in later stages) a calibrated per-voxel uncertainty and next-best views.

    \b
    Quick start:
      bftaichi run                        # built-in tabletop scene -> out/default/
      bftaichi fuse DATA --voxel 0.01     # your own frames (7scenes or bfsdf layout)
      bftaichi eval out/default/tsdf_mesh.ply gt.ply
    """


def _print_summary(report: dict, out: Path) -> None:
    from .metrics import format_table

    c, s = report["counts"], report["seconds"]
    click.echo(f"scene {report['scene']}: {c['frames']} frames, {c['pixels_used']:,} depth pixels, "
               f"{c['observed_voxels']:,} observed voxels in {c['blocks']:,} blocks")
    fps = c["frames"] / s["tsdf"] if s.get("tsdf") else float("nan")
    click.echo(f"time: total {s['total']:.2f} s (TSDF {s['tsdf']:.2f} s = {fps:.0f} frames/s, "
               f"mesh {s['mesh']:.2f} s, reading frames {s['read_frames']:.2f} s)")
    click.echo(f"tsdf_mesh.ply: {c['tsdf_mesh_vertices']:,} vertices, {c['tsdf_mesh_faces']:,} faces")
    if report.get("solver"):
        m, v = report["solver"]["map"], report["solver"]["variance"]
        state = "converged" if m["converged"] else "NOT CONVERGED"
        click.echo(f"mesh.ply: {c['mesh_vertices']:,} vertices, {c['mesh_faces']:,} faces; "
                   f"band {c['band_voxels']:,} voxels; MAP PCG {state} in {m['iterations']} "
                   f"iterations (relative residual {m['relative_residual']:.1e}); "
                   f"variance from {v['n_probes']} probes ({s['posterior']:.2f} s)")
        if not m["converged"]:
            click.echo("warning: the MAP solve did not converge; mesh.ply is written but flagged "
                       "in report.json (raise solver.maxiter or check the scene)", err=True)
    if c["empty_frames"]:
        click.echo(f"warning: {c['empty_frames']} of {c['frames']} frames observed no voxel; if that "
                   "is unexpected, check that poses are T_W_C (camera-to-world), not T_C_W, and the "
                   "depth scale", err=True)
    if report["metrics"]:
        click.echo("metrics vs ground truth:")
        click.echo(format_table(report["metrics"]))
        u = report.get("uncertainty")
        if u:
            click.echo(f"sigma vs true error ({u['n']:,} observed voxels within "
                       f"{u['near_voxels']:g} voxel of the surface): coverage of |e| <= 1/2/3 "
                       f"sigma {u['coverage@1sigma']:.1%} / {u['coverage@2sigma']:.1%} / "
                       f"{u['coverage@3sigma']:.1%} (Gaussian 68.3 / 95.4 / 99.7 %), "
                       f"Spearman {u['spearman']:.2f}")
    else:
        click.echo("no ground-truth mesh: geometry metrics skipped")
    click.echo(f"outputs in {out}/")


@cli.command()
@click.argument("scene", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "-o", type=click.Path(file_okay=False), default=None,
              help="Output folder [default: out/<scene name>].")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Override a scene value, e.g. --set tsdf.voxel_size_m=0.005 (repeatable).")
@click.option("--arch", type=ARCH, default=None, help="Taichi backend [default: cpu].")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def run(scene, out, sets, arch, overwrite, quiet):
    """Run a scene file end to end (the built-in tabletop scene if SCENE is omitted).

    Writes tsdf_mesh.ply, band.npz, report.json and config.toml into the output folder and
    prints a summary with metrics when the scene has ground truth.

    \b
    Examples:
      bftaichi run                                   # default tabletop, Kinect noise
      bftaichi run scenes/bunny.toml --out out/bunny
      bftaichi run scenes/seed_sphere.toml --set tsdf.voxel_size_m=0.01 --overwrite
    """
    from .config import load_config
    from .pipeline import run as run_pipeline

    cfg = load_config(scene, _overrides(arch, sets))
    out = Path(out or Path("out") / cfg.scene.name)
    report = run_pipeline(cfg, out, overwrite=overwrite, progress=not quiet)
    if not quiet:
        _print_summary(report, out)


@cli.command()
@click.argument("data_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", default="auto", show_default=True,
              help="Dataset layout: auto, 7scenes or bfsdf.")
@click.option("--voxel", type=float, default=0.01, show_default=True, help="Voxel size, metres.")
@click.option("--trunc", type=float, default=None,
              help="Observation truncation tau, metres [default: 2 voxels]; the TSDF uses alpha*tau.")
@click.option("--frames", default="", help="Slice of frames, e.g. 0:500:5 [default: all].")
@click.option("--depth-max", type=float, default=None, help="Ignore depth beyond this, metres.")
@click.option("--gt", "gt_mesh", type=click.Path(dir_okay=False), default="auto",
              help="Ground-truth mesh for metrics [default: gt_mesh.ply in DATA_DIR if present].")
@click.option("--out", "-o", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Other overrides.")
@click.option("--arch", type=ARCH, default=None, help="Taichi backend [default: cpu].")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def fuse(data_dir, fmt, voxel, trunc, frames, depth_max, gt_mesh, out, sets, arch, overwrite, quiet):
    """Fuse recorded depth frames from DATA_DIR into a TSDF mesh.

    \b
    Example (the shared 7-Scenes frames):
      bftaichi fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out out/kitchen
    """
    from .config import load_config
    from .pipeline import run as run_pipeline

    base = [f"scene.source=dataset", f"scene.data={json.dumps(str(data_dir))}",
            f"scene.format={fmt}", f"scene.name={json.dumps(Path(data_dir).name or 'data')}",
            f"tsdf.voxel_size_m={voxel}",
            f"tsdf.trunc_m={trunc if trunc is not None else 2 * voxel}",
            f"scene.gt_mesh={json.dumps(str(gt_mesh))}"]
    if frames:
        base.append(f"scene.frames={json.dumps(frames)}")
    if depth_max is not None:
        base.append(f"scene.depth_max_m={depth_max}")
    cfg = load_config(None, base + _overrides(arch, sets))
    report = run_pipeline(cfg, Path(out), overwrite=overwrite, progress=not quiet)
    if not quiet:
        _print_summary(report, Path(out))


@cli.command()
@click.argument("scene", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "-o", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Override a scene value, e.g. --set synthetic.n_views=100.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def synth(scene, out, sets, quiet):
    """Render a synthetic scene to disk in the 7scenes layout, plus gt_mesh.ply.

    The frames (depth PNG in millimetres, T_W_C pose files, camera-intrinsics.txt) can then be
    fused with `bftaichi fuse`, which finds gt_mesh.ply for metrics.

    \b
    Example:
      bftaichi synth scenes/bunny.toml --out data/bunny
      bftaichi fuse data/bunny --voxel 0.003 --out out/bunny-fused
    """
    from .config import load_config
    from .synthetic import SyntheticDataset, write_7scenes

    cfg = load_config(scene, sets)
    ds = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
    path = write_7scenes(ds, out, progress=not quiet)
    if not quiet:
        click.echo(f"wrote {len(ds)} frames of {ds.image_size[0]}x{ds.image_size[1]} and "
                   f"gt_mesh.ply to {path}/")


@cli.command(name="eval")
@click.argument("pred", type=click.Path(dir_okay=False))
@click.argument("gt", type=click.Path(dir_okay=False))
@click.option("--thresholds", default="5,10,20,50", show_default=True,
              help="Comma-separated F-score thresholds, millimetres.")
@click.option("--samples", type=int, default=200000, show_default=True,
              help="Points sampled on each surface.")
@click.option("--seed", type=int, default=0, show_default=True, help="Sampling seed.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def eval_cmd(pred, gt, thresholds, samples, seed, as_json):
    """Geometry metrics of mesh PRED against ground-truth mesh GT.

    Chamfer L2 (mean squared distance both ways), accuracy (mean PRED->GT distance), completeness
    (mean GT->PRED distance), and precision / recall / F-score at each threshold, from
    area-weighted surface samples with a fixed seed.

    \b
    Example:
      bftaichi eval out/default/tsdf_mesh.ply data/tabletop/gt_mesh.ply --json
    """
    from .config import EvalConfig
    from .metrics import format_table, geometry_metrics, load_mesh

    try:
        ts = [float(t) for t in thresholds.split(",") if t.strip()]
    except ValueError:
        raise BftaichiError(f"--thresholds {thresholds!r}: expected numbers like 5,10,20") from None
    EvalConfig(thresholds_mm=ts, n_samples=samples, seed=seed).check()
    m = geometry_metrics(load_mesh(pred), load_mesh(gt), ts, samples, seed)
    if as_json:
        click.echo(json.dumps(m, indent=2))
    else:
        click.echo(format_table({Path(pred).name: m}))


def main(argv=None) -> int:
    """Console entry point: run the CLI, turn user errors into ``error: ...`` and exit code 2."""
    try:
        cli.main(args=argv, prog_name="bftaichi", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("interrupted", err=True)
        return 130
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        return 130
    except click.ClickException as e:
        e.show()
        return e.exit_code
    except BftaichiError as e:
        if os.environ.get("BFTAICHI_DEBUG"):
            raise
        click.echo(f"error: {e}", err=True)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
