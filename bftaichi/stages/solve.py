"""Step 5 of Algorithm 1: the MAP ``Q mu = h`` by Jacobi-preconditioned conjugate gradients
(DESIGN.md section 3.5), with the free-space inequality of ``prior.free`` by an active set."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..checks import MAX_SEED, check_choice, check_range

__all__ = ["SolverConfig", "prior_bias", "solve_map"]


@dataclass
class SolverConfig:
    """``[solver]``: PCG for the MAP and the probe variance (DESIGN.md 3.5-3.6)."""

    tol: float = 1e-6
    """Relative residual ``||h - Q mu|| / ||h||`` (no unit) at which PCG stops."""

    maxiter: int = 2000
    """PCG iteration limit (iterations); a solve that reaches it is reported as not converged."""

    probes: int = 16
    """Number of probe vectors K for ``diag(Q^-1)`` (a count)."""

    probe_method: str = "coloring"
    """``coloring`` (lattice-coloured probes: one probe per colour, voxels of a colour at least
    2.45 voxels apart at K = 16) or ``rademacher`` (the paper). Lattice colouring measured about
    3x more accurate at K = 16 (docs/measurements.md)."""

    probe_tol: float = 1e-2
    """Relative residual (no unit) of the probe solves and the prior bias's: variance needs
    fewer digits than the mean. At 1e-2 the solves move sigma by ~3e-4 of itself (median; 0.4 %
    at the 99th percentile on 500 real frames at 2 cm) against 1e-3, far below the probes'
    sampling error (~6 % per voxel at K = 16), for a third fewer iterations; neither suite nor
    the real views moved (docs/measurements.md, "The probes' tolerance, again")."""

    seed: int = 0
    """Seed of the probe vectors (and, plus one, of the perturbation draws)."""

    variance: str = "blend"
    """Which variance the probes give (DESIGN.md 3.6; docs/measurements.md). ``posterior``:
    the Bayesian ``diag(Q^-1)``. ``blend``: the MAP's error under the measurement noise (the
    sandwich ``Q^-1 D Q^-1``, ``D`` the data term) plus the rest of ``Q^-1`` (the prior's
    part) in proportion to the prior's share of each voxel's precision, ``1 - D_ii / Q_ii``,
    with the sandwich's diagonal taken voxel by voxel (``rho B_ii``, ``rho = D_ii / Q_ii``):
    ``var = B_ii (1 - rho + rho^2)``, no extra solve. ``blend-sampled``: the same blend with
    the sandwich estimated by ``probes`` perturbation solves (a second batched solve). The
    sandwich alone is too narrow where the prior extrapolates; ``Q^-1`` alone too wide where
    the data pin a voxel down and the prior's modes are ones a smooth surface does not
    have."""

    prior_bias: bool = True
    """Add the MAP's bias under its own prior to the variance (DESIGN.md 3.6;
    docs/measurements.md). The prior pulls the mean where the surface bends: the MAP of a
    truth ``x`` sits ``-Q^-1 (P x - b0)`` from it on average, and ``b = -Q^-1 (P mu - b0)``
    estimates that with the mean in place of the truth (at the MAP the prior's force ``P mu
    - b0`` balances the data's). One more solve, to ``probe_tol``. The variance
    then holds the squared bias beyond what the mean's own noise puts into the estimate
    (:func:`~.variance.estimate_variance`), fully correlated between neighbours as a
    deterministic offset: creases, thin parts and the prior's extrapolation get the larger
    sigma their errors have. With the robust curvature prior (``prior.curvature_scale > 0``)
    the force is the prior's slope at the mean (its reweighted weights) and the solve uses its
    Hessian there (the Laplace approximation the variance uses)."""

    def check(self) -> None:
        check_range("solver.tol", self.tol, 0.0, 1.0, lo_open=True)
        check_range("solver.maxiter", self.maxiter, 1, 1_000_000)
        check_range("solver.probes", self.probes, 1, 1024)
        check_choice("solver.probe_method", self.probe_method, ("rademacher", "coloring"))
        check_range("solver.probe_tol", self.probe_tol, 0.0, 1.0, lo_open=True)
        check_range("solver.seed", self.seed, 0, MAX_SEED)
        check_choice("solver.variance", self.variance, ("posterior", "blend", "blend-sampled"))


ROBUST_PASSES = 2
"""Reweighting steps of the robust curvature prior (``prior.curvature_scale > 0``)."""

ACTIVE_SET_TOL = 1e-5
"""Relative residual of the MAP's solves that only lead to the next weights and anchors
(:func:`solve_map`): the active set they settle on is that of solves to 1e-6 (1,673 anchored
voxels against 1,672 on the built-in scene; 1e-4: 1,683), in 222 PCG iterations against 310
(every pass solving the whole band)."""


LOCAL_RINGS = 4
"""Neighbour rings (26-neighbourhood) around a free-space pass's new anchors that its solve
frees (:func:`solve_map`): an anchor moves the mean around it, and the loose passes only
choose the next anchors; the settled mean is solved whole."""

LOCAL_SHARE = 0.5
"""A pass whose region exceeds this share of the band solves the whole band instead."""

STIFFEN = 16
"""Largest anchor strength, in units of ``prior.free``, of a free voxel whose mean stays below
0 (:func:`solve_map`). Raising its target alone moves the mean by ``k / (k + pull)`` of the
raise, where ``pull`` is what the data and the curvature prior around the voxel put against
the anchor: 40 real frames at 4 cm had anchors pulled ~100x harder, whose means crept up by a
tenth of a voxel a pass, and 130 passes did not settle. From its second raise on, the anchor
also doubles its strength up to this (docs/measurements.md, "Anchors that the data overpower")."""


def _rings(nbr: np.ndarray, seeds: np.ndarray, rings: int,
           mark: np.ndarray | None = None) -> np.ndarray:
    """Sorted band indices within ``rings`` 26-neighbour steps of ``seeds`` (unique). ``mark``:
    an (N,) int32 scratch of -1, left so (the cost then grows with the region, not with the
    band; no sort but the last)."""
    if mark is None:
        mark = np.full(len(nbr), -1, np.int32)
    front = np.unique(np.asarray(seeds, np.int64))
    mark[front] = 0
    fronts = [front]
    for ring in range(1, rings + 1):
        reached = nbr[front].ravel()
        reached = reached[reached >= 0]  # -1: a missing neighbour
        reached = reached[mark[reached] < 0]
        # each new voxel once: the last of its copies keeps its position in ``order``
        order = np.arange(len(reached), dtype=np.int32)
        mark[reached] = order
        front = reached[mark[reached] == order].astype(np.int64)
        mark[front] = ring
        fronts.append(front)
    region = np.sort(np.concatenate(fronts))
    mark[region] = -1
    return region


def anchor_target(tsdf: np.ndarray, trunc_m: float, bootstrap_trunc_m: float,
                  voxel_size_m: float) -> np.ndarray:
    """(N,) float32: what a free-space anchor (:func:`solve_map`) pulls a voxel's SDF to,
    from its bootstrap TSDF ``tsdf`` (clamped at ``bootstrap_trunc_m``, ``tau_b``).

    The inequality says only ``sdf >= h/2``. The projective TSDF says more the farther in
    front it puts the voxel, but it overstates the distance wherever the frames saw the
    surface obliquely or curving away from the rays: at ``tau`` (``trunc_m``, where a voxel
    starts to count as free) it is trusted not at all, at ``tau_b`` (every frame saw the
    voxel beyond the truncation) fully::

        t = clip((tsdf - tau) / (tau_b - tau), 0, 1)
        target = h/2 + t (tsdf - h/2),  at least h/2

    On a sphere seen with perfect depth, anchors at the TSDF value made 90 % of the surface's
    squared error; anchors at ``h/2`` everywhere let false surfaces of real frames stay half
    a voxel from space other frames saw as free (docs/measurements.md, "The anchors' target
    between the bound and the projective value")."""
    half = np.float32(0.5 * voxel_size_m)
    tsdf = np.asarray(tsdf, np.float32)
    span = max(bootstrap_trunc_m - trunc_m, 1e-12)
    t = np.clip((tsdf - np.float32(trunc_m)) / np.float32(span), 0.0, 1.0).astype(np.float32)
    return np.maximum(half + t * (tsdf - half), half).astype(np.float32)


def solve_map(system, x0: np.ndarray, solver: SolverConfig, band, *, trunc_m: float,
              bootstrap_trunc_m: float, voxel_size_m: float, free: float, passes: int = 64,
              prior=None, carved: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The MAP of ``system`` (:class:`~.prior.System`) from ``x0``, then the free-space
    inequality: a voxel the bootstrap saw as free (observed, ``tsdf > trunc_m``), or one the
    rays carved (``carved``, (N,) bool: :class:`kernels.carve.FreeSpaceCounter`), whose mean
    fell below half a voxel is anchored (:func:`anchor_target`: at least half a voxel, more
    the farther beyond ``trunc_m`` its TSDF puts it), with strength ``free`` per voxel^2 (in
    ``system.S`` and ``system.h``, in place) and the MAP is solved again, warm-started, until
    no free voxel outside the anchored set is below half a voxel (the active set settled) or
    ``passes`` solves found one (``free = 0``: no constraint); an anchored voxel whose mean is
    still below 0 (the data pull harder than its anchor) has its target raised by what it
    lacks of half a voxel (an augmented-Lagrangian step), and from its second raise on its
    anchor doubles in strength, up to :data:`STIFFEN` times ``free``, so the inequality holds
    where it matters: no surface in free space. The anchors are taken out of ``system`` again at the
    end: they enforce an inequality on the mean and are no measurement, so the variance
    (step 6) is that of the data and the prior (kept in, they made the sigma of the vertices
    beside anchored voxels far smaller than their errors: docs/measurements.md,
    ``prior.carve``). With ``prior`` (the :class:`~.prior.PriorConfig` of ``system``) and
    ``prior.curvature_scale > 0``, the robust curvature prior is reweighted at the mean
    before each of the first :data:`ROBUST_PASSES` solves after the first, the anchors
    updated at the same mean (one solve for both), and ``system`` is left with the prior's
    Laplace approximation at the mean (:func:`kernels.prior.laplace_curvature_prior`; the
    reweighted weights in ``system.curvature_weights``) for the variance.

    The solves that only lead to the next weights and anchors stop at :data:`ACTIVE_SET_TOL`,
    and a pass that follows only new anchors (not a reweighting) solves only within
    :data:`LOCAL_RINGS` neighbour rings of them, the rest of the band held (the whole band when
    that region is more than :data:`LOCAL_SHARE` of it); the mean they settle on is solved
    again to ``solver.tol`` over the whole band and the active set settled on it the same
    way, its solves whole and to ``solver.tol``. Settling the active set makes the result
    independent of the solves' path: a spatial chunk and the whole scene anchor the same
    voxels (tests/test_chunks.py), where a fixed number of passes left each with the voxels
    its path happened to cross.

    Returns ``(mean, stats)``: ``converged``, ``iterations`` (summed over the solves of the
    whole band), ``solves`` (those), ``local_solves`` and ``local_iterations`` (the passes
    solved on a region), ``relative_residual`` (the last solve's), ``free_space`` (``passes``: the
    solves that followed new anchors or target raises, ``settled``: the last mean needed no
    new anchor, ``anchored``, ``lifted``: target raises summed over the passes,
    ``free_voxels``, ``carved_voxels``: those of ``carved``, which the averaged TSDF does not
    call free), ``residual_history`` (the last solve's) and ``reason`` when PCG stopped
    early. ``system.compact`` is set to the solves' compact layout of the system as returned
    (for :func:`prior_bias`)."""
    from kernels.compact import CompactStencil
    from kernels.layout import CENTRE
    from kernels.pcg import pcg
    from kernels.prior import laplace_curvature_prior, reweight_curvature_prior
    from kernels.submatrix import principal_submatrix

    S, h = system.S, system.h
    # one layout for every pass: the free-space anchors change only the diagonal
    # add_prior's stencil is exactly symmetric by construction (tests/test_prior.py): not
    # validated again (three stencil products, ~240 bytes per voxel of temporaries)
    compact = CompactStencil(S, system.nbr, system.far, check=False)

    reweight = prior is not None and prior.curvature > 0 and prior.curvature_scale > 0

    free_mask = band.observed & (band.tsdf > trunc_m)
    if carved is not None:
        free_mask |= carved
    target = anchor_target(band.tsdf, trunc_m, bootstrap_trunc_m, voxel_size_m)
    waiting = np.flatnonzero(free_mask)  # the free voxels not anchored yet
    anchored = np.zeros(0, np.int64)  # the anchored voxels, in the order anchored
    k = np.float32(free / voxel_size_m ** 2)
    count = dict(iterations=0, solves=0, passes=0, lifted=0, local_solves=0, local_iterations=0)
    raised = np.zeros(len(band), bool)  # the anchors whose target was raised
    extra = np.zeros(len(band), np.float32)  # their strength beyond k

    def solved(start, tol):
        mean, info = pcg(S, system.nbr, h, start, tol=tol, maxiter=solver.maxiter,
                         far=system.far, compact=compact)
        count["iterations"] += info["iterations"]
        count["solves"] += 1
        return mean, info

    def anchor(mean) -> np.ndarray:
        """Anchor the free voxels whose mean fell below half a voxel (and raise the targets
        of anchored ones still below 0); the indices of both (empty if there were none)."""
        nonlocal waiting, anchored
        if free <= 0:
            return np.zeros(0, np.int64)
        below = mean[waiting] < 0.5 * voxel_size_m
        viol = waiting[below]
        # an anchor is soft: where the data pull harder, its voxel may stay below 0, the
        # surface in free space; its target is raised by what it lacks of the bound
        lifted = anchored[mean[anchored] < 0]
        if not len(viol) and not len(lifted):
            return np.zeros(0, np.int64)
        waiting, anchored = waiting[~below], np.concatenate([anchored, viol])
        S[viol, CENTRE] += k
        h[viol] += k * target[viol]
        lift = (0.5 * voxel_size_m - mean[lifted]).astype(np.float32)
        target[lifted] += lift
        # the anchor's force (k + extra) target keeps up with the raise; raised before, the
        # anchor also stiffens (extra: k, 2k, 4k, ... up to (STIFFEN - 1) k)
        again = lifted[raised[lifted]]
        raised[lifted] = True
        h[lifted] += (k + extra[lifted]) * lift
        add = np.minimum(np.maximum(extra[again], k), (STIFFEN - 1) * k - extra[again])
        extra[again] += add
        S[again, CENTRE] += add
        h[again] += add * target[again]
        count["lifted"] += len(lifted)
        count["passes"] += 1
        compact.set_diagonal(S[:, CENTRE], np.union1d(viol, again))
        return np.union1d(viol, lifted)

    h_norm = float(np.linalg.norm(np.asarray(h, np.float64)))
    mark, loc = np.full(len(band), -1, np.int32), np.full(len(band) + 1, -1, np.int32)  # scratch

    def local(mean, seeds, tol):
        """The mean again after new anchors at ``seeds``, solved only within LOCAL_RINGS
        neighbour rings of them (the rest held), to the residual a global solve to ``tol``
        would stop at; a global solve when the region is more than LOCAL_SHARE of the band.
        Only for the loose passes: a whole solve to ``solver.tol`` follows them."""
        region = _rings(system.nbr, seeds, LOCAL_RINGS, mark)
        if len(region) > LOCAL_SHARE * len(band):
            return solved(mean, tol)[0]
        r = h[region].astype(np.float64) - compact.apply_rows(mean, region)
        r_norm = float(np.linalg.norm(r))
        count["local_solves"] += 1
        if r_norm <= tol * h_norm:
            return mean
        S_r, nbr_r, far_r = principal_submatrix(S, system.nbr, system.far, region, loc)
        # a principal submatrix of the symmetric Q: symmetric by construction, not checked
        d, info = pcg(S_r, nbr_r, r, None, tol=max(tol * h_norm / r_norm, 1e-8),
                      maxiter=solver.maxiter, far=far_r,
                      compact=CompactStencil(S_r, nbr_r, far_r, check=False))
        count["local_iterations"] += info["iterations"]
        mean = np.asarray(mean, np.float64)  # a solve's own array: updated in place
        mean[region] += d
        return mean

    def settle(mean, info, tol, reweights):
        """The robust prior reweighted at the mean before each of the first ``reweights``
        solves, the anchors updated at the same mean before every solve, until a mean needs
        no new anchor (True) or ``passes`` solves found one (False)."""
        for step in range(reweights + passes):
            if step < reweights:  # the robust prior's weights at the mean (kernels/prior.py)
                reweight_curvature_prior(S, system.far, system.nbr, mean, W,
                                         lam2=prior.curvature / voxel_size_m ** 2,
                                         scale_m=prior.curvature_scale * voxel_size_m)
                compact.refill(S, system.far)  # new values, the same neighbours
            seeds = anchor(mean)
            if not len(seeds) and step >= reweights:
                return mean, info, True
            if step >= reweights and tol > solver.tol:  # a global solve to solver.tol follows
                mean = local(mean, seeds, tol)
            else:
                mean, info = solved(mean, tol)
        return mean, info, not (free > 0 and passes > 0)

    # the solves that only lead to the next weights and anchors stop at ACTIVE_SET_TOL; the
    # mean they settle on is solved again to the solver's tolerance and checked again
    W = np.ones((len(band), 3), np.float32) if reweight else None  # weights S holds
    rounds = ROBUST_PASSES if reweight else 0
    loose = max(solver.tol, ACTIVE_SET_TOL) if rounds or free > 0 else solver.tol
    mean, info = solved(x0, loose)
    mean, info, settled = settle(mean, info, loose, rounds)
    if loose > solver.tol:
        mean, info = solved(mean, solver.tol)
        mean, info, settled = settle(mean, info, solver.tol, 0)
    compact.drop_scratch()  # the local passes' vectors
    n_free, n_anchored = (int(free_mask.sum()), len(anchored)) if free > 0 else (0, 0)
    # the anchors enforce an inequality on the mean; they are not measurements, so the
    # variance (step 6, on the same system) is that of the data and the prior without them
    S[anchored, CENTRE] -= k + extra[anchored]
    h[anchored] -= (k + extra[anchored]) * target[anchored]
    if reweight:  # the variance and the bias's solve see the robust prior's Hessian at the
        # mean; the bias's force, the prior's slope there, its reweighted weights
        noise = None
        if prior.noise_allowance and system.data_diagonal is not None:
            # the MAP's variance under the data's noise, Q^-1 D Q^-1, voxel by voxel (Jacobi):
            # Q the system the MAP was solved with, its reweighted prior in, the anchors out
            noise = system.data_diagonal.astype(np.float64) / S[:, CENTRE].astype(
                np.float64) ** 2
        laplace_curvature_prior(S, system.far, system.nbr, mean, W,
                                lam2=prior.curvature / voxel_size_m ** 2,
                                scale_m=prior.curvature_scale * voxel_size_m, noise=noise)
        system.curvature_weights = W
        compact.refill(S, system.far)
    else:
        compact.set_diagonal(S[:, CENTRE])
    system.compact = compact  # the layout of the system as left: prior_bias's
    stats = {"converged": info["converged"], "iterations": count["iterations"],
             "solves": count["solves"], "local_solves": count["local_solves"],
             "local_iterations": count["local_iterations"],
             "relative_residual": info["relative_residual"]}
    stats["free_space"] = {"passes": count["passes"], "settled": settled,
                           "anchored": n_anchored,
                           "lifted": count["lifted"],
                           "free_voxels": n_free,
                           "carved_voxels": int(carved.sum()) if carved is not None else 0}
    if "reason" in info:
        stats["reason"] = info["reason"]
    stats["residual_history"] = [float(r) for r in info.get("residual_history", [])]
    return np.asarray(mean, np.float32), stats


def prior_bias(system, band, prior, stencil: int, voxel_size_m: float, mean: np.ndarray,
               solver: SolverConfig) -> tuple[np.ndarray, dict]:
    """The MAP's bias under its prior, estimated at the mean: ``b = -Q^-1 (P mu - b0)``, (N,)
    float64 metres, and ``stats`` (iterations, converged, median and 90th percentile of
    ``|b|`` in metres).

    With ``Q = D + P`` (data and prior precision) and ``h = A^T W y + b0``, the MAP of data
    ``y = A x + e`` has the mean ``E[mu] = x - Q^-1 (P x - b0)``: the prior pulls it by the
    force it exerts on the truth. At the MAP that force equals the data's residual force
    ``A^T W (y - A mu)``. ``P mu - b0`` is computed from the prior alone
    (:func:`~.prior.prior_terms` on an empty stencil), so the data term need not be kept;
    ``system`` is the posterior's (without the free-space anchors, which enforce an
    inequality and are no prior; with the robust curvature prior, its Hessian at the mean,
    while the force is built at the weights its last reweighting left,
    :attr:`~.prior.System.curvature_weights`: the prior's slope). The solve stops at
    ``solver.probe_tol``: the bias enters a variance, like the probes."""
    from kernels.compact import CompactStencil
    from kernels.pcg import pcg
    from kernels.stencil import apply_Q

    from .prior import prior_terms

    P = np.zeros_like(system.S)
    b0, far = prior_terms(P, band, prior, stencil, voxel_size_m, system.curvature_weights)
    force = apply_Q(P, band.nbr, mean.astype(np.float64), far=far) - b0
    del P, far
    compact, system.compact = system.compact, None  # solve_map's layout, then let it go
    if compact is None:
        compact = CompactStencil(system.S, system.nbr, system.far, check=False)
    b, info = pcg(system.S, system.nbr, force, None, tol=solver.probe_tol,
                  maxiter=solver.maxiter, far=system.far, compact=compact)
    b = -b
    a = np.abs(b)
    stats = {"iterations": int(info["iterations"]), "converged": bool(info["converged"]),
             "median_m": float(np.median(a)) if len(a) else 0.0,
             "p90_m": float(np.quantile(a, 0.9)) if len(a) else 0.0}
    return b, stats
