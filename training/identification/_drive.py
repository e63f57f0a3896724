"""The drive values of one record (SPEC 3): each from the record, else estimated from the
signals where that is sound, else a documented default with a coded warning that names it.

The maps were trained on drives; the record says which drive it is. Nothing here is read from
the maps.

| value | record key | estimated from | default |
| --- | --- | --- | --- |
| ``T_s`` | ``T_s`` | ``t`` (:func:`sim.records.validate`) | |
| ``T_Ei`` | ``T_Ei`` | | the reference drive's 0.5 ms (warned) |
| ``encoder_counts`` | ``encoder_counts`` | the speed's quantum ``2 pi / (counts T_s)`` | the reference drive's 2^20 (warned) |
| ``M_star`` | ``M_star`` | the torque levels (the section detection) | |
| ``w_max`` | ``w_max`` | the speed at the end of section I (the switching law) | |
| ``M_N`` | ``M_N`` | | ``M*`` (warned: ``s_N`` and the class use it) |
| ``M_max`` | ``M_max`` | | none (only the envelope check uses it) |
| current noise | | the torque's sample-to-sample spread inside the sections | |
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim import DriveConfig, Record, speed_quantum, time_scale
from training._settings import POSITIVE, check_settings
from training.identification._plausibility import BOUNDS, on_grid
from training.identification._result import IdentWarning
from training.identification._sections import SectionSplit, diff_noise

#: The SPEC reference drive: its encoder and current loop are assumed where a record gives neither
#: (with a warning).
REFERENCE_DRIVE = DriveConfig()



@dataclass(frozen=True)
class DriveEstimates:
    """The thresholds of the drive values estimated from the signals."""

    #: current-loop time constants after each section start before the torque holds its level.
    settle_lags: float = 5.0
    #: an encoder the speed's steps show this many times finer than the metadata's replaces it.
    finer_encoder: float = 1.5
    #: the speed's steps below this many times the smallest are one quantum (a float32 speed's scatter).
    quantum_spread: float = 1.5
    #: the fewest encoder counts per revolution an estimate may give.
    min_counts: int = 16
    #: the fewest nonzero speed samples an encoder is estimated from.
    min_samples: int = 32

    def __post_init__(self) -> None:
        check_settings(self, {"settle_lags": POSITIVE, "finer_encoder": POSITIVE, "quantum_spread": POSITIVE,
                              "min_counts": POSITIVE, "min_samples": POSITIVE})


#: The drive estimates' thresholds.
ESTIMATES = DriveEstimates()


@dataclass(frozen=True)
class DriveValues:
    """What the identification uses of the drive and of the test, each with its ``source``
    (``"record"``, ``"estimated"`` or ``"default"``): ``T_s``, ``T_Ei`` [s], ``encoder_counts``,
    ``M_star``, ``w_max`` [rad/s], ``M_N``, ``M_max`` [Nm] (``None``: not given), and
    ``current_noise`` [Nm]: the std of the measured torque's noise (estimated), ``M_hold`` [Nm]: the
    holding torque the test's levels ran around (SPEC 1.1; 0 where the record names none: plain levels)."""

    T_s: float
    T_Ei: float
    encoder_counts: int
    M_star: float
    w_max: float
    M_N: float
    M_max: float | None
    current_noise: float
    sources: dict[str, str] = field(default_factory=dict)
    M_hold: float = 0.0

    @property
    def q_w(self) -> float:
        """Speed quantum ``2 pi / (encoder_counts T_s)`` [rad/s]."""
        return speed_quantum(self.encoder_counts, self.T_s)

    @property
    def q_phi(self) -> float:
        """Angle quantum ``2 pi / encoder_counts`` [rad]."""
        return 2.0 * math.pi / self.encoder_counts

    def time_scale(self, J_sigma: float) -> float:
        """The test's time scale ``tau = J_sigma w_max / M*`` [s] for the inertia ``J_sigma``: how long
        its torque takes to reach ``w_max`` (SPEC 3.1)."""
        return time_scale(J_sigma, self.M_star, self.w_max)


