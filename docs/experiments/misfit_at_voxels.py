"""The local-noise excess ``b^2`` against the mean's actual error at the band voxels near the
surface (issue 15; docs/measurements.md, "The misfit at the surface: the residuals' line taken
out").

For suite cases (``tools/suite.py``'s meshes and capture conditions), the posterior is solved
in-process with ``local_misfit`` watched (``tools/sigma_breakdown.py``: the variance before the
local noise, ``var0``, and ``b^2``); at the voxels within a voxel of the mean's surface the mean's error is the exact
signed distance of the voxel centre to the true mesh (libigl) minus the mean. Printed: the
coverage of that error by ``sqrt(var0)`` and by the final sigma, then, by bins of ``b^2 /
var0``, the mean squared error over ``var0`` against the mean ``b^2 / var0``::

    python docs/experiments/misfit_at_voxels.py stanford-bunny/grazing homer/dropout beetle/dense_near
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def run(mesh: str, condition: str, data: Path) -> None:
    import igl
    import suite
    from sigma_breakdown import solve_seeing_misfit

    import bftaichi as bf
    from bftaichi.geometry import mesh_in_local

    cfg = bf.load_config(None, suite.case_sets(mesh, condition, data))
    frames, post, seen = solve_seeing_misfit(cfg)
    h = cfg.tsdf.voxel_size_m
    gt = mesh_in_local(frames.gt_mesh, post.origin)
    near = np.abs(post.mean) < h
    centres = (post.ijk[near].astype(np.float64) + 0.5) * h
    sd = igl.signed_distance(centres, np.asarray(gt.vertices, np.float64),
                             np.asarray(gt.faces, np.int64))[0]
    e2 = (post.mean[near] - sd) ** 2
    v0, b2 = seen["var0"][near], seen["b2"][near].astype(np.float64)
    vf = post.var[near].astype(np.float64)
    print(f"{mesh}/{condition}: {int(near.sum())} voxels within a voxel of the mean's surface")
    print(f"  mean error^2 {e2.mean() * 1e6:.4f} mm^2; mean var0 {v0.mean() * 1e6:.4f}, "
          f"b^2 {b2.mean() * 1e6:.4f}, final variance {vf.mean() * 1e6:.4f}")
    print("  within 1 / 2 / 3 sqrt(var0): "
          + " / ".join(f"{100 * np.mean(e2 <= k * k * v0):.0f}" for k in (1, 2, 3))
          + " %; within 1 / 2 / 3 final sigma: "
          + " / ".join(f"{100 * np.mean(e2 <= k * k * vf):.0f}" for k in (1, 2, 3)) + " %")
    ratio = b2 / v0
    edges = np.quantile(ratio, [0, 0.5, 0.75, 0.9, 0.97, 1.0])
    print("  b^2 / var0 in [lo, hi): voxels | mean error^2 / var0 | mean b^2 / var0 | within"
          " 1 final sigma | within 1 sqrt(var0)")
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (ratio >= lo) & ((ratio < hi) if k < len(edges) - 2 else (ratio <= hi))
        if sel.sum() >= 10:
            print(f"    [{lo:6.2f}, {hi:6.2f}): {int(sel.sum()):6d} | {np.mean(e2[sel] / v0[sel]):6.2f}"
                  f" | {np.mean(ratio[sel]):6.2f} | {100 * np.mean(e2[sel] <= vf[sel]):3.0f} %"
                  f" | {100 * np.mean(e2[sel] <= v0[sel]):3.0f} %")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("cases", nargs="+", help="mesh/condition, e.g. stanford-bunny/grazing")
    ap.add_argument("--data", type=Path, default=None, help="shared data folder (default: tools/suite.py's)")
    args = ap.parse_args()
    import suite

    for case in args.cases:
        mesh, condition = case.split("/")
        run(mesh, condition, args.data or suite.DEFAULT_DATA)
    return 0


if __name__ == "__main__":
    sys.exit(main())
