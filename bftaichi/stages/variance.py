"""Step 6 of Algorithm 1: the marginal variances ``s ~ diag(Q^-1)`` from K probe vectors solved
together as one batched PCG (DESIGN.md section 3.6), configured by ``[solver]``."""

from __future__ import annotations

import numpy as np

__all__ = ["estimate_variance"]


def estimate_variance(system, solver, ijk: np.ndarray, *, probes: bool = True
                      ) -> tuple[np.ndarray, dict]:
    """``(var, stats)``: (N,) float32 marginal variances of ``system`` (:class:`~.prior.System`),
    metres^2, by ``solver.probes`` probes of ``solver.probe_method`` (``ijk`` (N, 3): the band's
    voxels, which lattice colouring needs).

    The probe estimate can dip below the conditional variance ``1/Q_ii`` (or below 0) where few
    probes average out; the marginal variance is never smaller than ``1/Q_ii``, so it is floored
    there (``stats["n_floored"]``). ``probes=False`` skips the probes: ``var`` is then ``1/Q_ii``,
    a lower bound, and the stats say so."""
    from kernels.layout import CENTRE
    from kernels.probes import probe_variance

    floor = (1.0 / system.S[:, CENTRE].astype(np.float64)).astype(np.float32)
    if not probes:
        return floor, {"n_probes": 0, "method": "conditional (1/Q_ii, no probes)"}
    var, stats = probe_variance(system.S, system.nbr, n_probes=solver.probes, seed=solver.seed,
                                method=solver.probe_method, tol=solver.probe_tol,
                                maxiter=solver.maxiter, ijk=ijk, far=system.far)
    stats = dict(stats, n_floored=int(np.count_nonzero(var < floor)))
    return np.maximum(var, floor), stats
