"""Features of the oscillating part ``w_osc`` of a test run (paper section 3.3, SPEC 4).

All functions work on one record: ``w_osc`` ``(N,)`` [rad/s] (from
:func:`training.identification._one_mass.fit_one_mass`), the sample time ``T_s`` [s] and the sections (``None`` =
the whole signal as one section, a ``SectionSplit``, or ``(K, 2)`` ``(start, stop)`` indices).
They never return NaN/inf: a section without oscillation contributes zeros.

The three parts of the feature vector (``training.identification._analysis.FEATURE_VERSION``
names the whole vector and is stored with a map's checkpoint):

- ``"paper-eig-v1"`` (26): :func:`eigenfrequency_features`. Per section the one-sided FFT
  magnitude of ``w_osc`` (mean removed, no window, no zero padding), normalized to 0..10 (its
  maximum is 10), integrated over 25 bins of constant relative width between ``EIG_F_LO`` = 2.5 Hz
  and ``EIG_F_HI`` = 1000 Hz (edges ``geomspace(2.5, 1000, 26)``, each bin 27 % wide, i.e. 0.104
  decades) and divided by the FFT's frequency spacing ``1/duration``. That is the sum of the FFT
  samples in the bin, with an FFT sample that straddles a bin edge shared in proportion to its
  overlap (the paper's "summing and weighting neighboured samples"). Mean over the sections,
  plus the index (0..24) of the highest mean bin. Range: the population's ``f_e`` of 5..500 Hz
  lies in bins 3..22 with one octave of margin below (the shortest sections, ~0.1 s, resolve only
  ~10 Hz, so the lowest bins receive fractional FFT samples) and a factor 2 above (harmonics and
  backlash distort towards higher frequencies; 1 kHz is half the Nyquist frequency at 4 kHz).
- ``"paper-struct-v1"`` (8): :func:`structure_features`. Per section the dominant frequency
  ``f_d`` (peak of the Hann-windowed, ~4x zero-padded FFT with parabolic interpolation, searched
  between ``2/duration`` and ``0.45/T_s``), ``w_osc`` resampled to ``STRUCT_SAMPLES_PER_PERIOD`` =
  64 samples per period (band-limited: upsampled by an integer factor first when the record has
  fewer than 64 samples per period, low-passed at ``30 f_d`` when it has many more), the first two
  periods (128 samples) transformed by the FFT and normalized to the signal energy
  (``|X_k| / sqrt(sum_k |X_k|^2)``, one-sided, DC removed), and the 8 amplitudes at
  ``f_d, 2 f_d, ..., 8 f_d`` (bins 2, 4, ..., 16). A sinusoid gives ``[1, 0, ..., 0]``, a triangle
  wave ``[0.993, 0, 0.110, 0, 0.040, ...]`` (1/9, 1/25 of the fundamental). Mean over the sections
  long enough for two periods.
- ``"extra-v1"`` (8): :func:`extra_features`, improvements beyond the paper (see
  ``docs/identification.md`` for what they measurably add).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from scipy import fft as _fft
from scipy import signal as _signal

from training.identification._one_mass import butter_sos, hann, section_bounds

__all__ = [
    "EIG_F_LO", "EIG_F_HI", "EIG_N_BINS", "EIG_EDGES", "EIG_NAMES", "STRUCT_SAMPLES_PER_PERIOD", "STRUCT_NAMES",
    "EXTRA_NAMES", "ExtraColumn", "eigenfrequency_features", "structure_features", "structure_and_peaks", "extra_features",
    "dominant_frequency", "zero_crossing_frequency",
]

EIG_F_LO = 2.5
EIG_F_HI = 1000.0
EIG_N_BINS = 25
EIG_EDGES = np.geomspace(EIG_F_LO, EIG_F_HI, EIG_N_BINS + 1)
STRUCT_SAMPLES_PER_PERIOD = 64
STRUCT_N_HARMONICS = 8
#: Component names of :func:`eigenfrequency_features` and :func:`structure_features`.
EIG_NAMES: tuple[str, ...] = tuple(f"eig_bin_{i}" for i in range(EIG_N_BINS)) + ("eig_peak_index",)
STRUCT_NAMES: tuple[str, ...] = tuple(f"harm_{h}" for h in range(1, STRUCT_N_HARMONICS + 1))
_MIN_SECTION = 8


def _check(w_osc: Any, T_s: Any) -> np.ndarray:
    x = np.asarray(w_osc, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"w_osc: expected a 1-D array (N,), received shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("w_osc: expected finite values, received NaN/inf")
    if not isinstance(T_s, (int, float, np.floating)) or not math.isfinite(T_s) or T_s <= 0:
        raise ValueError(f"T_s: expected a positive sample time [s], received {T_s!r}")
    return x


def _normalized(x: np.ndarray) -> tuple[np.ndarray, float]:
    """``x / max|x|`` and the scale (1.0 for a zero signal): keeps huge inputs from overflowing."""
    scale = float(np.max(np.abs(x), initial=0.0))
    if not scale > 0:
        return x, 1.0
    return x / scale, scale


def _centered(raw: np.ndarray) -> np.ndarray:
    """``raw`` minus its mean; all zeros when what is left is floating-point residue (constant input)."""
    seg = raw - np.mean(raw)
    if not np.max(np.abs(seg), initial=0.0) > 1e-9 * np.max(np.abs(raw), initial=0.0):
        return np.zeros_like(seg)
    return seg


def _bounds(x: np.ndarray, sections: Any) -> list[tuple[int, int]]:
    """The ``(start, stop)`` of each section of ``x`` (none for an empty ``x``)."""
    return section_bounds(sections, x.size) if x.size else []


def _segments(x: np.ndarray, bounds: list[tuple[int, int]]) -> list[tuple[int, int, np.ndarray]]:
    """``(i, start, segment)`` of each section ``bounds[i]`` of at least ``_MIN_SECTION`` samples, the
    segment of ``x`` centred: the one walk over the sections that every feature set makes."""
    return [(i, a, _centered(x[a:b])) for i, (a, b) in enumerate(bounds) if b - a >= _MIN_SECTION]


def _scale_ok(seg: np.ndarray) -> bool:
    """True when the segment holds a non-zero oscillation (relative to floating-point noise)."""
    peak = float(np.max(np.abs(seg))) if seg.size else 0.0
    return peak > 0 and math.isfinite(peak)


def _eig_bars(seg: np.ndarray, T_s: float) -> np.ndarray:
    n = seg.size
    if not _scale_ok(seg):
        return np.zeros(EIG_N_BINS)
    A = np.abs(np.fft.rfft(seg / np.max(np.abs(seg))))[1:]
    if A.size == 0 or not A.max() > 0:
        return np.zeros(EIG_N_BINS)
    A = 10.0 * A / A.max()
    df = 1.0 / (n * T_s)
    # FFT sample k (k >= 1) covers [(k - 1/2) df, (k + 1/2) df]; piecewise-constant integral
    cell_edges = (np.arange(A.size + 1) + 0.5) * df
    cum = np.concatenate([[0.0], np.cumsum(A) * df])
    F = np.interp(EIG_EDGES, cell_edges, cum, left=0.0, right=cum[-1])
    return np.diff(F) / df


def eigenfrequency_features(w_osc: Any, T_s: float, sections: Any = None) -> np.ndarray:
    """The paper's 26 eigenfrequency features (``"paper-eig-v1"``).

    Args:
        w_osc: ``(N,)`` oscillating part of the motor speed [rad/s].
        T_s: sample time [s].
        sections: ``None``, a ``SectionSplit`` or ``(K, 2)`` sample indices.

    Returns:
        ``(26,)`` float64: 25 mean bin heights (dimensionless, from the 0..10-normalized FFT) and
        the index 0..24 of the highest bin (0 when all are zero).
    """
    x, _ = _normalized(_check(w_osc, T_s))
    segs = _segments(x, _bounds(x, sections))
    bars = np.mean([_eig_bars(s, float(T_s)) for _, _, s in segs], axis=0) if segs else np.zeros(EIG_N_BINS)
    idx = float(np.argmax(bars)) if bars.max() > 0 else 0.0
    return np.concatenate([bars, [idx]])


def dominant_frequency(seg: Any, T_s: float, f_min: float | None = None, f_max: float | None = None) -> float:
    """Dominant frequency [Hz] of ``seg`` ``(N,)``: Hann window, 4x zero padding, parabolic peak.

    Searched between ``f_min`` (default ``2/duration``) and ``f_max`` (default ``0.45/T_s``).
    Returns 0.0 for a zero signal or an empty search range.
    """
    x, _ = _normalized(_check(seg, T_s))
    n = x.size
    x = _centered(x) if n else x
    if n < 4 or not _scale_ok(x):
        return 0.0
    x = x * hann(n)
    nfft = _fft.next_fast_len(4 * n, real=True)
    A = np.abs(_fft.rfft(x, nfft))
    f = np.fft.rfftfreq(nfft, T_s)
    lo = 2.0 / (n * T_s) if f_min is None else float(f_min)
    hi = 0.45 / T_s if f_max is None else float(f_max)
    band = np.flatnonzero((f >= lo) & (f <= hi))
    if band.size == 0:
        return 0.0
    k = int(band[np.argmax(A[band])])
    if not A[k] > 0:
        return 0.0
    if 0 < k < A.size - 1:
        a, b, c = np.log(A[k - 1:k + 2] + 1e-300)
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den < 0 else 0.0
        return float((k + np.clip(off, -0.5, 0.5)) * f[1])
    return float(f[k])


def _two_periods(seg: np.ndarray, T_s: float, f_d: float) -> np.ndarray | None:
    """``seg`` resampled to 64 samples per period of ``f_d``: the first two periods (128,)."""
    P = STRUCT_SAMPLES_PER_PERIOD
    fs = 1.0 / T_s
    if 2.0 / f_d > (seg.size - 1) * T_s:
        return None
    # only the first two periods (plus a margin for the filters' edges) are needed
    x, rate = seg[: min(seg.size, int(math.ceil(2.0 / (f_d * T_s))) + 32)], fs
    if fs / f_d > 2 * P and x.size > 27:
        x = _signal.sosfiltfilt(butter_sos(round(min(0.9, 2 * 30 * f_d / fs), 3)), x)
    elif fs / f_d < P:
        u = int(math.ceil(P * f_d / fs))
        x = _signal.resample_poly(x, u, 1)
        rate = fs * u
    t_new = np.arange(2 * P) / (P * f_d)
    return np.interp(t_new, np.arange(x.size) / rate, x)


def _harmonics(seg: np.ndarray, T_s: float, f_d: float) -> np.ndarray | None:
    y = _two_periods(seg, T_s, f_d)
    if y is None:
        return None
    X = np.abs(np.fft.rfft(y - y.mean()))[1:]
    wts = np.ones(X.size)
    wts[-1] = 0.25  # Nyquist bin counts once, not twice
    E = math.sqrt(float(np.sum(wts * X * X)))
    if not E > 0:
        return np.zeros(STRUCT_N_HARMONICS)
    return X[1:2 * STRUCT_N_HARMONICS:2] / E


def structure_features(w_osc: Any, T_s: float, sections: Any = None) -> np.ndarray:
    """The paper's 8 structure features (``"paper-struct-v1"``).

    Args:
        w_osc: ``(N,)`` [rad/s]; T_s: [s]; sections: as for :func:`eigenfrequency_features`.

    Returns:
        ``(8,)`` float64 in 0..1: energy-normalized amplitudes at ``f_d .. 8 f_d``, mean over the
        sections (zeros when no section holds two periods of an oscillation).
    """
    return structure_and_peaks(w_osc, T_s, sections)[0]


def structure_and_peaks(w_osc: Any, T_s: float, sections: Any = None) -> tuple[np.ndarray, dict[int, float]]:
    """:func:`structure_features` and the dominant frequency [Hz] of each section it looked at, by
    index into the section bounds: :func:`extra_features` finds the same ones (the same segment,
    normalized the same way), so a caller of both passes them on (``peaks``)."""
    x, _ = _normalized(_check(w_osc, T_s))
    out, peaks = [], {}
    for i, _, seg in _segments(x, _bounds(x, sections)):
        if not _scale_ok(seg):
            continue
        seg = seg / np.max(np.abs(seg))
        f_d = peaks[i] = dominant_frequency(seg, float(T_s))
        if f_d <= 0:
            continue
        h = _harmonics(seg, float(T_s), f_d)
        if h is not None:
            out.append(h)
    return (np.mean(out, axis=0) if out else np.zeros(STRUCT_N_HARMONICS)), peaks


def zero_crossing_frequency(seg: Any, T_s: float, hysteresis: float = 0.3) -> float:
    """Oscillation frequency [Hz] from level crossings with hysteresis (``hysteresis * rms``).

    Counts alternating crossings of ``+h`` and ``-h`` (robust to quantization chatter around zero);
    returns ``(crossings - 1) / 2 / time between first and last``, or 0.0 with fewer than 3.
    """
    x, _ = _normalized(_check(seg, T_s))
    if x.size < 4:
        return 0.0
    x = _centered(x)
    rms = float(np.sqrt(np.mean(x * x)))
    if not rms > 0:
        return 0.0
    h = hysteresis * rms
    # samples beyond +h (+1) or -h (-1) in time order; a change of side is one crossing
    above = np.flatnonzero(x > h)
    below = np.flatnonzero(x < -h)
    ev = np.concatenate([above, below])
    side = np.concatenate([np.ones(above.size, dtype=np.int8), -np.ones(below.size, dtype=np.int8)])
    order = np.argsort(ev, kind="stable")
    ev, side = ev[order], side[order]
    times = ev[np.flatnonzero(np.diff(side) != 0) + 1]
    if times.size < 3 or times[-1] == times[0]:
        return 0.0
    return float((times.size - 1) / 2.0 / ((times[-1] - times[0]) * T_s))


def _decay_damping(seg: np.ndarray, T_s: float, f: float) -> float:
    """Relative damping from the decay of the analytic envelope (0 when not measurable)."""
    n = seg.size
    if f <= 0 or n < 16:
        return 0.0
    env = np.abs(_signal.hilbert(seg, _fft.next_fast_len(n, real=False)))[:n]
    per = max(2, int(round(1.0 / (f * T_s))))
    if n < 4 * per:
        return 0.0
    k = np.arange(per // 2 + per, n - per, per)  # envelope away from the ends
    if k.size < 3:
        return 0.0
    e = np.convolve(env, np.ones(per) / per, mode="same")[k]
    if not np.all(e > 0):
        return 0.0
    slope = np.polyfit(k * T_s, np.log(e), 1)[0]
    return float(np.clip(-slope / (2 * math.pi * f), 0.0, 1.0))


class ExtraColumn(IntEnum):
    """The columns of :func:`extra_features`; each member's name is its feature's name."""

    log10_f_zc = 0
    log10_f_peak = 1
    log10_V_J_amp = 2
    d_decay = 3
    thd = 4
    log2_f_ratio_zero = 5
    log2_f_ratio_07 = 6
    log10_osc_rel = 7


#: Component names of :func:`extra_features`, in column order.
EXTRA_NAMES: tuple[str, ...] = tuple(column.name for column in ExtraColumn)
#: The periods of the oscillation after a torque step over which its amplitude is read (``log10_V_J_amp``).
AMPLITUDE_PERIODS = 1.5
#: The sections whose zero-crossing frequencies the ratio features compare with that of the ``M*``
#: sections I and IV (indices into I..VI): the zero-torque sections II, V and the ``0.7 M*`` ones III, VI.
_RATIO_SECTIONS = {ExtraColumn.log2_f_ratio_zero: (1, 4), ExtraColumn.log2_f_ratio_07: (2, 5)}
_FULL_TORQUE_SECTIONS = (0, 3)


def extra_features(
    w_osc: Any,
    T_s: float,
    sections: Any = None,
    *,
    J_sigma: float | None = None,
    torque_steps: Any = None,
    speed_span: float | None = None,
    structure: Any = None,
    peaks: dict[int, float] | None = None,
) -> np.ndarray:
    """Improved features (``"extra-v1"``, 8 components; columns :class:`ExtraColumn`, names :data:`EXTRA_NAMES`).

    Args:
        w_osc, T_s, sections: as for :func:`eigenfrequency_features` (sections ordered I..VI for
            the ratio features; with fewer sections those are 0).
        J_sigma: total inertia [kg m^2] from STEP 2, for the amplitude feature.
        torque_steps: ``(K,)`` torque step [Nm] at each section's start (e.g. ``M*, -M*, -0.7 M*,
            -0.3 M*, M*, 0.7 M*`` for I..VI; the level minus the previous level).
        speed_span: the record's speed range [rad/s] for the relative oscillation amplitude.
        structure: the record's :func:`structure_features` when already computed (saves time).
        peaks: the sections' dominant frequencies from :func:`structure_and_peaks` (saves time).

    Returns:
        ``(8,)`` float64:
        ``log10_f_zc``: median over sections of the hysteresis zero-crossing frequency [log10 Hz];
        ``log10_f_peak``: median dominant FFT frequency [log10 Hz];
        ``log10_V_J_amp``: median of ``A * J_sigma * 2 pi f / |dM|`` (paper eq. 1: a torque step
        ``dM`` excites ``A = V_J dM / (J_sigma w_0)``; ``A`` = half the peak-to-peak of ``w_osc`` in the
        first 1.5 periods) [log10]; ``d_decay``: median damping from the envelope decay;
        ``thd``: ``sqrt(1 - a1^2)`` of the structure features (harmonic content, backlash);
        ``log2_f_ratio_zero`` / ``log2_f_ratio_07``: zero-crossing frequency of the zero-torque
        sections (II, V) / of the 0.7 M* sections (III, VI) over that of the M* sections (I, IV)
        (backlash makes the apparent frequency depend on the torque); ``log10_osc_rel``:
        ``log10(rms(w_osc) / speed_span)``. Unavailable entries are 0.
    """
    x, scale = _normalized(_check(w_osc, T_s))
    T_s = float(T_s)
    bounds = _bounds(x, sections)
    steps = None if torque_steps is None else np.asarray(torque_steps, dtype=np.float64).ravel()
    amplitude = _StepAmplitude(x, scale, T_s, J_sigma, steps)
    measured = _section_measures(x, T_s, bounds, peaks, amplitude)
    out = np.zeros(len(ExtraColumn))
    if measured.zero_crossing:
        out[ExtraColumn.log10_f_zc] = math.log10(float(np.median(measured.zero_crossing)))
    if measured.peak:
        out[ExtraColumn.log10_f_peak] = math.log10(float(np.median(measured.peak)))
        out[ExtraColumn.d_decay] = float(np.median(measured.damping))
    if measured.amplitude:
        out[ExtraColumn.log10_V_J_amp] = float(np.median(measured.amplitude))
    out[ExtraColumn.thd] = _thd(x, T_s, sections, structure)
    if len(bounds) == 6:
        for column, sections_compared in _RATIO_SECTIONS.items():
            out[column] = _frequency_ratio(measured.section_zero_crossing, sections_compared)
    out[ExtraColumn.log10_osc_rel] = _relative_rms(x, bounds, scale, speed_span)
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


@dataclass(frozen=True)
class _StepAmplitude:
    """``log10(A J_sigma 2 pi f / |dM|)`` of a section (paper eq. 1): the amplitude ``A`` (half the
    peak-to-peak of ``x`` over the first :data:`AMPLITUDE_PERIODS` periods, in the input's units:
    ``scale``) the torque step ``steps[i]`` excites; ``None`` where ``J_sigma`` or the step is
    unknown or zero."""

    x: np.ndarray
    scale: float
    T_s: float
    J_sigma: float | None
    steps: np.ndarray | None

    def __call__(self, i: int, start: int, length: int, f: float) -> float | None:
        J_sigma, steps = self.J_sigma, self.steps
        if J_sigma is None or steps is None or i >= steps.size or not abs(steps[i]) > 0:
            return None
        m = min(length, max(2, int(AMPLITUDE_PERIODS / (f * self.T_s))))
        A = 0.5 * float(np.ptp(self.x[start:start + m]))
        if not (A > 0 and J_sigma):
            return None
        return (math.log10(A) + math.log10(self.scale) + math.log10(abs(float(J_sigma)) * 2 * math.pi * f)
                - math.log10(abs(steps[i])))


@dataclass(frozen=True)
class _SectionMeasures:
    """Per-section measures of :func:`extra_features` over the sections that oscillate: the
    zero-crossing and peak frequencies [Hz] (where found), the envelope's damping and the step
    amplitudes (where a peak was found), and each section's zero-crossing frequency (0: none)."""

    zero_crossing: list[float]
    peak: list[float]
    damping: list[float]
    amplitude: list[float]
    section_zero_crossing: np.ndarray


