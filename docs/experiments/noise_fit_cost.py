"""The noise fit's seconds with and without the frames' sharing in time
(``observation.in_time_order``), alternating, on the 250 even redkitchen frames (what
``tools/evalviews_table.py`` fuses)::

    python docs/experiments/noise_fit_cost.py            # 2 cm
    python docs/experiments/noise_fit_cost.py --voxel 0.01
"""
import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    import bftaichi as bf
    from bftaichi.frame import local_frames
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import estimate_extra_noise

    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={args.voxel}",
                                f"tsdf.trunc_m={2 * args.voxel}"])
    recon = bf.Reconstructor(cfg)
    for f in bf.open_dataset(DATA, frames=slice(0, 500, 2)):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)
    seconds = {True: [], False: []}
    for _ in range(args.rounds + 1):  # the first round compiles
        for order in (False, True):
            obs = replace(cfg.observation, in_time_order=order)
            t = time.perf_counter()
            fit = estimate_extra_noise(frames, band, obs, args.voxel,
                                       cfg.tsdf.bootstrap_trunc_m,
                                       (cfg.scene.depth_min_m, cfg.scene.depth_max_m))
            seconds[order].append(time.perf_counter() - t)
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in fit.items()})
    for order, s in seconds.items():
        print(f"in_time_order={order}: median {np.median(s[1:]):.2f} s over {args.rounds}")


if __name__ == "__main__":
    main()
