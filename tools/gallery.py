#!/usr/bin/env python
"""Regenerate the README gallery: run a scene with next-best-view ranking, then copy its
diagnostic plots (``plots/*.png``, :mod:`bftaichi.running.plots`) into ``docs/`` as
``docs/<scene>_<plot>.png`` and screenshot its ``preview.html`` in headless Chromium
(:func:`bftaichi.running.viz.screenshot`, the browser test's tooling) as ``docs/<scene>_preview.png``.

    python tools/gallery.py                               # scenes/bunny.toml
    python tools/gallery.py scenes/default.toml --set eval.n_samples=50000
    python tools/gallery.py --out runs/bunny --overwrite   # keep the run folder
    python tools/gallery.py --no-screenshot                # plots only (no Chromium needed)

Prints the size of preview.html and the seconds the run spent writing it. The scene needs a
ground truth for the precision / recall, F-score and calibration plots (every synthetic scene
has one).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from contextlib import nullcontext
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(ROOT / "scenes" / "bunny.toml"))
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override (repeatable)")
    ap.add_argument("--out", help="run folder to keep (default: a temporary folder)")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    ap.add_argument("--docs", default=str(ROOT / "docs"), help="where the PNGs are copied")
    ap.add_argument("--no-screenshot", action="store_true", help="skip the preview screenshot")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.io import ensure_out_dir
    from bftaichi.running.viz import screenshot

    cfg = bf.load_config(args.scene, ["nbv.enabled=true", *args.sets, "run.plots=true",
                                      "run.preview=true"])
    with (nullcontext(args.out) if args.out else
          tempfile.TemporaryDirectory(prefix="bftaichi-gallery-")) as out:
        out = Path(out)
        report = bf.run(cfg, out, overwrite=args.overwrite, progress=False)
        docs = ensure_out_dir(args.docs)
        name = report["scene"]
        for p in sorted((out / "plots").glob("*.png")):
            dest = docs / f"{name}_{p.name}"
            shutil.copyfile(p, dest)
            print(f"wrote {dest}")
        page = out / "preview.html"
        if not args.no_screenshot:
            dest = screenshot(page.as_uri(), docs / f"{name}_preview.png", size=(1000, 700))
            print(f"wrote {dest}")
        s = report["seconds"]
        print(f"{name}: run {s['total']:.1f} s (plots {s['plots']:.1f} s); preview.html "
              f"{page.stat().st_size / 1e6:.2f} MB written in {s['preview']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
