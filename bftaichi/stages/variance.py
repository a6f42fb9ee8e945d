"""Step 6 of Algorithm 1: the marginal variances ``s ~ diag(Q^-1)`` from K probe vectors solved
together as one batched PCG (DESIGN.md section 3.6), configured by ``[solver]``; from the same
probes, each voxel's covariance with its +x, +y, +z neighbours, which step 7 needs for the
variance of the SDF at a mesh vertex (DESIGN.md section 3.7)."""

from __future__ import annotations

import numpy as np

__all__ = ["estimate_variance"]


def estimate_variance(system, solver, ijk: np.ndarray, *, probes: bool = True
                      ) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(var, cov, stats)`` of ``system`` (:class:`~.prior.System`) by ``solver.probes``
    probes of ``solver.probe_method`` (``ijk`` (N, 3): the band's voxels, which lattice
    colouring needs).

    ``var`` (N,) float32: the marginal variances, metres^2. The probe estimate can dip below
    the conditional variance ``1/Q_ii`` (or below 0) where few probes average out; the
    marginal variance is never smaller than ``1/Q_ii``, so it is floored there
    (``stats["n_floored"]``).

    ``cov`` (N, 3) float32: the covariance of voxel i with its neighbour at +x, +y, +z,
    metres^2 (0 where that neighbour is not in the band;
    :func:`kernels.probes.probe_covariance`), clipped to the Cauchy-Schwarz bound
    ``|cov_ij| <= sqrt(var_i var_j)`` so that every 2x2 block, and hence the variance of the
    SDF interpolated on a grid edge, stays >= 0 (``stats["n_cov_clipped"]``).

    ``probes=False`` skips the probes: ``var`` is then ``1/Q_ii``, a lower bound, ``cov`` is 0
    (Q^-1 is unknown), and the stats say so."""
    from kernels.layout import CENTRE
    from kernels.probes import FACE_PLUS, probe_moments

    floor = (1.0 / system.S[:, CENTRE].astype(np.float64)).astype(np.float32)
    if not probes:
        return floor, np.zeros((len(floor), 3), np.float32), {
            "n_probes": 0, "method": "conditional (1/Q_ii, no probes)"}
    var, cov, stats = probe_moments(system.S, system.nbr, n_probes=solver.probes,
                                    seed=solver.seed, method=solver.probe_method,
                                    tol=solver.probe_tol, maxiter=solver.maxiter, ijk=ijk,
                                    far=system.far, check=False)  # add_prior's: symmetric
    stats = dict(stats, n_floored=int(np.count_nonzero(var < floor)))
    var = np.maximum(var, floor)
    nbr_var = np.zeros_like(cov)
    for e, o in enumerate(FACE_PLUS):
        j = system.nbr[:, o]
        nbr_var[j >= 0, e] = var[j[j >= 0]]
    bound = np.sqrt(var[:, None].astype(np.float64) * nbr_var).astype(np.float32)
    stats["n_cov_clipped"] = int(np.count_nonzero(np.abs(cov) > bound))
    return var, np.clip(cov, -bound, bound), stats
