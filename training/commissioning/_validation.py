"""Validation of an identified model by re-simulation (knowledge base, SPEC 8).

* :func:`validate_model` — re-simulate the identified model under the recorded test signal
  (``mode="replay"``: the recorded ``torque_ref`` sequence, open loop, :func:`sim.replay_speed`;
  ``mode="switching"``: the
  same switching law with the record's ``M_star``/``w_max``) and compare with the measured speed:
  normalized RMS error of the speed (``nrmse``) and of its oscillating part (``osc_nrmse``, the
  speed minus its moving average over one period of the model's ``f_e``), each with a threshold.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["ValidationResult", "validate_model", "VALIDATION_MODES", "OSC_METRICS"]

#: Re-simulation modes of :func:`validate_model` and its oscillation comparisons.
VALIDATION_MODES: tuple[str, ...] = ("replay", "switching")
OSC_METRICS: tuple[str, ...] = ("spectrum", "time")



def _segments(torque_ref: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The recorded ``torque_ref`` ``N`` as piecewise-constant segments ``1 x K`` (start, level)."""
    t = np.asarray(torque_ref, dtype=np.float64).reshape(-1)
    if t.size < 2 or not np.isfinite(t).all():
        raise ValueError(f"torque_ref: expected >= 2 finite samples, received {t.size}")
    start = np.concatenate([[0], np.flatnonzero(t[1:] != t[:-1]) + 1])
    return torch.as_tensor(start)[None], torch.as_tensor(t[start])[None]


@dataclass
class ValidationResult:
    """``passed``; ``nrmse`` = RMS(w_sim - w_meas)/RMS(w_meas) over the common length;
    ``osc_nrmse`` (None when the measured oscillation is below ``osc_min_quanta``) for the
    oscillating parts; thresholds; ``simulated`` / ``measured`` speed ``N`` [rad/s]; ``reason``."""

    passed: bool
    nrmse: float
    osc_nrmse: float | None
    threshold: float
    osc_threshold: float
    simulated: np.ndarray
    measured: np.ndarray
    mode: str
    reason: str


def _get(obj: Any, name: str) -> Any:
    if isinstance(obj, Mapping):
        return obj.get(name)
    return getattr(obj, name, None)


def _one(x: Any) -> np.ndarray:
    a = x.detach().to(torch.float64).cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)
    a = a.reshape(-1, a.shape[-1]) if a.ndim > 1 else a.reshape(1, -1)
    if a.shape[0] != 1:
        raise ValueError(f"record: expected one system, received a batch of {a.shape[0]}")
    return a[0]


def _measured(record: Any) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """(speed N, torque_ref N or None, meta) from a sim Response or a Record."""
    speed = _get(record, "speed")
    if speed is None:
        raise TypeError(f"record: expected a Record/Response with 'speed', received {type(record).__name__}")
    w = _one(speed)
    n = len(w)
    length = _get(record, "length")
    if length is not None:
        n = int(np.asarray(length.detach().cpu() if isinstance(length, torch.Tensor) else length).reshape(-1)[0])
    tr = _get(record, "torque_ref")
    meta = _get(record, "meta") or {}
    return w[:n], (_one(tr)[:n] if tr is not None else None), dict(meta)


def _as_sim_params(params: Any, drive: Any) -> Any:
    import sim

    if isinstance(params, sim.TwoMassParams):
        return params
    if not isinstance(params, Mapping):
        raise TypeError(f"params: expected TwoMassParams or a dict, received {type(params).__name__}")
    row = {k: params.get(k) for k in sim.PARAM_NAMES}
    if row["V_J"] is None or row["f_e"] is None:
        row.update(sim.one_mass_stand_in(float(drive.T_s)))
    row.update({k: params[k] for k in sim.REAL_AXIS_NAMES if k in params})  # SPEC 1.1: M_L0 holds the model at rest
    row = {k: (0.0 if v is None else float(v)) for k, v in row.items()}
    return sim.TwoMassParams.from_dicts(row)


