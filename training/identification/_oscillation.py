"""Fit of the elastic mode of paper eq. 1 to the oscillating part of a record.

Paper eq. 1 splits the motor speed into the one-mass response and an oscillating part::

    w_osc(s) = (V_J / J_sigma) * s / (s^2 + 2 d w_0 s + w_0^2) * M(s)

For given ``(f_0, d)`` the response of the filter to the measured torque is computed exactly
(zero-order hold of the sampled torque, :mod:`training.identification._resonance`, many
``(f_0, d)`` in one call), and the gain ``g = V_J / J_sigma`` is linear: a least squares over the
section samples, with a constant per section as nuisance (variable projection). ``(f_0, d)`` are
found by a coarse log-frequency scan around the spectral peak and a bounded refinement. For a
linear elastic mechanic this recovers ``f_0``, ``d`` and ``V_J``
(with ``J_sigma`` from STEP 2); with backlash the fit degrades and its ``r2`` says so, which the
maps learn to use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize as _optimize

from training.identification._resonance import zoh_responses


@dataclass(frozen=True)
class OscillationFit:
    """``f_0`` [Hz], ``d`` [-], ``gain`` = ``V_J / J_sigma`` [1/(kg m^2)], ``r2`` (share of the
    ``w_osc`` variance explained, 0..1); all 0 when nothing could be fitted."""

    f_0: float
    d: float
    gain: float
    r2: float


_EMPTY = OscillationFit(0.0, 0.0, 0.0, 0.0)


class _Projector:
    """Variable projection over the section samples: ``y ~ g x + c_k`` (constant per section).

    With ``y`` centred per section, ``<x_c, y_c> = <x, y_c>`` and ``|x_c|^2 = |x|^2 - sum_k S_k^2 / L_k``
    (``S_k`` the section sums of ``x``), so a regressor is never centred itself."""

    def __init__(self, y: np.ndarray, bounds: np.ndarray) -> None:
        self.bounds = [(int(a), int(b)) for a, b in bounds if b > a]
        self.lengths = np.array([b - a for a, b in self.bounds])
        self.starts = np.concatenate([[0], np.cumsum(self.lengths)[:-1]])
        self.stop = max(b for _, b in self.bounds)
        index = np.concatenate([np.arange(a, b) for a, b in self.bounds])  # the section samples, end to end
        contiguous = bool(np.all(np.diff(index) == 1))
        self.index = slice(int(index[0]), int(index[-1]) + 1) if contiguous else index  # a slice copies nothing
        ys = y[self.index]
        self.yc = ys - np.repeat(np.add.reduceat(ys, self.starts) / self.lengths, self.lengths)
        self.sst = float(self.yc @ self.yc)

    def fit(self, X_full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gains and residual sums of squares ``K`` for the regressors ``X_full`` (``K x N``)."""
        X = X_full[:, self.index]  # K x n: the section samples
        sums = np.add.reduceat(X, self.starts, axis=1)  # K x sections
        xx = np.einsum("kn,kn->k", X, X) - (sums * sums) @ (1.0 / self.lengths)
        ok = xx > 0
        g = np.where(ok, X @ self.yc / np.where(ok, xx, 1.0), 0.0)
        return g, np.where(ok, np.maximum(self.sst - g * g * xx, 0.0), self.sst)


def fit_oscillation(torque: np.ndarray, w_osc: np.ndarray, bounds: np.ndarray, T_s: float,
                    f_guess: float, *, f_max: float | None = None) -> OscillationFit:
    """Fit eq. 1's oscillating part to ``w_osc`` (``N``) driven by ``torque`` (``N``) [Nm].

    Args:
        bounds: ``(K, 2)`` section ``[start, stop)`` indices; only those samples are fitted.
        f_guess: a likely frequency [Hz] (e.g. the spectral peak of ``w_osc``), added to the scan;
            <= 0: no oscillation to fit.
        f_max: highest frequency considered [Hz] (default 0.45 / T_s).
    """
    M = np.asarray(torque, dtype=np.float64)
    w = np.asarray(w_osc, dtype=np.float64)
    if M.shape != w.shape or M.ndim != 1:
        raise ValueError(f"fit_oscillation: expected torque and w_osc of one length, received {M.shape}, {w.shape}")
    bounds = np.asarray(bounds)
    if not f_guess > 0 or bounds.size == 0 or int((bounds[:, 1] - bounds[:, 0]).sum()) < 16:
        return _EMPTY
    proj = _Projector(w, bounds)
    if proj.sst <= 0:
        return _EMPTY
    M = M[: proj.stop]
    f_hi = 0.45 / T_s if f_max is None else float(f_max)

    def rss(log_f: float, d: float) -> float:
        return float(proj.fit(zoh_responses(M, np.array([math.exp(log_f)]), np.array([d]), T_s))[1][0])

    # scan the whole band on a log grid (the spectral peak alone misleads on weak or nonlinear
    # oscillations), and the guess itself; then refine
    duration = float(proj.lengths.max()) * T_s
    grid = np.linspace(math.log(max(1.0 / duration, 1.0)), math.log(f_hi), 48)
    grid = np.sort(np.append(grid, math.log(min(max(f_guess, math.exp(grid[0])), f_hi))))
    d = 0.03
    log_f = float(grid[int(np.argmin(proj.fit(zoh_responses(M, np.exp(grid), np.full(grid.size, d), T_s))[1]))])
    step = float(np.diff(grid).max())
    for _ in range(2):  # alternate 1-D refinements: frequency, damping
        log_f = float(_optimize.minimize_scalar(lambda lf: rss(lf, d), bounds=(log_f - step, log_f + step),
                                                method="bounded", options={"xatol": 1e-4}).x)
        step = min(step, 0.05)
        d = math.exp(float(_optimize.minimize_scalar(lambda ld: rss(log_f, math.exp(ld)),
                                                     bounds=(math.log(1e-3), math.log(0.6)), method="bounded",
                                                     options={"xatol": 1e-2}).x))
    f_0 = math.exp(log_f)
    g, r = (float(v[0]) for v in proj.fit(zoh_responses(M, np.array([f_0]), np.array([d]), T_s)))
    return OscillationFit(f_0=f_0, d=d, gain=g, r2=max(0.0, 1.0 - r / proj.sst))
