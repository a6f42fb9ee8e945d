"""The noise fit's model of a pair of frames that see one point
(:func:`.observe.estimate_extra_noise`): their residuals differ by ``d ~ N(0, s^2 + 2 e^2)``,
``s`` the two frames' sensor noise in quadrature and ``e`` the extra noise of each, and a pair
is kept only where ``|d| < t``, so the kept ``|d|`` are a normal's truncated at ``t``."""

from __future__ import annotations

import numpy as np

__all__ = ["pair_quantile", "fit_extra"]


def pair_quantile(r: np.ndarray, s: np.ndarray, t: np.ndarray, e: float) -> np.ndarray:
    """``P(|d'| <= r | |d'| <= t)`` for each pair, ``d'`` of its model with extra noise ``e``:
    uniform on [0, 1] where the model holds (without the truncation, ``median(r / sqrt(s^2 + 2
    e^2)) = 0.6745`` is its median of 1/2)."""
    from scipy.special import erf

    scale = np.sqrt(2.0 * (s * s + 2.0 * e * e))
    return erf(r / scale) / np.maximum(erf(t / scale), 1e-300)


def fit_extra(r: np.ndarray, s: np.ndarray, t: np.ndarray, steps: int = 40) -> float:
    """The extra noise ``e >= 0`` whose truncated pair model puts half the pairs' ``|d|``
    below their own (the median of :func:`pair_quantile` is 1/2); 0 when the sensor model
    alone does. ``steps`` bisections after the bracket (40: the root to ~1e-12 of it)."""
    def stat(e):
        return float(np.median(pair_quantile(r, s, t, e)))

    if stat(0.0) <= 0.5:
        return 0.0
    lo, hi = 0.0, max(float(np.median(r)) / 0.6744897501960817, 1e-6)
    while stat(hi) > 0.5 and hi < 1.0:  # heavy truncation: the root can lie further out
        hi *= 2.0
    for _ in range(steps):  # bisection: stat decreases with e
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stat(mid) > 0.5 else (lo, mid)
    return hi
