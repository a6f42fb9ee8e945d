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
    alone does. ``steps`` bisections after the bracket (40: the root to ~1e-12 of it).

    Each step's median is that of every pair, but it is computed over fewer and fewer of
    them (:class:`_Median`): a pair whose quantile stays below (above) the median throughout
    the bracket only counts, so the same bisection takes a fraction of the time."""
    stat = _Median(r, s, t)
    if stat(0.0) <= 0.5:
        return 0.0
    lo, hi = 0.0, max(float(np.median(r)) / 0.6744897501960817, 1e-6)
    while stat(hi) > 0.5 and hi < 1.0:  # heavy truncation: the root can lie further out
        hi *= 2.0
    stat.bracket(lo, hi)
    for _ in range(steps):  # bisection: stat decreases with e
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stat(mid) > 0.5 else (lo, mid)
        stat.bracket(lo, hi)
    return hi


class _Median:
    """``median(pair_quantile(r, s, t, e))`` over all the pairs, as :func:`numpy.median`
    computes it (the same value, bit for bit), for a sequence of ``e`` that a bisection
    narrows. Each pair's quantile decreases with ``e``, and so do the median's two middle
    order statistics; so while ``e`` stays within a bracket ``[lo, hi]`` whose ends were
    evaluated, a pair whose quantile at ``lo`` is below the lower middle statistic at ``hi``
    is below it everywhere in the bracket (and one whose quantile at ``hi`` is above the
    upper middle statistic at ``lo``, above it): :meth:`bracket` drops such pairs and counts
    them, and the middle statistics are then those of the rest at ranks shifted by the count
    below. A margin (:data:`MARGIN`, far beyond the quantiles' rounding) keeps a pair whose
    quantile is within it of the statistic."""

    MARGIN = 1e-9

    def __init__(self, r: np.ndarray, s: np.ndarray, t: np.ndarray):
        self.r, self.s, self.t = r, s, t
        n = len(r)
        self.ranks = (n // 2,) if n % 2 else (n // 2 - 1, n // 2)
        self.below = 0  # pairs dropped below the middle
        self.seen = {}  # e -> (quantiles of the pairs kept, middle statistics)

    def __call__(self, e: float) -> float:
        q = pair_quantile(self.r, self.s, self.t, e)
        if not len(q) or not np.isfinite(q).all():  # numpy's median of these (nan), as it is
            self.seen.clear()
            return float(np.median(q))
        kth = [k - self.below for k in self.ranks]
        middle = np.partition(q, kth)[kth]
        self.seen[e] = (q, middle)
        return float(np.mean(middle))

    def bracket(self, lo: float, hi: float) -> None:
        """The bisection's bracket is now ``[lo, hi]`` (both evaluated): drop the pairs
        outside the middle for every ``e`` within it, and forget the other evaluations."""
        if lo not in self.seen or hi not in self.seen:
            self.seen.clear()
            return
        (q_lo, mid_lo), (q_hi, mid_hi) = self.seen[lo], self.seen[hi]
        low = q_lo < mid_hi[0] - self.MARGIN  # below the lower middle statistic throughout
        high = q_hi > mid_lo[-1] + self.MARGIN  # above the upper one throughout
        keep = ~(low | high)
        self.below += int(np.count_nonzero(low))
        self.r, self.s, self.t = self.r[keep], self.s[keep], self.t[keep]
        self.seen = {lo: (q_lo[keep], mid_lo), hi: (q_hi[keep], mid_hi)}
