#!/usr/bin/env python
"""Where the observation model's error lies: the residuals of the posterior's samples, by their
distance from their own pixel's measured surface (issue 15; docs/measurements.md).

One case of the development suite (``tools/suite.py``) is solved without the noise fit and the
local noise (the plain posterior). Every ``--every``-th frame is observed again
(:meth:`kernels.observe.Observer.frame_rows`: the samples, their observed SDF ``y`` and their
trilinear cells), and each accepted sample is compared with

- the exact signed distance of its position to the true mesh (libigl): ``y - true`` is the
  error of the data, sensor noise plus the model error of the projective distance;
- the posterior mean interpolated at it: ``y - mean`` is what the local-noise misfit sees;
- ``mean - true``: the posterior's own error there.

Rows bin the samples by ``(z - D) / voxel``, their distance along the ray from the pixel's
depth ``D``. Columns: RMS and robust (1.4826 MAD) values in mm, and the sensor model's axial
sigma ``sigma_z(D)``::

    python tools/residual_profile.py cheburashka/dropout
    python tools/residual_profile.py homer/few_views --every 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

BINS = ((-5.0, -3.0), (-3.0, -1.5), (-1.5, -0.5), (-0.5, 0.5), (0.5, 1.5), (1.5, 3.0), (3.0, 5.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("case", help="mesh/condition of tools/suite.py, e.g. cheburashka/dropout")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--every", type=int, default=3, help="observe every n-th frame (default 3)")
    args = ap.parse_args(argv)

    import igl

    import bftaichi as bf
    import suite
    from bftaichi.formats.synthetic import SyntheticDataset
    from bftaichi.reconstructor import Reconstructor
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import make_observer

    mesh, condition = args.case.split("/")
    cfg = bf.load_config(None, [*suite.case_sets(mesh, condition, args.data),
                                "observation.local_noise=false", "observation.fit_noise=false"])
    frames = list(open_frames(cfg))
    recon = Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    post = recon.solve(variance=False)
    gt = SyntheticDataset(cfg.synthetic).gt_mesh
    V, F = np.asarray(gt.vertices, np.float64), np.asarray(gt.faces, np.int64)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    h = cfg.tsdf.voxel_size_m
    observer = make_observer(band, cfg.observation, h, cfg.tsdf.trunc_m)
    mean, ijk = post.mean.astype(np.float64), band.ijk.astype(np.float64)
    cols = []
    for f in frames[::args.every]:
        rows = observer.frame_rows(f.depth_m, f.K, f.T_W_C)
        idx, a = rows["idx"], rows["a"]
        pos = ((a[:, :, None] * ijk[idx]).sum(1) + 0.5) * h + recon.origin  # voxel centres
        true = igl.signed_distance(pos, V, F)[0]
        W = f.depth_m.shape[1]
        D = np.asarray(f.depth_m, np.float64)[rows["pixel"] // W, rows["pixel"] % W]
        cols.append(np.stack([rows["y"], (a * mean[idx]).sum(1), true, D, rows["z"] - D], 1))
    y, pred, true, D, along = np.concatenate(cols).T
    sigma_z = cfg.observation.axial_sigma_m(D)

    def rms(x):
        return 1e3 * float(np.sqrt(np.mean(x * x)))

    def robust(x):
        return 1e3 * 1.4826 * float(np.median(np.abs(x)))

    print(f"{args.case}: {len(y)} samples of {len(frames[::args.every])} frames, voxel "
          f"{1e3 * h:g} mm (mm; RMS / robust)")
    print("| (z - D) / voxel | samples | y - true | y - mean | mean - true | sigma_z |")
    print("|---|---|---|---|---|---|")
    for lo, hi in BINS:
        sel = (along / h >= lo) & (along / h < hi)
        if sel.any():
            print(f"| [{lo:g}, {hi:g}) | {int(sel.sum())} | {rms(y[sel] - true[sel]):.2f} / "
                  f"{robust(y[sel] - true[sel]):.2f} | {rms(y[sel] - pred[sel]):.2f} / "
                  f"{robust(y[sel] - pred[sel]):.2f} | {rms(pred[sel] - true[sel]):.2f} / "
                  f"{robust(pred[sel] - true[sel]):.2f} | {rms(sigma_z[sel]):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
