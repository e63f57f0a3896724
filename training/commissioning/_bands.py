"""What a test run cannot exclude: the eigenfrequency bands per inertia ratio of the mechanics a
measured test allows, for the fallback F1 and for the resonances a ``stiff`` answer may hide.

Both rest on the last accepted test run's figures (:func:`measure_response`), never on the truth:

* a visible oscillation at ``f_osc`` (``osc_quanta >= min_osc_quanta``): around ``f_osc``, widened
  by the spectrum's resolution ``1 / longest_section`` (a few periods in a section make ``f_osc``
  uncertain; fewer than 3: from the class's lowest);
* below resolution: a resonance at ``w_0`` rings after a torque step ``M*`` with the motor-speed
  amplitude ``V_J M* / (J_sigma w_0)`` (SPEC 1's ``r_osc q_w``), seen through the current loop
  (``|1 / (1 + j w_0 T_Ei)|``) and the speed measurement over one sample
  (``|sinc(w_0 T_s / 2)|``); it stays unseen where that amplitude is below what the test resolves.

Units SI, frequencies in Hz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from training._settings import POSITIVE, Interval, check_settings
from training.errors import CommissioningError

__all__ = ["BandSettings", "HiddenResonances", "ringing_amplitude", "f1_bands", "hidden_bands", "widen"]


@dataclass(frozen=True)
class BandSettings:
    """How wide the bands of what a test run cannot exclude are; checked on construction."""

    f_osc_resolutions: float = 2.0
    """F1: the spectrum's resolution ``1 / longest_section`` [Hz] counted this many times either side of ``f_osc``."""
    f_osc_width: float = 1.5
    """F1: relative width of the band around ``f_osc`` (``f_osc / w .. f_osc * w``)."""
    min_periods: float = 3.0
    """F1: fewer periods of ``f_osc`` in the longest section leave its lower end open (from the class's lowest)."""
    grid_points: int = 400
    """Frequencies of the log grid on which the ringing is compared with what the test resolves."""
    peak_factor: float = 4.0
    """R7b: a visible oscillation's amplitude as this many times its RMS (a damped ringing shows less RMS than its amplitude)."""
    peak_width: float = 1.2
    """R7b: relative width of the band around a visible oscillation the answer left out."""
    nyquist_share: float = 0.45
    """R7b: the bands end at this share of the sampling frequency (beyond it the measurement aliases)."""

    def __post_init__(self) -> None:
        check_settings(self, {"f_osc_resolutions": POSITIVE, "f_osc_width": Interval(1.0), "min_periods": POSITIVE,
                              "grid_points": Interval(2, integer=True), "peak_factor": POSITIVE, "peak_width": Interval(1.0),
                              "nyquist_share": Interval(0.0, 0.5, open_low=True)}, CommissioningError)


class HiddenResonances(NamedTuple):
    """:func:`hidden_bands`' answer: ``bands`` (``V_J -> (f_lo, f_hi)`` [Hz]) and ``notch_at``, the
    visible resonance [Hz] the answer left out (a notch may sit there), or None."""

    bands: dict[float, tuple[float, float]]
    notch_at: float | None


def ringing_amplitude(f: np.ndarray, V_J: float, J_sigma: float, M_step: float, config: Any) -> np.ndarray:
    """Amplitude [rad/s] of the motor-speed ringing of a resonance at ``f`` [Hz] (array) after a
    torque-reference step ``M_step`` [Nm], as the measured speed shows it (module docstring)."""
    w = 2 * math.pi * np.asarray(f, dtype=np.float64)
    T_s, T_Ei = float(config.T_s), float(config.T_Ei)
    return V_J * M_step / (J_sigma * w) / np.hypot(1.0, w * T_Ei) * np.abs(np.sinc(w * T_s / (2 * math.pi)))


def _unseen_from(V_J: float, J_sigma: float, M_step: float, amplitude: float, config: Any, f_lo: float, f_top: float,
                 points: int) -> float:
    """The lowest frequency [Hz] of ``points`` log-spaced in ``[f_lo, f_top]`` from which a resonance
    of ``V_J`` rings below ``amplitude`` [rad/s] up to ``f_top``."""
    f = np.geomspace(f_lo, f_top, points)
    seen = np.nonzero(ringing_amplitude(f, V_J, J_sigma, M_step, config) >= amplitude)[0]
    return float(f[min(seen[-1] + 1, len(f) - 1)]) if len(seen) else f_lo


def widen(bands: dict[float, tuple[float, float]], V_J: float, lo: float, hi: float) -> None:
    """Widen the band of ``V_J`` in ``bands`` (``V_J -> (f_lo, f_hi)`` [Hz], in place) to cover ``lo .. hi``."""
    old_lo, old_hi = bands.get(V_J, (math.inf, 0.0))
    bands[V_J] = (min(old_lo, lo), max(old_hi, hi))


