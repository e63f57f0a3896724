"""The measured frequency response of the plant on the drive (SPEC 8.2): a periodic multisine
disturbance torque ``M_dist`` on the running, safe speed loop (``drive.run_closed_loop``), its
amplitude planned inside the limits on the identified model's closed loop (:mod:`._measure`), and
the plant's torque-to-speed response estimated from the record with the closed-loop-safe indirect
method (here: the typed result, the signal, the estimate; no model, so that the loop analysis can
read a :class:`MeasuredResponse`).

The experiment: a zero speed reference (the travel stays bounded: the loop's integrator holds the
mean speed at zero) and ``periods`` identical periods of ``period`` samples of a Schroeder-phased
multisine on log-spaced DFT lines up to Nyquist; the first period is discarded as transient.

The estimate, per excited line ``f``: ``G(f) = S_wd(f) / S_ud(f)``, ``w`` the measured speed, ``u``
the torque the drive was commanded (the law's output plus the injected ``M_dist``, as the record's
``torque_ref`` holds it), ``d`` the injected multisine. Noise that the loop feeds back into ``u``
is uncorrelated with ``d`` and averages out of both cross-spectra, which the direct ratio
``S_wu / S_uu`` of a closed loop would not do. Since ``d`` repeats exactly, ``S_xd`` is the
period-averaged DFT of ``x`` times ``conj(D)``, and ``G`` is the ratio of the period-averaged DFTs.
The coherence ``|S|^2 / (|S|^2 + sigma^2)`` is the share of the measured speed's power at the line
that repeats with the excitation: ``S`` the period-averaged DFT of the speed, ``sigma^2`` the power
of one period's deviation from it (pooled over the neighbouring lines, :data:`NOISE_POOL`) plus the
encoder quantization's (which repeats with the signal and does not average out); the estimate's
relative error is about ``sqrt((1 - coherence) / coherence)``.

Convention (:meth:`LinearPlant.speed_response`): ``M_ref`` computed at sample ``k`` acts from
``k+1``; the speed is the angle gained over the last sample. A drive's record holds in
``torque_ref[k]`` the reference applied over ``[t_k, t_{k+1})``, that is, the one computed at
``k-1``: the commanded torque at ``k`` is ``torque_ref[k+1]``.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.signal

import sim
from training._settings import POSITIVE_OR_INF, SHARE, Interval, check_settings

__all__ = ["MeasuredResponse", "FRFSettings", "FRF_SETTINGS", "FRFPlan", "excited_lines", "multisine", "estimate_response",
           "find_resonances", "NOISE_POOL"]


@dataclass(frozen=True)
class FRFSettings:
    """The frequency-response experiment and its evaluation."""

    period: int = 2048
    """Samples per period of the multisine (line spacing ``1 / (period T_s)``: 1.95 Hz at 4 kHz)."""
    periods: int = 6
    """Periods run; the first is discarded as the loop's transient, the others averaged."""
    lines_per_decade: float = 100.0
    """Log-spaced excited lines (2.3 % apart: a resonance of damping 0.01 is 2 % wide at half power);
    below that spacing every DFT line is excited."""
    limit_share: float = 0.25
    """The model's predicted peaks of motor and load speed and travel use at most this share of the
    limits handed to the drive (a resonance the model lacks may add to the measured ones)."""
    torque_share: float = 0.4
    """The predicted peak commanded torque is at most this share of the torque cap."""
    min_coherence: float = 0.8
    """A line with a lower coherence is not used to find resonances."""
    resonance_excess_dB: float = 6.0
    """A local maximum of the measured magnitude over the model's, at least this high and standing out
    by as much, may be a resonance the model lacks ..."""
    model_gain_factor: float = 2.0
    """Near the loop's crossover (a decade around it) the measured magnitude may differ from the
    identified model's by at most this factor (median over the coherent lines); beyond it the drive
    is unlike its model (a torque scale or ``K_M`` off?) and the warning ``loop_unlike_model`` says so."""
    resonance_shape_dB: float = 3.0
    """... where the measured magnitude over an inertia's (``|G| w``) has a peak there standing out by
    at least this much (a resonance, not the model's misplaced anti-resonance nor noise)."""

    def __post_init__(self) -> None:
        check_settings(self, {"period": Interval(64, integer=True), "periods": Interval(3, integer=True),
                              "lines_per_decade": POSITIVE_OR_INF, "limit_share": SHARE, "torque_share": SHARE,
                              "min_coherence": SHARE, "resonance_excess_dB": POSITIVE_OR_INF, "model_gain_factor": Interval(1.0),
                              "resonance_shape_dB": POSITIVE_OR_INF})


#: The experiment's settings.
FRF_SETTINGS = FRFSettings()