def _section_measures(x: np.ndarray, T_s: float, bounds: list[tuple[int, int]], peaks: dict[int, float] | None,
                      amplitude: _StepAmplitude) -> _SectionMeasures:
    measured = _SectionMeasures([], [], [], [], np.zeros(len(bounds)))
    for i, start, seg in _segments(x, bounds):
        if not _scale_ok(seg):
            continue
        f_zc = zero_crossing_frequency(seg, T_s)
        f_peak = peaks[i] if peaks is not None and i in peaks else dominant_frequency(seg, T_s)
        measured.section_zero_crossing[i] = f_zc
        if f_zc > 0:
            measured.zero_crossing.append(f_zc)
        if f_peak > 0:
            measured.peak.append(f_peak)
            measured.damping.append(_decay_damping(seg, T_s, f_peak))
            step_amplitude = amplitude(i, start, seg.size, f_peak)
            if step_amplitude is not None:
                measured.amplitude.append(step_amplitude)
    return measured


def _thd(x: np.ndarray, T_s: float, sections: Any, structure: Any) -> float:
    """``sqrt(1 - a1^2)`` of the structure features' fundamental ``a1`` (given, else computed)."""
    if structure is not None:
        a1 = float(np.asarray(structure, dtype=np.float64).ravel()[0])
    else:
        a1 = float(structure_features(x, T_s, sections)[0]) if x.size else 0.0
    return math.sqrt(max(0.0, 1.0 - min(1.0, a1) ** 2)) if a1 > 0 else 0.0


def _frequency_ratio(section_zero_crossing: np.ndarray, compared: tuple[int, int]) -> float:
    """``log2`` of the mean zero-crossing frequency of the ``compared`` sections over that of the
    ``M*`` sections I and IV (0 where either has none)."""
    den = [section_zero_crossing[i] for i in _FULL_TORQUE_SECTIONS if section_zero_crossing[i] > 0]
    num = [section_zero_crossing[i] for i in compared if section_zero_crossing[i] > 0]
    return math.log2(float(np.mean(num)) / float(np.mean(den))) if den and num else 0.0


def _relative_rms(x: np.ndarray, bounds: list[tuple[int, int]], scale: float, speed_span: float | None) -> float:
    """``log10(rms(w_osc) / speed_span)`` over the sections (0 where unknown)."""
    if speed_span is None or not speed_span > 0 or not x.size:
        return 0.0
    sel = np.concatenate([x[a:b] for a, b in bounds]) if bounds else x
    rms = float(np.sqrt(np.mean(sel * sel)))
    return math.log10(rms) + math.log10(scale) - math.log10(float(speed_span)) if rms > 0 else 0.0
