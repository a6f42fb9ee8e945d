#!/usr/bin/env python
"""The same scene near the origin and moved by (500 km, 5,000 km, 100 m): how far apart are the
outputs once the offset is subtracted? (issue 17, "a map that works anywhere on Earth")

    python tools/translated_scene.py                  # the tiny tabletop, 8 views, 2.5 cm voxels
    python tools/translated_scene.py --views 24 --voxel 0.01

Renders the synthetic tabletop with ``bftaichi synth``, writes a copy whose poses and
ground-truth mesh are moved by the offset (tests/test_coordinates.py ``translated_copy``), fuses
both with ``bftaichi fuse`` and prints, per mesh, the vertex and face counts, the largest vertex
difference after subtracting the offset, the largest ``sigma`` difference, and the largest
difference of every metric against ground truth. tests/test_coordinates.py asserts the same
on the default settings.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

OFFSET = np.array([500_000.0, 5_000_000.0, 100.0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--voxel", type=float, default=0.025)
    args = ap.parse_args(argv)

    from bftaichi.cli import main as cli
    from bftaichi.io import read_mesh_ply
    from robustness_cases import sets
    from test_coordinates import translated_copy

    fuse = ["--voxel", str(args.voxel), "-q", "--set", "run.plots=false", "--set",
            "run.preview=false", "--set", "eval.n_samples=20000"]
    with tempfile.TemporaryDirectory(prefix="bftaichi-translated-") as tmp:
        tmp = Path(tmp)
        near = tmp / "near"
        assert cli(["synth", "--out", str(near), "-q",
                    *sets(f"synthetic.n_views={args.views}")]) == 0
        far = translated_copy(near, tmp / "far", OFFSET)
        out = {}
        for name, data in (("near", near), ("far", far)):
            out[name] = tmp / f"out-{name}"
            if cli(["fuse", str(data), "--out", str(out[name]), *fuse]) != 0:
                print(f"fuse of the {name} scene failed")
                return 1
        report = {k: json.loads((v / "report.json").read_text()) for k, v in out.items()}
        print(f"offset {OFFSET.tolist()} m; far origin_m {report['far']['origin_m']}; "
              f"{args.views} views, voxel {args.voxel} m")
        print("| mesh | vertices near / far | faces equal | max vertex diff (m) | "
              "max sigma diff (m) | max metric diff (relative) |")
        print("|---|---|---|---|---|---|")
        for mesh in ("tsdf_mesh.ply", "mesh.ply"):
            vn, fn, an = read_mesh_ply(out["near"] / mesh)
            vf, ff, af = read_mesh_ply(out["far"] / mesh)
            same = len(vn) == len(vf)
            dv = float(np.abs((vf - OFFSET) - vn).max()) if same else float("nan")
            ds = (float(np.abs(af["sigma"] - an["sigma"]).max())
                  if same and "sigma" in an else float("nan"))
            mn, mf = report["near"]["metrics"][mesh], report["far"]["metrics"][mesh]
            rel = max(abs(mf[k] - v) / max(abs(v), 1e-12) for k, v in mn.items())
            print(f"| {mesh} | {len(vn)} / {len(vf)} | "
                  f"{same and np.array_equal(fn, ff)} | {dv:.2e} | {ds:.2e} | {rel:.2e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
