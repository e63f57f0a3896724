"""The controller rules (knowledge base, docs/commissioning.md "Controller rules"): turn an
identified structure and parameters into a speed-controller concept and its parameters (R1-R7),
or the cautious fallback F1, and check them on the exact sampled linear model
(:func:`training.commissioning._loop.loop_figures`), lowering the gain until the margins hold.

Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s].
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import torch

import sim

from ._law import NotchSpec, PISpeedController
from ._loop import Mechanics, drive_value, loop_figures, mechanics_from

__all__ = ["ControllerSpec", "ControllerProposal", "propose_controller", "propose_cautious"]


@dataclass(frozen=True)
class ControllerSpec:
    """Design requirements and rule constants (see docs/commissioning.md, "Controller rules").

    ``a``: symmetric-optimum ratio (``w_c = 1/(a T_sigma)``, ``Ti = a^2 T_sigma``; 2 = classic
    SO, 37 deg; 3 = 53 deg). ``a_backlash``: the same for backlash structures (lower gain).
    ``anti_resonance_ratio``: ``w_c <= ratio(V_J) * w_A`` as ``(V_J_small, ratio_small,
    ratio_mid, V_J_large, ratio_large)``. ``min_phase_margin`` [deg], ``min_gain_margin_dB``:
    the check on the linear model; the gain is lowered by ``backoff`` until both hold.
    ``speed_filter_samples``: low-pass ``T_f`` in samples (0: none). ``allow_notch``: try a notch
    at the resonance when the elastic bandwidth limit costs more than ``notch_gain_factor``.
    ``cautious_bandwidth`` [rad/s]: the crossover of the fallback F1 (:func:`propose_cautious`),
    below R3's limit for every mechanic of the SPEC population (the lowest anti-resonance there,
    5 Hz with ``V_J = 5``, is 12.8 rad/s; R3 allows 0.3 of it).
    """

    a: float = 3.0
    a_backlash: float = 4.0
    anti_resonance_ratio: tuple[float, float, float, float, float] = (0.5, 1.0, 0.5, 2.0, 0.3)
    min_phase_margin: float = 45.0
    min_gain_margin_dB: float = 6.0
    backoff: float = 0.8
    max_backoff_steps: int = 30
    speed_filter_samples: float = 1.0
    allow_notch: bool = True
    notch_gain_factor: float = 3.0
    cautious_bandwidth: float = 3.0


@dataclass(frozen=True)
class ControllerProposal:
    """A speed-controller concept and its parameters, with the expected figures and the rules used.

    ``concept``: "PI", "PI+lowpass" or "PI+lowpass+notch". ``Kp`` [Nm s/rad], ``Ti`` [s],
    ``T_f`` [s] (speed low-pass, 0 = none), ``notch`` (or None). ``figures``: :func:`loop_figures`.
    """

    concept: str
    Kp: float
    Ti: float
    T_f: float
    notch: NotchSpec | None
    figures: dict[str, float]
    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    structure: str = "stiff"
    mechanics: Mechanics | None = field(default=None, repr=False)

    def build(self, drive: Any, *, w_ref: float | torch.Tensor = 0.0, Kp: Any = None, Ti: Any = None, T_f: Any = None) -> PISpeedController:
        """The controller object on ``drive`` (gains overridable, e.g. by batched tensors)."""
        return PISpeedController(
            self.Kp if Kp is None else Kp,
            self.Ti if Ti is None else Ti,
            T_s=drive_value(drive, "T_s"),
            M_max=drive_value(drive, "M_max"),
            T_f=self.T_f if T_f is None else T_f,
            notch=self.notch,
            w_ref=w_ref,
        )

    def with_gains(self, drive: Any, Kp: float, Ti: float, T_f: float, rule: str) -> ControllerProposal:
        """A copy with new gains, new figures and one more rule line."""
        figs = loop_figures(self.mechanics, drive, Kp, Ti, T_f, self.notch)
        return replace(self, Kp=Kp, Ti=Ti, T_f=T_f, figures=figs, rules=self.rules + (rule,))

    def to_dict(self) -> dict[str, Any]:
        return {
            "concept": self.concept, "structure": self.structure, "Kp": self.Kp, "Ti": self.Ti, "T_f": self.T_f,
            "notch": None if self.notch is None else {"f_n": self.notch.f_n, "D_z": self.notch.D_z, "D_p": self.notch.D_p},
            "figures": dict(self.figures), "rules": list(self.rules), "warnings": list(self.warnings),
        }


def _margins_ok(f: dict[str, float], spec: ControllerSpec) -> bool:
    return bool(f["stable"]) and f["phase_margin"] >= spec.min_phase_margin and f["gain_margin_dB"] >= spec.min_gain_margin_dB


def propose_controller(
    structure: str,
    params: Mapping[str, Any] | Any,
    drive: Any,
    spec: ControllerSpec | None = None,
) -> ControllerProposal:
    """Propose a speed controller from the identified structure and parameters (rules R1-R7).

    Args:
        structure: one of :data:`sim.STRUCTURE_CLASSES`.
        params: identified parameters (dict or one-system TwoMassParams), at least ``J_sigma``;
            ``V_J`` and ``f_e`` for the elastic structures.
        drive: DriveConfig (``T_s``, ``T_Ei``, ``M_max``).
        spec: rule constants and margin requirements.

    Returns a :class:`ControllerProposal` whose ``figures`` come from the exact sampled linear
    two-mass model (delays included) and meet ``spec``'s margins where the rules could reach them
    (else a warning says so).
    """
    spec = spec or ControllerSpec()
    if structure not in sim.STRUCTURE_CLASSES:
        raise ValueError(f"structure: expected one of {sim.STRUCTURE_CLASSES}, received {structure!r}")
    mech = mechanics_from(params)
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    drive_value(drive, "M_max")
    elastic = structure in ("elastic", "elastic_backlash")
    if elastic and not mech.two_mass:
        raise ValueError(f"structure {structure!r} needs V_J and f_e, received V_J={mech.V_J}, f_e={mech.f_e}")
    rules: list[str] = []
    warnings: list[str] = []
    backlash = structure in ("elastic_backlash", "stiff_backlash")

    # R1: small sum time constant of the current loop, filter and sampled speed loop
    T_f = spec.speed_filter_samples * T_s
    T_sigma = T_Ei + 2.0 * T_s + T_f
    rules.append(f"R1 T_sigma = T_Ei + 2 T_s + T_f = {T_sigma:.3g} s (T_f = {T_f:.3g} s speed low-pass)")
    # R2: symmetric optimum on the total inertia
    a = spec.a_backlash if backlash else spec.a
    w_c = 1.0 / (a * T_sigma)
    rules.append(f"R2 symmetric optimum a = {a:g}: w_c = 1/(a T_sigma) = {w_c:.4g} rad/s on J_sigma")
    if backlash:
        rules.append(f"R6 backlash: a = {spec.a_backlash:g} (lower gain) instead of {spec.a:g}")
        warnings.append("backlash: integral action with backlash can cause a limit cycle around standstill; "
                        "keep Ti long and check the closed loop at low speed")
    notch, w_lim = None, w_c
    if elastic:
        w_c, w_lim, notch = _elastic_limit(mech, w_c, T_s, spec, rules)
    Kp = mech.J_sigma * w_c
    Ti = a / w_c if not elastic else max(a / w_c, a * a * T_sigma)
    rules.append(f"R5 Kp = J_sigma w_c = {Kp:.4g} Nm s/rad, Ti = a / w_c = {Ti:.4g} s")
    concept = "PI" + ("+lowpass" if T_f > 0 else "") + ("+notch" if notch is not None else "")
    prop = ControllerProposal(concept, Kp, Ti, T_f, notch, loop_figures(mech, drive, Kp, Ti, T_f, notch),
                              tuple(rules), tuple(warnings), structure, mech)
    # R4b: a notch that does not help is dropped again
    if notch is not None and not _margins_ok(prop.figures, spec):
        Kp, Ti = mech.J_sigma * w_lim, max(a / w_lim, a * a * T_sigma)
        prop = replace(prop, concept=concept.replace("+notch", ""), notch=None,
                       figures=loop_figures(mech, drive, Kp, Ti, T_f, None), Kp=Kp, Ti=Ti,
                       rules=prop.rules + (f"R4b notch did not meet the margins: dropped, w_c = {w_lim:.4g} rad/s",))
    return _back_off(prop, mech, drive, spec)


def _elastic_limit(mech: Mechanics, w_c: float, T_s: float, spec: ControllerSpec,
                   rules: list[str]) -> tuple[float, float, NotchSpec | None]:
    """R3 (the elastic bandwidth limit ``w_lim`` from the anti-resonance, by inertia ratio) and R4
    (a notch at the resonance when the limit costs much bandwidth and ``f_0`` is resolvable).
    Returns ``(w_c, w_lim, notch)`` and appends the rule lines to ``rules``."""
    v_small, r_small, r_mid, v_large, r_large = spec.anti_resonance_ratio
    ratio = r_small if mech.V_J <= v_small else (r_mid if mech.V_J <= v_large else r_large)
    w_lim = ratio * mech.w_A
    rules.append(f"R3 elastic: V_J = {mech.V_J:.3g} -> w_c <= {ratio:g} w_A = {w_lim:.4g} rad/s "
                 f"(w_A = {mech.w_A:.4g}, w_0 = {mech.derived.w_0:.4g} rad/s)")
    if w_c <= w_lim:
        return w_c, w_lim, None
    f_0 = mech.derived.w_0 / (2 * math.pi)
    if not (spec.allow_notch and w_c > spec.notch_gain_factor * w_lim and f_0 < 0.4 / T_s):
        return w_lim, w_lim, None
    notch = NotchSpec(f_n=f_0, D_z=max(mech.d, 0.02), D_p=0.7)
    w_c = min(w_c, 0.8 * mech.w_A)
    rules.append(f"R4 notch at f_0 = {f_0:.4g} Hz (D_z = {notch.D_z:.3g}, D_p = 0.7): w_c = 0.8 w_A = {w_c:.4g} rad/s")
    return w_c, w_lim, notch


def _back_off(prop: ControllerProposal, mech: Mechanics, drive: Any, spec: ControllerSpec) -> ControllerProposal:
    """R7: check on the linear model; lower the gain (and slow the integral) until the margins
    hold, else warn that they were not reached."""
    steps = 0
    while not _margins_ok(prop.figures, spec) and steps < spec.max_backoff_steps:
        steps += 1
        prop = replace(prop, Kp=prop.Kp * spec.backoff, Ti=prop.Ti / spec.backoff)
        prop = replace(prop, figures=loop_figures(mech, drive, prop.Kp, prop.Ti, prop.T_f, prop.notch))
    if steps:
        prop = replace(prop, rules=prop.rules + (f"R7 margins: Kp x {spec.backoff:g}^{steps}, Ti / {spec.backoff:g}^{steps} "
                                                 f"-> PM {prop.figures['phase_margin']:.1f} deg, GM {prop.figures['gain_margin_dB']:.1f} dB",))
    if not _margins_ok(prop.figures, spec):
        prop = replace(prop, warnings=prop.warnings + (
            f"margins not reached on the linear model (PM {prop.figures['phase_margin']:.1f} deg, "
            f"GM {prop.figures['gain_margin_dB']:.1f} dB, stable={bool(prop.figures['stable'])})",))
    return prop


def propose_cautious(J_sigma: float, drive: Any, spec: ControllerSpec | None = None) -> ControllerProposal:
    """Fallback F1 when the identification is refused: a PI on the one-mass ``J_sigma`` of STEP 2
    alone (least squares on the whole record, the most robust figure of a test run) with the
    crossover ``spec.cautious_bandwidth``, far below any plausible anti-resonance, and a long
    integral time (``Ti = a / w_c``). It is meant as the start of a search on the plant itself
    (the mechanic's model is not trusted), not as a tuned controller."""
    spec = spec or ControllerSpec()
    if not (isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0):
        raise ValueError(f"J_sigma: expected a finite number > 0, received {J_sigma!r}")
    prop = propose_controller("stiff", {"J_sigma": float(J_sigma)}, drive, spec)
    w_c = spec.cautious_bandwidth
    return prop.with_gains(drive, float(J_sigma) * w_c, spec.a / w_c, prop.T_f, rule=(
        f"F1 identification refused: cautious PI on J_sigma alone, w_c = {w_c:g} rad/s (below R3's limit for "
        f"every mechanic of the SPEC population), Kp = {float(J_sigma) * w_c:.4g} Nm s/rad, Ti = a / w_c = "
        f"{spec.a / w_c:.4g} s; to be tuned on the plant"))
