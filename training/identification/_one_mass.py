"""STEP 2: one-mass approximation of a drive record by least squares (paper section 3.1).

Model (SI units; linear units kg, N, m work the same way)::

    M(t) = J_sigma * dw/dt + mu_F * w + M_FC * sign(w) + M_0

with ``M`` the motor (air-gap) torque [Nm], ``w`` the motor speed [rad/s], ``J_sigma`` the total
inertia [kg m^2], ``mu_F`` the viscous friction [Nm s/rad], ``M_FC`` the Coulomb friction [Nm] and
``M_0`` an optional constant offset torque [Nm] (the EMPS benchmark's ``offset``).

Three formulations estimate the four numbers from one record:

- ``"trajectory"`` (default when sections are given): output error of the integrated model,
  ``w(t) = w0_k + (1/J_sigma) int_{t_k}^t (M - mu_F w - M_FC sign(w) - M_0) dt`` in section ``k``,
  linear in ``(1/J_sigma, mu_F/J_sigma, M_FC/J_sigma, M_0/J_sigma, w0_1..w0_K)``. The elastic
  oscillation (zero mean after each torque step, eq. 1) and the quantization are output noise.

- ``"integral"`` (default without sections): the torque balance integrated over windows ``[a, b]``::

      int_a^b M dt = J_sigma*(w(b) - w(a)) + mu_F*int_a^b w dt + M_FC*int_a^b sign(w) dt + M_0*(b - a)

  It needs no derivative of the (quantized) speed. Windows of lengths ``window * 2**j``
  (``j < n_scales``, hop half a window) are stacked, and the speed increment is the dependent
  variable (``w(b) - w(a)`` regressed on the integrals of torque, speed, sign and time): the
  elastic mode's oscillation and the speed quantization then sit in the equation error only,
  not in a regressor, so they do not bias ``J_sigma`` towards zero (errors-in-variables).
- ``"derivative"``: torque and speed through the same zero-phase low-pass (parallel filtering), the
  acceleration by central differences, then ordinary least squares sample by sample (the inverse
  dynamic model of the EMPS benchmark).

Near zero speed the sign term is undefined (stiction); rows (samples or windows) in which the
low-passed speed comes within ``speed_deadband`` of zero are left out of the fit.

Per section the smooth response ``w_bar`` is the one-mass model driven by the measured torque with
the overall parameters, started from a fitted initial speed and (``section_drift=True``) corrected
by a fitted constant torque per section (fitted together with the damped sin/cos of the
oscillation, which are then left out of ``w_bar``), so that ``w_osc = w_m - w_bar`` (paper eq. 1) keeps the
elastic oscillation and little else.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from scipy import signal as _signal

from training._settings import POSITIVE, check_settings
from training._checks import as_signal
from training.identification._result import IdentWarning

__all__ = ["OneMassFit", "SectionFit", "FORMULATIONS", "fit_one_mass", "speed_from_position", "section_bounds"]


@dataclass(frozen=True)
class SectionFit:
    """One section's part of the fit.

    ``start``/``stop``: sample indices, half open. ``w_bar0`` [rad/s]: fitted initial speed of
    ``w_bar``. ``M_drift`` [Nm]: fitted constant torque correction of this section (0 when
    ``section_drift=False``). ``J_sigma`` [kg m^2]: this section's own inertia estimate with the
    overall friction and offset (nan when the section's net torque is too small to tell).
    ``osc_rms`` [rad/s]: rms of ``w_osc`` in the section.
    """

    start: int
    stop: int
    w_bar0: float
    M_drift: float
    J_sigma: float
    osc_rms: float


@dataclass(frozen=True)
class OneMassFit:
    """Result of :func:`fit_one_mass`.

    Scalars in SI units (see module docstring). ``w_bar``, ``w_osc``: shape ``(N,)`` [rad/s];
    zero outside the sections. ``speed``: the speed used (``(N,)``; the differentiated position
    when a position was given). ``sections``: one :class:`SectionFit` per section.
    ``rel_residual``: rms equation error over the rms of the dependent variable (dimensionless):
    speed for ``"trajectory"`` (below 2 % for a good test-run fit), speed increments over short
    windows for ``"integral"`` (noise dominated: 7 % on EMPS), filtered torque for ``"derivative"``.
    ``std``: standard deviations of ``(J_sigma, mu_F, M_FC, M_0)`` from the least squares.
    ``warnings``: reasons (coded) to distrust the fit: any formulation's collinear regressors
    (variance inflation above :attr:`OneMassTrust.collinear_inflation`) or a residual above
    :attr:`OneMassTrust.uninformative_residual`; a ``"trajectory"`` fit's residual above 5 % or sections
    shorter than two periods of the oscillation; empty when none.
    """

    J_sigma: float
    M_FC: float
    mu_F: float
    M_0: float
    w_bar: np.ndarray
    w_osc: np.ndarray
    speed: np.ndarray
    sections: tuple[SectionFit, ...]
    rel_residual: float
    std: tuple[float, float, float, float]
    n_rows: int
    method: str
    warnings: tuple[IdentWarning, ...] = ()


def _lowpass(x: np.ndarray, cutoff: float, T_s: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass; returns ``x`` unchanged when the cutoff is at Nyquist."""
    wn = 2.0 * cutoff * T_s
    if wn >= 0.99 or x.size < 3 * (2 * order + 1):
        return x.copy()
    return _signal.sosfiltfilt(butter_sos(wn, order), x)


@lru_cache(maxsize=1024)
def butter_sos(wn: float, order: int = 4) -> np.ndarray:
    """Butterworth low-pass sections of ``order`` at normalized cutoff ``wn`` (cached: the design
    costs more than filtering a record)."""
    return _signal.butter(order, wn, output="sos")


@lru_cache(maxsize=256)
def hann(n: int) -> np.ndarray:
    """``np.hanning(n)``, cached and read-only (the spectral peaks window every section with it)."""
    w = np.hanning(n)
    w.flags.writeable = False
    return w


def speed_from_position(position: Any, T_s: float, cutoff: float | None = None) -> np.ndarray:
    """Speed ``(N,)`` [rad/s or m/s] from a position ``(N,)`` [rad or m] sampled at ``T_s`` [s].

    Zero-phase 4th-order Butterworth low-pass at ``cutoff`` [Hz] (default ``0.04/T_s``, i.e.
    40 Hz at 1 kHz), then central differences, as the EMPS benchmark does.
    """
    q = as_signal("position", position)
    _check_T_s(T_s)
    if q.size < 3:
        raise ValueError(f"position: expected at least 3 samples, received {q.size}")
    fc = 0.04 / T_s if cutoff is None else float(cutoff)
    return np.gradient(_lowpass(q, fc, T_s), T_s)


def _check_T_s(T_s: Any) -> None:
    if not isinstance(T_s, (int, float, np.floating)) or not np.isfinite(T_s) or T_s <= 0:
        raise ValueError(f"T_s: expected a positive sample time [s], received {T_s!r}")


def section_bounds(sections: Any, n: int) -> list[tuple[int, int]]:
    """Normalize ``sections`` to a list of ``(start, stop)`` sample indices within ``0..n``.

    Accepts ``None`` (the whole record), an object with a ``bounds`` attribute (a
    :class:`training.identification._sections.SectionSplit`), or a sequence of ``(start, stop)`` pairs / an
    array of shape ``(K, 2)``.
    """
    if sections is None:
        return [(0, n)]
    if hasattr(sections, "bounds"):
        sections = sections.bounds
    arr = np.asarray(sections)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
        raise ValueError(f"sections: expected (start, stop) pairs of shape (K, 2), received shape {arr.shape}")
    out = []
    for a, b in arr.tolist():
        a, b = int(a), int(b)
        if not 0 <= a < b <= n:
            raise ValueError(f"sections: expected 0 <= start < stop <= {n}, received ({a}, {b})")
        out.append((a, b))
    return out


def _cumint(x: np.ndarray, T_s: float) -> np.ndarray:
    """Trapezoidal cumulative integral, ``out[0] = 0``, shape ``(N,)``."""
    out = np.zeros_like(x)
    out[1:] = np.cumsum(0.5 * (x[1:] + x[:-1])) * T_s
    return out


def _windows(n: int, window: int, n_scales: int) -> tuple[np.ndarray, np.ndarray]:
    """Start/stop sample indices of windows of lengths ``window * 2**j``, ``j < n_scales``, hop half a window."""
    starts, stops = [], []
    L = max(1, window)
    for _ in range(n_scales):
        if L >= n:
            break
        a = np.arange(0, n - L, max(1, L // 2))
        starts.append(a)
        stops.append(a + L)
        L *= 2
    if not starts:
        return np.array([0]), np.array([n - 1])
    return np.concatenate(starts), np.concatenate(stops)


def _residual_frequency(r: np.ndarray, bounds: list[tuple[int, int]], T_s: float) -> float:
    """Median over sections of the dominant frequency [Hz] of ``r`` (sections concatenated)."""
    out, pos = [], 0
    for a, b in bounds:
        seg = r[pos:pos + b - a]
        pos += b - a
        if seg.size < 16:
            continue
        seg = (seg - seg.mean()) * hann(seg.size)
        nfft = 1 << int(np.ceil(np.log2(4 * seg.size)))
        A = np.abs(np.fft.rfft(seg, nfft))
        f = np.fft.rfftfreq(nfft, T_s)
        band = (f >= 0.5 / (seg.size * T_s)) & (f <= 0.45 / T_s)
        if band.any() and A[band].max() > 0:
            out.append(float(f[band][np.argmax(A[band])]))
    return float(np.median(out)) if out else 0.0


def _osc_pairs(bounds: list[tuple[int, int]], T_s: float, f: float, ds: tuple[float, ...]) -> list[np.ndarray]:
    """Damped sin/cos at ``f`` [Hz], one pair per relative damping in ``ds``, restarted per section,
    the sections laid end to end: ``(sum N_k, 2)`` each (each section's pair is its own two regressors)."""
    tt = np.concatenate([np.arange(b - a) for a, b in bounds]) * T_s
    w_d = 2 * np.pi * f
    sin_cos = np.stack([np.sin(w_d * tt), np.cos(w_d * tt)], axis=1)
    return [np.exp(-(d * w_d / np.sqrt(1 - d * d)) * tt)[:, None] * sin_cos for d in ds]


@dataclass(frozen=True)
class _SectionDesign:
    """The trajectory fit's regressors by their structure, the sections' rows laid end to end: dense
    columns ``D`` ``(n, p)``, one constant per section (``K`` columns) and, with ``O`` ``(n, 2)``, a
    damped sin/cos pair per section (``2K`` columns, sin and cos of section ``k`` at ``p + K + 2k``).
    Its Gram matrix and products skip the zeros of the dense ``n x (p + 3K)`` matrix."""

    D: np.ndarray
    lengths: np.ndarray  # K: rows per section
    O: np.ndarray | None = None

    @cached_property
    def starts(self) -> np.ndarray:
        """K: the first row of each section."""
        return np.concatenate([[0], np.cumsum(self.lengths)[:-1]])

    @property
    def width(self) -> int:
        return self.D.shape[1] + len(self.lengths) * (1 if self.O is None else 3)

    def _blocks(self, v: np.ndarray) -> np.ndarray:
        """Per-section sums of ``v`` ``(n, ...)`` -> ``(K, ...)``."""
        return np.add.reduceat(v, self.starts, axis=0)

    def gram(self) -> np.ndarray:
        """``X^T X`` ``(m, m)``."""
        p, K = self.D.shape[1], len(self.lengths)
        G = np.zeros((self.width, self.width))
        G[:p, :p] = self.D.T @ self.D
        G[:p, p:p + K] = self._blocks(self.D).T
        G[p:p + K, p:p + K] = np.diag(self.lengths.astype(np.float64))
        if self.O is not None:
            o = p + K + 2 * np.arange(K)  # the sin column of each section
            for j in range(2):
                G[:p, o + j] = self._blocks(self.D * self.O[:, j:j + 1]).T
                G[p + np.arange(K), o + j] = self._blocks(self.O[:, j])
                for i in range(2):
                    G[o + i, o + j] = self._blocks(self.O[:, i] * self.O[:, j])
        upper = np.triu(G, 1)
        return np.triu(G) + upper.T

    def rmatvec(self, y: np.ndarray) -> np.ndarray:
        """``X^T y`` ``(m,)``."""
        parts = [self.D.T @ y, self._blocks(y)]
        if self.O is not None:
            parts.append(self._blocks(self.O * y[:, None]).reshape(-1))  # K x 2 -> sin, cos per section
        return np.concatenate(parts)

    def matvec(self, theta: np.ndarray) -> np.ndarray:
        """``X theta`` ``(n,)``."""
        p, K = self.D.shape[1], len(self.lengths)
        out = self.D @ theta[:p] + np.repeat(theta[p:p + K], self.lengths)
        if self.O is not None:
            sc = theta[p + K:].reshape(K, 2)
            out += (self.O * np.repeat(sc, self.lengths, axis=0)).sum(1)
        return out


def _lstsq_normal(G: np.ndarray, b: np.ndarray, y: np.ndarray,
                  predict: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """Column-scaled least squares from the normal equations ``G = X^T X``, ``b = X^T y``
    (``predict(theta) = X theta``); returns parameters, their std, rms residual.

    The normal equations of the unit-norm columns, factored by Cholesky (``R^T R``, the R of a QR
    of the scaled ``X``): half the flops of Householder QR on these tall matrices and, with the
    columns scaled, accurate to ~1e-8 relative in float64 for the condition numbers met here."""
    scale = np.sqrt(np.diag(G)).copy()
    scale[scale == 0] = 1.0
    Gs = G / np.outer(scale, scale)
    p = Gs.shape[1]
    if y.size < p:
        raise ValueError(f"one-mass fit: expected at least {p} rows, received {y.size}")
    try:
        R = np.linalg.cholesky(Gs).T  # upper
        d = np.abs(np.diag(R))
        rank = int(np.sum(d > 1e-7 * max(float(d.max(initial=0.0)), 1e-300)))
    except np.linalg.LinAlgError:
        rank = -1
    if rank < p:
        raise ValueError(
            f"one-mass fit: expected an informative record (regressor rank {p}), received "
            f"{'a rank-deficient regressor' if rank < 0 else f'rank {rank}'}; "
            "the speed must change sign or vary enough to separate inertia, friction and offset "
            "(fit_one_mass in Python: try offset=False)")
    theta = np.linalg.solve(Gs, b / scale) / scale
    r = y - predict(theta)
    sigma2 = float(r @ r) / max(1, y.size - p)
    Rinv = np.linalg.inv(R)
    std = np.sqrt(sigma2 * np.sum(Rinv * Rinv, axis=1)) / scale
    return theta, std, float(np.sqrt(np.mean(r * r)))


@dataclass(frozen=True)
class OneMassTrust:
    """When STEP 2's one-mass fit is not trusted (its coded warnings)."""

    #: the variance inflation ``1 / (1 - R^2)`` of a parameter's regressor on the others above which
    #: the parameter is not determined (test runs: at most 10^2.4; a speed that never reverses makes
    #: Coulomb friction and offset collinear: 10^5 and more).
    collinear_inflation: float = 1e4
    #: the relative residual above which the one-mass model explains too little to be trusted (the
    #: trajectory fit of a test run: below 0.05; the integral form on EMPS: 0.07).
    uninformative_residual: float = 0.5
    #: the trajectory fit's relative residual above which the record is not one mass.
    trajectory_residual: float = 0.05
    #: the trajectory fit's relative residual above which short sections are checked.
    short_sections_residual: float = 0.01
    #: the periods of the oscillation the shortest test section must hold for the trajectory fit to
    #: be trusted (shorter, and the fit reads about the motor's inertia: the load has not followed yet).
    section_periods: float = 2.0

    def __post_init__(self) -> None:
        check_settings(self, {"collinear_inflation": POSITIVE, "uninformative_residual": POSITIVE,
                              "trajectory_residual": POSITIVE, "short_sections_residual": POSITIVE,
                              "section_periods": POSITIVE})


#: STEP 2's trust thresholds.
TRUST = OneMassTrust()
#: :attr:`OneMassTrust.section_periods` of :data:`TRUST` (the refinement's free stage reads it).
SECTION_PERIODS = TRUST.section_periods
_PARAMETERS = ("J_sigma", "mu_F", "M_FC", "M_0")


def _trust_warnings(G: np.ndarray, n_par: int, rel: float) -> tuple[IdentWarning, ...]:
    """Reasons to distrust any formulation's fit with regressors of Gram matrix ``G = X^T X`` (the
    first ``n_par`` columns carry ``J_sigma, mu_F, M_FC, M_0``): collinear regressors, a residual
    near the signal's rms."""
    scale = np.sqrt(np.diag(G))
    scale = np.where(scale > 0, scale, 1.0)
    try:
        inflation = np.diag(np.linalg.inv(G / np.outer(scale, scale)))[:n_par]
    except np.linalg.LinAlgError:
        inflation = np.full(n_par, np.inf)
    out = []
    collinear = [_PARAMETERS[j] for j in range(n_par) if not inflation[j] < TRUST.collinear_inflation]
    if collinear:
        out.append(IdentWarning("one_mass_fit_collinear", f"one-mass fit: the regressors of {', '.join(collinear)} are "
                                "nearly collinear (does the speed never reverse? fit_one_mass in Python: "
                                "offset=False): those values are not determined by this record"))
    if rel > TRUST.uninformative_residual:
        out.append(IdentWarning("one_mass_fit_uninformative", f"one-mass fit: residual {rel:.2f} of the signal's rms: "
                                "the model explains little of this record (noisy current, too little acceleration?); "
                                "J_sigma and friction cannot be trusted"))
    return tuple(out)


@dataclass(frozen=True)
class _Signals:
    """One record, checked, as every formulation sees it (arrays ``(N,)``)."""

    M: np.ndarray  # torque [Nm]
    w: np.ndarray  # speed [rad/s]
    w_lp: np.ndarray  # low-passed speed [rad/s]
    sgn: np.ndarray  # sign of w_lp, 0 within the deadband
    moving: np.ndarray  # bool: |w_lp| above the deadband
    in_sec: np.ndarray  # bool: inside a section
    bounds: list[tuple[int, int]]
    T_s: float
    cutoff: float  # low-pass cutoff [Hz]
    dead: float  # speed deadband [rad/s]
    n_par: int  # 4 with the offset M_0, else 3


@dataclass(frozen=True)
class _Options:
    """The formulation-specific options of :func:`fit_one_mass`."""

    window: int | None
    n_scales: int
    oscillation: bool


@dataclass(frozen=True)
class _Estimate:
    """What a formulation estimates; ``sgn``: the speed sign the friction acts with (the trajectory
    formulation refines it); ``f_osc``, ``d_osc``: the oscillation it fitted as a nuisance (0: none)."""

    J_sigma: float
    mu_F: float
    M_FC: float
    M_0: float
    std: tuple[float, ...]
    rel_residual: float
    n_rows: int
    sgn: np.ndarray
    f_osc: float = 0.0
    d_osc: float = 0.0
    warnings: tuple[IdentWarning, ...] = ()


def _inverse_inertia_values(theta: np.ndarray, std: np.ndarray, n_par: int,
                            sign: float) -> tuple[float, float, float, float, tuple[float, ...]]:
    """``J_sigma, mu_F, M_FC, M_0`` and their standard deviations from a fit whose parameters are
    ``(1/J_sigma, sign mu_F/J_sigma, sign M_FC/J_sigma, sign M_0/J_sigma)`` (the first ``n_par``)."""
    if not theta[0] > 0:
        raise ValueError(f"one-mass fit: expected a positive inertia, received 1/J_sigma = {theta[0]:.4g}; "
                         "the record does not excite the inertia")
    J_sigma = float(1.0 / theta[0])
    p = sign * theta[:n_par] * J_sigma
    sd, th = std[:n_par], theta[:n_par]
    std_p = np.abs(p) * np.sqrt((sd / np.where(th == 0, 1, th)) ** 2 + (sd[0] / theta[0]) ** 2)
    std_p[0] = sd[0] / theta[0] ** 2
    M_0 = float(p[3]) if n_par == 4 else 0.0
    return J_sigma, float(p[1]), float(p[2]), M_0, tuple(float(v) for v in std_p) + ((0.0,) if n_par == 3 else ())


def _fit_integral(s: _Signals, opt: _Options) -> _Estimate:
    """The integrated torque balance over windows, the speed increment as the dependent variable."""
    n, T_s = s.w.size, s.T_s
    L = max(4, int(round(0.005 / T_s))) if opt.window is None else int(opt.window)
    if L < 1:
        raise ValueError(f"window: expected >= 1 samples, received {opt.window}")
    C_M, C_w, C_s, C_1 = _cumint(s.M, T_s), _cumint(s.w, T_s), _cumint(s.sgn, T_s), np.arange(n) * T_s
    # a window is usable when every sample in it is moving and belongs to a section
    bad = np.concatenate([[0], np.cumsum(~(s.moving & s.in_sec))])
    ia, ib = _windows(n, L, opt.n_scales)
    ok = (bad[ib + 1] - bad[ia]) == 0
    ia, ib = ia[ok], ib[ok]
    if ia.size < s.n_par:
        raise ValueError(f"one-mass fit: expected >= {s.n_par} usable windows away from zero speed, received {ia.size}")
    X = np.stack([C_M[ib] - C_M[ia], C_w[ib] - C_w[ia], C_s[ib] - C_s[ia], C_1[ib] - C_1[ia]], axis=1)[:, :s.n_par]
    y = s.w[ib] - s.w[ia]
    # speed-increment regression: the elastic oscillation enters the dependent variable only
    G = X.T @ X
    theta, std, rms = _lstsq_normal(G, X.T @ y, y, lambda th: X @ th)
    J_sigma, mu_F, M_FC, M_0, std_t = _inverse_inertia_values(theta, std, s.n_par, -1.0)
    rel = rms / max(float(np.sqrt(np.mean(y * y))), 1e-300)
    return _Estimate(J_sigma, mu_F, M_FC, M_0, std_t, rel, int(X.shape[0]), s.sgn,
                     warnings=_trust_warnings(G, s.n_par, rel))


def _trajectory_rows(s: _Signals, sgn: np.ndarray) -> tuple[_SectionDesign, np.ndarray]:
    """Regressors and speeds of the output error per section:
    ``w(t) = w0_k + (1/J) int_{t_k}^t (M - mu_F w - M_FC sgn - M_0) dt`` (``w0_k``: the section's constant)."""
    T_s, n = s.T_s, s.w.size
    C_M, C_w, C_1, C_s = _cumint(s.M, T_s), _cumint(s.w, T_s), np.arange(n) * T_s, _cumint(sgn, T_s)
    idx = np.concatenate([np.arange(a0, b0) for a0, b0 in s.bounds])  # the sections' samples, end to end
    first = np.repeat([a0 for a0, _ in s.bounds], [b0 - a0 for a0, b0 in s.bounds])  # each row's section start
    D = np.stack([C_M[idx] - C_M[first], -(C_w[idx] - C_w[first]), -(C_s[idx] - C_s[first]),
                  -(C_1[idx] - C_1[first])], axis=1)[:, :s.n_par]  # n x n_par
    return _SectionDesign(D, np.array([b0 - a0 for a0, b0 in s.bounds])), s.w[idx]


def _fit_trajectory(s: _Signals, opt: _Options) -> _Estimate:
    """Output error of the integrated model per section, in two passes: pass 2 with the sign of the
    fitted smooth speed (a proxy of the load speed, which the friction acts on) and, with
    ``oscillation``, damped sin/cos nuisance regressors per section at the residual's dominant
    frequency (the eq.-1 oscillation, so that it does not leak into the slopes that carry inertia
    and friction)."""
    idx = np.concatenate([np.arange(a0, b0) for a0, b0 in s.bounds])
    sgn, f_osc, d_osc = s.sgn, 0.0, 0.0
    for _pass in range(2):
        X, y = _trajectory_rows(s, sgn)
        G = X.gram()
        w_model = np.array(s.w_lp)
        if _pass == 1 and f_osc > 0:
            best = None
            tries = (0.0, 0.03, 0.1)
            for d_try, O in zip(tries, _osc_pairs(s.bounds, s.T_s, f_osc, tries)):
                Xo = replace(X, O=O)
                th_o, sd_o, rms_o = _lstsq_normal(Xo.gram(), Xo.rmatvec(y), y, Xo.matvec)
                if best is None or rms_o < best[2]:
                    best = (th_o, sd_o, rms_o, d_try)
            theta, std, rms, d_osc = best
            w_model[idx] = X.matvec(theta[:X.width])
        else:
            theta, std, rms = _lstsq_normal(G, X.rmatvec(y), y, X.matvec)
            w_model[idx] = X.matvec(theta)
            if opt.oscillation:
                f_osc = _residual_frequency(y - w_model[idx], s.bounds, s.T_s)
        sgn = np.where(np.abs(w_model) > s.dead, np.sign(w_model), 0.0)
    J_sigma, mu_F, M_FC, M_0, std_t = _inverse_inertia_values(theta, std, s.n_par, 1.0)
    rel = rms / max(float(np.sqrt(np.mean((y - y.mean()) ** 2))), 1e-300)
    return _Estimate(J_sigma, mu_F, M_FC, M_0, std_t, rel, int(y.size), sgn, f_osc, d_osc,
                     _trajectory_warnings(rel, f_osc, s.bounds, s.T_s) + _trust_warnings(G, s.n_par, rel))


def _trajectory_warnings(rel: float, f_osc: float, bounds: list[tuple[int, int]],
                         T_s: float) -> tuple[IdentWarning, ...]:
    """Reasons to distrust a trajectory fit: residual above 5 %, sections shorter than two periods."""
    warns = []
    if rel > TRUST.trajectory_residual:
        warns.append(IdentWarning("one_mass_fit_residual", f"one-mass fit residual is {100 * rel:.1f} % of the "
                                  "signal: the record is not well described by one mass (oscillation too large?)"))
    if f_osc > 0 and rel > TRUST.short_sections_residual:
        shortest = min(b - a for a, b in bounds) * T_s
        if shortest * f_osc < TRUST.section_periods:
            warns.append(IdentWarning("one_mass_fit_short_sections",
                                      f"shortest section ({1e3 * shortest:.0f} ms) holds fewer than two periods of "
                                      f"the {f_osc:.3g} Hz oscillation: lower M* or raise w_max"))
    return tuple(warns)


def _fit_derivative(s: _Signals, opt: _Options) -> _Estimate:
    """Filtered torque against the differentiated filtered speed, sample by sample."""
    Mf = _lowpass(s.M, s.cutoff, s.T_s)
    acc = np.gradient(s.w_lp, s.T_s)
    use = s.moving & s.in_sec
    if int(use.sum()) < s.n_par:
        raise ValueError(f"one-mass fit: expected >= {s.n_par} samples away from zero speed, received {int(use.sum())}")
    X = np.stack([acc, s.w_lp, s.sgn, np.ones(s.w.size)], axis=1)[use][:, :s.n_par]
    y = Mf[use]
    G = X.T @ X
    theta, std, rms = _lstsq_normal(G, X.T @ y, y, lambda th: X @ th)
    J_sigma, mu_F, M_FC = (float(v) for v in theta[:3])
    M_0 = float(theta[3]) if s.n_par == 4 else 0.0
    std_t = tuple(float(v) for v in std) + ((0.0,) if s.n_par == 3 else ())
    rel = rms / max(float(np.sqrt(np.mean(y * y))), 1e-300)
    return _Estimate(J_sigma, mu_F, M_FC, M_0, std_t, rel, int(X.shape[0]), s.sgn,
                     warnings=_trust_warnings(G, s.n_par, rel))


#: The formulations of :func:`fit_one_mass` (see the module docstring), by ``method`` name.
FORMULATIONS: dict[str, Callable[[_Signals, _Options], _Estimate]] = {
    "trajectory": _fit_trajectory,
    "integral": _fit_integral,
    "derivative": _fit_derivative,
}


def _signals(torque: Any, speed: Any, T_s: float, sections: Any, offset: bool, position: Any,
             speed_deadband: float | None, cutoff: float | None) -> _Signals:
    """Check the inputs of :func:`fit_one_mass` and prepare what the formulations share."""
    _check_T_s(T_s)
    M = as_signal("torque", torque)
    if speed is None:
        if position is None:
            raise ValueError("fit_one_mass: expected speed or position, received neither")
        w = speed_from_position(position, T_s)
        if w.size != M.size:
            raise ValueError(f"position: expected {M.size} samples like torque, received {w.size}")
    else:
        w = as_signal("speed", speed)
        if w.size != M.size:
            raise ValueError(f"speed: expected {M.size} samples like torque, received {w.size}")
    n = M.size
    if n < 16:
        raise ValueError(f"fit_one_mass: expected at least 16 samples, received {n}")
    if not np.ptp(w) > 0:
        raise ValueError("fit_one_mass: expected a varying speed, received a constant speed")
    bounds = section_bounds(sections, n)
    fc = 0.02 / T_s if cutoff is None else float(cutoff)
    w_lp = _lowpass(w, fc, T_s)
    dead = 0.005 * float(np.max(np.abs(w_lp))) if speed_deadband is None else float(speed_deadband)
    in_sec = np.zeros(n, dtype=bool)
    for a, b in bounds:
        in_sec[a:b] = True
    return _Signals(M=M, w=w, w_lp=w_lp, sgn=np.where(np.abs(w_lp) > dead, np.sign(w_lp), 0.0),
                    moving=np.abs(w_lp) > dead, in_sec=in_sec, bounds=bounds, T_s=T_s, cutoff=fc, dead=dead,
                    n_par=4 if offset else 3)


def _smooth_response(s: _Signals, est: _Estimate, section_drift: bool) -> tuple[np.ndarray, tuple[SectionFit, ...]]:
    """``w_bar`` ``(N,)`` (the one-mass model per section, see the module docstring) and the sections' fits."""
    w, T_s = s.w, s.T_s
    w_bar = np.zeros(w.size)
    acc_torque = s.M - est.mu_F * s.w_lp - est.M_FC * est.sgn - est.M_0  # accelerating torque [Nm]
    C_acc = _cumint(acc_torque, T_s)
    sec_fits = []
    for a, b in s.bounds:
        tt = np.arange(b - a) * T_s
        base = (C_acc[a:b] - C_acc[a]) / est.J_sigma
        cols = [np.ones(b - a)] + ([tt / est.J_sigma] if section_drift and b - a > 2 else [])
        A = np.stack(cols, axis=1)
        # the oscillation's sin/cos take part in the fit (so the drift cannot absorb it) but not in w_bar
        extra = (_osc_pairs([(a, b)], T_s, est.f_osc, (est.d_osc,))[0] if est.f_osc > 0 and b - a > 8
                 else np.zeros((b - a, 0)))
        coef, *_ = np.linalg.lstsq(np.concatenate([A, extra], axis=1), w[a:b] - base, rcond=None)
        coef = coef[:A.shape[1]]
        w_bar[a:b] = base + A @ coef
        drift = float(coef[1]) if len(coef) > 1 else 0.0
        # section's own inertia with the overall friction
        dw = w[b - 1] - w[a]
        num = C_acc[b - 1] - C_acc[a]
        J_k = float(num / dw) if abs(dw) > 1e-6 * max(float(np.max(np.abs(w))), 1e-300) else float("nan")
        osc = w[a:b] - w_bar[a:b]
        sec_fits.append(SectionFit(a, b, float(coef[0]), drift, J_k, float(np.sqrt(np.mean(osc * osc)))))
    return w_bar, tuple(sec_fits)


def fit_one_mass(
    torque: Any,
    speed: Any,
    T_s: float,
    *,
    sections: Any = None,
    offset: bool = True,
    position: Any = None,
    method: str = "auto",
    window: int | None = None,
    speed_deadband: float | None = None,
    cutoff: float | None = None,
    n_scales: int = 2,
    section_drift: bool = True,
    oscillation: bool = True,
) -> OneMassFit:
    """Least-squares one-mass approximation (STEP 2) of one record.

    Args:
        torque: ``(N,)`` motor torque [Nm] (or ``current * K_M``; force [N] for linear axes).
        speed: ``(N,)`` measured motor speed [rad/s], or ``None`` when ``position`` is given.
        T_s: sample time [s].
        sections: ``None`` (one section: the whole record), a ``SectionSplit``, or ``(K, 2)``
            ``(start, stop)`` sample indices. The overall fit uses the samples of all sections.
        offset: estimate the constant offset torque ``M_0`` (else ``M_0 = 0``).
        position: ``(N,)`` position [rad or m]; used for the speed (see
            :func:`speed_from_position`) when ``speed`` is ``None``.
        method: ``"trajectory"`` (output error of the integrated model per section with a free
            initial speed per section; best on test-signal records), ``"integral"`` (windows of the
            integrated torque balance; best on long records with many reversals such as EMPS),
            ``"derivative"`` (filtered, differentiated speed), or ``"auto"``: ``"trajectory"``
            when ``sections`` is given, else ``"integral"``.
        window: shortest integration window [samples] (default ``round(5 ms / T_s)``, at least 4).
        speed_deadband: rows whose low-passed speed is within this of zero are left out [rad/s]
            (default 0.5 % of the largest low-passed speed).
        cutoff: low-pass cutoff [Hz] for the sign of the speed and the derivative formulation
            (default ``0.02/T_s``: 80 Hz at 4 kHz, 20 Hz at 1 kHz).
        n_scales: number of window lengths (``window * 2**j``, ``j < n_scales``) in the
            integral formulation; longer windows average an elastic mode better, shorter ones
            follow unmodelled friction effects less (EMPS: 2 is best).
        oscillation: (``"trajectory"`` only) add damped sin/cos regressors per section at the
            first pass's residual frequency, so that a strong elastic oscillation does not bias the
            friction estimates; they are not part of ``w_bar``.
        section_drift: fit a constant torque correction per section for ``w_bar``.

    Returns:
        :class:`OneMassFit`.

    Raises:
        ValueError: bad shapes, non-finite input, too few samples, or an uninformative record.
    """
    if method != "auto" and method not in FORMULATIONS:
        raise ValueError(f"method: expected 'auto' or one of {sorted(FORMULATIONS)}, received {method!r}")
    s = _signals(torque, speed, T_s, sections, offset, position, speed_deadband, cutoff)
    if method == "auto":
        method = "integral" if sections is None else "trajectory"
    est = FORMULATIONS[method](s, _Options(window, n_scales, oscillation))
    if not est.J_sigma > 0:
        raise ValueError(f"one-mass fit: expected a positive inertia, received J_sigma = {est.J_sigma:.4g}; "
                         "the record does not excite the inertia")
    w_bar, sec_fits = _smooth_response(s, est, section_drift)
    w_osc = np.where(s.in_sec, s.w - w_bar, 0.0)
    return OneMassFit(est.J_sigma, est.M_FC, est.mu_F, est.M_0, w_bar, w_osc, s.w, sec_fits, float(est.rel_residual),
                      est.std, est.n_rows, method, est.warnings)
