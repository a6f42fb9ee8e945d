#!/usr/bin/env python
r"""The pixel normal's angle noise in each sample's weight (issue 15; measured, not adopted).

A sample ``delta`` in depth from its pixel's surface point observes ``y = delta <n, ray>``. A
normal off by ``eps`` in the plane of the ray moves it by ``delta |ray| eps sin(angle)``: zero
at the surface, growing with the distance and the incidence angle. ``eps`` is the normal's
angle noise at its baseline, ``sigma fx / (sqrt(2) r D)`` (:func:`kernels.dataterm.pixel_normal`,
the per-pixel rule of the default), which the default noise model leaves out (the incidence
floor ``observation.cos_min`` stands in for it). ``docs/experiments/normal_slope_noise.patch``
(``git apply`` it first) adds the kernel parameter ``P_SLOPE`` (0 leaves every weight as it is,
byte for byte), which divides each sample's weight by ``1 +
delta^2 eps^2 sin^2(angle) |ray|^2 |P_SLOPE| / sigma^2``, and the local-noise misfit expects
that much more variance of the sample; negative, only the samples behind the surface (``delta >
0``). (Until 027a8a8 the misfit's expectation left the term out.) This runs a script with
``P_SLOPE = SLOPE`` (environment), the patch applied::

    SLOPE=1 python docs/experiments/normal_slope_noise.py tools/suite.py --json slope.json
    SLOPE=-1 python docs/experiments/normal_slope_noise.py tools/suite.py --json behind.json

and ``python tools/suite_diff.py default.json slope.json`` compares it with ``python
tools/suite.py --json default.json``. Results: docs/measurements.md, "The normal's angle
noise in the samples' weights".
"""

import os
import runpy
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

try:
    from kernels.dataterm import P_SLOPE  # noqa: E402
except ImportError:
    sys.exit("apply docs/experiments/normal_slope_noise.patch first (git apply)")
from kernels.observe import Observer  # noqa: E402

SLOPE = float(os.environ.get("SLOPE", "1"))


def _frame_params(self, depth_m, K, T_W_C, sigma_pose_m):
    depth, prm = _frame_params_base(self, depth_m, K, T_W_C, sigma_pose_m)
    prm[P_SLOPE] = SLOPE  # copied into every super-pixel level's parameters
    return depth, prm


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    _frame_params_base = Observer._frame_params
    Observer._frame_params = _frame_params
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
