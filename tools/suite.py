#!/usr/bin/env python
"""The development suite: is the posterior better than its own TSDF bootstrap, and is its vertex
sigma honest, on every mesh and capture condition (issue 15, DESIGN.md section 6)?

Each case renders a mesh the way ``bftaichi synth`` renders (Kinect axial noise, 1 mm
quantisation, 2 % dropout unless the condition says otherwise), normalised so its largest
extent is 0.3 m and centred at the origin, fuses it with ``bftaichi run`` and judges:

- geometry of ``mesh.ply`` against ``tsdf_mesh.ply``: Chamfer distance (CD, m^2) and the
  F-score at the finest threshold (of 0.5, 1, 2, 5, 10 mm) where the TSDF's F reaches 0.5
  (finer ones only measure noise; coarser ones saturate);
- vertex calibration (:func:`bftaichi.evaluation.metrics.vertex_uncertainty`: error = exact
  distance of each vertex to the true mesh): coverage at 1, 2, 3 sigma, NLL minus the best
  constant sigma's, AUSE, the mean error of the 10 % most uncertain vertices over the mean
  error, Spearman.

Capture conditions (``CONDITIONS``; the object is 0.3 m across):

==============  ============================================================================
dense_near      60 views on a ring 0.6 m away, 320x240, 3 mm voxels
sparse_far      20 views 1.5 m away, 160x120 (each pixel ~1.1 cm), 5 mm voxels
few_views       6 views 0.8 m away, 320x240, 4 mm voxels
grazing         24 views on a low ring (3 cm above the centre), 0.8 m away, 4 mm voxels
heavy_noise     as few_views' camera but 24 views, with 2x the Kinect noise (the observation
                model is not told: it keeps the default sensor model)
dropout         24 views, 0.8 m, 10 % of the valid pixels dropped
==============  ============================================================================

plus the paper's controlled sphere (``scenes/seed_sphere.toml``). Meshes: the Stanford bunny
and the six development meshes of ``../shared/data/meshes`` (or ``--data``).

Every figure of the README's suite table comes from this script::

    python tools/suite.py                                  # 7 meshes x 6 conditions + sphere
    python tools/suite.py --quick                          # the subset the tests run
    python tools/suite.py --meshes suzanne,homer --conditions sparse_far --set prior.curvature=1
    python tools/suite.py --json suite.json --markdown suite.md
    python tools/suite.py --heldout                        # 5 meshes it was not tuned on
    python tools/suite.py --heldout --meshes disk --conditions few_views --keep runs
    python docs/experiments/seen_unseen.py runs/disk-few_views   # its CD and F, seen or not

Targets (issue 15), checked per case and counted at the end: coverage at 1 sigma in 60-76 %,
at 2 sigma in 90-98 %, at 3 sigma >= 98 %; NLL below the constant's; posterior CD <= TSDF's
and F >= TSDF's; CD <= 0.8x the TSDF's on sparse_far, few_views and heavy_noise.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data"
MESHES = ("stanford-bunny", "suzanne", "beetle", "cheburashka", "homer", "rocker-arm", "ogre")
SIZE_M = 0.3
THRESHOLDS_MM = (0.5, 1.0, 2.0, 5.0, 10.0)

_QVGA = {"width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}
_QQVGA = {"width": 160, "height": 120, "fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5}
_MID = {**_QVGA, "n_views": 24, "cam_radius_m": 0.8, "cam_height_m": 0.4, "voxel": 0.004}

#: name -> synthetic.* settings plus "voxel" (metres; the truncation is 2 voxels).
CONDITIONS = {
    "dense_near": {**_QVGA, "n_views": 60, "cam_radius_m": 0.6, "cam_height_m": 0.3,
                   "voxel": 0.003},
    "sparse_far": {**_QQVGA, "n_views": 20, "cam_radius_m": 1.5, "cam_height_m": 0.4,
                   "voxel": 0.005},
    "few_views": {**_MID, "n_views": 6},
    "grazing": {**_MID, "cam_height_m": 0.03},
    "heavy_noise": {**_MID, "depth_a_m": 0.0024, "depth_b": 0.0038},
    "dropout": {**_MID, "dropout": 0.10},
}
#: Conditions where a prior should pay: posterior CD at most 0.8x the TSDF's.
PRIOR_PAYS = ("sparse_far", "few_views", "heavy_noise")
#: The subset tests/test_suite.py runs (two shapes, two conditions).
QUICK = (("suzanne", "homer"), ("sparse_far", "few_views"))
SPHERE = "seed_sphere"


def mesh_sets(mesh_path: Path) -> list[str]:
    """``--set`` overrides rendering ``mesh_path`` (y-up OBJ) centred, largest extent 0.3 m."""
    import trimesh

    m = trimesh.load(str(mesh_path), force="mesh", process=False)
    scale = SIZE_M / float(max(m.extents))
    return [f"synthetic.mesh={mesh_path}", "synthetic.mesh_up=y", "synthetic.center_mesh=true",
            f"synthetic.mesh_scale={scale:.9g}"]


def case_sets(mesh: str, condition: str, data: Path) -> list[str]:
    """The overrides of one case on the default config (scene name ``mesh/condition``)."""
    c = dict(CONDITIONS[condition])
    voxel = c.pop("voxel")
    sets = [f"scene.name={mesh}-{condition}", "scene.source=synthetic",
            "synthetic.trajectory=ring", "synthetic.noise=kinect",
            "synthetic.quantization_m=0.001", "synthetic.look_at=[0.0, 0.0, 0.0]"]
    c.setdefault("dropout", 0.02)
    sets += [f"synthetic.{k}={v}" for k, v in c.items()]
    sets += mesh_sets(data / "meshes" / f"{mesh}.obj")
    sets += [f"tsdf.voxel_size_m={voxel}", f"tsdf.trunc_m={2 * voxel}",
             f"eval.thresholds_mm=[{', '.join(str(t) for t in THRESHOLDS_MM)}]"]
    return sets


def judge(report: dict) -> dict:
    """One case's row from its report.json dict."""
    m = report["metrics"]
    tsdf, post = m["tsdf_mesh.ply"], m["mesh.ply"]
    thresholds = report["config"]["eval"]["thresholds_mm"]
    t = next((t for t in thresholds if tsdf[f"fscore@{t:g}mm"] >= 0.5), thresholds[-1])
    u = report.get("uncertainty") or {}
    row = {"cd_tsdf": tsdf["chamfer_l2"], "cd_post": post["chamfer_l2"],
           "f_mm": t, "f_tsdf": tsdf[f"fscore@{t:g}mm"], "f_post": post[f"fscore@{t:g}mm"],
           # the two halves of CD (metres): mesh to truth, truth to mesh
           "accuracy_tsdf": tsdf["accuracy_m"], "accuracy_post": post["accuracy_m"],
           "completeness_tsdf": tsdf["completeness_m"], "completeness_post": post["completeness_m"],
           "seconds": report["seconds"]["total"],
           # frames in a row that share one error of the fitted noise (1: none found)
           "frames_sharing_noise": report["solver"]["observations"].get("noise_fit", {}).get(
               "frames_sharing_noise")}
    for k in ("coverage@1sigma", "coverage@2sigma", "coverage@3sigma", "nll_vs_constant",
              "ause", "top10_ratio", "spearman", "mean_error_m", "median_error_m", "median_sigma_m",
              "n"):
        row[k] = u.get(k, float("nan"))
    return row


