#!/usr/bin/env python
"""Closed-loop active scanning on the bunny and the tabletop: every policy, 48 candidates,
12 steps (``bftaichi scan`` for each scene), printed as one Markdown table.

    python tools/scan_table.py                                  # both scenes, out/scan-*/
    python tools/scan_table.py scenes/bunny.toml --steps 4      # one scene, fewer steps
    python tools/scan_table.py --markdown scan.md --set nbv.random_seeds=5

Columns, each the mean ± std over the runs (``nbv.initial_seeds`` draws of the initial views;
for ``random`` also ``nbv.random_seeds`` seeds): the area under recall@5mm against views
(trapezoid, divided by the views spanned, so it is the mean recall over the scan), the views
needed to reach 95 % recall@5mm (mean over the runs that reached it, with the fraction that
did), the final recall at 5 and 2 mm, the area under F@10mm and the final completeness; then
the seconds per step (the solve and the choice of the next view). The scan.json and scan.png of each scene are
kept in ``--out``/scan-<scene>/.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
SCENES = [ROOT / "scenes" / "bunny.toml", ROOT / "scenes" / "default.toml"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=[str(s) for s in SCENES])
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--candidates", type=int, default=48)
    ap.add_argument("--policies", default="bayes,coverage,frontier,entropy,farthest,random")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override (repeatable)")
    ap.add_argument("--out", default=str(ROOT / "out"), help="parent of the scan folders")
    ap.add_argument("--markdown", help="also write the table to this file")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.planning.scan import scan

    lines = ["| scene | policy | runs | AUC recall@5mm | views to 95 % recall@5mm (reached) | "
             "final recall@5mm | final recall@2mm | AUC F@10mm | final completeness (mm) | "
             "s/step (solve + choose) |", "|---|---|---|---|---|---|---|---|---|---|"]

    def pm(s, key, fmt=".4f"):
        v, sd = s[key], s["std"][key]
        return "-" if v is None else f"{v:{fmt}} ± {sd:{fmt}}"
    for path in args.scenes:
        cfg = bf.load_config(path, [*args.sets, f"nbv.steps={args.steps}",
                                    f"nbv.n_candidates={args.candidates}"])
        out = Path(args.out) / f"scan-{cfg.scene.name}"
        report = scan(cfg, out, tuple(args.policies.split(",")), overwrite=True)
        for policy, res in report["policies"].items():
            s = res["summary"]
            steps = [st for run in res["runs"] for st in run["steps"][:-1]]
            per_step = sum(st["seconds_fuse"] + st["seconds_choose"] for st in steps) / len(steps)
            reached = s["reached"]["views_to_recall5_0.95"]
            lines.append(f"| {report['scene']} | {policy} | {s['n_runs']} | "
                         f"{pm(s, 'auc_recall5')} | {pm(s, 'views_to_recall5_0.95', '.1f')} "
                         f"({reached:.0%}) | {pm(s, 'final_recall5', '.3f')} | "
                         f"{pm(s, 'final_recall2', '.3f')} | {pm(s, 'auc_f10')} | "
                         f"{pm(s, 'final_completeness_mm', '.2f')} | {per_step:.2f} |")
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
