"""On which side of the true surface a suite run's meshes lie (issue 15; a diagnosis:
docs/measurements.md, "The tangent plane's bias on curved surfaces").

For each run a suite kept (``python tools/suite.py --keep DIR``), the signed distance of every
vertex of ``mesh.ply`` (the posterior) and ``tsdf_mesh.ply`` (its bootstrap) to the true mesh
of the run's ``config.toml`` (libigl; > 0 outside a closed, outward-facing mesh), over the
vertices within two voxels of it, as the median and mean in voxels::

    python tools/suite.py --keep runs/dev
    python docs/experiments/signed_bias.py runs/dev
    python docs/experiments/signed_bias.py runs/dev --cases homer-dense_near,ogre-dense_near
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, help="a folder of kept suite runs")
    ap.add_argument("--cases", default="", help="comma-separated run folder names (default all)")
    args = ap.parse_args()
    import igl

    import bftaichi as bf
    from bftaichi.formats.synthetic import SyntheticDataset
    from bftaichi.io import read_mesh_ply

    runs = sorted(p.parent for p in args.runs.glob("*/mesh.ply"))
    if args.cases:
        runs = [r for r in runs if r.name in args.cases.split(",")]
    if not runs:
        ap.error(f"{args.runs}: no kept runs (*/mesh.ply) to judge")
    print("| run | posterior: median / mean (voxels) | TSDF: median / mean (voxels) |")
    print("|---|---|---|")
    for run in runs:
        cfg = bf.load_config(str(run / "config.toml"), [])
        gt = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m).gt_mesh
        h = cfg.tsdf.voxel_size_m
        cells = []
        for name in ("mesh.ply", "tsdf_mesh.ply"):
            xyz = np.asarray(read_mesh_ply(run / name)[0], np.float64)
            s = igl.signed_distance(xyz, np.asarray(gt.vertices, np.float64),
                                    np.asarray(gt.faces, np.int64))[0] / h
            near = np.abs(s) < 2
            cells.append(f"{np.median(s[near]):+.3f} / {np.mean(s[near]):+.3f}")
        print(f"| {run.name} | {cells[0]} | {cells[1]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
