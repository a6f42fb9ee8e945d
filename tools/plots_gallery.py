#!/usr/bin/env python
"""Regenerate the README's plot gallery: run a scene, draw its diagnostic plots
(:func:`bftaichi.plots.write_run_plots`) and copy them into ``docs/`` as
``docs/<scene>_<plot>.png`` (e.g. ``docs/bunny_precision_recall.png``).

    python tools/plots_gallery.py                              # scenes/bunny.toml
    python tools/plots_gallery.py scenes/default.toml --set eval.n_samples=50000
    python tools/plots_gallery.py --out runs/bunny --overwrite  # keep the run folder

The scene needs a ground truth for the precision / recall, F-score and calibration plots (every
synthetic scene has one); a scene without one gets the posterior plots only.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(ROOT / "scenes" / "bunny.toml"))
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override (repeatable)")
    ap.add_argument("--out", help="run folder to keep (default: a temporary folder)")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    ap.add_argument("--docs", default=str(ROOT / "docs"), help="where the PNGs are copied")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.io import ensure_out_dir
    from bftaichi.pipeline import load_gt_mesh, open_frames
    from bftaichi.plots import write_run_plots

    cfg = bf.load_config(args.scene, args.sets)
    t0 = time.perf_counter()
    with (nullcontext(args.out) if args.out else
          tempfile.TemporaryDirectory(prefix="bftaichi-gallery-")) as out:
        report = bf.run(cfg, out, overwrite=args.overwrite, progress=False)
        t_run = time.perf_counter() - t0
        gt = load_gt_mesh(cfg, open_frames(cfg))
        paths = write_run_plots(report, out, gt=gt)
        docs = ensure_out_dir(args.docs)
        for p in paths:
            dest = docs / f"{report['scene']}_{p.name}"
            shutil.copyfile(p, dest)
            print(f"wrote {dest}")
    print(f"{report['scene']}: run {t_run:.1f} s, plots {time.perf_counter() - t0 - t_run:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
