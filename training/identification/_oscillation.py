"""Fit of the elastic mode of paper eq. 1 to the oscillating part of a record.

Paper eq. 1 splits the motor speed into the one-mass response and an oscillating part::

    w_osc(s) = (V_J / J_sigma) * s / (s^2 + 2 d w_0 s + w_0^2) * M(s)

For given ``(f_0, d)`` the response of the filter to the measured torque is computed exactly
(zero-order hold of the sampled torque), and the gain ``g = V_J / J_sigma`` is linear: a least
squares over the section samples, with a constant per section as nuisance (variable
projection). ``(f_0, d)`` are found by a coarse log-frequency scan around the spectral peak and a
bounded refinement. For a linear elastic mechanic this recovers ``f_0``, ``d`` and ``V_J``
(with ``J_sigma`` from STEP 2); with backlash the fit degrades and its ``r2`` says so, which the
maps learn to use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize as _optimize
from scipy import signal as _signal


@dataclass(frozen=True)
class OscillationFit:
    """``f_0`` [Hz], ``d`` [-], ``gain`` = ``V_J / J_sigma`` [1/(kg m^2)], ``r2`` (share of the
    ``w_osc`` variance explained, 0..1); all 0 when nothing could be fitted."""

    f_0: float
    d: float
    gain: float
    r2: float


_EMPTY = OscillationFit(0.0, 0.0, 0.0, 0.0)


def _response(M: np.ndarray, f_0: float, d: float, T_s: float) -> np.ndarray:
    """Exact ZOH response of ``s / (s^2 + 2 d w0 s + w0^2)`` to the sampled torque ``M`` (``N``).

    The step response is ``exp(-sigma t) sin(w_d t) / w_d``; ZOH gives
    ``H(z) = (1 - z^-1) Z{step}`` = ``c (z^-1 - z^-2) / (1 - 2 r cos(w_d T) z^-1 + r^2 z^-2)``
    with ``r = exp(-sigma T)``, ``c = r sin(w_d T) / w_d``."""
    w0 = 2 * math.pi * f_0
    sigma, w_d = d * w0, w0 * math.sqrt(1.0 - d * d)
    r = math.exp(-sigma * T_s)
    c = r * math.sin(w_d * T_s) / w_d
    x = _signal.lfilter([0.0, c, -c], [1.0, -2 * r * math.cos(w_d * T_s), r * r], M)
    x[np.abs(x) < 1e-150] = 0.0  # decayed transients end in subnormals, which make later arithmetic 100x slower
    return x


class _Projector:
    """Variable projection over the section samples: ``y ~ g x + c_k`` (constant per section)."""

    def __init__(self, y: np.ndarray, bounds: np.ndarray) -> None:
        self.bounds = [(int(a), int(b)) for a, b in bounds if b > a]
        self.lengths = np.array([b - a for a, b in self.bounds])
        self.starts = np.concatenate([[0], np.cumsum(self.lengths)[:-1]])
        self.stop = max(b for _, b in self.bounds)
        self.yc = self._centered(np.concatenate([y[a:b] for a, b in self.bounds]))
        self.sst = float(self.yc @ self.yc)

    def _centered(self, v: np.ndarray) -> np.ndarray:
        means = np.add.reduceat(v, self.starts) / self.lengths
        return v - np.repeat(means, self.lengths)

    def fit(self, x_full: np.ndarray) -> tuple[float, float]:
        """Gain and residual sum of squares for the regressor ``x_full`` (``N``)."""
        xc = self._centered(np.concatenate([x_full[a:b] for a, b in self.bounds]))
        xx = float(xc @ xc)
        if xx <= 0:
            return 0.0, self.sst
        g = float(xc @ self.yc) / xx
        return g, max(self.sst - g * g * xx, 0.0)


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
        return proj.fit(_response(M, math.exp(log_f), d, T_s))[1]

    # scan the whole band on a log grid (the spectral peak alone misleads on weak or nonlinear
    # oscillations), and the guess itself; then refine
    duration = float(proj.lengths.max()) * T_s
    grid = np.linspace(math.log(max(1.0 / duration, 1.0)), math.log(f_hi), 48)
    grid = np.sort(np.append(grid, math.log(min(max(f_guess, math.exp(grid[0])), f_hi))))
    d = 0.03
    log_f = float(grid[int(np.argmin([rss(lf, d) for lf in grid]))])
    step = float(np.diff(grid).max())
    for _ in range(2):  # alternate 1-D refinements: frequency, damping
        log_f = float(_optimize.minimize_scalar(lambda lf: rss(lf, d), bounds=(log_f - step, log_f + step),
                                                method="bounded", options={"xatol": 1e-4}).x)
        step = min(step, 0.05)
        d = math.exp(float(_optimize.minimize_scalar(lambda ld: rss(log_f, math.exp(ld)),
                                                     bounds=(math.log(1e-3), math.log(0.6)), method="bounded",
                                                     options={"xatol": 1e-2}).x))
    f_0 = math.exp(log_f)
    g, r = proj.fit(_response(M, f_0, d, T_s))
    return OscillationFit(f_0=f_0, d=d, gain=g, r2=max(0.0, 1.0 - r / proj.sst))
