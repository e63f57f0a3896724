"""What a record can show, and what an answer may claim.

- **Backlash resolution**: a gap of width ``2s`` shows where the motor crosses it alone, in its
  speed or in its angle. Speed: under the smallest torque step that closes it (``0.7 M*``,
  sections III and VI) the motor reaches the relative speed ``sqrt(2 * 2s * 0.7 M* / J_M)`` at the
  contact, seen from :attr:`AnswerLimits.backlash_visible_quanta` speed quanta on (with ``J_M <= J_sigma``):
  ``2s_speed = k^2 q_w^2 J_sigma / (1.4 M*)``. Angle: the motor runs ahead of the one-mass motion
  by ``2s J_L / J_sigma = 2s V_J / (1 + V_J)`` (the ``log10_gap_lead`` feature), seen from
  :attr:`AnswerLimits.backlash_visible_counts` encoder counts on: ``2s_angle = k_phi q_phi (1 + V_J) / V_J``
  (``V_J`` the answer's, else SPEC 3.1's smallest). The record cannot show a gap below
  ``2s_res = max(q_phi, min(2s_speed, 2s_angle))``. A stiff answer (or a backlash below that
  width) then reports no width but this upper bound, with a warning, where the bound exceeds the
  width that matters (:func:`backlash_negligible`): :attr:`AnswerLimits.backlash_negligible` (precision
  gearboxes: about 1 arcmin), or less where a narrower gap already gives the mechanic a backlash
  class (``s_N = 2s C_F / (2 M_N)`` reaches ``S_N_ELASTIC``: on a small drive's stiff shaft a few
  thousandths of a degree).
- **Implausible outputs** (kept, warned): ``f_e`` above Nyquist ``0.5/T_s`` or above the current
  loop's bandwidth ``1/(2 pi T_Ei)`` (the test does not excite it), a backlash wider than the
  motor's travel in the test, a two-mass ``J_sigma`` off STEP 2's one-mass fit by more than
  :attr:`AnswerLimits.J_sigma_ratio`.
- **Impossible outputs** (not reported: ``None``, warned): non-finite or non-positive inertias,
  ``V_J``, ``f_e``, ``C_F``; a damping outside ``[0, 1)``; a negative or non-finite backlash.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sim import S_N_ELASTIC, SECTION_LEVELS, W_E_T_EI_STIFF, gap_width

from training._settings import POSITIVE, check_settings
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._result import IdentWarning, Parameters



@dataclass(frozen=True)
class AnswerLimits:
    """The thresholds of what a record can show and what an answer may claim (module docstring)."""

    #: speed quanta the motor's gap crossing must reach to be seen.
    backlash_visible_quanta: float = 2.0
    #: encoder counts the motor's lead over the one-mass motion must reach to be seen.
    backlash_visible_counts: float = 2.0
    #: [rad] a backlash bound below this is not worth a warning (precision gearboxes: about 1 arcmin).
    backlash_negligible: float = math.radians(0.01)
    #: a two-mass ``J_sigma`` off STEP 2's by more than this factor (either way) is warned.
    J_sigma_ratio: float = 2.0

    def __post_init__(self) -> None:
        check_settings(self, {"backlash_visible_quanta": POSITIVE, "backlash_visible_counts": POSITIVE,
                              "backlash_negligible": POSITIVE, "J_sigma_ratio": POSITIVE})


#: The limits of the answers.
LIMITS = AnswerLimits()
#: :attr:`AnswerLimits.backlash_visible_counts` of :data:`LIMITS` (the evaluation's figures read it).
BACKLASH_VISIBLE_COUNTS = LIMITS.backlash_visible_counts
V_J_SMALLEST = SPEC_ENVELOPE["V_J"][0]  # the inertia ratio assumed where the answer has none
#: ``J_M J_L / J_sigma^2 = V_J / (1 + V_J)^2`` at its smallest over SPEC 3.1's ``V_J`` (at either end)
_MASS_PRODUCT_SMALLEST = min(v / (1.0 + v) ** 2 for v in SPEC_ENVELOPE["V_J"])
_LOW_LEVEL = SECTION_LEVELS[5]  # the torque of sections III and VI over M*

_POSITIVE = ("J_sigma", "V_J", "J_M", "J_L", "f_e", "C_F")


def motor_lead(backlash: float, V_J: float) -> float:
    """The angle [rad] by which the motor runs ahead of the one-mass motion after crossing a gap of
    width ``backlash`` alone: ``2s J_L / J_sigma = 2s V_J / (1 + V_J)`` (floats or arrays)."""
    return backlash * V_J / (1.0 + V_J)


def backlash_resolution(q_w: float, q_phi: float, J_sigma: float, M_star: float, V_J: float | None = None) -> float:
    """The widest backlash ``2s`` [rad] the record cannot show (see the module docstring)."""
    v = V_J if V_J is not None and V_J > 0 else V_J_SMALLEST
    by_angle = LIMITS.backlash_visible_counts * q_phi / motor_lead(1.0, v)
    return max(q_phi, min(speed_resolution(q_w, J_sigma, M_star), by_angle))


def speed_resolution(q_w: float, J_sigma: float, M_star: float) -> float:
    """The widest backlash ``2s`` [rad] the motor speed alone cannot show (see the module docstring)."""
    k = LIMITS.backlash_visible_quanta
    return k * k * q_w * q_w * J_sigma / (2.0 * _LOW_LEVEL * M_star)


def backlash_negligible(M_N: float, T_Ei: float, J_sigma: float, C_F: float | None = None) -> float:
    """The widest backlash ``2s`` [rad] not worth a warning: :attr:`AnswerLimits.backlash_negligible`, or the
    width from which the class rule counts the gap (``s_N >= S_N_ELASTIC``: ``2s = 2 S_N_ELASTIC M_N
    / C_F``) where that is narrower. ``C_F`` [Nm/rad] the answer's; without one (a stiff answer) that
    of the softest stiff shaft, ``w_e T_Ei = 1`` at SPEC 3.1's extreme ``V_J`` (``J_M J_L / J_sigma
    = J_sigma V_J / (1 + V_J)^2`` is smallest there): the widest gap that can still count."""
    if C_F is None or not C_F > 0:
        C_F = _MASS_PRODUCT_SMALLEST * J_sigma * (W_E_T_EI_STIFF / T_Ei) ** 2
    return min(LIMITS.backlash_negligible, gap_width(S_N_ELASTIC, M_N, C_F))


def travel(speed: np.ndarray, T_s: float) -> float:
    """The motor's travel in the test [rad]: the span of its angle (the integrated speed)."""
    angle = np.cumsum(np.asarray(speed, dtype=np.float64)) * T_s
    return float(np.ptp(angle)) if angle.size else 0.0