def _moving_average(x: np.ndarray, W: int) -> np.ndarray:
    if W <= 1:
        return x.copy()
    k = np.ones(W) / W
    pad = np.concatenate([np.full(W // 2, x[0]), x, np.full(W - 1 - W // 2, x[-1])])
    return np.convolve(pad, k, mode="valid")


def _spectrum_error(a: np.ndarray, b: np.ndarray, T_s: float, rel_width: float = 0.2) -> float:
    """``||A - B|| / ||B||`` of the amplitude spectra of ``a`` (model) and ``b`` (measured),
    summed in bins of constant relative width ``rel_width`` (equal width on a log axis) from
    1 Hz to Nyquist: insensitive to the phase drift that a small frequency error accumulates."""
    n = len(b)
    f = np.fft.rfftfreq(n, T_s)
    A, B = np.abs(np.fft.rfft(a)), np.abs(np.fft.rfft(b))
    f_lo, f_hi = max(1.0, f[1] if n > 1 else 1.0), 0.5 / T_s
    edges = f_lo * (1.0 + rel_width) ** np.arange(int(math.log(f_hi / f_lo) / math.log1p(rel_width)) + 2)
    idx = np.digitize(f, edges)
    keep = (f >= f_lo) & (f <= f_hi)
    Ab = np.bincount(idx[keep], weights=A[keep] ** 2, minlength=len(edges) + 1) ** 0.5
    Bb = np.bincount(idx[keep], weights=B[keep] ** 2, minlength=len(edges) + 1) ** 0.5
    den = float(np.sqrt(np.sum(Bb**2)))
    return float(np.sqrt(np.sum((Ab - Bb) ** 2)) / den) if den > 0 else 0.0


def _simulated_speed(p: Any, drive: Any, mode: str, torque_ref: np.ndarray | None, meta: dict[str, Any],
                     signal: Any, seed: int, n: int) -> np.ndarray:
    """The model ``p`` (batch ``(1,)``) under the record's test: its recorded torque reference
    replayed open loop (``"replay"``, ``n`` samples) or the switching law rerun (``"switching"``)."""
    import sim

    if mode == "replay":
        if torque_ref is None:
            raise ValueError("mode='replay' needs the recorded torque_ref")
        start, level = _segments(torque_ref)
        return _one(sim.replay_speed(p, drive, start, level, n))[:n]
    if signal is None:
        if "M_star" not in meta or "w_max" not in meta:
            raise ValueError("mode='switching' needs signal= or record meta with M_star and w_max")
        signal = sim.TestSignalConfig(M_star=float(meta["M_star"]), w_max=float(meta["w_max"]),  # the test's own defaults
                                      **{k: float(meta[k]) for k in ("timeout", "tail") if k in meta})
    resp = sim.simulate_test(p, drive, signal, seed=seed)
    w_sim = _one(resp.speed)
    L = _get(resp, "length")
    return w_sim if L is None else w_sim[: int(torch.as_tensor(L).reshape(-1)[0])]


#: The moving-average window [s] that separates the oscillating part where no ``f_e`` is identified.
NO_RESONANCE_WINDOW: float = 0.01


def _oscillation_error(a: np.ndarray, b: np.ndarray, f_e: Any, drive: Any, osc_min_quanta: float,
                       osc_metric: str) -> float | None:
    """Error of the oscillating parts (speed minus its moving average over one period of ``f_e``,
    else :data:`NO_RESONANCE_WINDOW`) of the model ``a`` against the measurement ``b`` (both ``m``); None when the
    measured oscillation is below ``osc_min_quanta`` speed quanta rms."""
    f_e = float(f_e.reshape(-1)[0]) if isinstance(f_e, torch.Tensor) else (None if f_e is None else float(f_e))
    m = len(b)
    W = int(round(1.0 / (f_e * float(drive.T_s)))) if f_e else int(round(NO_RESONANCE_WINDOW / float(drive.T_s)))
    W = int(min(max(W, 3), max(m // 4, 3)))
    hp_b = b - _moving_average(b, W)
    hp_a = a - _moving_average(a, W)
    osc_rms = float(np.sqrt(np.mean(hp_b**2)))
    if osc_rms < osc_min_quanta * float(drive.q_w):
        return None
    if not np.isfinite(hp_a).all():
        return math.inf
    if osc_metric == "spectrum":
        return _spectrum_error(hp_a, hp_b, float(drive.T_s))
    return float(np.sqrt(np.mean((hp_a - hp_b) ** 2)) / osc_rms)


def validate_model(
    params: Any,
    drive: Any,
    record: Any,
    *,
    mode: str = "replay",
    threshold: float = 0.1,
    osc_threshold: float = 0.5,
    osc_min_quanta: float = 3.0,
    signal: Any = None,
    seed: int = 0,
    osc_metric: str = "time",
) -> ValidationResult:
    """Re-simulate ``params`` under ``record``'s test signal and compare with its measured speed.

    Args:
        params: identified model: ``sim.TwoMassParams`` (one system) or a dict of the seven
            parameters (``V_J``/``f_e`` None: one-mass surrogate), optionally with SPEC 1.1's
            ``M_L0``, ``M_FCM``, ``mu_FM`` (None or absent: 0); a model with ``M_L0`` starts at
            rest held by it, as the drive holds the axis (the recorded ``torque_ref`` holds it).
        drive: DriveConfig.
        record: sim Response (one system) or Record: ``speed`` ``N`` [rad/s], ``torque_ref`` ``N``
            [Nm] (needed for ``mode="replay"``), for ``"switching"`` ``meta`` with ``M_star``,
            ``w_max`` (or pass ``signal``).
        mode: "replay" (open loop, recorded ``torque_ref``) or "switching" (same switching law).
        threshold: largest accepted ``nrmse``; osc_threshold: largest accepted ``osc_nrmse``.
        osc_min_quanta: the oscillation check runs when the measured oscillating part has an RMS
            of at least this many speed quanta ``q_w`` (else it is noise).
        osc_metric: "time" (sample by sample: phase-sensitive, a few % of ``f_e`` error over a
            long record already reads ~1.3) or "spectrum" (:func:`_spectrum_error`: amplitude
            spectra of the oscillating parts in bins of 20 % relative width, phase-insensitive;
            a model without oscillation reads 1, one at a clearly wrong frequency ~1.4).

    Returns :class:`ValidationResult`.
    """
    if osc_metric not in OSC_METRICS:
        raise ValueError(f"osc_metric: expected one of {OSC_METRICS}, received {osc_metric!r}")
    if mode not in VALIDATION_MODES:
        raise ValueError(f"mode: expected one of {VALIDATION_MODES}, received {mode!r}")
    if not (threshold > 0 and osc_threshold > 0):
        raise ValueError(f"threshold, osc_threshold: expected > 0, received {threshold}, {osc_threshold}")
    w_meas, torque_ref, meta = _measured(record)
    p = _as_sim_params(params, drive)
    if p.J_sigma.numel() != 1:
        raise ValueError(f"params: expected one system, received batch {tuple(p.batch_shape)}")
    n = len(w_meas)
    w_sim = _simulated_speed(p.reshape(1), drive, mode, torque_ref, meta, signal, seed, n)
    m = min(len(w_sim), n)
    a, b = w_sim[:m], w_meas[:m]
    rms = float(np.sqrt(np.mean(b**2))) or 1e-300
    nrmse = float(np.sqrt(np.mean((a - b) ** 2)) / rms) if np.isfinite(a).all() else math.inf
    if mode == "switching" and max(len(w_sim), n) > 0:
        nrmse = max(nrmse, abs(len(w_sim) - n) / max(n, 1))  # a different test length is an error too
    osc_nrmse = _oscillation_error(a, b, _get(params, "f_e"), drive, osc_min_quanta, osc_metric)
    reasons = []
    if not nrmse <= threshold:
        reasons.append(f"speed error {nrmse:.3g} > {threshold:g}")
    if osc_nrmse is not None and not osc_nrmse <= osc_threshold:
        reasons.append(f"oscillation error {osc_nrmse:.3g} > {osc_threshold:g}")
    return ValidationResult(
        passed=not reasons, nrmse=nrmse, osc_nrmse=osc_nrmse, threshold=threshold, osc_threshold=osc_threshold,
        simulated=a, measured=b, mode=mode, reason="; ".join(reasons) if reasons else "model reproduces the record",
    )
