"""Run time of the band's build and of the prior's assembly after their first call (issue 16;
docs/measurements.md, "Start-up: the band, stencil and layout kernels loop over their offsets
at run time"): every 5th of the first 500 redkitchen frames fused at ``--voxel``, then
``build_band`` and ``add_prior`` called four times each; the first call includes loading (or
compiling) the kernels, the others are their run time::

    python docs/experiments/band_prior_timing.py               # 2 cm
    python docs/experiments/band_prior_timing.py --voxel 0.01
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA))
    ap.add_argument("--voxel", type=float, default=0.02)
    args = ap.parse_args()

    import bftaichi as bf
    from bftaichi.stages.band import build_band
    from bftaichi.stages.prior import add_prior

    vox = args.voxel
    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={vox}", f"tsdf.trunc_m={2 * vox}"])
    recon = bf.Reconstructor(cfg)
    for f in bf.open_dataset(args.data, frames=slice(0, 500, 5)):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    voxels = recon.voxels
    times = []
    for _ in range(4):
        t0 = time.perf_counter()
        band, _ = build_band(voxels, cfg.tsdf.bootstrap_trunc_m)
        times.append(time.perf_counter() - t0)
    print(f"band of {len(band):,} voxels; build_band s: " + ", ".join(f"{t:.3f}" for t in times))
    S = np.zeros((len(band), 27), np.float32)
    h = np.zeros(len(band), np.float32)
    times = []
    for _ in range(4):
        t0 = time.perf_counter()
        add_prior(S.copy(), h.copy(), band, cfg.prior, cfg.band.stencil, vox)
        times.append(time.perf_counter() - t0)
    print("add_prior s: " + ", ".join(f"{t:.3f}" for t in times))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