def impossible(p: Parameters) -> tuple[Parameters, list[IdentWarning]]:
    """``p`` without the values no mechanic can have (set to ``None``), and a warning for each."""
    bad: dict[str, float] = {}
    for name in _POSITIVE:
        v = getattr(p, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            bad[name] = v
    if p.d is not None and not (math.isfinite(p.d) and 0.0 <= p.d < 1.0):
        bad["d"] = p.d
    for name in ("backlash", "M_FC", "mu_F"):
        v = getattr(p, name)
        if v is not None and not (math.isfinite(v) and v >= 0):
            bad[name] = v
    if not bad:
        return p, []
    warns = [IdentWarning("impossible_output", f"{name} = {v!r} is physically impossible: not reported")
             for name, v in bad.items()]
    return replace(p, **dict.fromkeys(bad)), warns


def implausible(p: Parameters, *, T_s: float, T_Ei: float, travel: float, J_sigma_one_mass: float) -> list[IdentWarning]:
    """A warning for each value of ``p`` that the record cannot support (module docstring)."""
    out = []
    if p.f_e is not None:
        nyquist, bandwidth = 0.5 / T_s, 1.0 / (2.0 * math.pi * T_Ei)
        if p.f_e > nyquist:
            out.append(IdentWarning("implausible_output", f"f_e = {p.f_e:.4g} Hz lies above Nyquist ({nyquist:.4g} Hz "
                                                          "= 0.5/T_s): the record cannot show it"))
        elif p.f_e > bandwidth:
            out.append(IdentWarning("implausible_output", f"f_e = {p.f_e:.4g} Hz lies above the current loop's "
                                                          f"bandwidth ({bandwidth:.4g} Hz = 1/(2 pi T_Ei)): the test "
                                                          "excites it weakly, f_e is less certain"))
    if p.backlash is not None and travel > 0 and p.backlash > travel:
        out.append(IdentWarning("implausible_output", f"backlash = {p.backlash:.4g} rad is wider than the motor's "
                                                      f"travel in the test ({travel:.4g} rad)"))
    if p.J_sigma is not None and J_sigma_one_mass > 0:
        ratio = p.J_sigma / J_sigma_one_mass
        if not 1.0 / LIMITS.J_sigma_ratio <= ratio <= LIMITS.J_sigma_ratio:
            out.append(IdentWarning("implausible_output", f"J_sigma = {p.J_sigma:.4g} kg m^2 is {ratio:.3g} x the "
                                                          f"one-mass fit's ({J_sigma_one_mass:.4g} kg m^2)"))
    return out
