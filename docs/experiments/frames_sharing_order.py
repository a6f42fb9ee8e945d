"""The frames-sharing fit of tests/test_sharednoise.py's drifting tabletop (a drift over ~17
frames) with the frames as recorded, reversed and shuffled (docs/measurements.md, "The frames'
shared pose error in the variance")::

    python docs/experiments/frames_sharing_order.py
"""
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

sys.path.insert(0, str(ROOT / "tests"))
import test_sharednoise as t  # noqa: E402
from bftaichi.running.pipeline import open_frames  # noqa: E402

cfg = t._tabletop()
frames = list(open_frames(cfg))
white = np.random.default_rng(0).normal(0, 1, len(frames))
drift = gaussian_filter1d(white, t.SPAN / np.sqrt(2), mode="wrap")
off = drift / drift.std() * t.RMS_M
n = len(frames)
print("| order | frames_sharing_noise | sharing_z |\n|---|---|---|")
for name, order in (("as recorded", np.arange(n)), ("reversed", np.arange(n)[::-1]),
                    ("shuffled (seed 1)", np.random.default_rng(1).permutation(n)),
                    ("shuffled (seed 2)", np.random.default_rng(2).permutation(n))):
    fit = t._fit(cfg, [frames[i] for i in order], off[order])
    print(f"| {name} | {fit['frames_sharing_noise']:.1f} | {fit['sharing_z']:.2f} |", flush=True)
