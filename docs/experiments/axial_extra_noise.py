#!/usr/bin/env python
r"""Ablations of the observation model's axial extra noise and per-pixel normal baseline
(issue 15; the default since they were measured, docs/measurements.md, "The fitted extra noise
as axial noise" and "The rule, measured").

The noise fit (:func:`bftaichi.stages.observe.estimate_extra_noise`) measures the frames' extra
noise as a residual along the ray on head-on pixels and splits it into a part neighbouring
pixels share and an independent part. :func:`bftaichi.stages.observe.make_observer` passes the
independent part as axial depth noise (``sigma_axial_m`` of :class:`kernels.observe.Observer`:
an oblique pixel's ``y`` moves by ``cos(angle)`` of it, as with the sensor's own noise), and
lets each pixel take the shortest normal baseline ``r <= 4`` whose normal angle noise
``sigma fx / (sqrt(2) r D)`` is at most ``NORMAL_MAX_NOISE_RAD`` = 0.6 rad. This runs a script
with either choice undone::

    AXIAL=0 RADIUS=1 python docs/experiments/axial_extra_noise.py tools/suite.py --json old.json
    RADIUS=frame python docs/experiments/axial_extra_noise.py tools/evalviews_table.py \
        --voxels 0.02,0.01 --no-open3d

and ``python tools/suite_diff.py old.json default.json`` compares it with ``python
tools/suite.py --json default.json``. Environment: ``AXIAL=0`` adds the independent part to
every sample's noise as it is (isotropic, ``sigma_model_m``); ``RADIUS=R`` gives every pixel
the baseline ``R`` (``AXIAL=0 RADIUS=1`` is the model before these two changes, byte for
byte); ``RADIUS=frame`` one baseline per frame, the rule's at the frame's median valid depth
(every 4th pixel each way: the first form measured); ``THETA`` the rule's largest angle noise
(radians, default 0.6).
"""

import os
import runpy
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

from bftaichi.stages import bandsolve, observe  # noqa: E402

_make_observer = observe.make_observer
THETA = float(os.environ.get("THETA", str(observe.NORMAL_MAX_NOISE_RAD)))
RADIUS = os.environ.get("RADIUS", "pixel")


def make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m=0.0, sigma_corr_m=0.0):
    """:func:`bftaichi.stages.observe.make_observer` with the environment's ablations."""
    if os.environ.get("AXIAL", "1") == "0":  # the independent part isotropic, as it was:
        corr = min(float(sigma_corr_m), float(sigma_extra_m))  # in the model noise instead
        independent = float(np.sqrt(max(sigma_extra_m ** 2 - corr ** 2, 0.0)))
        obs = replace(obs, sigma_model_m=float(np.hypot(obs.sigma_model_m, independent)))
        sigma_extra_m = sigma_corr_m = corr
    observer = _make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m, sigma_corr_m)
    observer.normal_max_noise_rad = THETA  # read per frame
    if RADIUS == "frame":
        observer.normal_max_noise_rad = 0.0
        observer.frame_rule = True
    elif RADIUS != "pixel":
        observer.normal_radius_px, observer.normal_max_noise_rad = int(RADIUS), 0.0
    return observer


def _frame_params(self, depth_m, K, T_W_C, sigma_pose_m):
    """``RADIUS=frame``: the frame's baseline from its median depth, then the parameters."""
    if getattr(self, "frame_rule", False):
        d = np.asarray(depth_m)[::4, ::4]
        d = d[d > 0]
        if len(d):
            D = float(np.median(d))
            a, b, z0, _ = self.depth_model
            theta1 = np.hypot(a + b * (D - z0) ** 2, self.sigma_axial_m) * \
                float(np.asarray(K)[0][0]) / (np.sqrt(2.0) * D)
            self.normal_radius_px = int(np.clip(np.ceil(theta1 / THETA), 1,
                                                observe.NORMAL_RADIUS_MAX_PX))
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
