#!/usr/bin/env python
"""The ``blend`` variance without the prior's part (issue 15; measured, not adopted).

``solver.variance = "blend"`` keeps ``var = B_ii (1 - rho + rho^2)``: the sandwich's
``rho B_ii`` plus the prior's part ``B_ii - rho B_ii`` in proportion ``1 - rho`` to the prior's
share of the voxel's precision (``bftaichi/stages/variance.py``). This wrapper runs a tool or
command with the prior's part left out, ``var = rho B_ii`` (the covariances scaled alike), to
see how much of the sparse captures' width that part holds (docs/measurements.md, "The noise
fit against the other frame's interpolated depth")::

    python docs/experiments/variance_share.py tools/suite.py --meshes suzanne --conditions sparse_far --no-sphere
"""

import runpy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

from bftaichi.stages import variance  # noqa: E402


def _sandwich_only(system, faces, var_b, cov_b, stats, D_ii, kappa=None):
    rho = variance._data_share(system, D_ii)
    var = var_b.astype(np.float64) * rho
    cov = cov_b.astype(np.float64) * np.sqrt(rho[:, None] * variance._face_neighbours(faces, rho))
    stats = dict(stats, method=f"sandwich only ({stats['method']}; experiment)",
                 mean_data_share=float(rho.mean()) if len(rho) else 0.0)
    return var.astype(np.float32), cov.astype(np.float32), stats


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    variance._blend = _sandwich_only
    sys.argv = sys.argv[1:]
    runpy.run_path(sys.argv[0], run_name="__main__")
