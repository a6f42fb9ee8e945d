#!/usr/bin/env python
"""Held-out-view evaluation on real frames (``bftaichi evalviews``) at several voxel sizes, one
Markdown table: bftaichi's posterior, its TSDF bootstrap and (when installed) Open3D's
VoxelBlockGrid, fused from every other frame and judged on the frames in between.

    python tools/evalviews_table.py                                  # redkitchen, 2 cm and 1 cm
    python tools/evalviews_table.py --voxels 0.04 --frames 0:100     # a quick look
    python tools/evalviews_table.py --set prior.free=100 --markdown ev.md
    python tools/evalviews_table.py --block 100    # held out in blocks of 100 frames

``--block 100`` fuses frames 0-99, 200-299, ... and judges 100-199, 300-399, ...: a recorded
trajectory's pose errors drift, so a frame between two fused ones shares theirs and flatters
sigma; a block judges the map away in time from the frames it was fused from.

Columns: median and mean absolute depth error on the pixels where both the method and the
measurement have a depth, the fraction within 1 / 2 / 5 cm, completeness (predicted share of
the valid measured pixels), the median and mean again on the pixels every method predicts
(a method that predicts more pixels, the hard ones included, is not judged on more), and for
bftaichi the coverage of its depth sigma (``|r| <= k
sqrt(sigma_z^2 + sigma_D^2)``, k = 1, 2, 3; bftaichi/evaluation/evalviews.py says exactly what is
computed) and the mean Gaussian NLL of the residuals under that sigma minus the NLL under the
best constant sigma (below 0: the per-pixel sigma is informative).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA))
    ap.add_argument("--voxels", default="0.02,0.01", help="comma-separated voxel sizes, metres")
    ap.add_argument("--frames", default="", help="slice of frames, e.g. 0:100")
    ap.add_argument("--held-out-stride", type=int, default=1)
    ap.add_argument("--block", type=int, default=1,
                    help="fuse every other block of this many frames, hold out the others "
                         "(1: every other frame)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override (repeatable)")
    ap.add_argument("--out", default=str(ROOT / "out"), help="parent of the run folders")
    ap.add_argument("--markdown", help="also write the table to this file")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.evaluation.evalviews import evaluate_views

    lines = ["| voxel | method | median abs (mm) | mean abs (mm) | within 1 / 2 / 5 cm | "
             "completeness | on the pixels all predict: median / mean (mm) | "
             "sigma coverage 1 / 2 / 3 (%) | NLL - const |",
             "|---|---|---|---|---|---|---|---|---|"]
    for voxel in (float(v) for v in args.voxels.split(",")):
        sets = ["scene.source=dataset", f"scene.data={args.data!r}".replace("'", '"'),
                f"tsdf.voxel_size_m={voxel}", f"tsdf.trunc_m={2 * voxel}",
                "scene.name=\"evalviews\""]
        if args.frames:
            sets.append(f'scene.frames="{args.frames}"')
        cfg = bf.load_config(None, sets + args.sets)
        out = Path(args.out) / f"evalviews-{voxel * 100:g}cm"
        r = evaluate_views(cfg, out, held_out_stride=args.held_out_stride, block=args.block,
                           open3d=not args.no_open3d, overwrite=True, progress=False)
        cov = " / ".join(f"{100 * c:.1f}" for c in r["calibration"]["coverage_normalised"])
        nll = f"{r['calibration']['nll_vs_constant']:+.2f}"
        for m, s in r["methods"].items():
            if not s["pixels"]:
                continue
            c = r["methods_common_pixels"][m]
            both = (f"{1000 * c['median_abs_m']:.2f} / {1000 * c['mean_abs_m']:.1f}"
                    if c["pixels"] else "-")
            lines.append(f"| {voxel * 100:g} cm | {m} | {1000 * s['median_abs_m']:.2f} | "
                         f"{1000 * s['mean_abs_m']:.1f} | {s['within_1cm']:.3f} / "
                         f"{s['within_2cm']:.3f} / {s['within_5cm']:.3f} | "
                         f"{s['completeness']:.4f} | {both} | "
                         f"{cov if m == 'bftaichi' else '-'} | {nll if m == 'bftaichi' else '-'} |")
        print(f"{voxel * 100:g} cm: {r['fused']} fused, {r['held_out_evaluated']} held out, "
              f"{r['seconds']}; {r['open3d']}", file=sys.stderr)
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
