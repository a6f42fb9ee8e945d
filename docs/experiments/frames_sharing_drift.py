"""How many frames in a row share one pose error, as the noise fit finds it
(``frames_sharing_noise``, :mod:`bftaichi.stages.sharednoise`), on the tabletop rendered from
48 views on a quarter turn of a spiral and fused at poses shifted along each camera's axis by
7.1 mm rms: drifting smoothly (white noise smoothed by a Gaussian; correlation
``exp(-(g / l)^2)``, ``l`` = 5.7 or 17 frames: ``L`` ~ 10 or 30), jittered independently (``L``
= 1), or not at all (``L`` = 1); per seed (docs/measurements.md, "The frames' shared pose error
in the variance")::

    python docs/experiments/frames_sharing_drift.py                 # 3 seeds
    python docs/experiments/frames_sharing_drift.py --seeds 8 --ring   # on a full ring instead

Before that was built (fe5044a), ``docs/experiments/frames_sharing_estimate.patch`` and the
earlier version of this script measured the first estimator on a full ring with a sine drift.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
import bftaichi as bf  # noqa: E402
from bftaichi.frame import local_frames  # noqa: E402
from bftaichi.running.pipeline import open_frames  # noqa: E402
from bftaichi.stages.band import build_band  # noqa: E402
from bftaichi.stages.observe import estimate_extra_noise  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__)
ap.add_argument("--seeds", type=int, default=3)
ap.add_argument("--ring", action="store_true", help="a full ring of views, not a quarter turn")
args = ap.parse_args()
cfg = bf.load_config(None, [
    "synthetic.width=160", "synthetic.height=120", "synthetic.fx=131.25", "synthetic.fy=131.25",
    "synthetic.cx=79.5", "synthetic.cy=59.5", "synthetic.n_views=48", "tsdf.voxel_size_m=0.02",
    "tsdf.trunc_m=0.04", "run.plots=false",
    *([] if args.ring else ["synthetic.trajectory=spiral", "synthetic.turns=0.25"])])
frames = list(open_frames(cfg))
keys = ("sigma_extra_m", "frames_sharing_noise", "sharing_z", "sharing_length",
        "shared_fraction")
print("| seed | poses | seconds | " + " | ".join(keys) + " |\n|" + "---|" * (3 + len(keys)))
for seed in range(args.seeds):
    rng = np.random.default_rng(seed)
    for kind in ("drift l=5.7", "drift l=17", "jitter", "none"):
        white = rng.normal(0, 1, len(frames))
        if kind.startswith("drift"):  # a Gaussian of sigma s gives exp(-(g / (2 s))^2)
            white = gaussian_filter1d(white, float(kind[8:]) / 2, mode="wrap")
        off = np.zeros(len(frames)) if kind == "none" else white / white.std() * 0.01 / np.sqrt(2)
        recon = bf.Reconstructor(cfg)
        for f, o in zip(frames, off):
            T = np.array(f.T_W_C, np.float64).copy()
            T[:3, 3] += T[:3, 2] * o
            recon.integrate(f.depth_m, f.K, T, name=f.name)
        band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
        t = time.perf_counter()
        fit = estimate_extra_noise(local_frames(recon.frames, recon.origin), band,
                                   cfg.observation, cfg.tsdf.voxel_size_m,
                                   cfg.tsdf.bootstrap_trunc_m, (0.1, 10.0))
        vals = [fit.get(k) for k in keys]
        cells = ["-" if v is None else f"{v:.4g}" for v in vals]
        print(f"| {seed} | {kind} | {time.perf_counter() - t:.2f} | " + " | ".join(cells) + " |",
              flush=True)
