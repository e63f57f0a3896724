"""Rule R7d: the measured frequency response narrows the set's intervals (model invalidation).

The identification's calibrated 90 % intervals bound ``f_e``, ``V_J`` and ``d`` from the test run
alone. Where the plant's frequency response was measured (:mod:`._frf`), the two-mass mechanics on
a grid over those intervals are held against it on the trusted lines around the resonance: per
mechanic ``k`` the residual ``r = log(G / G_k)`` (complex: magnitude and phase) of each line,
weighted by the line's relative variance ``(1 - coherence) / coherence`` (at least ``floor^2``),
gives ``chi2_k = sum |r|^2 / var``. Kept are the mechanics inside the profile-likelihood region of
the best one, ``chi2_k <= chi2_min + q s^2``: ``q`` the chi-square quantile of ``confidence`` for
the three parameters, ``s^2 = max(1, chi2_min / (2 n - 3))`` over the ``n`` lines (a misfit left
at the best mechanic, from friction, a gap or the drive's own loop, widens the region instead of
narrowing it on a model the plant does not follow). Each narrowed interval spans the kept grid
values one step outwards and the identified value (the design's nominal model stays in its set);
an interval only shrinks, and where the lines are too few it stays as it is.

Not on a backlash answer (:func:`training.commissioning._rules.uncertainty_set` leaves it out): at
the measurement's small amplitude the load sticks and the gap rattles, and the response, periodic
and so coherent, is not the plant's (a resonance read 16 % above the truth, lines 0.3-60 x it).

A resonance the measurement found and a ``stiff`` answer lacks (:func:`measured_mode`) is fitted
the same way, over ``f_e`` within the measured peak's +-5 %, ``V_J`` up to the plateau's cap and
``d`` from the class's worst case: its worst cases in the set are the fitted ones, ``mode_margin``
beyond them in ``1 + V_J`` and in ``d`` (a small-signal measurement may understate a resonance).

The drive's part of each response (current loop, delays, hold, the speed by difference) comes from
the identified mechanic's exact sampled model (:func:`linear_plant`), with the SPEC's loop and with
the set's pessimistic variant, the better fit counting per mechanic; the mechanics' part from the
continuous two-mass response: ``G_k = G_id H_k / H_id`` (the hold's warping differs between them
only near the sampling frequency; the lines are taken below ``top`` of it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.stats

import sim
from training._settings import POSITIVE, Interval, Pair, check_settings
from training.errors import CommissioningError

from ._design import MeasuredMode, MechanicsBounds
from ._frf import MeasuredResponse
from ._loop import Mechanics, linear_plant

__all__ = ["NarrowSettings", "NARROW_SETTINGS", "two_mass_response", "narrowed_bounds", "measured_mode"]


@dataclass(frozen=True)
class NarrowSettings:
    """How rule R7d narrows the intervals with the measured response (module docstring)."""

    confidence: float = 0.99
    """The profile-likelihood region's level (three parameters: ``f_e``, ``V_J``, ``d``)."""
    floor: float = 0.03
    """The smallest relative error a line counts with (the estimate's and the model's own)."""
    points: int = 41
    """Grid values of ``f_e`` and of ``V_J`` over their intervals (log-spaced) ..."""
    damping_points: int = 9
    """... and of ``d``."""
    mode_damping: float = 0.2
    """A resonance fitted to a ``stiff`` answer (:func:`measured_mode`): the highest damping tried
    (the lowest: the class's worst case) ..."""
    mode_margin: float = 1.5
    """... and its worst cases reach this factor beyond the fitted region: ``1 + V_J`` above it, the
    damping below it (within the class's): a small-signal measurement may understate a resonance
    (friction makes it lead the plant), as the plateau's cap (``UncertaintySet.inertia_factor``) allows."""
    band: tuple[float, float] = (0.5, 2.0)
    """The lines used: from ``band[0]`` x the lowest anti-resonance to ``band[1]`` x the highest resonance of the grid ..."""
    top: float = 0.4
    """... and below this share of the sampling frequency."""
    min_lines: int = 6
    """Fewer trusted lines in the band leave the intervals as they are."""
    max_gap_probability: float = 0.5
    """R7d runs only where the identification's calibrated probability of a backlash class is below
    this (a gap as likely as not: a gap the answer missed makes the small-signal response not the
    plant's). Not lower: the bench's 366 Hz shaft without a gap, answered ``elastic`` at 268 Hz with a
    gap's probability 0.27, lost 0.79 -> 0.52 of the oracle at 0.1."""

    def __post_init__(self) -> None:
        check_settings(self, {"confidence": Interval(0.0, 1.0, open_low=True, open_high=True), "floor": POSITIVE,
                              "points": Interval(3, integer=True), "damping_points": Interval(1, integer=True),
                              "mode_damping": Interval(0.0, 1.0, open_low=True, open_high=True), "mode_margin": Interval(1.0),
                              "band": Pair(POSITIVE), "top": Interval(0.0, 0.5, open_low=True),
                              "min_lines": Interval(1, integer=True), "max_gap_probability": Interval(0.0, 1.0)}, CommissioningError)


