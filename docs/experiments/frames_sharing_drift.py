"""The tabletop rendered from 48 views and fused at poses shifted along each camera's axis:
drifting smoothly (1 cm sine over 24 frames), jittered independently (the same rms) or not
at all; prints the noise fit with ``frames_sharing_noise`` (needs
docs/experiments/frames_sharing_estimate.patch applied; docs/measurements.md)::

    git apply docs/experiments/frames_sharing_estimate.patch
    python docs/experiments/frames_sharing_drift.py 48
"""
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
import bftaichi as bf  # noqa: E402
from bftaichi.running.pipeline import open_frames  # noqa: E402
from bftaichi.stages.band import build_band  # noqa: E402
from bftaichi.frame import local_frames  # noqa: E402
from bftaichi.stages.observe import estimate_extra_noise  # noqa: E402
n = int(sys.argv[1]) if len(sys.argv) > 1 else 48
cfg = bf.load_config(None, ["synthetic.width=160", "synthetic.height=120", "synthetic.fx=131.25", "synthetic.fy=131.25",
                            "synthetic.cx=79.5", "synthetic.cy=59.5", f"synthetic.n_views={n}",
                            "tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.04", "run.plots=false"])
frames = list(open_frames(cfg))
rng = np.random.default_rng(0)
for kind in ("drift", "jitter", "none"):
    k = np.arange(len(frames))
    off = {"drift": 0.01 * np.sin(2 * np.pi * k / 24), "jitter": rng.normal(0, 0.01 / np.sqrt(2), len(k)),
           "none": 0 * k}[kind]
    recon = bf.Reconstructor(cfg)
    for f, o in zip(frames, off):
        T = np.array(f.T_W_C, np.float64).copy()
        T[:3, 3] += T[:3, 2] * o
        recon.integrate(f.depth_m, f.K, T, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    t = time.perf_counter()
    fit = estimate_extra_noise(local_frames(recon.frames, recon.origin), band, cfg.observation,
                               cfg.tsdf.voxel_size_m, cfg.tsdf.bootstrap_trunc_m, (0.1, 10.0))
    print(kind, round(time.perf_counter() - t, 2), {a: (round(b, 4) if isinstance(b, float) else b) for a, b in fit.items()}, flush=True)
