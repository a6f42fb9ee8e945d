#!/usr/bin/env python
"""Is sigma honest? Coverage of the posterior against an analytic ground truth (DESIGN.md 6).

Runs a noisy sphere scene (Kinect noise; the true SDF is ``|x| - r``), then for band voxels
near the surface (``|phi_true| <= --near`` voxels) computes the error ``e = mean - phi_true`` and

- coverage of ``|e| <= k sigma`` for k = 1, 2, 3 (ideal 68.3 / 95.4 / 99.7 %),
- the Spearman rank correlation between sigma and |e|,
- the median of |e| / sigma.

    python tools/calibration.py
    python tools/calibration.py --set observation.sigma_model_m=0.002 --near 1
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

SPHERE = ["synthetic.mesh=sphere", "synthetic.radius_m=0.3", "synthetic.trajectory=hemisphere",
          "synthetic.n_views=20", "synthetic.cam_radius_m=1.0", "synthetic.min_elevation_deg=-30",
          "synthetic.noise=kinect", "tsdf.voxel_size_m=0.01", "tsdf.trunc_m=0.02",
          "eval.n_samples=20000"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override")
    ap.add_argument("--near", type=float, default=1.0,
                    help="voxels with |true SDF| <= near voxels are evaluated (default 1)")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from scipy.stats import spearmanr

    cfg = bf.load_config(None, SPHERE + args.sets)
    r = cfg.synthetic.radius_m
    with tempfile.TemporaryDirectory(prefix="bftaichi-calib-") as tmp:
        report = bf.run(cfg, Path(tmp), progress=False)
        band = dict(np.load(Path(tmp) / "band.npz"))
    vs = float(band["voxel_size"])
    centres = (band["ijk"] + 0.5) * vs
    phi = np.linalg.norm(centres, axis=1) - r
    near = (np.abs(phi) <= args.near * vs) & (band["weight"] > 0)
    e = band["mean"][near] - phi[near]
    sigma = np.sqrt(np.maximum(band["var"][near], 0))
    ratio = np.abs(e) / sigma
    cover = [float(np.mean(ratio <= k)) for k in (1, 2, 3)]
    rho = spearmanr(sigma, np.abs(e)).statistic
    m = report["metrics"]
    print(f"noisy sphere r = {r} m, {cfg.synthetic.n_views} views, voxel {vs} m: "
          f"{near.sum()} band voxels within {args.near:g} voxel of the surface")
    print(f"RMS error: posterior {np.sqrt(np.mean(e ** 2)) * 1000:.2f} mm; median sigma "
          f"{np.median(sigma) * 1000:.2f} mm; median |e|/sigma {np.median(ratio):.2f}")
    print(f"coverage |e| <= 1/2/3 sigma: {cover[0] * 100:.1f} / {cover[1] * 100:.1f} / "
          f"{cover[2] * 100:.1f} %   (ideal 68.3 / 95.4 / 99.7 %)")
    print(f"Spearman(sigma, |e|) = {rho:.3f}")
    print(f"CD tsdf_mesh {m['tsdf_mesh.ply']['chamfer_l2']:.3g}  mesh {m['mesh.ply']['chamfer_l2']:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