@dataclass(frozen=True)
class MeasuredResponse:
    """The plant's response from the torque reference to the measured motor speed, measured on the
    drive, in the convention of ``LinearPlant.speed_response`` (``M_ref`` computed at sample ``k``
    and applied from ``k+1``, the speed measured as the angle gained over the last sample: both
    sample delays included), so that ``C(z) F(z) G`` is the loop the law closes.

    ``w`` [rad/s] (``F``, increasing, up to Nyquist), ``G`` (``F``, complex, [rad/s / Nm]),
    ``coherence`` (``F``, in [0, 1]: how much of the measured speed the injected torque explains),
    ``T_s`` [s]; ``model`` (``F``, complex, or None): the identified model's response on the same
    lines; ``resonances`` [rad/s]: peaks of the measured response the model lacks
    (:func:`find_resonances`); ``amplitude`` [Nm]: the multisine's amplitude per line.
    """

    w: np.ndarray
    G: np.ndarray
    coherence: np.ndarray
    T_s: float
    model: np.ndarray | None = None
    resonances: tuple[float, ...] = ()
    amplitude: float = math.nan

    def coherent_share(self, min_coherence: float) -> float:
        """The share of the lines whose coherence reaches ``min_coherence`` (0 without lines)."""
        return float(np.mean(np.asarray(self.coherence) >= min_coherence)) if len(self.coherence) else 0.0

    def model_gain_ratio(self, w_c: float, min_coherence: float) -> float | None:
        """The median of ``|G / model|`` over the coherent lines within ``w_c / 3 .. 3 w_c`` [rad/s]
        (None: no model, or no such line)."""
        if self.model is None:
            return None
        near = (self.w >= w_c / 3) & (self.w <= 3 * w_c) & (self.coherence >= min_coherence)
        return float(np.median(np.abs(self.G[near] / self.model[near]))) if near.any() else None

    def inertia_ratio(self, w_r: float, band: tuple[float, float], min_coherence: float, min_lines: int = 3) -> float | None:
        """``1 + V_J`` (``J_sigma / J_M``) of a resonance at ``w_r`` [rad/s] that a one-mass model
        lacks, read above it: the median over the lines of coherence at least ``min_coherence``
        within ``band`` x ``w_r`` of ``(r (x^2 - 1) + 1) / x^2``, ``r = |G / model|``, ``x = w / w_r``
        (the undamped two-mass over the one-mass response there; its damping hardly matters above
        ``1.4 w_r``). None: no model, or fewer than ``min_lines`` such lines."""
        if self.model is None:
            return None
        near = (self.w >= band[0] * w_r) & (self.w <= band[1] * w_r) & (self.coherence >= min_coherence)
        if near.sum() < min_lines:
            return None
        x2 = (self.w[near] / w_r) ** 2
        return float(np.median((np.abs(self.G[near] / self.model[near]) * (x2 - 1.0) + 1.0) / x2))

    def to_csv(self, path: str | Path) -> Path:
        """Write the response as CSV: ``f_Hz, magnitude_dB, phase_deg, coherence`` and, where the
        model is given, ``model_magnitude_dB, model_phase_deg``. Returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        cols = {"f_Hz": self.w / (2 * math.pi), "magnitude_dB": _dB(self.G), "phase_deg": _phase_deg(self.G),
                "coherence": self.coherence}
        if self.model is not None:
            cols.update(model_magnitude_dB=_dB(self.model), model_phase_deg=_phase_deg(self.model))
        with path.open("w", newline="") as fh:
            out = csv.writer(fh)
            out.writerow(cols)
            out.writerows(zip(*(np.asarray(v, dtype=np.float64) for v in cols.values())))
        return path

    def to_dict(self) -> dict[str, Any]:
        """Summary for the report's JSON (the lines themselves go to the CSV)."""
        good = self.coherence >= FRF_SETTINGS.min_coherence
        return {"lines": int(len(self.w)), "f_min_Hz": float(self.w[0] / (2 * math.pi)), "f_max_Hz": float(self.w[-1] / (2 * math.pi)),
                "coherent_share": float(good.mean()) if len(good) else 0.0, "amplitude_Nm": self.amplitude,
                "resonances_Hz": [r / (2 * math.pi) for r in self.resonances]}


def _dB(G: np.ndarray) -> np.ndarray:
    return 20 * np.log10(np.maximum(np.abs(G), 1e-300))


def _phase_deg(G: np.ndarray) -> np.ndarray:
    return np.degrees(np.unwrap(np.angle(G)))