def narrowed(a: dict[float, tuple[float, float]], b: dict[float, tuple[float, float]]) -> dict[float, tuple[float, float]]:
    """The bands two test runs of one plant allow together: per ``V_J`` of both the overlap of its
    bands (a resonance either run excludes is excluded); where they do not overlap (the runs
    disagree), the two together."""
    out = dict(a)
    for V_J, (lo, hi) in b.items():
        old_lo, old_hi = out.get(V_J, (lo, hi))
        both = (max(old_lo, lo), min(old_hi, hi))
        out[V_J] = both if both[0] <= both[1] else (min(old_lo, lo), max(old_hi, hi))
    return out


def f1_bands(entry: dict[str, Any], J_sigma: float, config: Any, class_V_J: tuple[float, ...], class_f_e: tuple[float, float],
             *, min_osc_quanta: float, osc_visible_ratio: float,
             settings: BandSettings | None = None) -> dict[float, tuple[float, float]]:
    """F1's eigenfrequency band [Hz] per inertia ratio from one test run's figures ``entry``
    (``osc_quanta``, ``f_osc``, ``longest_section``, ``M_star``): a visible oscillation: ``(f_osc -
    2/T) / 1.5 .. (f_osc + 2/T) * 1.5`` with ``T`` the longest section (from the class's lowest
    when fewer than 3 periods fit in it; :class:`BandSettings`); below resolution: from where a
    resonance rings below ``osc_visible_ratio`` speed quanta up to the class's highest."""
    settings = settings or BandSettings()
    lo, hi = class_f_e
    if entry["osc_quanta"] >= min_osc_quanta and entry["f_osc"] > 0:
        f, T = entry["f_osc"], entry["longest_section"]
        df = settings.f_osc_resolutions / T if T > 0 else f
        band = (max((f - df) / settings.f_osc_width, lo) if f * T >= settings.min_periods else lo, (f + df) * settings.f_osc_width)
        return {v: band for v in class_V_J}
    amp = osc_visible_ratio * float(config.q_w)
    return {v: (_unseen_from(v, J_sigma, entry["M_star"], amp, config, lo, hi, settings.grid_points), hi) for v in class_V_J}


def hidden_bands(entry: dict[str, Any], J_sigma: float, config: Any, class_V_J: tuple[float, ...], *, f_lo: float,
                 min_osc_quanta: float, settings: BandSettings | None = None) -> HiddenResonances:
    """The resonances a ``stiff`` answer cannot exclude, from the accepted test run's figures
    ``entry`` (``M_star``, ``osc_quanta``, ``f_osc``): per inertia ratio of ``class_V_J`` the band
    [Hz] from where a resonance rings below ``sqrt(2) max(osc_quanta, min_osc_quanta)`` speed quanta
    (a sustained ringing of that RMS) up to ``nyquist_share / T_s`` (beyond it the measurement
    aliases; the current loop hides the top of the band). A visible oscillation (``osc_quanta >=
    min_osc_quanta``) at ``f_osc`` is a resonance the answer left out: ``f_osc / peak_width ..
    f_osc * peak_width`` is added at the inertia ratio its amplitude allows (RMS x ``peak_factor``:
    a damped ringing shows less RMS than its amplitude), at most the class's largest.

    Returns :class:`HiddenResonances` (it unpacks as ``bands, notch_at``); ``nyquist_share``,
    ``peak_factor`` and ``peak_width`` from :class:`BandSettings`.
    """
    settings = settings or BandSettings()
    f_top = settings.nyquist_share / float(config.T_s)
    osc, q_w, M = float(entry["osc_quanta"]), float(config.q_w), float(entry["M_star"])
    amp = math.sqrt(2.0) * max(osc, min_osc_quanta) * q_w  # the amplitude of a sustained ringing of that RMS
    bands = {v: (_unseen_from(v, J_sigma, M, amp, config, f_lo, f_top, settings.grid_points), f_top) for v in class_V_J}
    f_osc = float(entry.get("f_osc", 0.0))
    if not (osc >= min_osc_quanta and f_lo <= f_osc < f_top):
        return HiddenResonances(bands, None)
    ring_per_V_J = float(ringing_amplitude(np.array([f_osc]), 1.0, J_sigma, M, config)[0])
    V_J = min(settings.peak_factor * osc * q_w / ring_per_V_J, max(class_V_J))
    widen(bands, V_J, f_osc / settings.peak_width, min(f_osc * settings.peak_width, f_top))
    return HiddenResonances(bands, f_osc)
