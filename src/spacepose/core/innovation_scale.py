"""Measurement-noise scale from a filter's own innovations (methods.md §2.4).

A measurement model gives each update a covariance ``R`` from first principles (the plane fit's
residual, the pixel pitch); the data can still be noisier than that, and, worse for a filter,
correlated from frame to frame: a face seen from nearly the same aspect is cut by the pixel grid
in nearly the same way, so its attitude error repeats. A Kalman filter that takes such errors as
independent averages them as if they were, and grows over-confident in what it learns slowly
(rate, inertia ratios, centre of mass).

:class:`InnovationScale` measures both effects on the innovations ``ν`` it is given (those the
filter accepted, or every one when another kind of measurement holds the prediction):

- the variance ratio by covariance matching: ``E[νᵀ R⁻¹ ν] = m f + tr(R⁻¹ H P Hᵀ)`` when the
  true covariance is ``f R``, so ``f̂ = mean(νᵀ R⁻¹ ν − tr(R⁻¹ H P Hᵀ)) / m``;
- the integrated autocorrelation time ``τ = 1 + 2 Σ_{k=1..K} ρ_k`` of the whitened innovations
  ``R^{-1/2} ν`` of the same measurement source (a catalogue face) ``k`` frames apart: the mean
  of ``n`` such samples has the variance of ``n / τ`` independent ones. The sum stops at the
  first ``K ≥ 5 τ(K)`` (Sokal's automatic window: long enough for the correlation, short
  enough not to sum the noise of the far lags).

The covariance the filter should use is then ``R · max(1, f̂ τ)``: never smaller than the
model's, which is the sensor's bound. The filter's own tracking removes part of the
correlation from its innovations, so ``τ`` measured on them is a lower bound of the error's.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["InnovationScale"]

# Sokal's window constant: sum the correlations up to the first lag K >= C * tau(K).
_WINDOW_C = 5.0
_MAX_LAG = 50


class InnovationScale:
    """Running factor on one kind of measurement covariance, from the filter's innovations.

    Parameters
    ----------
    window
        Number of the latest innovations kept.
    min_samples
        Updates needed before the factor leaves 1.
    """

    def __init__(self, window: int = 400, min_samples: int = 30) -> None:
        self.min_samples = int(min_samples)
        # (source, step, whitened innovation, excess νᵀR⁻¹ν − tr(R⁻¹HPHᵀ) per dimension)
        self._rows: deque[tuple[str, int, NDArray[np.float64], float]] = deque(maxlen=window)

    def add(
        self,
        source: str,
        step: int,
        innovation: ArrayLike,
        R: ArrayLike,
        HPHt: ArrayLike,
    ) -> None:
        """Record one update's innovation.

        Parameters
        ----------
        source
            What measured it (a catalogue face's name): correlation is taken within a source.
        step
            Index of the frame (consecutive frames differ by 1).
        innovation
            (m,) measured minus predicted, before the update.
        R
            (m, m) the model's measurement covariance (unscaled).
        HPHt
            (m, m) the prediction's covariance in measurement space, before the update.
        """
        nu = np.asarray(innovation, dtype=np.float64)
        L = np.linalg.cholesky(np.asarray(R, dtype=np.float64))
        w = np.linalg.solve(L, nu)
        prior = np.linalg.solve(L, np.linalg.solve(L, np.asarray(HPHt, np.float64)).T)
        excess = (float(w @ w) - float(np.trace(prior))) / len(nu)
        self._rows.append((source, int(step), w, excess))

    @property
    def variance_ratio(self) -> float:
        """``f̂``: the measured variance over the model's (1 until ``min_samples``)."""
        if len(self._rows) < self.min_samples:
            return 1.0
        return float(np.mean([row[3] for row in self._rows]))

    def correlations(self, max_lag: int = _MAX_LAG) -> NDArray[np.float64]:
        """``ρ_1 … ρ_max_lag`` (max_lag,): correlation of a source's whitened innovations
        ``lag`` frames apart, pooled over sources and components (0 for a lag without a pair).

        Each source's rows are laid on a dense run of steps, so every lag is one product of
        two shifted arrays.
        """
        num, den_a, den_b = np.zeros((3, max_lag))
        sources: dict[str, list[tuple[int, NDArray[np.float64]]]] = {}
        for source, step, w, _ in self._rows:
            sources.setdefault(source, []).append((step, w))
        for rows in sources.values():
            steps = np.array([step for step, _ in rows])
            first = int(steps.min())
            dense = np.zeros((int(steps.max()) - first + 1, len(rows[0][1])))
            dense[steps - first] = [w for _, w in rows]  # a repeated step keeps its last row
            present = np.zeros(len(dense), dtype=bool)
            present[steps - first] = True
            for lag in range(1, min(max_lag, len(dense) - 1) + 1):
                both = present[:-lag] & present[lag:]
                a, b = dense[:-lag][both], dense[lag:][both]
                num[lag - 1] += np.sum(a * b)
                den_a[lag - 1] += np.sum(a * a)
                den_b[lag - 1] += np.sum(b * b)
        rho = np.zeros(max_lag)
        ok = (den_a > 0.0) & (den_b > 0.0)
        rho[ok] = num[ok] / np.sqrt(den_a[ok] * den_b[ok])
        return rho

    def correlation(self, lag: int) -> float:
        """``ρ_lag`` alone (see :meth:`correlations`)."""
        return float(self.correlations(lag)[lag - 1])

    @property
    def correlation_time(self) -> float:
        """``τ``, in frames (≥ 1): how many consecutive innovations count as one."""
        if len(self._rows) < self.min_samples:
            return 1.0
        rho = self.correlations()
        tau = 1.0
        for lag in range(1, _MAX_LAG + 1):
            tau += 2.0 * rho[lag - 1]
            if lag >= _WINDOW_C * tau:
                break
        return max(tau, 1.0)

    @property
    def factor(self) -> float:
        """``max(1, f̂ τ)``: the multiplier of the model's covariance."""
        return max(1.0, self.variance_ratio * self.correlation_time)
