#!/usr/bin/env python
"""Run shipped scenes end to end and print the README results table (markdown): one row for the
TSDF bootstrap mesh and one for the posterior mesh of each scene, with the seconds of that stage.

Every number in the README's results table comes from this script::

    python tools/results_table.py              # default, seed_sphere, bunny, bunny_far
    python tools/results_table.py scenes/bunny.toml --json results.json

Scenes whose data is missing are reported as skipped, not as failures.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENES = ["scenes/default.toml", "scenes/seed_sphere.toml", "scenes/bunny.toml",
                  "scenes/bunny_far.toml"]
COLUMNS = ["chamfer_l2", "accuracy_m", "completeness_m"]


def _rows(scene: str, report: dict) -> list[dict]:
    """One row per mesh the run wrote (tsdf_mesh.ply, and mesh.ply for the full stage)."""
    c, s = report["counts"], report["seconds"]
    base = {"scene": Path(scene).stem, "frames": c["frames"],
            "voxel_m": report["tsdf"]["voxel_size_m"], "total_s": s["total"]}
    rows = [{**base, "mesh": "tsdf_mesh.ply", "seconds": s["tsdf"],
             "metrics": report["metrics"].get("tsdf_mesh.ply", {})}]
    if "mesh.ply" in report["metrics"] or report.get("solver"):
        rows.append({**base, "mesh": "mesh.ply", "seconds": s.get("posterior", float("nan")),
                     "metrics": report["metrics"].get("mesh.ply", {})})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=DEFAULT_SCENES, help="scene files")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override for all scenes")
    ap.add_argument("--json", help="also write the rows as JSON to this file")
    args = ap.parse_args(argv)

    import bftaichi as bf

    rows = []
    with tempfile.TemporaryDirectory(prefix="bftaichi-results-") as tmp:
        for scene in args.scenes:
            path = Path(scene) if Path(scene).exists() else ROOT / scene
            try:
                cfg = bf.load_config(path, args.sets)
                report = bf.run(cfg, Path(tmp) / path.stem, overwrite=True, progress=False)
            except bf.DataError as e:
                print(f"skipped {scene}: {e}", file=sys.stderr)
                continue
            rows.extend(_rows(scene, report))

    thresholds = sorted({k.split("@")[1] for r in rows for k in r["metrics"] if "@" in k},
                        key=lambda t: float(t[:-2]))
    head = ["scene", "frames", "voxel", "mesh", "stage s", "CD (m^2)", "Acc (mm)", "Comp (mm)"]
    head += [f"F@{t}" for t in thresholds]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        m = r["metrics"]
        cells = [r["scene"], str(r["frames"]), f"{r['voxel_m'] * 1000:g} mm", r["mesh"],
                 f"{r['seconds']:.2f}"]
        if m:
            cells += [f"{m['chamfer_l2']:.3g}", f"{m['accuracy_m'] * 1000:.2f}",
                      f"{m['completeness_m'] * 1000:.2f}"]
            cells += [f"{m[f'fscore@{t}']:.3f}" if f"fscore@{t}" in m else "-" for t in thresholds]
        else:
            cells += ["-"] * (3 + len(thresholds))
        print("| " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