@dataclass(frozen=True)
class FRFPlan:
    """The planned experiment: the scenario for the drive, the excited DFT ``lines`` of one period,
    the per-line ``amplitude`` [Nm] and the model's predicted peaks (``peak_speed``, ``travel`` of
    motor and load [rad/s, rad], ``peak_torque`` [Nm])."""

    scenario: sim.Scenario
    lines: np.ndarray
    period: int
    amplitude: float
    prediction: dict[str, float]

    @property
    def periods(self) -> int:
        return (len(self.scenario) - 1) // self.period


def excited_lines(period: int, lines_per_decade: float) -> np.ndarray:
    """The DFT lines (``1 .. period/2 - 1``) of the multisine: log-spaced, every line where the spacing is finer."""
    top = period // 2 - 1
    n = max(int(math.ceil(math.log10(top) * lines_per_decade)) + 1, 2)
    return np.unique(np.round(np.logspace(0.0, math.log10(top), n)).astype(np.int64))


def multisine(period: int, lines: np.ndarray) -> np.ndarray:
    """One period of the unit-amplitude multisine on ``lines`` with Schroeder phases (low crest factor)."""
    n = np.arange(period)
    L = len(lines)
    phases = -math.pi * np.arange(L) * (np.arange(L) + 1) / L
    return np.cos(2 * math.pi * np.outer(n, lines) / period + phases).sum(axis=1)


#: The noise power at a line is pooled over this many lines on each side (a smooth noise spectrum:
#: a few periods alone give a noisy estimate of it).
NOISE_POOL: int = 4


def estimate_response(record: sim.Record, plan: FRFPlan, T_s: float, q_w: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w, G, coherence)`` on the excited lines from a complete record of ``plan`` (module
    docstring); ``q_w`` [rad/s]: the encoder's speed quantum, whose error repeats with a periodic
    signal (averaging does not remove it): it counts as noise of power ``q_w^2 / 12`` per sample."""
    N, P = plan.period, plan.periods
    speed = np.asarray(record.speed, dtype=np.float64)
    if record.torque_ref is None or len(speed) < P * N + 1:
        raise ValueError(f"frequency-response record: expected {P * N + 1} samples with torque_ref, received {len(speed)}")
    commanded = np.asarray(record.torque_ref, dtype=np.float64)[1:P * N + 1]
    W = np.fft.rfft(speed[N:P * N].reshape(P - 1, N), axis=1)[:, plan.lines]
    U = np.fft.rfft(commanded[N:].reshape(P - 1, N), axis=1)[:, plan.lines]
    W_mean, U_mean = W.mean(axis=0), U.mean(axis=0)
    noise = (np.abs(W - W_mean) ** 2).sum(axis=0) / (P - 2)  # per period, unbiased over the P - 1 periods used
    window = np.ones(2 * NOISE_POOL + 1)
    pooled = np.convolve(noise, window, "same") / np.convolve(np.ones_like(noise), window, "same") + N * q_w**2 / 12
    signal = np.abs(W_mean) ** 2
    coherence = signal / np.maximum(signal + pooled, 1e-300)
    return 2 * math.pi * plan.lines / (N * T_s), W_mean / U_mean, np.clip(coherence, 0.0, 1.0)


def find_resonances(w: np.ndarray, G: np.ndarray, coherence: np.ndarray, model: np.ndarray,
                    settings: FRFSettings = FRF_SETTINGS) -> tuple[float, ...]:
    """The resonances [rad/s] the model lacks: over the lines of coherence at least
    ``settings.min_coherence``, the peaks of the measured magnitude over the model's (in dB) that
    reach ``settings.resonance_excess_dB`` and stand out by as much from their surroundings (a
    two-mass plant read as one-mass is +``20 log10(1 + V_J)`` dB everywhere above its resonance: a
    plateau, not a peak) and where the measured magnitude itself has a resonance's shape
    (``settings.resonance_shape_dB``); each placed by a parabola through the excess at the line and
    its two neighbours over log frequency."""
    good = coherence >= settings.min_coherence
    lw, mag = np.log(w[good]), _dB(G[good])
    excess = mag - _dB(model[good])
    level = settings.resonance_excess_dB
    peaks, _ = scipy.signal.find_peaks(excess, height=level, prominence=level)
    # the measured response itself peaks: its magnitude over an inertia's (|G| w) stands out
    shaped, _ = scipy.signal.find_peaks(mag + 20 * lw / math.log(10), prominence=settings.resonance_shape_dB)
    out = []
    for i in peaks:
        if not np.any(np.abs(shaped - i) <= 1):
            continue  # no resonance in the measurement here (e.g. the model's anti-resonance, misplaced)
        x, y = lw[i - 1:i + 2], excess[i - 1:i + 2]
        a, b, _ = np.polyfit(x - x[1], y, 2)
        shift = float(np.clip(-b / (2 * a), x[0] - x[1], x[2] - x[1])) if a < 0 else 0.0
        out.append(float(math.exp(x[1] + shift)))
    return tuple(out)
