#!/usr/bin/env python
"""The side gate against the frames' free space, not their average (issue 15; measured, not built).

The side gate (``observation.gate``, kernels/observe.py step 3b) drops a sample behind its
pixel's surface where the bootstrap TSDF interpolated at it says free space by more than
``gate * tau``. The TSDF is an average, so where frames disagree (a sheet seen from both sides,
a thin part, a silhouette) a voxel that some frames saw in front of their surface can still
average near 0 and take "inside" samples. This wrapper makes the gate's reference say free
space (``+tau_b``, or ``--big``: 1 km, so any such corner gates) at every band voxel that at
least ``GF`` of the frames observing it (as the TSDF observes: nearest pixel, ``sdf >= -tau_b``)
saw more than ``GM * gate * tau`` in front of their surface, counted in numpy from the frames the
solve observes. It runs a tool in-process with the patch::

    GF=0.4 GM=2 python docs/experiments/free_space_gate.py tools/suite.py --json after.json
    GF=0.4 GM=2 python docs/experiments/free_space_gate.py tools/evalviews_table.py --voxels 0.02 --no-open3d

Environment: ``GF`` (fraction of frames, default 0.4, the ``prior.carve`` fraction), ``GM``
(margin in units of the gate, default 1), ``GREF=big`` for the 1 km reference (default).
"""

import os
import runpy
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

import bftaichi.reconstructor as reconstructor  # noqa: E402
from bftaichi.stages import band as band_module  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sheet_conflict import projective_sdf  # noqa: E402  (the TSDF's observation, in numpy)

FRACTION = float(os.environ.get("GF", "0.4"))
MARGIN = float(os.environ.get("GM", "1.0"))
BIG = os.environ.get("GREF", "big") == "big"
_solve_band = reconstructor.solve_band
_reference = band_module.Band.reference


def free_fraction(config, band, frames) -> np.ndarray:
    """(N,) the fraction of the frames observing each band voxel that saw it more than the
    margin in front of their surface."""
    h, tb = config.tsdf.voxel_size_m, config.tsdf.bootstrap_trunc_m
    margin = MARGIN * config.observation.gate * config.tsdf.trunc_m
    X = (band.ijk.astype(np.float64) + 0.5) * h
    seen, free = np.zeros(len(X)), np.zeros(len(X))
    for i in range(len(frames)):
        f = frames[i]
        ok, _, sdf, _, _ = projective_sdf(X, f, np.asarray(f.T_W_C, np.float64), tb)
        seen += ok
        free += ok & (sdf > margin)
    return np.where(seen > 0, free / np.maximum(seen, 1), 0.0)


def solve_band(config, band, x0, frames, *args, **kwargs):
    band._free = free_fraction(config, band, frames)
    band._tb = config.tsdf.bootstrap_trunc_m
    return _solve_band(config, band, x0, frames, *args, **kwargs)


def reference(self):
    ref = _reference.fget(self)
    free = getattr(self, "_free", None)
    if free is None or FRACTION <= 0:
        return ref
    return np.where(free >= FRACTION, np.float32(1e3 if BIG else self._tb), ref).astype(np.float32)


if __name__ == "__main__":
    reconstructor.solve_band = solve_band
    band_module.Band.reference = property(reference)
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
