#!/usr/bin/env python
r"""The fitted extra noise as axial depth noise instead of isotropic (issue 15; measured, not
adopted).

The noise fit (:func:`bftaichi.stages.observe.estimate_extra_noise`) measures the frames' extra
noise as a residual along the ray on head-on pixels and splits it into a part neighbouring
pixels share and an independent part. :func:`bftaichi.stages.observe.make_observer` adds the
independent part to every sample's noise as it is (``sigma_model_m``, isotropic). Were it
sensor noise, a depth error along the ray, it would move an oblique pixel's ``y`` by only
``cos(angle)`` of it, as the sensor's own noise does (``sigma_axial_m`` of
:class:`kernels.observe.Observer`). This runs a script with the independent part passed that
way::

    python docs/experiments/axial_extra_noise.py tools/suite.py --json axial.json
    python docs/experiments/axial_extra_noise.py tools/evalviews_table.py \
        --voxels 0.02,0.01 --no-open3d

and ``python tools/suite_diff.py default.json axial.json`` compares it with ``python
tools/suite.py --json default.json``. Environment: ``RADIUS=R`` also estimates each pixel's
normal from the pixels ``R`` away instead of 1 (``normal_radius_px`` of the Observer: a
longer baseline, a normal less disturbed by the depth noise); ``AXIAL=0`` keeps the extra noise
isotropic. ``RADIUS=auto`` picks ``r`` per frame: the smallest ``r`` (at most 4) whose normal
angle noise ``sigma / (sqrt(2) r D / f)`` is at most ``THETA`` radians (default 0.6), ``D`` the
frame's median valid depth, ``sigma`` the depth noise a pixel has alone (the sensor model and
the fit's independent part, in quadrature). Results: docs/measurements.md, "The fitted extra
noise as axial noise".
"""

import os
import runpy
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

from bftaichi.stages import bandsolve, observe  # noqa: E402


_make_observer = observe.make_observer
THETA = float(os.environ.get("THETA", "0.6"))  # RADIUS=auto: largest normal angle noise, rad


def make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m=0.0, sigma_corr_m=0.0):
    """:func:`bftaichi.stages.observe.make_observer` with the independent part of the extra
    noise added to the axial noise (``sigma_axial_m``) instead of to ``sigma_model_m``."""
    corr = min(float(sigma_corr_m), float(sigma_extra_m))
    independent = float(np.sqrt(max(sigma_extra_m ** 2 - corr ** 2, 0.0)))
    if os.environ.get("AXIAL", "1") == "1":
        observer = _make_observer(band, obs, voxel_size_m, trunc_m, corr, corr)  # no independent
        observer.sigma_axial_m = independent  # read per frame (the fixed-point scale's bound holds)
    else:
        observer = _make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m, sigma_corr_m)
    radius = os.environ.get("RADIUS", "1")
    if radius != "auto":
        observer.normal_radius_px = int(radius)  # read per frame too
    else:
        observer._independent = independent
    return observer


def _frame_params(self, depth_m, K, T_W_C, sigma_pose_m):
    """``RADIUS=auto``: the frame's normal radius from its noise, then the parameters."""
    e = getattr(self, "_independent", None)
    if e is not None:
        d = np.asarray(depth_m)[::4, ::4]
        d = d[d > 0]
        if len(d):
            D = float(np.median(d))
            a, b, z0, _ = self.depth_model
            theta1 = np.hypot(a + b * (D - z0) ** 2, e) * float(np.asarray(K)[0][0]) / \
                (np.sqrt(2.0) * D)
            self.normal_radius_px = int(np.clip(np.ceil(theta1 / THETA), 1, 4))
    return _frame_params_base(self, depth_m, K, T_W_C, sigma_pose_m)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    from kernels.observe import Observer

    _frame_params_base = Observer._frame_params
    Observer._frame_params = _frame_params
    observe.make_observer = bandsolve.make_observer = make_observer
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
