"""Step 6 of Algorithm 1: the marginal variances ``s ~ diag(Q^-1)`` from K probe vectors solved
together as one batched PCG (DESIGN.md section 3.6), configured by ``[solver]``; from the same
probes, each voxel's covariance with its +x, +y, +z neighbours, which step 7 needs for the
variance of the SDF at a mesh vertex (DESIGN.md section 3.7). By default
(``solver.variance = "blend"``) the prior's part of ``Q^-1`` is kept only in proportion to the
prior's share of each voxel's precision (:func:`estimate_variance`)."""

from __future__ import annotations

import numpy as np

__all__ = ["estimate_variance"]


def estimate_variance(system, solver, ijk: np.ndarray, *, probes: bool = True,
                      data: tuple | None = None,
                      bias: tuple | None = None,
                      kappa: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
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
    (Q^-1 is unknown), and the stats say so.

    ``solver.variance`` other than ``posterior`` (needs ``data = (W, D_ii)``, the data term's
    row sums and diagonal, (N,) each) takes from ``B``, the probes' ``Q^-1``, the part the
    prior adds beyond the MAP's error under the noise, in proportion to the data's share
    ``rho = D_ii / Q_ii`` of each voxel's precision: ``S + (1 - rho) (B - S)``, ``S`` the
    sandwich ``Q^-1 D Q^-1``.

    - ``blend`` (default): ``S_ii ~ rho_i B_ii``, exact where the voxels are independent (a
      diagonal Q: ``S = d / q^2 = rho / q``), so ``var = B_ii (1 - rho + rho^2)``; the
      covariances ``F^1/2 B F^1/2``, ``F = diag(1 - rho + rho^2)``, which keeps every 2x2
      block positive semi-definite. No solve.
    - ``blend-sampled``: ``S`` by ``solver.probes`` perturbation solves
      (:func:`kernels.probes.perturbation_moments`), one more batched PCG; Monte Carlo
      (about 26 % per voxel at 16 probes).

    ``B`` is floored as above before the blend, ``B - S`` (the prior's part, >= 0 in exact
    arithmetic) at 0; the blend is not floored at ``1/Q_ii``, which bounds the Bayesian
    variance, not the sandwich.

    ``bias = (b, stats)`` (:func:`~.solve.prior_bias`, ``solver.prior_bias``; needs
    ``data``): the MAP's bias under its prior, estimated at the mean, is added as a
    deterministic offset: ``var += e^2``, ``cov_ij += e_i e_j``. The estimate carries the
    noise of the mean it is computed from, ``b = Q^-1 P mu`` moving by ``Q^-1 P`` times the
    mean's noise; for independent voxels that is ``(1 - rho)`` times it, variance ``(1 -
    rho)^2 rho B_ii`` (the blend's approximation of the sandwich, ``rho B_ii``). Only the
    excess counts: ``e^2 = max(b^2 - (1 - rho)^2 rho B_ii, 0)``, ``e`` with the sign of ``b``.

    ``kappa`` (N,) (:func:`~.sharednoise.shared_noise_factor`; None: 1): how much more
    variance the data leave than independent frames would, where frames share their noise.
    The sandwich (the MAP's error under the noise) is scaled by it: ``blend`` gives ``B_ii
    (kappa rho + (1 - rho)^2)``, ``blend-sampled`` ``kappa S + (1 - rho) max(B - S, 0)``, and
    the bias's own noise is ``kappa`` times the above. ``posterior`` ignores it.

    The covariances are clipped to the final variances' bound.
    """
    from kernels.layout import CENTRE
    from kernels.probes import probe_moments

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
    var_b = var
    faces = _faces(system.nbr)
    if solver.variance == "blend" and data is not None:
        var, cov, stats = _blend(system, faces, var, cov, stats, data[1], kappa)
    elif solver.variance == "blend-sampled" and data is not None:
        var, cov, stats = _blend_sampled(system, faces, solver, var, cov, stats, *data,
                                          kappa)
    if bias is not None:
        if data is None:
            raise ValueError("the prior bias needs data = (W, D_ii): the data's share")
        var, cov, stats = _add_bias(system, faces, var_b, var, cov, stats, bias, data[1],
                                     kappa)
    nbr_var = _face_neighbours(faces, var)
    bound = np.sqrt(var[:, None].astype(np.float64) * nbr_var).astype(np.float32)
    stats["n_cov_clipped"] = int(np.count_nonzero(np.abs(cov) > bound))
    return var, np.clip(cov, -bound, bound), stats


def _faces(nbr: np.ndarray) -> np.ndarray:
    """(N, 3) int32: the +x, +y, +z neighbours of each voxel (-1 outside the band), the columns
    of ``cov``; taken once (each column of the (N, 27) table is a pass over all of it)."""
    from kernels.probes import FACE_PLUS

    return np.ascontiguousarray(nbr[:, list(FACE_PLUS)])


def _face_neighbours(faces: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(N, 3): ``x`` of each voxel's +x, +y, +z neighbour (``faces``, :func:`_faces`), 0 where
    that neighbour is not in the band."""
    return np.where(faces >= 0, x[faces], 0).astype(x.dtype, copy=False)  # -1 reads x[-1], masked


def _data_share(system, D_ii) -> np.ndarray:
    """``rho = D_ii / Q_ii`` in [0, 1], float64: the data's share of each voxel's precision."""
    from kernels.layout import CENTRE

    q = system.S[:, CENTRE].astype(np.float64)
    return np.clip(np.asarray(D_ii, np.float64) / q, 0.0, 1.0)


def _blend(system, faces, var_b, cov_b, stats, D_ii, kappa=None):
    """``blend``: ``F^1/2 B F^1/2`` with ``F = diag(kappa rho + (1 - rho)^2)`` (``1 - rho +
    rho^2`` at ``kappa`` = 1)."""
    rho = _data_share(system, D_ii)
    f = 1.0 - rho + rho * rho if kappa is None else kappa * rho + (1.0 - rho) ** 2
    var = var_b.astype(np.float64) * f
    cov = cov_b.astype(np.float64) * np.sqrt(f[:, None] * _face_neighbours(faces, f))
    stats = dict(stats, method=f"blend ({stats['method']}, local data share)",
                 mean_data_share=float(rho.mean()) if len(rho) else 0.0)
    return var.astype(np.float32), cov.astype(np.float32), stats


def _blend_sampled(system, faces, solver, var_b, cov_b, stats, W, D_ii, kappa=None):
    """``blend-sampled``: ``kappa S + (1 - rho) max(B - S, 0)``, S by perturbation."""
    from kernels.probes import perturbation_moments

    var_s, cov_s, sand = perturbation_moments(system.S, system.nbr, W, n_probes=solver.probes,
                                              seed=solver.seed + 1, tol=solver.probe_tol,
                                              maxiter=solver.maxiter, far=system.far)
    rho = _data_share(system, D_ii)
    prior_share = 1.0 - rho
    var = var_s + prior_share * np.maximum(var_b.astype(np.float64) - var_s, 0.0)
    cov = cov_s + prior_share[:, None] * (cov_b.astype(np.float64) - cov_s)
    if kappa is not None:  # the sandwich under the noise the frames share
        var = var + (kappa - 1.0) * var_s
        cov = cov + (np.sqrt(kappa[:, None] * _face_neighbours(faces, kappa)) - 1.0) * cov_s
    stats = dict(stats, method=f"blend ({stats['method']} and perturbation)",
                 converged=bool(stats["converged"] and sand["converged"]),
                 n_not_converged=stats["n_not_converged"] + sand["n_not_converged"],
                 perturbation=dict(iterations=sand["iterations"],
                                   relative_residuals=sand["relative_residuals"]),
                 mean_data_share=float(rho.mean()) if len(rho) else 0.0)
    return var.astype(np.float32), cov.astype(np.float32), stats


def _add_bias(system, faces, var_b, var, cov, stats, bias, D_ii, kappa=None):
    """``var + e^2`` and ``cov_ij + e_i e_j``, ``e`` the prior's bias beyond the noise of its
    estimate (:func:`estimate_variance`)."""
    b, b_stats = bias
    rho = _data_share(system, D_ii)
    noise = (1.0 - rho) ** 2 * rho * var_b.astype(np.float64)
    if kappa is not None:
        noise = noise * kappa
    e = np.sign(b) * np.sqrt(np.maximum(b * b - noise, 0.0))
    var = (var.astype(np.float64) + e * e).astype(np.float32)
    cov = (cov.astype(np.float64) + e[:, None] * _face_neighbours(faces, e)).astype(
        np.float32)
    stats = dict(stats, prior_bias=dict(b_stats, voxels=int(np.count_nonzero(e))))
    return var, cov, stats
