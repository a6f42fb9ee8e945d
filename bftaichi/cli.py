"""The ``bftaichi`` command line. Commands stay thin: parse, call the library, print.

Errors the user can fix (bad file, key or value) print ``error: ...`` and exit with code 2;
Ctrl-C exits with 130, SIGTERM with 143, SIGHUP with 129 (:mod:`bftaichi.running.signals`).
No traceback unless ``BFTAICHI_DEBUG=1``.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import warnings
from pathlib import Path

import click

from .errors import BftaichiError
from .process import freeze_heap, quick_exit
from .running.summary import print_ranking as _print_ranking
from .running.summary import print_scan_summary as _print_scan_summary
from .running.summary import print_summary as _print_summary

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


#: ``--strict`` of ``run`` and ``fuse`` (``run.strict``).
STRICT_HELP = ("Refuse input that fails a plausibility check (8-bit depth, depth outside the "
               "depth range, depth scale off by 10, poses given as T_C_W, image size against "
               "K, GPU backend fallen back to the CPU: otherwise warnings) and a MAP solve that "
               "does not converge (otherwise the mesh is flagged): exit 2, no mesh written.")


@contextlib.contextmanager
def _warnings_on_stderr():
    """Print bftaichi's warnings (plausibility checks, datasets, locks) as ``warning: ...`` on
    stderr, every time (also with ``-q``: it silences progress and summary, not what may be
    wrong with the result)."""
    from .errors import BftaichiWarning

    with warnings.catch_warnings():
        warnings.simplefilter("always", BftaichiWarning)
        show_other = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, BftaichiWarning):
                click.echo(f"warning: {message}", err=True)
            else:
                show_other(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


@cli.command()
@click.argument("scene", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "-o", type=click.Path(file_okay=False), default=None,
              help="Output folder [default: out/<scene name>].")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Override a scene value, e.g. --set tsdf.voxel_size_m=0.005 (repeatable).")
@click.option("--arch", type=ARCH, default=None, help="Taichi backend [default: cpu].")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
@click.option("--verbose", "-v", is_flag=True, help="Every metric, stage time and count.")
@click.option("--strict", is_flag=True, help=STRICT_HELP)
def run(scene, out, sets, arch, overwrite, quiet, verbose, strict):
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
    from .running.pipeline import run as run_pipeline

    cfg = load_config(scene, _overrides(arch, sets) + (["run.strict=true"] if strict else []))
    out = Path(out or Path("out") / cfg.scene.name)
    freeze_heap()
    report = run_pipeline(cfg, out, overwrite=overwrite, progress=not quiet)
    if not quiet:
        _print_summary(out, report, verbose)


@cli.command()
@click.argument("data_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", default="auto", show_default=True,
              help="Dataset layout: auto, 7scenes, bfsdf, tum, replica, scannet, co3d, redwood, "
              "folder.")
@click.option("--voxel", type=float, default=0.01, show_default=True, help="Voxel size, metres.")
@click.option("--trunc", type=float, default=None,
              help="Observation truncation tau, metres [default: 2 voxels]; the TSDF uses alpha*tau.")
@click.option("--frames", default="", help="Slice of frames, e.g. 0:500:5 [default: all].")
@click.option("--depth-max", type=float, default=None, help="Ignore depth beyond this, metres.")
@click.option("--gt", "gt_mesh", type=click.Path(dir_okay=False), default="auto",
              help="Ground-truth mesh for metrics [default: gt_mesh.ply in DATA_DIR if present].")
@click.option("--depth-scale", type=float, default=None,
              help="Stored depth units per metre [default: the format's own, e.g. 1000 for mm "
              "PNG, 5000 for tum].")
@click.option("--pose-convention", type=click.Choice(["T_W_C", "T_C_W"]), default=None,
              help="What the folder format's pose files hold [default: T_W_C, camera-to-world].")
@click.option("--rgb", is_flag=True, help="Integrate colour (where the format has it) and "
              "write vertex colours into both meshes.")
@click.option("--out", "-o", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Other overrides.")
@click.option("--arch", type=ARCH, default=None, help="Taichi backend [default: cpu].")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
@click.option("--verbose", "-v", is_flag=True, help="Every metric, stage time and count.")
@click.option("--strict", is_flag=True, help=STRICT_HELP)
def fuse(data_dir, fmt, voxel, trunc, frames, depth_max, gt_mesh, depth_scale, pose_convention,
         rgb, out, sets, arch, overwrite, quiet, verbose, strict):
    """Fuse recorded depth frames from DATA_DIR into a TSDF mesh.

    \b
    Example (the shared 7-Scenes frames):
      bftaichi fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out out/kitchen
    """
    from .config import load_config
    from .running.pipeline import run as run_pipeline

    extra = []
    if depth_scale is not None:
        extra.append(f"scene.depth_scale={depth_scale}")
    if pose_convention:
        extra.append(f"scene.pose_convention={pose_convention}")
    if rgb:
        extra.append("tsdf.integrate_rgb=true")
    if strict:
        extra.append("run.strict=true")
    cfg = load_config(None, _dataset_overrides(data_dir, fmt, voxel, trunc, frames, depth_max,
                                               gt_mesh) + extra + _overrides(arch, sets))
    freeze_heap()
    report = run_pipeline(cfg, Path(out), overwrite=overwrite, progress=not quiet)
    if not quiet:
        _print_summary(Path(out), report, verbose)


@cli.command()
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--poses", "poses", type=click.Path(), required=True,
              help="New poses T_W_C: a folder of <frame name>.txt / .pose.txt 4x4 files, or a "
              "text file with one pose per line (frame name and 16 numbers, row-major; or the 16 "
              "numbers alone, one line per frame in order), a TUM trajectory (timestamp tx ty "
              "tz qx qy qz qw) or an Open3D .log.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
@click.option("--verbose", "-v", is_flag=True, help="Every metric, stage time and count.")
def update(out_dir, poses, quiet, verbose):
    """Move frames of a run to corrected poses (after a loop closure) without re-fusing.

    OUT_DIR must come from `bftaichi run` or `fuse` with --set run.keep_state=true, which also
    writes fusion_state.npz (the TSDF's integer sums, 24 bytes an observed voxel, and each
    frame's pose). Only the frames whose pose changed are subtracted from the TSDF and added
    again, exactly: the TSDF equals fusing every frame at its new pose. The posterior is then
    solved again on all frames and every output is replaced together; report.json records the
    frames that moved under "update".

    \b
    Example:
      bftaichi fuse DATA --voxel 0.02 --out out/kitchen --set run.keep_state=true
      bftaichi update out/kitchen --poses corrected_poses.txt
    """
    from .running.update import update_run

    report = update_run(out_dir, poses, progress=not quiet)
    if report is None:
        if not quiet:
            click.echo(f"no frame of {out_dir} has a new pose in {poses}: nothing to do")
        return
    if not quiet:
        u = report["update"]
        click.echo(f"moved {u['n_moved']} of {u['n_frames']} frames: "
                   + ", ".join(u["moved"][:8]) + (" ..." if u["n_moved"] > 8 else ""))
        _print_summary(Path(out_dir), report, verbose)


def _dataset_overrides(data_dir, fmt, voxel, trunc, frames, depth_max, gt_mesh) -> list[str]:
    """``--set`` lines of a recorded dataset run (``fuse``, ``evalviews``)."""
    base = [f"scene.source=dataset", f"scene.data={json.dumps(str(data_dir))}",
            f"scene.format={fmt}", f"scene.name={json.dumps(Path(data_dir).name or 'data')}",
            f"tsdf.voxel_size_m={voxel}",
            f"tsdf.trunc_m={trunc if trunc is not None else 2 * voxel}",
            f"scene.gt_mesh={json.dumps(str(gt_mesh))}"]
    if frames:
        base.append(f"scene.frames={json.dumps(frames)}")
    if depth_max is not None:
        base.append(f"scene.depth_max_m={depth_max}")
    return base


@cli.command()
@click.argument("data_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", default="auto", show_default=True, help="Dataset layout.")
@click.option("--voxel", type=float, default=0.02, show_default=True, help="Voxel size, metres.")
@click.option("--trunc", type=float, default=None,
              help="Observation truncation tau, metres [default: 2 voxels].")
@click.option("--frames", default="", help="Slice of frames, e.g. 0:500 [default: all].")
@click.option("--depth-max", type=float, default=None, help="Ignore depth beyond this, metres.")
@click.option("--every", type=int, default=2, show_default=True,
              help="Fuse every n-th frame; the others are held out.")
@click.option("--held-out-stride", type=int, default=1, show_default=True,
              help="Evaluate every n-th held-out frame.")
@click.option("--block", type=int, default=1, show_default=True,
              help="Split in blocks of n consecutive frames: every --every-th block fused, "
                   "the others held out (1: frames interleaved). Recorded poses drift, so a "
                   "held-out frame between fused ones shares their pose error; blocks judge "
                   "the map away in time from its frames.")
@click.option("--no-open3d", is_flag=True, help="Skip Open3D's VoxelBlockGrid even if installed.")
@click.option("--out", "-o", type=click.Path(file_okay=False), required=True, help="Output folder.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Other overrides.")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or table.")
def evalviews(data_dir, fmt, voxel, trunc, frames, depth_max, every, held_out_stride, block,
              no_open3d, out, sets, overwrite, quiet):
    """Judge the reconstruction of DATA_DIR on depth frames that were not fused.

    Fuses every --every-th frame (bftaichi posterior, TSDF bootstrap and, when installed,
    Open3D's VoxelBlockGrid, all at the same voxel size), renders depth at each held-out
    frame's pose from each, and compares it with the measured depth: mean and median absolute
    error, the fraction within 1 / 2 / 5 cm, and completeness (the share of measured pixels
    that get a prediction). Also the coverage of bftaichi's predicted depth sigma. Writes the
    run's outputs and evalviews.json into --out.

    \b
    Examples (the shared 7-Scenes frames; the second holds out blocks of 100 frames):
      bftaichi evalviews ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out out/ev2
      bftaichi evalviews ../shared/data/rgbd/7scenes-redkitchen --block 100 --out out/ev2b
    """
    from .config import load_config
    from .evaluation.evalviews import evaluate_views, format_result

    cfg = load_config(None, _dataset_overrides(data_dir, fmt, voxel, trunc, frames, depth_max,
                                               "auto") + list(sets))
    result = evaluate_views(cfg, Path(out), every=every, held_out_stride=held_out_stride,
                            block=block, open3d=not no_open3d, overwrite=overwrite,
                            progress=not quiet)
    if not quiet:
        click.echo(format_result(result))
        click.echo(f"wrote {Path(out) / 'evalviews.json'}")


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
    from .formats.synthetic import SyntheticDataset, write_7scenes
    from .io import ensure_out_dir
    from .running import folder

    cfg = load_config(scene, sets)
    ds = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
    with folder.hold(ensure_out_dir(out)):  # one writer at a time
        path = write_7scenes(ds, out, progress=not quiet)
    if not quiet:
        click.echo(f"wrote {len(ds)} frames of {ds.image_size[0]}x{ds.image_size[1]} and "
                   f"gt_mesh.ply to {path}/")


@cli.command()
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--candidates", type=click.Choice(["sphere", "hemisphere", "ring", "file"]),
              default=None, help="Candidate generator [default: the run's nbv.candidates, "
              "hemisphere].")
@click.option("--n", "n_candidates", type=int, default=None,
              help="Number of generated candidates [default: 48].")
@click.option("--radius", type=float, default=None,
              help="Distance of the candidates from the target, metres [default: 3x the "
              "band's bounding radius].")
@click.option("--poses", type=click.Path(dir_okay=True), default=None,
              help="Candidate poses file (one row-major 4x4 T_W_C per line) or folder of 4x4 "
              "files; implies --candidates file.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Other overrides, e.g. --set nbv.stride=4.")
@click.option("--top", type=int, default=5, show_default=True, help="Rows to print.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing.")
@click.option("--verbose", "-v", is_flag=True, help="Print every candidate and the planner's "
              "settings.")
def nbv(out_dir, candidates, n_candidates, radius, poses, sets, top, quiet, verbose):
    """Rank next-best views for the outputs of a run (OUT_DIR of `bftaichi run` or `fuse`).

    Reads OUT_DIR/config.toml and band.npz, re-reads the run's frames to mark the space they
    saw, scores every candidate by the posterior variance its depth image would remove
    (known surface) plus the unseen space it would reveal, and writes OUT_DIR/nbv.json (each
    candidate's pose, utility and rank); report.json gains the top view.

    \b
    Example:
      bftaichi run scenes/bunny.toml --out out/bunny
      bftaichi nbv out/bunny --n 48 --top 3
    """
    import json as _json

    from . import backend
    from .config import load_config
    from .errors import DataError
    from .io import write_json
    from .planning.nbv import nbv_summary, rank_run
    from .running.pipeline import open_frames
    from .running.report import read_report
    from .posterior import Posterior

    out = Path(out_dir)
    for name in ("config.toml", "band.npz"):
        if not (out / name).exists():
            raise DataError(f"{out / name} does not exist: OUT_DIR must hold the outputs of "
                            "`bftaichi run` or `bftaichi fuse`")
    extra = list(sets)
    if poses:
        extra += ["nbv.candidates=file", f"nbv.poses_file={_json.dumps(str(Path(poses).resolve()))}"]
    elif candidates:
        extra.append(f"nbv.candidates={candidates}")
    if n_candidates is not None:
        extra.append(f"nbv.n_candidates={n_candidates}")
    if radius is not None:
        extra.append(f"nbv.radius_m={radius}")
    from tqdm import tqdm

    from .running import folder

    def bar(it):
        return tqdm(it, desc="nbv", unit="view", leave=False, disable=None if not quiet else True)

    # a writer: no run may replace the posterior while it is ranked, and nbv.json and the
    # report's ranking are replaced together
    with folder.hold(out):
        cfg = load_config(out / "config.toml", extra)
        post = Posterior.load(out / "band.npz")
        frames = open_frames(cfg)
        backend.init(cfg.run.arch)
        report_path = out / "report.json"
        report = read_report(report_path) if report_path.exists() else None
        with folder.staged(out) as staging:
            result = rank_run(post, cfg, frames, staging, progress=bar)
            if report is not None:
                report["nbv"] = nbv_summary(result)
                write_json(staging / "report.json", report)
    if not quiet:
        _print_ranking(result, len(result["candidates"]) if verbose else top)
        if verbose:
            click.echo("planner: " + json.dumps(result["settings"]))
        click.echo(f"wrote {out / 'nbv.json'}")


@cli.command()
@click.argument("scene", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "-o", type=click.Path(file_okay=False), default=None,
              help="Output folder [default: out/scan-<scene name>].")
@click.option("--policies", default="bayes,coverage,frontier,entropy,farthest,random",
              show_default=True, help="Comma-separated policies (bftaichi.planning.scan).")
@click.option("--steps", type=int, default=None, help="Views added after the initial ones "
              "[default: nbv.steps = 12].")
@click.option("--candidates", "n_candidates", type=int, default=None,
              help="Number of candidate views [default: nbv.n_candidates = 48].")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Override a scene value, e.g. --set nbv.random_seeds=5.")
@click.option("--arch", type=ARCH, default=None, help="Taichi backend [default: cpu].")
@click.option("--overwrite", is_flag=True, help="Replace an earlier scan in --out.")
@click.option("--quiet", "-q", is_flag=True, help="No progress or summary.")
@click.option("--verbose", "-v", is_flag=True, help="A line per step of every policy.")
def scan(scene, out, policies, steps, n_candidates, sets, arch, overwrite, quiet, verbose):
    """Closed-loop active scanning of a synthetic SCENE (default: the built-in tabletop).

    Every policy starts from the same 2 views and adds one view at a time from the same
    candidate set; each new view is rendered (with the scene's noise) from the true mesh,
    fused, and scored against the truth; repeated from nbv.initial_seeds draws of the initial
    views. Writes scan.json (per step: recall at 2/5/10 mm, completeness, accuracy, bayes' sigma
    calibration; mean ± std: AUC of recall@5mm, views to 90/95 % recall@5mm) and scan.png.

    \b
    Example:
      bftaichi scan scenes/bunny.toml --out out/scan-bunny
      bftaichi scan --policies bayes,random --steps 4 --out out/scan-quick
    """
    from .config import load_config
    from .planning.scan import scan as run_scan

    extra = _overrides(arch, sets)
    if steps is not None:
        extra.append(f"nbv.steps={steps}")
    if n_candidates is not None:
        extra.append(f"nbv.n_candidates={n_candidates}")
    cfg = load_config(scene, extra)
    chosen = tuple(p.strip() for p in policies.split(",") if p.strip())
    from tqdm import tqdm

    runs = cfg.nbv.initial_seeds * sum(cfg.nbv.random_seeds if p == "random" else 1
                                       for p in chosen)
    bar = tqdm(total=runs * cfg.nbv.steps, desc="scan", unit="view", leave=False,
               disable=None if not quiet else True)

    def show(policy, seed, rec):
        bar.set_postfix_str(policy)
        bar.update(1)
        if verbose:
            bar.write(f"  {policy}{'' if policy != 'random' else f' (seed {seed})'}: "
                      f"{rec['views']} views, F@10mm {rec['fscore@10mm']:.3f}, completeness "
                      f"{rec['completeness_mm']:.2f} mm", file=sys.stderr)

    out = Path(out or Path("out") / f"scan-{cfg.scene.name}")
    try:
        run_scan(cfg, out, chosen, overwrite=overwrite, progress=show)
    finally:
        bar.close()
    if not quiet:
        _print_scan_summary(out)


@cli.command()
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--html", "html_file", type=click.Path(dir_okay=False), default=None,
              help="Write a self-contained static page to this file instead of serving.")
@click.option("--band", is_flag=True, help="Also show the band voxels near the surface as "
              "points coloured by sigma.")
@click.option("--max-faces", type=int, default=200_000, show_default=True,
              help="Decimate meshes above this many faces before sending them.")
@click.option("--timeout", type=float, default=None,
              help="Stop serving after this many seconds [default: until Ctrl-C].")
def view(out_dir, html_file, band, max_faces, timeout):
    """Show the outputs of a run (OUT_DIR) in the browser with meshcat.

    The mesh is coloured by its posterior sigma (legend in the page); the TSDF baseline mesh,
    the input cameras and the NBV candidates (if nbv.json exists) are layers you can toggle
    under Open Controls > Scene. Without --html this serves the live viewer and prints its URL
    (open it in a browser; Ctrl-C stops the server). Every `bftaichi run` also writes
    OUT_DIR/preview.html, the same page as --html.

    \b
    Examples:
      bftaichi view out/bunny                      # live viewer, prints the URL
      bftaichi view out/bunny --html bunny.html    # one self-contained file
    """
    from .errors import BftaichiError as _Error
    from .running.viz import serve, write_preview

    if max_faces < 1000:
        raise _Error(f"--max-faces {max_faces}: must be at least 1000")
    if html_file:
        from .io import writable_target

        writable_target(html_file)  # before any work: never a device, FIFO or folder
        path = write_preview(out_dir, html_file, max_faces=max_faces, band=band)
        click.echo(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
        return
    serve(out_dir, timeout_s=timeout, max_faces=max_faces, band=band,
          on_url=lambda url: click.echo(f"meshcat viewer of {out_dir}: {url}  (Ctrl-C to stop)"))


@cli.command()
@click.argument("manifest", type=click.Path(dir_okay=False))
@click.option("--out", "-o", type=click.Path(file_okay=False), required=True,
              help="Output folder: one sub-folder per run, and batch.json.")
@click.option("--workers", type=int, default=None,
              help="CPUs of the local Ray cluster, one run each [default: all cores].")
@click.option("--address", default=None,
              help="Join a running Ray cluster (e.g. ray://head:10001 or auto) instead.")
@click.option("--resume", is_flag=True, help="Skip runs whose outputs are complete.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary table.")
def batch(manifest, out, workers, address, resume, quiet):
    """Run many scenes on Ray, one task per run (needs the "distributed" extra).

    MANIFEST is a TOML file of [[run]] tables: scene (a scene file, relative to the manifest),
    optional name (the output sub-folder; default the scene's name) and optional set (a list of
    "section.key=value" overrides). Each run writes OUT/<name>/ exactly as `bftaichi run` would;
    OUT/batch.json records each run's status, seconds, peak memory, worker and error. A failing
    run does not stop the others; the exit code is 0 only if every run succeeded. A run set to
    solve in spatial chunks (run.chunk_m) sends each chunk to Ray as a task of its own.

    \b
    Example (scenes.toml):
      [[run]]
      scene = "scenes/bunny.toml"
      [[run]]
      scene = "scenes/bunny.toml"
      name = "bunny-far"
      set = ["synthetic.cam_radius_m=1.2"]
    \b
      bftaichi batch scenes.toml --out out/batch --workers 2
    """
    from .running.batch import run_batch, summary_lines

    result = run_batch(manifest, out, workers=workers, address=address, resume=resume,
                       progress=not quiet)
    if not quiet:
        click.echo("\n".join(summary_lines(result)))
        click.echo(f"wrote {Path(out) / 'batch.json'}")
    return 0 if result["counts"]["failed"] == 0 else 1


@cli.command(name="eval")
@click.argument("pred", type=click.Path(dir_okay=False))
@click.argument("gt", type=click.Path(dir_okay=False))
@click.option("--thresholds", default="5,10,20,50", show_default=True,
              help="Comma-separated F-score thresholds, millimetres.")
@click.option("--samples", type=int, default=200000, show_default=True,
              help="Points sampled on each surface.")
@click.option("--seed", type=int, default=0, show_default=True, help="Sampling seed.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table (strict "
              "JSON: a distance that is not defined, inf in the table, is null).")
def eval_cmd(pred, gt, thresholds, samples, seed, as_json):
    """Geometry metrics of mesh PRED against ground-truth mesh GT.

    Chamfer L2 (mean squared distance both ways), accuracy (mean PRED->GT distance), completeness
    (mean GT->PRED distance), and precision / recall / F-score at each threshold, from
    area-weighted surface samples with a fixed seed. A PRED without surface (no triangle of
    positive area) has no distances: inf in the table, null in --json, and F-scores 0.

    \b
    Example:
      bftaichi eval out/default/tsdf_mesh.ply data/tabletop/gt_mesh.ply --json
    """
    from .config import EvalConfig
    from .evaluation.metrics import format_table, geometry_metrics, load_mesh
    from .io import to_json

    try:
        ts = [float(t) for t in thresholds.split(",") if t.strip()]
    except ValueError:
        raise BftaichiError(f"--thresholds {thresholds!r}: expected numbers like 5,10,20") from None
    EvalConfig(thresholds_mm=ts, n_samples=samples, seed=seed).check()
    m = geometry_metrics(load_mesh(pred), load_mesh(gt, surface=True), ts, samples, seed)
    if as_json:
        click.echo(to_json(m))
    else:
        click.echo(format_table({Path(pred).name: m}))


def main(argv=None) -> int:
    """Console entry point: run the CLI, turn user errors into ``error: ...`` and exit code 2."""
    from .running import folder, signals

    args = sys.argv[1:] if argv is None else list(argv)
    folder.command_line = " ".join(["bftaichi", *args])  # names a folder's lock holder
    try:
        with signals.handled(), _warnings_on_stderr():  # SIGTERM, SIGHUP: as Ctrl-C
            rc = cli.main(args=args, prog_name="bftaichi", standalone_mode=False)
    except (click.exceptions.Abort, KeyboardInterrupt) as e:
        click.echo(signals.describe_interrupt(e), err=True)
        return signals.exit_code(e)
    except click.ClickException as e:
        e.show()
        return e.exit_code
    except BftaichiError as e:
        if os.environ.get("BFTAICHI_DEBUG"):
            raise
        click.echo(f"error: {e}", err=True)
        return 2
    return rc if isinstance(rc, int) else 0  # a command's own exit code (batch: 1 = a run failed)


def console() -> None:
    """The ``bftaichi`` command: :func:`main`, then :func:`~bftaichi.process.quick_exit`. An
    exception :func:`main` does not handle (a bug) ends the process the usual way."""
    quick_exit(main())


if __name__ == "__main__":  # pragma: no cover
    console()
