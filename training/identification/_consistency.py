"""Does the record show SPEC 2's test with its own metadata? Warnings where it does not.

A record can be well formed and plausible in its units (:mod:`._plausibility`) and still not be
the test its metadata describe: a speed clipped at the scope's full scale just below ``w_max``, a
``w_max`` or ``K_M`` that is not the drive's, a recording triggered after the test had started,
a run the drive aborted at a limit. The identification then fits the wrong torque or the wrong
speed and answers with confidence; these checks say so (coded warnings, the answer stands):

- ``test_law_mismatch``: the switching law replayed on the record's own speed with its ``w_max``
  (:func:`._sections.law_end`) ends a section elsewhere than the record does, by more than the
  section detection's uncertainty (exact with ``torque_ref``; the current loop's lag without);
  not checked on runs that timed out, were aborted or start late (the law's durations fail there);
  also a speed clipped at ``w_max`` itself, whose ends the law keeps (:func:`_clipped`);
- ``torque_scale_mismatch``: the measured torque (``current * K_M``) holds its levels at another
  scale than ``M*`` (metadata, else ``torque_ref``'s levels) by more than :attr:`ConsistencyTolerances.torque_scale`;
- ``record_starts_late``: section I starts at a speed above a few quanta (the test starts at rest);
- ``run_aborted``: metadata ``aborted: true`` (the drive stopped the run at a limit, SPEC 8.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim import SECTION_LEVELS, SECTION_NAMES, Record
from training._settings import POSITIVE, SHARE, check_settings
from training.identification._drive import DriveValues, settled_bounds
from training.identification._result import IdentWarning
from training.identification._sections import SectionSplit, law_end, torque_amplitude

__all__ = ["consistency_warnings", "torque_scale_hint", "ConsistencyTolerances", "TOLERANCES"]


@dataclass(frozen=True)
class ConsistencyTolerances:
    """How far a record may stray from its metadata and from SPEC 2's test before a warning."""

    #: the measured torque's levels may differ from ``M*``'s by this share before ``torque_scale_mismatch``.
    torque_scale: float = 0.15
    #: section I starts "late" above this many speed quanta ...
    start_quanta: float = 3.0
    #: ... or this share of ``w_max``, the larger.
    start_share: float = 0.01
    #: the speed quanta per sample the speed must still gain at a switch to call a flat top clipped.
    clip_quanta: float = 3.0
    #: a section may end this many current-loop lags ``T_Ei`` (plus two samples) off the law's end.
    law_lags: float = 2.0

    def __post_init__(self) -> None:
        check_settings(self, {"torque_scale": SHARE, "start_quanta": POSITIVE, "start_share": SHARE,
                              "clip_quanta": POSITIVE, "law_lags": POSITIVE})


#: The consistency checks' tolerances.
TOLERANCES = ConsistencyTolerances()


def consistency_warnings(record: Record, split: SectionSplit, drive: DriveValues,
                         torque: np.ndarray) -> list[IdentWarning]:
    """The warnings of the module docstring for ``record`` with sections ``split``, its drive
    values ``drive`` (its test's ``w_max`` [rad/s] from the record or estimated, speed quantum
    ``q_w`` [rad/s], current-loop lag ``T_Ei`` [s]) and measured torque ``torque`` [Nm]
    (``record.motor_torque``)."""
    w_max, q_w, T_Ei = drive.w_max, drive.q_w, drive.T_Ei
    out = []
    if record.meta.get("aborted"):
        out.append(IdentWarning("run_aborted", "the drive aborted this run at a limit (metadata aborted: true): the "
                                               "test is incomplete, its values are suspect"))
    speed = record.speed
    start = int(split.bounds[0, 0])
    if abs(speed[start]) > max(TOLERANCES.start_quanta * q_w, TOLERANCES.start_share * w_max):
        out.append(IdentWarning("record_starts_late", f"section I starts at {speed[start]:.4g} rad/s, not at rest: the "
                                                      "recording began after the test had started (its first torque "
                                                      "step is missing)"))
    # the law's durations and thresholds hold for a whole run that no limit or timeout cut short
    law = _law_mismatch(speed, split, w_max, math.ceil(TOLERANCES.law_lags * T_Ei / record.T_s) + 2) \
        if not out and not record.timed_out else []
    return out + (law or _clipped(speed, split, q_w)) + _torque_scale(record, split, torque, T_Ei)


