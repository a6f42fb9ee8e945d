"""The mesh's own bending as a vertex variance term (issue 15; measured offline, not built:
docs/measurements.md, "The mesh's bending as a vertex variance term").

Reads the runs a suite kept (``python tools/suite.py --keep DIR``, and ``--heldout --keep
DIR2``), judges every vertex of each run's ``mesh.ply`` against the true mesh of its
``config.toml`` (the suite's exact point-to-triangle error, ``vertex_errors``), and scores
vertex sigmas built from the run's own ``sigma`` and its mesh, without solving again::

    sigma'^2 = (k sigma)^2 + (c h max(angle - a0, 0))^2

``angle`` the mean angle (radians) between a vertex's normal and its neighbours' (what
``tools/sigma_breakdown.py`` calls the normal angle: a crease, a crumpled patch), ``h`` the
voxel. ``k = 1, c = 0`` is today's sigma. Printed per variant and set of runs: how many
cases meet issue 15's coverage bands at 1 / 2 / 3 sigma and the NLL target, and the mean NLL
minus the best constant's (the suite's own definitions, ``tools/suite.py`` ``targets``)::

    python tools/suite.py --keep runs/dev && python tools/suite.py --heldout --keep runs/ho
    python docs/experiments/crease_variance.py runs/dev runs/ho
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def vertices(run: Path) -> dict:
    """error, sigma, normal angle and voxel of every vertex of one kept suite run."""
    import trimesh
    from sigma_breakdown import normal_angle

    import bftaichi as bf
    from bftaichi.evaluation.metrics import vertex_errors
    from bftaichi.formats.synthetic import SyntheticDataset
    from bftaichi.io import read_mesh_ply

    cfg = bf.load_config(str(run / "config.toml"), [])
    gt = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m).gt_mesh
    xyz, faces, extra = read_mesh_ply(run / "mesh.ply")
    xyz = np.asarray(xyz, np.float64)
    return {"err": vertex_errors(xyz, gt), "sigma": np.asarray(extra["sigma"], np.float64),
            "angle": normal_angle(trimesh.Trimesh(xyz, faces, process=False)),
            "h": cfg.tsdf.voxel_size_m}


def scores(err: np.ndarray, sigma: np.ndarray) -> tuple:
    """coverage at 1, 2, 3 sigma and the NLL minus the best constant's."""
    from bftaichi.evaluation.metrics import uncertainty_metrics

    m = uncertainty_metrics(err, sigma, np.zeros_like(err))
    return (*(m[f"coverage@{k}sigma"] for k in (1, 2, 3)), m["nll_vs_constant"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="folders of kept suite runs")
    args = ap.parse_args()
    sets = []
    for folder in args.runs:
        runs = sorted(p.parent for p in folder.glob("*/mesh.ply"))
        if not runs:
            ap.error(f"{folder}: no kept runs (*/mesh.ply)")
        sets.append((folder.name, [vertices(r) for r in runs]))
    variants = [(1.0, 0.0, 0.0)]
    variants += [(1.0, a0, c) for a0 in (0.0, 0.3, 0.5) for c in (0.3, 0.6, 1.0)]
    variants += [(k, a0, c) for k in (0.8, 0.9) for a0 in (0.3,) for c in (0.0, 0.3, 0.6)]
    print("| k | a0 (rad) | c | " + " | ".join(
        f"{name}: cov1 / cov2 / cov3 / NLL of {len(runs)}, mean NLL - const"
        for name, runs in sets) + " |")
    print("|---|---|---|" + "---|" * len(sets))
    for k, a0, c in variants:
        cells = []
        for _, runs in sets:
            rows = [scores(r["err"], np.hypot(k * r["sigma"],
                                              c * r["h"] * np.maximum(r["angle"] - a0, 0.0)))
                    for r in runs]
            met = [sum(0.60 <= x[0] <= 0.76 for x in rows), sum(0.90 <= x[1] <= 0.98 for x in rows),
                   sum(x[2] >= 0.98 for x in rows), sum(x[3] < 0 for x in rows)]
            cells.append(" / ".join(map(str, met)) + f", {np.mean([x[3] for x in rows]):+.3f}")
        print(f"| {k:g} | {a0:g} | {c:g} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
