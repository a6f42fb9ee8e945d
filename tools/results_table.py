#!/usr/bin/env python
"""Run shipped scenes end to end and print the README results table (markdown).

Every number in the README's results table comes from this script::

    python tools/results_table.py                       # default, seed_sphere, bunny
    python tools/results_table.py scenes/bunny.toml --json results.json

Scenes whose data is missing are reported as skipped, not as failures.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENES = ["scenes/default.toml", "scenes/seed_sphere.toml", "scenes/bunny.toml"]
COLUMNS = ["chamfer_l2", "accuracy_m", "completeness_m"]


def _row(scene: str, report: dict) -> dict:
    m = report["metrics"].get("tsdf_mesh.ply", {})
    c, s = report["counts"], report["seconds"]
    return {"scene": Path(scene).stem, "frames": c["frames"],
            "voxel_m": report["tsdf"]["voxel_size_m"], "voxels": c["observed_voxels"],
            "tsdf_s": s["tsdf"], "total_s": s["total"],
            "fps": c["frames"] / s["tsdf"] if s["tsdf"] else float("nan"), "metrics": m}


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
            rows.append(_row(scene, report))

    thresholds = sorted({k.split("@")[1] for r in rows for k in r["metrics"] if "@" in k},
                        key=lambda t: float(t[:-2]))
    head = ["scene", "frames", "voxel", "TSDF frames/s", "CD (m^2)", "Acc (mm)", "Comp (mm)"]
    head += [f"F@{t}" for t in thresholds]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        m = r["metrics"]
        cells = [r["scene"], str(r["frames"]), f"{r['voxel_m'] * 1000:g} mm", f"{r['fps']:.0f}"]
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