def _clipped(speed: np.ndarray, split: SectionSplit, q_w: float) -> list[IdentWarning]:
    """``test_law_mismatch`` for a speed clipped at the switching speed itself (a scope's full
    scale set to ``w_max``): where I (IV) ends the speed rose (fell) by :attr:`ConsistencyTolerances.clip_quanta` quanta
    a sample, and the current loop's lag still drives it on for a sample or more; the record
    instead holds its extreme value, exactly, from the switch on."""
    for k, sign in ((0, 1.0), (3, -1.0)):
        j = int(split.bounds[k, 1]) - 1  # the sample whose speed ended the section
        if j < 2 or j + 3 > speed.size:
            continue
        w = sign * speed
        if w[j - 1] - w[j - 2] >= TOLERANCES.clip_quanta * q_w and np.all(w[j:j + 3] == w.max()):
            return [IdentWarning("test_law_mismatch", f"the speed holds {speed[j]:.4g} rad/s exactly from the end of "
                                                      f"section {SECTION_NAMES[k]} on, where it moved by "
                                                      f"{w[j - 1] - w[j - 2]:.3g} rad/s a sample before: a speed "
                                                      "clipped at the scope's full scale? the values are suspect")]
    return []


def torque_scale_hint(record: Record) -> str | None:
    """Why the sections may not show: the largest level of ``torque_ref``, else of the measured
    torque, off the metadata's ``M_star`` by more than :attr:`ConsistencyTolerances.torque_scale` (else None)."""
    M_star = record.meta.get("M_star")
    if M_star is None:
        return None
    for what, signal in (("torque_ref", record.torque_ref), (_measured(record), record.motor_torque)):
        if signal is None or not np.any(signal):
            continue
        scale = torque_amplitude(signal) / float(M_star)
        if abs(scale - 1.0) > TOLERANCES.torque_scale:
            why = "its units (Nm) or M_star wrong?" if what == "torque_ref" else "K_M, M_star or the current's units wrong?"
            return f"{what} reaches {scale:.3g} x metadata M_star = {float(M_star):.4g} Nm: {why}"
    return None


def _law_mismatch(speed: np.ndarray, split: SectionSplit, w_max: float, lag: int) -> list[IdentWarning]:
    """``test_law_mismatch`` for the first section whose end the law puts elsewhere (each section
    replayed from the record's own start of it, so that one disagreement does not cascade)."""
    tol = 1 if split.source == "torque_ref" else lag
    bounds = split.bounds.tolist()
    before = [0] + [b - a for a, b in bounds]  # the length of the section before each one
    for k, (a, b) in enumerate(bounds):
        try:
            end = law_end(speed, k, a, before[k], w_max)
        except ValueError:
            end = None
        if k == 5 and b >= speed.size and (end is None or end >= b):
            continue  # the record ends in VI
        if end is None or abs(end - b) > tol:
            law = "never" if end is None else f"at sample {end} ({speed[end - 1]:.4g} rad/s)"
            return [IdentWarning("test_law_mismatch", f"section {SECTION_NAMES[k]} ends at sample {b} (speed "
                                                      f"{speed[b - 1]:.4g} rad/s) but SPEC 2's switching law with w_max = "
                                                      f"{w_max:.4g} rad/s ends it {law}: a clipped or filtered speed, a "
                                                      "wrong w_max, or another test; the values are suspect")]
    return []


def _torque_scale(record: Record, split: SectionSplit, torque: np.ndarray, T_Ei: float) -> list[IdentWarning]:
    """``torque_scale_mismatch`` where the measured ``torque``'s settled section means, fitted to the
    levels ``SECTION_LEVELS x M*``, give a scale off ``M*`` (unless ``M*`` was estimated from the
    measured torque itself)."""
    if split.M_star_estimated and split.source == "torque":
        return []
    num = den = 0.0
    for settled, level in zip(settled_bounds(split, record.T_s, T_Ei), SECTION_LEVELS):
        if level and settled is not None:
            lo, hi = settled
            num += level * float(np.sum(torque[lo:hi]))
            den += level * level * (hi - lo)
    if not den > 0:
        return []
    scale = num / den / split.M_star
    if abs(scale - 1.0) <= TOLERANCES.torque_scale:
        return []
    return [IdentWarning("torque_scale_mismatch", f"{_measured(record)} holds the test's levels at {scale:.3g} x M* = "
                                                  f"{split.M_star:.4g} Nm: K_M, M_star or the current's units are "
                                                  "wrong; J_sigma, V_J and friction scale with it")]


def _measured(record: Record) -> str:
    """What the measured torque of ``record`` is, as the warnings name it."""
    return "current * K_M" if record.torque is None else "the torque column"