def seen_samples(cfg) -> tuple:
    """``(target, seen)``: the true mesh of the synthetic ``cfg`` sampled as its run's metrics
    sample it (``SampledSurface``) and the samples some frame observed
    (:func:`bftaichi.evaluation.seen.seen_points`, with the noise the frames were rendered
    with)."""
    from bftaichi.evaluation.metrics import SampledSurface
    from bftaichi.evaluation.seen import seen_points
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    frames = open_frames(cfg)
    target = SampledSurface(load_gt_mesh(cfg, frames), cfg.eval.n_samples, cfg.eval.seed)
    return target, seen_points(target.points(), frames, cfg.synthetic.depth_sigma_m)


def seen_geometry(cfg, out: Path) -> dict:
    """The two meshes' Chamfer distance on the part of the true surface the frames saw
    (:func:`seen_samples`; ``SampledSurface.chamfer_split``, the same samples as the run's
    metrics): the CD of the rest is how each mesh closes what no frame saw."""
    import trimesh

    target, seen = seen_samples(cfg)
    row = {"seen_share": float(seen.mean())}
    for key, name in (("tsdf", "tsdf_mesh.ply"), ("post", "mesh.ply")):
        split = target.chamfer_split(trimesh.load(str(out / name), process=False), seen)
        row[f"cd_seen_{key}"] = split[0] if split is not None else math.inf
    return row