#: The settings rule R7d uses by default.
NARROW_SETTINGS = NarrowSettings()


def two_mass_response(w: np.ndarray, J_sigma: Any, V_J: Any, f_e: Any, d: Any, mu_F: float = 0.0) -> np.ndarray:
    """The continuous two-mass response motor torque -> motor speed at ``w`` [rad/s]
    (``1 / (J_M s + K (J_L s + mu_F) / (J_L s + mu_F + K))``, ``K = D_F + C_F / s`` the shaft);
    the parameters broadcast against ``w``."""
    dv = sim.two_mass_derived(J_sigma, V_J, f_e, d)
    s = 1j * w
    shaft = dv.D_F + dv.C_F / s
    load = dv.J_L * s + mu_F
    return 1.0 / (dv.J_M * s + shaft * load / (load + shaft))


def narrowed_bounds(bounds: MechanicsBounds, mechanics: Mechanics, measured: MeasuredResponse | None, drive: Any, *,
                    min_coherence: float, current_loop_damping: float, extra_delay: int,
                    settings: NarrowSettings = NARROW_SETTINGS) -> MechanicsBounds:
    """``bounds`` narrowed to the two-mass mechanics ``measured`` does not invalidate on its lines
    of coherence at least ``min_coherence`` (module docstring); ``bounds`` as they are for a
    one-mass ``mechanics``, without a measurement, or with too few such lines in the band.
    ``current_loop_damping``, ``extra_delay``: the set's pessimistic loop."""
    m = mechanics
    if measured is None or not m.two_mass:
        return bounds
    F = _grid(bounds.f_e, m.f_e, settings.points)
    V = _grid((max(bounds.V_J[0], 1e-3), bounds.V_J[1]), m.V_J, settings.points)
    D = _grid((max(bounds.d[0], 1e-4), max(bounds.d[1], 1e-4)), max(m.d, 1e-4), settings.damping_points)
    fit = _Fit.of(measured, m, drive, F, V, min_coherence, current_loop_damping, extra_delay, settings)
    if fit is None:
        return bounds
    region = fit.region(V, F, D, settings)
    f_e = _span(F, region.any(axis=(0, 2)), m.f_e, bounds.f_e)
    V_J = _span(V, region.any(axis=(1, 2)), m.V_J, bounds.V_J)
    d = _span(D, region.any(axis=(0, 1)), m.d, bounds.d)
    if (f_e, V_J, d) == (bounds.f_e, bounds.V_J, bounds.d):
        return bounds
    note = (f"R7d the measured response ({fit.lines} lines) narrows f_e to {f_e[0]:.4g}..{f_e[1]:.4g} Hz, "
            f"V_J to {V_J[0]:.3g}..{V_J[1]:.3g}, d to {d[0]:.3g}..{d[1]:.3g}")
    return replace(bounds, f_e=f_e, V_J=V_J, d=d, widened="; ".join(filter(None, (bounds.widened, note))))


def measured_mode(w_r: float, mechanics: Mechanics, measured: MeasuredResponse | None, drive: Any, *,
                  V_J: tuple[float, float], d: tuple[float, float], f_spread: float, min_coherence: float,
                  current_loop_damping: float, extra_delay: int, settings: NarrowSettings = NARROW_SETTINGS) -> MeasuredMode | None:
    """A resonance at ``w_r`` [rad/s] that the measurement found and a one-mass ``mechanics`` lacks
    (a ``stiff`` answer): the two-mass modes (``J_sigma`` of the answer, ``f_e`` within ``w_r``
    x(1 -+ ``f_spread``), ``V_J`` and ``d`` in their ranges) the measurement does not invalidate
    (module docstring), as the worst cases the set holds: the ends of their ``f_e``, the lowest and
    ``settings.mode_margin`` beyond the highest ``V_J`` (in ``1 + V_J``), their lowest ``d`` over that
    factor (none outside ``V_J`` and ``d``). None: no measurement, a two-mass ``mechanics``, or too
    few lines."""
    m = mechanics
    if measured is None or m.two_mass:
        return None
    f_r = w_r / (2 * math.pi)
    F = _grid((f_r * (1 - f_spread), f_r * (1 + f_spread)), f_r, settings.points)
    Vs = _grid((min(V_J), max(V_J)), min(V_J), settings.points)
    D = _grid(d, d[0], settings.damping_points)
    fit = _Fit.of(measured, m, drive, F, Vs, min_coherence, current_loop_damping, extra_delay, settings)
    if fit is None:
        return None
    region = fit.region(Vs, F, D, settings)
    f_lo, f_hi = _span(F, region.any(axis=(0, 2)), f_r, (F[0], F[-1]))
    V_lo, V_hi = _span(Vs, region.any(axis=(1, 2)), None, (Vs[0], Vs[-1]))
    d_lo = _span(D, region.any(axis=(0, 1)), None, d)[0]
    k = settings.mode_margin
    V_worst = min(k * (1.0 + V_hi) - 1.0, max(V_J))  # >= V_hi: k >= 1 and V_hi <= max(V_J)
    return MeasuredMode(w_r, (f_lo, f_hi), tuple(dict.fromkeys((V_lo, V_worst))), max(d_lo / k, d[0]), fit.lines)


