#!/usr/bin/env python
r"""Run a tool with every frame's correlated extra noise counted as shared by ``L`` frames
(issue 15; a measurement, not built: docs/measurements.md, "The real frames' extra noise is
shared by frames close in time").

:func:`bftaichi.stages.observe.make_observer` gets ``sigma_corr_m * sqrt(L)``: one frame
then tells a voxel at most ``1 / (L sigma_corr^2)`` instead of ``1 / sigma_corr^2``, as if
each pose error were shared by ``L`` frames that all see the voxel::

    L=16 python docs/experiments/frames_share_pose_noise.py tools/evalviews_table.py \
        --voxels 0.02 --no-open3d

``L=1`` (the default) is the model as it is.
"""

import os
import runpy
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

from bftaichi.stages import bandsolve, observe  # noqa: E402

_make_observer = observe.make_observer
L = float(os.environ.get("L", "1"))


def make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m=0.0, sigma_corr_m=0.0):
    """:func:`bftaichi.stages.observe.make_observer`, the correlated part shared by L frames."""
    observer = _make_observer(band, obs, voxel_size_m, trunc_m, sigma_extra_m, sigma_corr_m)
    observer.sigma_corr_m *= L ** 0.5
    return observer


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    observe.make_observer = bandsolve.make_observer = make_observer
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