def _geometric_mean(x: list) -> float:
    return math.exp(sum(math.log(v) for v in x) / len(x)) if x else float("nan")


def targets(name: str, row: dict) -> dict:
    """Which of issue 15's targets the row meets (True/False per target)."""
    condition = name.split("/")[-1]
    out = {"cov1": 0.60 <= row["coverage@1sigma"] <= 0.76,
           "cov2": 0.90 <= row["coverage@2sigma"] <= 0.98,
           "cov3": row["coverage@3sigma"] >= 0.98,
           "nll": row["nll_vs_constant"] < 0,
           "cd": row["cd_post"] <= row["cd_tsdf"],
           "f": row["f_post"] >= row["f_tsdf"]}
    if condition in PRIOR_PAYS:
        out["cd0.8"] = row["cd_post"] <= 0.8 * row["cd_tsdf"]
    return out


def misses(name: str, row: dict) -> list[str]:
    """The names of the targets the row misses (:func:`targets`), in their order."""
    return [k for k, ok in targets(name, row).items() if not ok]


def markdown(rows: dict) -> str:
    head = ("| case | CD TSDF | CD post | ratio | seen: share, CD ratio | F@t TSDF / post | "
            "cov 1/2/3 sigma (%) | NLL - const | AUSE (mm) | top10 | Spearman | misses |")
    lines = [head, "|" + "---|" * 12]
    for name, r in rows.items():
        miss = misses(name, r)
        seen = (f"{100 * r['seen_share']:.0f} %, {r['cd_seen_post'] / r['cd_seen_tsdf']:.2f}"
                if "cd_seen_post" in r else "-")
        lines.append(
            f"| {name} | {r['cd_tsdf']:.3g} | {r['cd_post']:.3g} | "
            f"{r['cd_post'] / r['cd_tsdf']:.2f} | {seen} | @{r['f_mm']:g}: {r['f_tsdf']:.3f} / "
            f"{r['f_post']:.3f} | {100 * r['coverage@1sigma']:.0f} / "
            f"{100 * r['coverage@2sigma']:.0f} / {100 * r['coverage@3sigma']:.1f} | "
            f"{r['nll_vs_constant']:+.2f} | {1000 * r['ause']:.3f} | {r['top10_ratio']:.2f} | "
            f"{r['spearman']:.2f} | {', '.join(miss) or '-'} |")
    return "\n".join(lines)


