"""Step 4 of Algorithm 1: the GMRF prior added to the data term (DESIGN.md section 3.4), giving
the posterior's linear system ``Q mu = h`` on the band's stencil."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..checks import check_choice, check_range

__all__ = ["PriorConfig", "System", "add_prior", "prior_terms"]


@dataclass
class PriorConfig:
    """``[prior]``: the GMRF prior ``lam * sum w_ij (x_i - x_j)^2 + lam_b * sum (x_i - tsdf_i)^2``
    (+ a curvature term and the free-space constraint).

    Every strength is per voxel^2 (dimensionless per voxel) and divided by ``voxel_size^2``
    internally, so a prior means the same at every resolution: the prior standard deviation of
    the difference of two face neighbours is ``voxel_size / sqrt(lam)``. Measurements behind the
    defaults: docs/measurements.md."""

    lam: float = 0.01
    """Membrane (first-order smoothness) strength, per voxel^2. The membrane penalises the
    SDF's unit slope, so a strong one bends the surface where data ends (plane edges,
    silhouettes) and shrinks small curved objects: it is kept weak."""

    lam_b: float = 1.0
    """Anchor strength pulling anchored voxels to their TSDF value, per voxel^2."""

    anchors: str = "boundary"
    """Anchored voxels: ``none``, ``boundary`` (the band boundary, as in the paper) or ``all``
    (every observed voxel, weighted by its TSDF weight)."""

    free: float = 1000.0
    """Free-space constraint strength, per voxel^2 (0 = off). A voxel the bootstrap saw as free
    space (``tsdf > tau``, observed) cannot hold the surface: its SDF is positive. That is an
    inequality, so it is enforced by an active set (:mod:`.solve`): after the MAP, every such
    voxel whose mean is below half a voxel is anchored with this strength, to half a voxel
    or, the farther beyond ``tau`` its TSDF puts it, the more toward that TSDF value
    (:func:`.solve.anchor_target`), and the MAP is solved again. 1000 per voxel^2 is about
    the data term of 40 frames at 2 cm; 10 was too weak to hold the voxels against straddling
    samples."""

    carve: float = 0.4
    """Free space seen by the rays (0 = off): a voxel also counts as free space for the
    constraint above when at least this fraction of the frames that observe it, and at least
    two, saw it farther than the bootstrap truncation in front of their measured surface (the
    rays passed through it; :mod:`kernels.carve`, counted in the observation pass). The
    averaged TSDF alone misses the voxels beside thin parts and in gaps narrower than the
    truncation, which other frames place behind a surface: the data term, which samples only
    near each pixel's surface, then bent the posterior through zero there (surfaces bridged
    across gaps, thin parts fattened). Measured in docs/measurements.md."""

    curvature_scale: float = 0.25
    """Scale ``c`` of the robust curvature prior, in voxels (0 = the Gaussian prior). With
    ``c > 0`` each second difference ``d`` costs ``lam2 c^2 log(1 + d^2 / c^2)`` instead of
    ``lam2 d^2``: full strength where the field is smooth (``|d| << c``), letting go at creases
    and thin parts (``|d| >> c``). Solved by reweighting (:data:`ROBUST_PASSES` MAP solves);
    the variance is the Laplace approximation at the MAP, the penalty's own curvature ``(1 -
    u) / (1 + u)^2`` (``u = d^2 / c^2``, 0 where negative), not the reweighting's weights
    (:func:`kernels.prior.laplace_curvature_prior`). The default since issue 15's measurement
    of both suites with that variance (docs/measurements.md, "The robust prior's variance from
    its Hessian"): a lower CD and a more informative sigma than the Gaussian prior of 0.1."""

    noise_allowance: bool = True
    """The robust prior's Laplace curvature (the variance's; the mean does not change) takes
    each second difference ``d`` of the MAP at ``u = d^2 / (c^2 + a)`` instead of ``d^2 /
    c^2``: ``a`` is the variance the data's noise gives ``d`` in the MAP, from each voxel's
    ``D_ii / Q_ii^2`` (``D`` the data term, ``Q`` the MAP's system), so a bend no larger than
    the noise makes is not taken for a crease the prior lets go of
    (:func:`kernels.prior.laplace_curvature_prior`). Without it the sparse captures' sigma
    was too wide (80-86 % within 1 sigma); measured on both suites in docs/measurements.md,
    "The MAP's noise in the robust prior's Hessian"."""

    eps: float = 1e-4
    """``eps * I``, per voxel^2: keeps Q positive definite where nothing else does."""

    curvature: float = 0.5
    """Second-order (curvature) prior strength ``lam2``, per voxel^2: ``lam2 sum (x_{j-e} - 2
    x_j + x_{j+e})^2`` over the band's second differences along each axis (0 = off, the paper's
    model). It leaves a field of unit slope alone (only bending costs), so unlike the membrane
    it does not pull the SDF flat. The prior standard deviation of one second difference is
    ``voxel_size / sqrt(lam2)``; a sphere of radius R has second differences of about
    ``voxel^2 / R``. Without it (membrane alone) sigma was ~3x too large: the membrane is a
    vague prior for an SDF, whose neighbour differences are a full voxel."""

    def check(self) -> None:
        check_range("prior.curvature", self.curvature, 0.0)
        check_range("prior.lam", self.lam, 0.0)
        check_range("prior.curvature_scale", self.curvature_scale, 0.0, 100.0)
        check_range("prior.lam_b", self.lam_b, 0.0)
        check_range("prior.free", self.free, 0.0)
        check_range("prior.carve", self.carve, 0.0, 1.0)
        check_choice("prior.anchors", self.anchors, ("none", "boundary", "all"))
        check_range("prior.eps", self.eps, 0.0, lo_open=True)


@dataclass(eq=False)
class System:
    """The posterior's linear system ``Q mu = h`` in the stencil layout of :mod:`kernels.stencil`:
    ``S`` (N, 27) float32 entries of Q at the offsets ``{-1, 0, 1}^3``, ``nbr`` (N, 27) the band's
    neighbour table, ``far`` Q's entries at offsets +-2 (curvature prior; None without it),
    ``h`` (N,) float32."""

    S: np.ndarray
    nbr: np.ndarray
    h: np.ndarray
    far: tuple | None = None
    curvature_weights: np.ndarray | None = None
    """(N, 3) float32 weights of the robust curvature prior's second differences at the MAP,
    ``1 / (1 + d^2 / c^2)`` (``prior.curvature_scale > 0``; set by :func:`~.solve.solve_map`),
    None: all one. They give the prior's slope (its force, :func:`~.solve.prior_bias`); ``S``
    and ``far`` hold its curvature there instead (the Laplace approximation,
    :func:`kernels.prior.laplace_curvature_prior`)."""
    data_diagonal: np.ndarray | None = None
    """(N,) float32 ``D_ii``, the data term's diagonal before the prior was added (set by
    :func:`add_prior`): the robust prior's noise allowance (:attr:`PriorConfig.noise_allowance`)
    and the variance's data share read it. None: not known (no allowance)."""
    compact: object | None = None
    """The :class:`kernels.compact.CompactStencil` of ``(S, nbr, far)`` as
    :func:`~.solve.solve_map` left them (its free-space anchors taken out again), which
    :func:`~.solve.prior_bias` solves with instead of building it a second time (~0.2 s at 2
    cm on redkitchen) and then drops; None: build one."""


def add_prior(S: np.ndarray, h_data: np.ndarray, band, prior: PriorConfig, stencil: int,
              voxel_size_m: float) -> System:
    """Add the prior of ``prior`` (stencil 6/18/26) to the data term ``S`` (in place) and
    ``h_data``; return the :class:`System`. ``band``: the :class:`~.band.Band`."""
    from kernels.layout import CENTRE

    D = S[:, CENTRE].copy()
    b0, far = prior_terms(S, band, prior, stencil, voxel_size_m)
    h = (h_data.astype(np.float64) + b0).astype(np.float32)
    return System(S=S, nbr=band.nbr, h=h, far=far, data_diagonal=D)


def prior_terms(S: np.ndarray, band, prior: PriorConfig, stencil: int,
                voxel_size_m: float, curvature_weights: np.ndarray | None = None) -> tuple:
    """Add the prior's precision to ``S`` (N, 27), in place; return ``(b0, far)``: its part of
    the right-hand side (the anchors' pull to the TSDF), (N,) float32, and its entries at
    offsets +-2 (the curvature prior; None without it). ``curvature_weights``: the robust
    curvature prior's weights (:attr:`System.curvature_weights`; None: all one). On ``S = 0``
    this is the prior alone (:func:`~.solve.prior_bias`)."""
    from kernels.prior import add_curvature_prior
    from kernels.prior import add_prior as add_membrane

    scale = voxel_size_m ** 2  # strengths are per voxel^2
    b0 = np.zeros(len(band), np.float32)
    add_membrane(S, b0, band.nbr, band.tsdf, band.weight, lam=prior.lam / scale,
                 lam_b=prior.lam_b / scale, eps=prior.eps / scale, stencil=stencil,
                 anchors=prior.anchors)
    far = None
    if prior.curvature > 0:
        far = add_curvature_prior(S, band.nbr, lam2=prior.curvature / scale,
                                  weights=curvature_weights)
    return b0, far