@dataclass(frozen=True)
class _Fit:
    """The measured lines in the band (``w`` [rad/s], ``G``, relative variance ``var``) and the
    drive's part of the response with each current loop (``parts``: loops x lines), against which
    grids of two-mass mechanics are held."""

    w: np.ndarray
    G: np.ndarray
    var: np.ndarray
    parts: np.ndarray
    J_sigma: float
    mu_F: float

    @property
    def lines(self) -> int:
        return len(self.w)

    @classmethod
    def of(cls, measured: MeasuredResponse, m: Mechanics, drive: Any, F: np.ndarray, V: np.ndarray, min_coherence: float,
           current_loop_damping: float, extra_delay: int, settings: NarrowSettings) -> _Fit | None:
        """The lines of coherence at least ``min_coherence`` from ``band[0]`` x the lowest
        anti-resonance of the grid (``F`` [Hz], ``V``) to ``band[1]`` x its highest resonance, below
        ``top`` of the sampling frequency; None where fewer than ``min_lines``."""
        T_s = float(measured.T_s)
        w = np.asarray(measured.w, dtype=float)
        c = np.asarray(measured.coherence, dtype=float)
        lowest = 2 * math.pi * F[0] / math.sqrt(1.0 + V[-1])
        keep = ((c >= min_coherence) & (w >= settings.band[0] * lowest) & (w <= settings.band[1] * 2 * math.pi * F[-1])
                & (w <= settings.top * 2 * math.pi / T_s))
        if keep.sum() < settings.min_lines:
            return None
        w, c = w[keep], np.clip(c[keep], 1e-6, 1.0)
        z = np.exp(1j * w * T_s)
        H_id = (two_mass_response(w, m.J_sigma, m.V_J, m.f_e, m.d, m.mu_F) if m.two_mass
                else 1.0 / (1j * w * m.J_sigma + m.mu_F))
        loops = (linear_plant(m, drive), linear_plant(m, drive, current_loop_damping=current_loop_damping, extra_delay=extra_delay))
        parts = np.stack([plant.speed_response(z) / H_id for plant in loops])  # loops x n
        return cls(w, np.asarray(measured.G)[keep], np.maximum((1.0 - c) / c, settings.floor ** 2), parts, m.J_sigma, m.mu_F)

    def region(self, V: np.ndarray, F: np.ndarray, D: np.ndarray, settings: NarrowSettings) -> np.ndarray:
        """``V x F x D`` booleans: the two-mass mechanics of the grid inside the profile-likelihood
        region of the best one (module docstring), the better of the two loops counting for each."""
        H = two_mass_response(self.w, self.J_sigma, V[:, None, None, None], F[None, :, None, None], D[None, None, :, None],
                              self.mu_F)  # V x F x D x n
        chi2 = np.full(H.shape[:3], np.inf)
        for part in self.parts:
            r = np.log(self.G / (H * part))
            chi2 = np.minimum(chi2, (np.abs(r) ** 2 / self.var).sum(axis=-1))
        best = float(chi2.min())
        scale = max(1.0, best / max(2 * self.lines - 3, 1))
        return chi2 <= best + scipy.stats.chi2.ppf(settings.confidence, 3) * scale


def _grid(interval: tuple[float, float], value: float, points: int) -> np.ndarray:
    """``points`` log-spaced values over ``interval`` and the identified ``value`` (sorted)."""
    low, high = interval
    return np.unique(np.concatenate([np.geomspace(low, max(high, low), points), [value]]))


def _span(grid: np.ndarray, kept: np.ndarray, value: float | None, interval: tuple[float, float]) -> tuple[float, float]:
    """The narrowed interval: the ``kept`` grid values one step outwards and ``value`` (None: none),
    inside ``interval`` (an end whose grid value was kept stays)."""
    idx = np.nonzero(kept)[0]
    if not len(idx):
        return interval
    low, high = float(grid[max(idx[0] - 1, 0)]), float(grid[min(idx[-1] + 1, len(grid) - 1)])
    if value is not None:
        low, high = min(low, value), max(high, value)
    low, high = max(interval[0], low), min(interval[1], high)
    return (interval[0] if idx[0] == 0 else low, interval[1] if idx[-1] == len(grid) - 1 else high)