def summary(rows: dict) -> str:
    """Counts of met targets, and the geometric means of the CD ratio."""
    counts: dict[str, list[int]] = {}
    for name, r in rows.items():
        for k, ok in targets(name, r).items():
            counts.setdefault(k, [0, 0])
            counts[k][0] += int(ok)
            counts[k][1] += 1
    gm = _geometric_mean([r["cd_post"] / r["cd_tsdf"] for r in rows.values()])
    parts = [f"{k} {a}/{b}" for k, (a, b) in counts.items()]
    line = f"targets met: {', '.join(parts)}; geometric mean CD ratio {gm:.3f}"
    seen = [r["cd_seen_post"] / r["cd_seen_tsdf"] for r in rows.values() if "cd_seen_post" in r]
    if seen:
        sparse = [r["cd_seen_post"] / r["cd_seen_tsdf"] for n, r in rows.items()
                  if "cd_seen_post" in r and n.split("/")[-1] in PRIOR_PAYS]
        line += (f"\non the surface the frames saw: CD <= TSDF on {sum(x <= 1 for x in seen)}/"
                 f"{len(seen)}, <= 0.8x on {sum(x <= 0.8 for x in sparse)}/{len(sparse)} of the "
                 f"sparse, few-view and noisy cases; geometric mean CD ratio "
                 f"{_geometric_mean(seen):.3f}")
    return line


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA,
                    help="shared data folder holding meshes/ (default: ../shared/data)")
    ap.add_argument("--meshes", default=",".join(MESHES), help="comma-separated mesh names")
    ap.add_argument("--conditions", default=",".join(CONDITIONS),
                    help="comma-separated capture conditions")
    ap.add_argument("--no-sphere", action="store_true", help="skip scenes/seed_sphere.toml")
    ap.add_argument("--heldout", action="store_true",
                    help="the meshes the model was not developed on (tools/heldout_meshes.py: "
                    "head, disk, torus, capsule, bracket; written to a temporary folder) instead "
                    "of --data's, without the sphere")
    ap.add_argument("--quick", action="store_true",
                    help=f"the tests' subset: {', '.join(QUICK[0])} x {', '.join(QUICK[1])}")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override applied to every case (a model change to judge)")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument("--markdown", type=Path, help="also write the table as Markdown here")
    ap.add_argument("--keep", type=Path, metavar="DIR",
                    help="keep each case's run folder in DIR/<mesh>-<condition> (and, with "
                    "--heldout, its meshes in DIR/meshes), e.g. for "
                    "docs/experiments/seen_unseen.py; default: a temporary folder")
    args = ap.parse_args(argv)

    import bftaichi as bf

    meshes = QUICK[0] if args.quick else tuple(m for m in args.meshes.split(",") if m)
    heldout = tempfile.TemporaryDirectory(prefix="bftaichi-heldout-") if args.heldout else None
    if heldout is not None:
        from heldout_meshes import HELDOUT, write_heldout

        args.data = write_heldout(args.keep if args.keep else Path(heldout.name))
        args.no_sphere = True
        meshes = HELDOUT if args.meshes == ",".join(MESHES) else meshes
    conditions = QUICK[1] if args.quick else tuple(c for c in args.conditions.split(",") if c)
    for c in conditions:
        if c not in CONDITIONS:
            ap.error(f"unknown condition {c!r}; choose from {', '.join(CONDITIONS)}")
    for m in meshes:
        if not (args.data / "meshes" / f"{m}.obj").is_file():
            print(f"error: mesh {args.data / 'meshes' / f'{m}.obj'} not found (pass --data)",
                  file=sys.stderr)
            return 2
    cases = [(f"{m}/{c}", case_sets(m, c, args.data)) for m in meshes for c in conditions]
    if not (args.no_sphere or args.quick):
        cases.append((SPHERE, ["--scene", str(ROOT / "scenes" / "seed_sphere.toml")]))
    rows = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bftaichi-suite-") as tmp:
        for i, (name, sets) in enumerate(cases):
            scene = None
            if sets[:1] == ["--scene"]:
                scene, sets = sets[1], []
            cfg = bf.load_config(scene, [*sets, *args.sets])
            out = args.keep / name.replace("/", "-") if args.keep else Path(tmp) / f"case{i}"
            report = bf.run(cfg, out, overwrite=True, progress=False)
            rows[name] = dict(judge(report), **seen_geometry(cfg, out))
            r = rows[name]
            print(f"[{i + 1}/{len(cases)}] {name}: CD {r['cd_tsdf']:.3g} -> {r['cd_post']:.3g}, "
                  f"cov {100 * r['coverage@1sigma']:.0f}/{100 * r['coverage@2sigma']:.0f}/"
                  f"{100 * r['coverage@3sigma']:.0f}, NLL-c {r['nll_vs_constant']:+.2f} "
                  f"({r['seconds']:.0f} s)", file=sys.stderr, flush=True)
    table = markdown(rows)
    print(table)
    print()
    print(summary(rows))
    print(f"({len(rows)} cases in {time.perf_counter() - t0:.0f} s; overrides: "
          f"{' '.join(args.sets) or 'none'})")
    if args.json:
        args.json.write_text(json.dumps({"sets": args.sets, "rows": rows}, indent=1))
    if args.markdown:
        args.markdown.write_text(table + "\n\n" + summary(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
