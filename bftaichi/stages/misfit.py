"""The local-noise step of ``observation.local_noise`` (:func:`local_misfit`): after the solve,
every frame's samples near their pixel's surface are compared with the posterior mean, and the
excess of their residuals over the noise model, where it would move the surface, is added to
the variance."""

from __future__ import annotations

import numpy as np

__all__ = ["local_misfit", "surface_excess", "SLOPE_AGREEMENT"]


def local_misfit(observer, frames, mean: np.ndarray, var: np.ndarray, nbr: np.ndarray,
                 stride: int) -> tuple[np.ndarray, dict]:
    """How well the noise model explains the data around each band voxel.

    Every frame is observed again (same samples and weights as the data term) against the
    posterior mean; the samples within 1.5 voxels of their pixel's measured surface count
    (``kernels.dataterm.MISFIT_NEAR``): they fix the zero crossing, where the vertices lie,
    while farther ones carry the projective distance's own model error. Per voxel, the
    squared residuals of the pixels reaching it and what the model expects of them (their
    noise variance less the part the fit absorbs,
    :meth:`kernels.observe.Observer.misfit_sums`) are summed over the voxel and its 26
    neighbours (a 3-voxel window: a few pixels per voxel are too few for a variance). Their
    ratio ``chi2`` (mean squared residual over its expectation) tells:

    - ``chi2 > 1``: the data disagree with each other and with any surface the voxels can hold
      (thin sheets seen from both sides, occlusion edges, creases finer than a voxel,
      misregistered frames). The excess ``b^2 = mean r^2 - expected`` does not average down
      over the pixels: it is a bias of the mean there, added to the variance as it is, less
      the part of it that does not move the surface (:func:`surface_excess`).
    - ``chi2 < 1``: the data are quieter than the noise model says; the variance is kept. The
      ratio is an average over every sample in the window, and the quiet ones are mostly
      oblique pixels, whose modelled noise is floored (``cos_min``) and whose fitted extra
      noise is taken as isotropic, while the posterior variance is set mostly by the head-on
      pixels, which the model gets right; scaling the variance by it made sigma too small
      (docs/measurements.md).

    A voxel reached by less than one pixel's worth of samples in its window gets ``b = 0``.

    Returns ``(b2, stats)``: (N,) float32 metres^2, and ``voxels`` (with an estimate),
    ``median_chi2`` (a diagnostic), ``voxels_misfit`` (``b > 0``), ``p90_b_m``, ``voxels_line``
    (those whose residuals' line was taken out, :func:`surface_excess`).
    """
    for frame in frames:
        observer.misfit(frame.depth_m, frame.K, frame.T_W_C, mean, var, stride=stride)
    window = observer.misfit_window(nbr)  # (N, 7), or (N, 3), over the 27 voxels around each
    ok = window[:, 2] >= 1.0
    b2 = np.zeros(len(mean), np.float64)
    if window.shape[1] >= 7:
        b2[ok], line = surface_excess(window[ok])
    else:  # observation.model = "voxels": no distances to fit a line across (VoxelObserver)
        w = window[ok, 2]
        b2[ok], line = np.maximum(0.0, window[ok, 0] / w - window[ok, 1] / w), []
    chi2 = window[ok, 0] / window[ok, 1]
    stats = {"voxels": int(ok.sum()), "voxels_misfit": int(np.count_nonzero(b2 > 0)),
             "voxels_line": int(np.count_nonzero(line)),
             "median_chi2": float(np.median(chi2)) if ok.any() else None,
             "p90_b_m": float(np.sqrt(np.percentile(b2[ok], 90))) if ok.any() else None}
    return b2.astype(np.float32), stats


SLOPE_AGREEMENT = 0.5
"""Largest slope ``|g|`` of the residuals' line across ``y`` (no unit) at which the line is
taken as the mean's slope error and its part of the excess left out (:func:`surface_excess`):
the mean's slope along the rays within half of the data's either way."""


def surface_excess(window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The local misfit's excess at the surface, from the sums of a window
    (:meth:`kernels.observe.Observer.misfit_window`, rows with column 2 > 0): ``(b2, line)``,
    (M,) float64 metres^2 (>= 0) and (M,) bool.

    The samples reach 1.5 voxels either side of their pixel's surface, and the mean's error
    there grows with the distance ``y`` from it where the mean's slope differs from the data's
    (``tools/residual_profile.py``: 0.38 mm RMS at the surface, 0.59 a voxel away, on the bunny's
    grazing capture). That part of the excess ``mean r^2 - expected`` does not move the zero
    crossing, where the vertices lie: a line ``r = r0 + g y`` fitted to the window's residuals
    (weighted least squares, the misfit's weights) splits ``mean r^2`` into ``rbar^2 + g^2
    var(y) + scatter``, and the excess at the surface is ``r0^2 + scatter - expected``, that is
    the whole excess less ``g^2 var(y)``, with ``r0^2`` for ``rbar^2``. It is an error of the
    SDF's value; the mean's slope along the rays is the data's ``1 - g``, so the surface itself
    is off by that error over ``1 - g``, and ``b^2`` is the excess at the surface over ``(1 -
    g)^2``: a distance, as the vertex errors are.

    Where ``|g| > SLOPE_AGREEMENT`` the residuals' line is no slope error of a surface in the
    right place: the data disagree with the mean about the gradient itself (a sheet seen from
    both sides, whose mean is flattened between them; an occlusion edge), and the whole excess
    is kept (``line`` False). Measured on both suites in docs/measurements.md ("The misfit at
    the surface: the residuals' line taken out")."""
    w = window[:, 2]
    excess = (window[:, 0] - window[:, 1]) / w
    rbar, ybar = window[:, 3] / w, window[:, 4] / w
    var_y = np.maximum(window[:, 5] / w - ybar * ybar, 0.0)
    cov_ry = window[:, 6] / w - rbar * ybar
    spread = var_y > 1e-12 * np.maximum(window[:, 5] / w, 1e-300)  # y varies in the window
    g = np.divide(cov_ry, var_y, out=np.zeros_like(cov_ry), where=spread)
    line = spread & (np.abs(g) <= SLOPE_AGREEMENT)
    r0 = rbar - g * ybar
    at_surface = np.maximum(0.0, excess - g * cov_ry + r0 * r0 - rbar * rbar)
    # in distance: the mean's slope along the rays is the data's 1 - g (in [0.5, 1.5] here)
    at_surface /= np.where(line, 1.0 - g, 1.0) ** 2
    return np.where(line, at_surface, np.maximum(0.0, excess)), line