def drive_values(record: Record, split: SectionSplit, torque: np.ndarray) -> tuple[DriveValues, list[IdentWarning]]:
    """The drive values of ``record`` (sections ``split``, measured ``torque`` [Nm]) and the
    warnings for each one that had to be defaulted."""
    meta, T_s = record.meta, record.T_s
    sources: dict[str, str] = {"T_s": "record"}
    warnings: list[IdentWarning] = []

    def default(name: str, value: float, why: str) -> float:
        sources[name] = "default"
        warnings.append(IdentWarning("drive_value_default", f"{name} not in the record: {why}"))
        return value

    T_Ei = meta.get("T_Ei")
    sources["T_Ei"] = "record"
    if T_Ei is None:
        T_Ei = default("T_Ei", REFERENCE_DRIVE.T_Ei, f"the reference drive's {REFERENCE_DRIVE.T_Ei:g} s is used "
                                                     "(the class rule w_e T_Ei and the refinement depend on it)")
    counts = record.encoder_counts
    sources["encoder_counts"] = "record"
    if counts is not None and on_grid(np.abs(record.speed), record.q_w) < BOUNDS.quantized_share:
        finer = estimated_encoder_counts(record.speed, T_s)  # the speed shows steps the encoder cannot make
        if finer is not None and finer > ESTIMATES.finer_encoder * counts:
            warnings.append(IdentWarning("drive_value_mismatch", f"encoder_counts {counts} (metadata) cannot make the "
                                                                 f"speed's steps of 2*pi/({finer} T_s): {finer} counts "
                                                                 "are used"))
            counts, sources["encoder_counts"] = finer, "estimated"
    if counts is None:
        counts = estimated_encoder_counts(record.speed, T_s)
        sources["encoder_counts"] = "estimated"
        if counts is None:
            counts = int(default("encoder_counts", REFERENCE_DRIVE.encoder_counts,
                                 f"the speed is not quantized, the reference drive's {REFERENCE_DRIVE.encoder_counts} "
                                 "counts are used (the oscillation's visibility in speed quanta depends on it)"))
    M_star = float(split.M_star)
    sources["M_star"] = "estimated" if split.M_star_estimated else "record"
    w_max = meta.get("w_max")
    sources["w_max"] = "record"
    if w_max is None:
        w_max = float(abs(record.speed[max(int(split.bounds[0, 1]) - 1, 0)]))  # I ends at w_m >= w_max
        sources["w_max"] = "estimated"
    M_N = meta.get("M_N")
    sources["M_N"] = "record"
    if M_N is None:
        M_N = default("M_N", M_star, f"s_N and the class use M_N = M* = {M_star:.4g} Nm (the test's torque)")
    M_max = meta.get("M_max")
    sources["M_max"] = "record" if M_max is not None else "none"
    sources["current_noise"] = "estimated"
    M_hold = meta.get("M_hold")
    sources["M_hold"] = "record" if M_hold is not None else "none"
    return DriveValues(M_hold=0.0 if M_hold is None else float(M_hold), T_s=T_s, T_Ei=float(T_Ei), encoder_counts=int(counts), M_star=M_star, w_max=float(w_max),
                       M_N=float(M_N), M_max=None if M_max is None else float(M_max),
                       current_noise=torque_noise(torque, split, T_s, float(T_Ei)), sources=sources), warnings


def estimated_encoder_counts(speed: np.ndarray, T_s: float) -> int | None:
    """Encoder counts per revolution from a quantized speed (its values are multiples of
    ``q_w = 2 pi / (counts T_s)``), or ``None`` when the speed is not quantized."""
    x = np.abs(np.asarray(speed, dtype=np.float64))
    x = x[x > 0]
    if x.size < ESTIMATES.min_samples:
        return None
    u = np.unique(x)
    if u.size < 4:
        return None
    steps = np.diff(np.concatenate([[0.0], u]))
    q0 = float(steps.min())
    if not q0 > 0:
        return None
    q = float(np.median(steps[steps < ESTIMATES.quantum_spread * q0]))
    n = np.round(x / q)  # each speed's multiple; their ratios refine q (a float32 speed's steps scatter)
    whole = n >= 1
    q = float(np.median(x[whole] / n[whole]))
    counts = int(round(2.0 * math.pi / (q * T_s)))
    if counts < ESTIMATES.min_counts or on_grid(x, speed_quantum(counts, T_s)) < BOUNDS.quantized_share:
        return None
    return counts


def torque_noise(torque: np.ndarray, split: SectionSplit, T_s: float, T_Ei: float) -> float:
    """Std [Nm] of the measured torque's noise: inside the sections, once the current loop has
    settled, the torque follows a constant reference, so the sample-to-sample spread is the noise
    (:func:`training.identification._sections.diff_noise`)."""
    parts = [torque[s[0]:s[1]] for s in settled_bounds(split, T_s, T_Ei) if s is not None]
    return diff_noise(*(parts or [torque]))


def settled_bounds(split: SectionSplit, T_s: float, T_Ei: float) -> list[tuple[int, int] | None]:
    """Per section I..VI of ``split``: ``[start, stop)`` once the current loop has settled on the
    section's level (:attr:`DriveEstimates.settle_lags` time constants ``T_Ei`` in), ``None`` where it is too short."""
    skip = int(math.ceil(ESTIMATES.settle_lags * T_Ei / T_s)) + 1
    return [(a + skip, b) if b - a > skip + 2 else None for a, b in split.bounds.tolist()]
