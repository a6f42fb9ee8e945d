#!/usr/bin/env python
"""Closed-loop active scanning on the bunny and the tabletop: every policy, 48 candidates,
12 steps (``bftaichi scan`` for each scene), printed as one Markdown table.

    python tools/scan_table.py                                  # both scenes, out/scan-*/
    python tools/scan_table.py scenes/bunny.toml --steps 4      # one scene, fewer steps
    python tools/scan_table.py --markdown scan.md --set nbv.random_seeds=5

Columns: the area under F@10mm against views (trapezoid, divided by the views spanned, so it
is the mean F@10mm over the scan), the views needed to reach F@10mm >= 0.9 ("-" if never), and
the final F@10mm and completeness. ``random`` is the mean curve over ``nbv.random_seeds``
seeds. The scan.json and scan.png of each scene are kept in ``--out``/scan-<scene>/.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = [ROOT / "scenes" / "bunny.toml", ROOT / "scenes" / "default.toml"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=[str(s) for s in SCENES])
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--candidates", type=int, default=48)
    ap.add_argument("--policies", default="bayes,coverage,farthest,random")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override (repeatable)")
    ap.add_argument("--out", default=str(ROOT / "out"), help="parent of the scan folders")
    ap.add_argument("--markdown", help="also write the table to this file")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.planning.scan import scan

    lines = ["| scene | policy | AUC F@10mm | views to F@10mm >= 0.9 | final F@10mm | "
             "final completeness (mm) | seconds |", "|---|---|---|---|---|---|---|"]
    for path in args.scenes:
        cfg = bf.load_config(path, [*args.sets, f"nbv.steps={args.steps}",
                                    f"nbv.n_candidates={args.candidates}"])
        out = Path(args.out) / f"scan-{cfg.scene.name}"
        report = scan(cfg, out, tuple(args.policies.split(",")), overwrite=True)
        for policy, res in report["policies"].items():
            s = res["summary"]
            secs = sum(st.get("seconds_fuse", 0) + st.get("seconds_choose", 0)
                       for run in res["runs"] for st in run["steps"])
            name = policy if len(res["runs"]) == 1 else f"{policy} (mean of {len(res['runs'])})"
            lines.append(f"| {report['scene']} | {name} | {s['auc_f10']:.4f} | "
                         f"{s['views_to_f10_0.9'] or '-'} | {s['final_f10']:.3f} | "
                         f"{s['final_completeness_mm']:.2f} | {secs:.0f} |")
        print(f"{report['scene']}: initial views {report['initial_views']}, "
              f"{report['candidates']} candidates at {report['radius_m']} m; {out}/scan.png",
              file=sys.stderr)
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
