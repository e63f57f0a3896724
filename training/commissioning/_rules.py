"""The controller rules (knowledge base, docs/commissioning.md "Controller rules"): turn an
identified structure and parameters into a speed-controller concept and its parameters, or the
cautious fallback F1, and check them on the exact sampled linear model
(:func:`training.commissioning._loop.loop_figures`), lowering the gain until the margins hold.

:func:`propose_controller` applies :data:`CONTROLLER_RULES` in order, each a named function over
the typed inputs (:class:`DesignInputs`) and the design so far (:class:`Design`):

    R1 sum time constant -> R2 symmetric optimum -> R6 backlash -> R3 elastic limit -> R4 notch
    -> R5 gains -> R7/R7b the guarantee's model set -> R4b drop a useless notch -> R7 back off
    -> R8 alternatives

Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s].
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

import sim
from training._settings import FLAG, NON_NEGATIVE, POSITIVE, SHARE, Constraint, Interval, Pair, Values, check_settings
from training.errors import CommissioningError

from ._law import NotchSpec, PISpeedLaw
from ._loop import Margins, Mechanics, ModelSet, drive_value, loop_figures, mechanics_from, model_set

__all__ = ["ControllerSpec", "ControllerProposal", "DesignInputs", "Design", "CONTROLLER_RULES", "propose_controller",
           "propose_cautious", "robust_models"]


@dataclass(frozen=True)
class ControllerSpec:
    """Design requirements and rule settings (docs/commissioning.md, "Controller rules"); checked
    on construction.

    The guarantee (rule R7; every delivered loop): ``min_phase_margin`` and ``min_gain_margin_dB``
    on every model of :func:`robust_models`: the identified mechanic as it is and with ``f_e``,
    ``V_J`` x (1 -+ ``spread``), each with the current loop as a second-order lag of damping
    ``current_loop_damping`` and ``extra_delay`` more samples of dead time; the gain is lowered by
    ``backoff`` (at most ``max_backoff_steps`` times) until the margins hold.

    Fallback F1 (:func:`propose_cautious`): the worst case of the class over ``class_V_J`` and the
    eigenfrequency band the test run allows (inside ``class_f_e``) at damping ``class_d``; the
    highest crossover of ``f1_steps`` log-spaced values from the symmetric optimum down to
    ``f1_w_c_min`` that keeps the margins; ``Ti = a_backlash / w_c``.
    """

    a: float = 3.0
    """R2: symmetric-optimum ratio (``w_c = 1/(a T_sigma)``, ``Ti = a^2 T_sigma``; 2 = classic SO, 37 deg; 3 = 53 deg)."""
    a_backlash: float = 4.0
    """R6: the symmetric-optimum ratio of backlash structures (lower gain); F1's ``Ti = a_backlash / w_c``."""
    anti_resonance_ratio: tuple[float, float, float, float, float] = (0.5, 1.0, 0.5, 2.0, 0.3)
    """R3: ``w_c <= ratio(V_J) w_A`` as ``(V_J_small, ratio_small, ratio_mid, V_J_large, ratio_large)``."""
    min_phase_margin: float = 40.0
    """R7: the guaranteed phase margin [deg]."""
    min_gain_margin_dB: float = 6.0
    """R7: the guaranteed gain margin [dB]."""
    spread: float = 0.3
    """R7: the guarantee's relative spread of ``f_e`` and ``V_J``."""
    current_loop_damping: float = 1 / math.sqrt(2)
    """R7: damping of the current loop as a second-order lag in the guarantee's models."""
    extra_delay: int = 1
    """R7: samples of dead time the guarantee's models add."""
    backoff: float = 0.8
    """R7: the factor the gain is lowered by per step."""
    max_backoff_steps: int = 30
    """R7: most steps of ``backoff``."""
    speed_filter_samples: float = 1.0
    """R1: the speed low-pass ``T_f`` in samples (0: none)."""
    allow_notch: bool = True
    """R4: a notch at the resonance may be tried."""
    notch_gain_factor: float = 3.0
    """R4: the notch is tried when the elastic limit costs more than this factor of crossover."""
    notch_max_share: float = 0.4
    """R4, R8: a notch only below this share of the sampling frequency (resolvable, little warped)."""
    notch_min_depth: float = 0.02
    """R4: the notch's ``D_z`` is the mechanic's damping, at least this."""
    notch_width: float = 0.7
    """R4: the notch's ``D_p``."""
    notch_w_A_share: float = 0.8
    """R4: with a notch, the crossover at most this share of the anti-resonance ``w_A``."""
    alternative_below: float = 0.5
    """R8: alternatives are tried when R7 lowered the crossover below this share of the design's."""
    wide_notch_depth: float = 0.05
    """R8: the wide notch's ``D_z`` (at least the mechanic's damping)."""
    wide_notch_width: float = 1.0
    """R8: the wide notch's ``D_p`` (the spread of ``f_e`` stays inside it)."""
    alternative_filters_elastic: tuple[float, ...] = (0.0,)
    """R8, an elastic design: the speed low-pass ``T_f`` tried, as multiples of R1's (0: none)."""
    alternative_filters_hidden: tuple[float, ...] = (0.0, 2.0, 4.0)
    """R8, a design with R7b's hidden resonances: the speed low-pass ``T_f`` tried, as multiples of R1's."""
    class_f_e: tuple[float, float] = (5.0, 500.0)
    """F1: the class's eigenfrequency band [Hz] (the drive envelope)."""
    class_V_J: tuple[float, ...] = (0.2, 1.0, 5.0)
    """F1, R7b: the class's inertia ratios."""
    class_d: float = 0.005
    """F1, R7b: the class's damping (light: the worst case)."""
    class_points_per_decade: float = 8.0
    """F1, R7b: eigenfrequencies per decade of a band (a lightly damped resonance is narrow; its worst case moves smoothly)."""
    class_min_points: int = 5
    """F1, R7b: fewest eigenfrequencies of a band."""
    class_single_width: float = 1.01
    """F1, R7b: a band no wider than this ratio is one eigenfrequency."""
    f1_steps: int = 40
    """F1: crossovers tried, log-spaced from the symmetric optimum down."""
    f1_w_c_min: float = 1.0
    """F1: the lowest crossover tried [rad/s]."""

    def __post_init__(self) -> None:
        check_settings(self, _SPEC_CONSTRAINTS, CommissioningError)


_SPEC_CONSTRAINTS: dict[str, Constraint] = {
    "a": Interval(1.0, open_low=True), "a_backlash": Interval(1.0, open_low=True), "min_phase_margin": Interval(0.0, 90.0),
    "min_gain_margin_dB": NON_NEGATIVE, "spread": Interval(0.0, 1.0, open_high=True), "current_loop_damping": POSITIVE,
    "extra_delay": Interval(0, integer=True), "backoff": Interval(0.0, 1.0, open_low=True, open_high=True),
    "max_backoff_steps": Interval(1, integer=True), "speed_filter_samples": NON_NEGATIVE, "notch_gain_factor": POSITIVE,
    "notch_max_share": Interval(0.0, 0.5, open_low=True, open_high=True), "notch_min_depth": NON_NEGATIVE, "notch_width": POSITIVE,
    "notch_w_A_share": POSITIVE, "alternative_below": SHARE, "wide_notch_depth": NON_NEGATIVE, "wide_notch_width": POSITIVE,
    "class_d": NON_NEGATIVE, "class_points_per_decade": POSITIVE, "class_min_points": Interval(1, integer=True),
    "class_single_width": Interval(1.0), "f1_steps": Interval(1, integer=True), "f1_w_c_min": POSITIVE, "allow_notch": FLAG,
    "anti_resonance_ratio": Values(POSITIVE, 5), "class_f_e": Pair(POSITIVE), "class_V_J": Values(POSITIVE, empty=False),
    "alternative_filters_elastic": Values(NON_NEGATIVE, empty=False), "alternative_filters_hidden": Values(NON_NEGATIVE, empty=False),
}


@dataclass(frozen=True)
class ControllerProposal:
    """A speed-controller concept and its parameters, with the expected figures and the rules used.

    ``concept``: "PI", "PI+lowpass" or "PI+lowpass+notch". ``Kp`` [Nm s/rad], ``Ti`` [s],
    ``T_f`` [s] (speed low-pass, 0 = none), ``notch`` (or None). ``figures``: :func:`loop_figures`
    on the model the design assumes; ``margins``: the worst :class:`Margins` over ``models`` (the
    guarantee's model set); ``rules``: the rule lines (each starts with its code).
    """

    concept: str
    Kp: float
    Ti: float
    T_f: float
    notch: NotchSpec | None
    figures: dict[str, float]
    margins: Margins
    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    structure: str = "stiff"
    mechanics: Mechanics | None = field(default=None, repr=False)
    models: ModelSet | None = field(default=None, repr=False)

    def law(self, config: Any, *, Kp: Any = None, Ti: Any = None, T_f: Any = None) -> PISpeedLaw:
        """The SPEC 8.1 law on the drive ``config`` (gains overridable, e.g. by arrays ``B``)."""
        return PISpeedLaw(self.Kp if Kp is None else Kp, self.Ti if Ti is None else Ti,
                          T_s=drive_value(config, "T_s"), M_max=drive_value(config, "M_max"),
                          T_f=self.T_f if T_f is None else T_f, notch=self.notch)

    def meets(self, spec: ControllerSpec) -> bool:
        """The guarantee: ``spec``'s margins on every model of the set."""
        return self.margins.meets(spec.min_phase_margin, spec.min_gain_margin_dB)

    def with_gains(self, config: Any, Kp: float, Ti: float, T_f: float, rule: str) -> ControllerProposal:
        """A copy with new gains, new figures and margins, and one more rule line."""
        return replace(self, Kp=Kp, Ti=Ti, T_f=T_f, figures=loop_figures(self.mechanics, config, Kp, Ti, T_f, self.notch),
                       margins=self.models.margins(Kp, Ti, T_f, self.notch), rules=self.rules + (rule,))

    def to_dict(self) -> dict[str, Any]:
        m = self.margins
        return {
            "concept": self.concept, "structure": self.structure, "Kp": self.Kp, "Ti": self.Ti, "T_f": self.T_f,
            "notch": None if self.notch is None else {"f_n": self.notch.f_n, "D_z": self.notch.D_z, "D_p": self.notch.D_p},
            "figures": dict(self.figures),
            "margins": {"phase_margin": m.phase_margin, "gain_margin_dB": m.gain_margin_dB, "w_c": m.w_c,
                        "stable": m.stable, "worst_model": m.model},
            "rules": list(self.rules), "rule_codes": [r.split(" ", 1)[0] for r in self.rules], "warnings": list(self.warnings),
        }


def robust_models(mechanics: Any, config: Any, spec: ControllerSpec, *,
                  hidden: dict[float, tuple[float, float]] | None = None) -> ModelSet:
    """The guarantee's model set for one mechanic or a list (:func:`model_set` with ``spec``'s spread,
    second-order current loop and extra delay), plus, with ``hidden`` (``V_J -> (f_lo, f_hi)`` [Hz]),
    the lightly damped resonances a ``stiff`` answer cannot exclude on the first mechanic's
    ``J_sigma`` (each as it is and with the current loop and delay, no spread: they are a grid)."""
    mechs = list(mechanics) if isinstance(mechanics, (list, tuple)) else [mechanics]
    out = model_set(mechs, config, spread=spec.spread, current_loop_damping=spec.current_loop_damping,
                    extra_delay=spec.extra_delay)
    if hidden:
        J = mechanics_from(mechs[0]).J_sigma
        more = model_set(_class_mechanics(J, hidden, spec, clip=(0.0, math.inf))[1:], config, spread=0.0,
                         current_loop_damping=spec.current_loop_damping, extra_delay=spec.extra_delay)
        out = ModelSet(out.plants + more.plants, out.labels + tuple(f"hidden resonance {lab}" for lab in more.labels))
    return out


@dataclass(frozen=True)
class DesignInputs:
    """What the controller rules design from: the identified ``structure`` and ``mechanics``, the
    drive (``T_s``, ``T_Ei``), the settings, and (R7b, R8) the resonances a ``stiff`` answer cannot
    exclude (``V_J -> (f_lo, f_hi)`` [Hz]) and one the test showed (``notch_at`` [Hz])."""

    structure: str
    mechanics: Mechanics
    drive: Any
    T_s: float
    T_Ei: float
    spec: ControllerSpec
    hidden: dict[float, tuple[float, float]] | None = None
    notch_at: float | None = None

    @property
    def elastic(self) -> bool:
        return self.structure in ("elastic", "elastic_backlash")

    @property
    def backlash(self) -> bool:
        return self.structure in ("elastic_backlash", "stiff_backlash")


@dataclass(frozen=True)
class Design:
    """The design as the rules so far made it: R1's ``T_f``, ``T_sigma`` [s]; R2's ratio ``a`` and
    crossover ``w_c`` [rad/s]; R3's elastic limit ``w_lim`` [rad/s]; R4's ``notch``; R5's ``Kp``,
    ``Ti``; the rule lines and warnings; from R7's model set on the ``proposal`` (the design with
    its figures and margins) and the ``chosen`` one (after R7's back-off and R8's alternatives)."""

    T_f: float = 0.0
    T_sigma: float = 0.0
    a: float = 0.0
    w_c: float = 0.0
    w_lim: float = 0.0
    notch: NotchSpec | None = None
    Kp: float = 0.0
    Ti: float = 0.0
    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    proposal: ControllerProposal | None = None
    chosen: ControllerProposal | None = None

    def noted(self, rule: str, **changes: Any) -> Design:
        """With ``changes`` and one more rule line."""
        return replace(self, rules=self.rules + (rule,), **changes)


def _sum_time_constant(T_Ei: float, T_s: float, T_f: float) -> float:
    """R1's ``T_sigma`` [s]: the current loop's ``T_Ei``, the computation and speed-measurement delays (2 ``T_s``), the filter."""
    return T_Ei + 2.0 * T_s + T_f


def r1_sum_time_constant(inputs: DesignInputs, design: Design) -> Design:
    """R1, runs always: the small sum time constant of the current loop, the speed filter and the sampled speed loop."""
    T_f = inputs.spec.speed_filter_samples * inputs.T_s
    T_sigma = _sum_time_constant(inputs.T_Ei, inputs.T_s, T_f)
    return design.noted(f"R1 T_sigma = T_Ei + 2 T_s + T_f = {T_sigma:.3g} s (T_f = {T_f:.3g} s speed low-pass)",
                        T_f=T_f, T_sigma=T_sigma)


def r2_symmetric_optimum(inputs: DesignInputs, design: Design) -> Design:
    """R2, runs always: the symmetric optimum on the total inertia (R6's ratio for backlash)."""
    a = inputs.spec.a_backlash if inputs.backlash else inputs.spec.a
    w_c = 1.0 / (a * design.T_sigma)
    return design.noted(f"R2 symmetric optimum a = {a:g}: w_c = 1/(a T_sigma) = {w_c:.4g} rad/s on J_sigma",
                        a=a, w_c=w_c, w_lim=w_c)


def r6_backlash(inputs: DesignInputs, design: Design) -> Design:
    """R6, runs for a backlash structure: the lower gain of R2, and a warning about limit cycles."""
    if not inputs.backlash:
        return design
    spec = inputs.spec
    return design.noted(f"R6 backlash: a = {spec.a_backlash:g} (lower gain) instead of {spec.a:g}",
                        warnings=design.warnings + ("backlash: integral action with backlash can cause a limit cycle around "
                                                    "standstill; keep Ti long and check the closed loop at low speed",))


def _resonance(inputs: DesignInputs) -> float:
    """The identified resonance ``f_0`` [Hz]."""
    return inputs.mechanics.derived.w_0 / (2 * math.pi)


def _notch_pays(inputs: DesignInputs, design: Design) -> bool:
    """R4's condition: notches allowed, the elastic limit costs more than ``notch_gain_factor`` of
    crossover and the resonance is resolvable."""
    spec = inputs.spec
    return spec.allow_notch and design.w_c > spec.notch_gain_factor * design.w_lim \
        and _resonance(inputs) < spec.notch_max_share / inputs.T_s


def r3_elastic_limit(inputs: DesignInputs, design: Design) -> Design:
    """R3, runs for an elastic structure: the bandwidth limit ``w_lim`` from the anti-resonance, by
    inertia ratio; the crossover down to it unless R4's notch pays."""
    if not inputs.elastic:
        return design
    mech = inputs.mechanics
    v_small, r_small, r_mid, v_large, r_large = inputs.spec.anti_resonance_ratio
    ratio = r_small if mech.V_J <= v_small else (r_mid if mech.V_J <= v_large else r_large)
    w_lim = ratio * mech.w_A
    noted = design.noted(f"R3 elastic: V_J = {mech.V_J:.3g} -> w_c <= {ratio:g} w_A = {w_lim:.4g} rad/s "
                         f"(w_A = {mech.w_A:.4g}, w_0 = {mech.derived.w_0:.4g} rad/s)", w_lim=w_lim)
    if design.w_c <= w_lim or _notch_pays(inputs, noted):
        return noted
    return replace(noted, w_c=w_lim)


def r4_notch(inputs: DesignInputs, design: Design) -> Design:
    """R4, runs when R3's limit stays below the crossover (a notch pays): a notch at the resonance,
    the crossover at most ``notch_w_A_share`` of ``w_A``."""
    if not (inputs.elastic and design.w_c > design.w_lim and _notch_pays(inputs, design)):
        return design
    spec, mech, f_0 = inputs.spec, inputs.mechanics, _resonance(inputs)
    notch = NotchSpec(f_n=f_0, D_z=max(mech.d, spec.notch_min_depth), D_p=spec.notch_width)
    w_c = min(design.w_c, spec.notch_w_A_share * mech.w_A)
    return design.noted(f"R4 notch at f_0 = {f_0:.4g} Hz (D_z = {notch.D_z:.3g}, D_p = {spec.notch_width:g}): "
                        f"w_c = {spec.notch_w_A_share:g} w_A = {w_c:.4g} rad/s", notch=notch, w_c=w_c)


def _integral_time(inputs: DesignInputs, design: Design, w_c: float) -> float:
    """R5's ``Ti`` at the crossover ``w_c``: ``a / w_c``, for an elastic structure at least ``a^2 T_sigma``."""
    a = design.a
    return a / w_c if not inputs.elastic else max(a / w_c, a * a * design.T_sigma)


def r5_gains(inputs: DesignInputs, design: Design) -> Design:
    """R5, runs always: ``Kp = J_sigma w_c``, ``Ti`` (:func:`_integral_time`)."""
    Kp, Ti = inputs.mechanics.J_sigma * design.w_c, _integral_time(inputs, design, design.w_c)
    return design.noted(f"R5 Kp = J_sigma w_c = {Kp:.4g} Nm s/rad, Ti = a / w_c = {Ti:.4g} s", Kp=Kp, Ti=Ti)


def _concept(T_f: float, notch: NotchSpec | None) -> str:
    return "PI" + ("+lowpass" if T_f > 0 else "") + ("+notch" if notch is not None else "")


def r7_model_set(inputs: DesignInputs, design: Design) -> Design:
    """R7 and R7b, runs always: the design as a proposal with its figures and its margins on the
    guarantee's model set (R7b: with the resonances a ``stiff`` answer cannot exclude)."""
    mech, drive, hidden = inputs.mechanics, inputs.drive, inputs.hidden
    models = robust_models(mech, drive, inputs.spec, hidden=hidden)
    if hidden:
        design = design.noted(f"R7b resonances the test cannot exclude in the guarantee: {_bands_text(hidden)} "
                              f"(d {inputs.spec.class_d:g})")
    Kp, Ti, T_f, notch = design.Kp, design.Ti, design.T_f, design.notch
    proposal = ControllerProposal(_concept(T_f, notch), Kp, Ti, T_f, notch, loop_figures(mech, drive, Kp, Ti, T_f, notch),
                                  models.margins(Kp, Ti, T_f, notch), design.rules, design.warnings, inputs.structure, mech, models)
    return replace(design, proposal=proposal)


def r4b_drop_notch(inputs: DesignInputs, design: Design) -> Design:
    """R4b, runs when R4's notch does not meet the margins: dropped again, the crossover at R3's limit."""
    proposal = design.proposal
    if proposal.notch is None or proposal.meets(inputs.spec):
        return design
    mech, drive, w_lim = inputs.mechanics, inputs.drive, design.w_lim
    Kp, Ti = mech.J_sigma * w_lim, max(design.a / w_lim, design.a * design.a * design.T_sigma)
    T_f = proposal.T_f
    return replace(design, proposal=replace(
        proposal, concept=proposal.concept.replace("+notch", ""), notch=None, figures=loop_figures(mech, drive, Kp, Ti, T_f, None),
        margins=proposal.models.margins(Kp, Ti, T_f, None), Kp=Kp, Ti=Ti,
        rules=proposal.rules + (f"R4b notch did not meet the margins: dropped, w_c = {w_lim:.4g} rad/s",)))


def r7_back_off(inputs: DesignInputs, design: Design) -> Design:
    """R7, runs always: the gain lowered until the margins hold on the model set (:func:`_back_off`)."""
    return replace(design, chosen=_back_off(design.proposal, inputs.drive, inputs.spec))


def r8_alternatives(inputs: DesignInputs, design: Design) -> Design:
    """R8, runs when R7 lowered the crossover below ``alternative_below`` of the design's, for a
    two-mass mechanic or with R7b's hidden resonances: other speed filters and a wide notch (:func:`_alternatives`)."""
    spec, mech, proposal, chosen = inputs.spec, inputs.mechanics, design.proposal, design.chosen
    if chosen.figures["w_c"] >= spec.alternative_below * proposal.figures["w_c"]:
        return design
    if mech.two_mass:
        filters = tuple(share * design.T_f for share in spec.alternative_filters_elastic)
        return replace(design, chosen=_alternatives(proposal, chosen, inputs, _resonance(inputs), max(mech.d, spec.wide_notch_depth),
                                                    filters))
    if inputs.hidden:
        filters = tuple(share * design.T_f for share in spec.alternative_filters_hidden)
        return replace(design, chosen=_alternatives(proposal, chosen, inputs, inputs.notch_at, spec.wide_notch_depth, filters))
    return design


#: The controller rules :func:`propose_controller` applies, in this order.
CONTROLLER_RULES: tuple[Callable[[DesignInputs, Design], Design], ...] = (
    r1_sum_time_constant,
    r2_symmetric_optimum,
    r6_backlash,
    r3_elastic_limit,
    r4_notch,
    r5_gains,
    r7_model_set,
    r4b_drop_notch,
    r7_back_off,
    r8_alternatives,
)


def propose_controller(
    structure: str,
    params: Mapping[str, Any] | Any,
    drive: Any,
    spec: ControllerSpec | None = None,
    *,
    hidden: dict[float, tuple[float, float]] | None = None,
    notch_at: float | None = None,
) -> ControllerProposal:
    """Propose a speed controller from the identified structure and parameters (:data:`CONTROLLER_RULES`).

    Args:
        structure: one of :data:`sim.STRUCTURE_CLASSES`.
        params: identified parameters (dict or one-system TwoMassParams), at least ``J_sigma``;
            ``V_J`` and ``f_e`` for the elastic structures.
        drive: DriveConfig (``T_s``, ``T_Ei``, ``M_max``).
        spec: rule settings and margin requirements.
        hidden: for a ``stiff`` answer (or one whose oscillation the model does not reproduce), the
            resonances the test cannot exclude (``V_J -> (f_lo,
            f_hi)`` [Hz], :func:`training.commissioning._bands.hidden_bands`): rule R7b adds them to the
            guarantee's model set; ``notch_at`` [Hz]: a resonance the test showed (rule R8 may
            put a wide notch there).

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
    inputs = DesignInputs(structure, mech, drive, T_s, T_Ei, spec, hidden, notch_at)
    if inputs.elastic and not mech.two_mass:
        raise ValueError(f"structure {structure!r} needs V_J and f_e, received V_J={mech.V_J}, f_e={mech.f_e}")
    design = Design()
    for rule in CONTROLLER_RULES:
        design = rule(inputs, design)
    return design.chosen


def _alternative(prop: ControllerProposal, drive: Any, T_f: float, notch: NotchSpec | None) -> ControllerProposal:
    """``prop`` with the speed low-pass ``T_f`` [s] and ``notch`` instead of its own (an R8 line says which)."""
    what = (f"speed low-pass T_f {T_f:.3g} s" if T_f > 0 else "no speed low-pass") + \
        (f", notch at {notch.f_n:.4g} Hz (D_z {notch.D_z:.3g}, D_p {notch.D_p:g})" if notch is not None else "")
    return replace(prop, concept=_concept(T_f, notch), T_f=T_f, notch=notch, margins=prop.models.margins(prop.Kp, prop.Ti, T_f, notch),
                   figures=loop_figures(prop.mechanics, drive, prop.Kp, prop.Ti, T_f, notch),
                   rules=prop.rules + (f"R8 alternative: {what}",))


def _alternatives(prop: ControllerProposal, best: ControllerProposal, inputs: DesignInputs, f_0: float | None,
                  D_z: float, filters: tuple[float, ...]) -> ControllerProposal:
    """R8: the design with the speed low-pass ``T_f`` [s] of ``filters`` (0: none) instead of its
    own, with a wide notch at the resonance ``f_0`` [Hz] (``D_p = wide_notch_width``: the spread of
    ``f_e`` stays inside it), or both, each through R7; the highest crossover that keeps the margins
    wins (``best``: R7's)."""
    spec, drive = inputs.spec, inputs.drive
    resolvable = f_0 is not None and f_0 < spec.notch_max_share / inputs.T_s
    wide = NotchSpec(f_n=f_0, D_z=D_z, D_p=spec.wide_notch_width) if resolvable else None
    tried = {(prop.T_f, prop.notch)}
    for T_f, notch in [(T_f, notch) for T_f in (*filters, prop.T_f) for notch in (prop.notch, wide)]:
        if (T_f, notch) in tried:
            continue
        tried.add((T_f, notch))
        alt = _back_off(_alternative(prop, drive, T_f, notch), drive, spec)
        if alt.meets(spec) and (not best.meets(spec) or alt.figures["w_c"] > best.figures["w_c"]):
            best = alt
    return best


def _back_off(prop: ControllerProposal, drive: Any, spec: ControllerSpec) -> ControllerProposal:
    """R7: the margins on the guarantee's model set; lower the gain (and slow the integral) by
    ``backoff^n`` with the smallest ``n <= max_backoff_steps`` that keeps them (bisection on ``n``:
    a lower gain keeps the margins of a higher one), else warn that they were not reached (the chain
    then delivers no model-based loop)."""
    start = prop.margins

    def at(n: int) -> ControllerProposal:
        Kp, Ti = prop.Kp * spec.backoff**n, prop.Ti / spec.backoff**n
        return replace(prop, Kp=Kp, Ti=Ti, margins=prop.models.margins(Kp, Ti, prop.T_f, prop.notch))

    steps = 0
    if not prop.meets(spec):
        lo, hi, top = 0, spec.max_backoff_steps, at(spec.max_backoff_steps)
        found = {hi: top}
        if top.meets(spec):
            while hi - lo > 1:
                mid = (lo + hi) // 2
                found[mid] = at(mid)
                lo, hi = (lo, mid) if found[mid].meets(spec) else (mid, hi)
        steps, prop = hi, found[hi]
    m = prop.margins
    if steps:
        prop = replace(prop, figures=loop_figures(prop.mechanics, drive, prop.Kp, prop.Ti, prop.T_f, prop.notch),
                       rules=prop.rules + (f"R7 margins (worst of {len(prop.models.plants)} models) PM {start.phase_margin:.1f} deg, "
                                           f"GM {start.gain_margin_dB:.1f} dB: Kp x {spec.backoff:g}^{steps}, Ti / {spec.backoff:g}^{steps} "
                                           f"-> PM {m.phase_margin:.1f} deg, GM {m.gain_margin_dB:.1f} dB",))
    if not prop.meets(spec):
        prop = replace(prop, warnings=prop.warnings + (
            f"margins not reached (PM {m.phase_margin:.1f} deg, GM {m.gain_margin_dB:.1f} dB, stable={m.stable}, "
            f"worst model: {m.model})",))
    return prop


def _class_mechanics(J_sigma: float, bands: dict[float, tuple[float, float]], spec: ControllerSpec, *,
                     clip: tuple[float, float] | None = None) -> list[Mechanics]:
    """The worst cases of the class: the one-mass ``J_sigma`` and, per inertia ratio of ``bands``,
    two-mass mechanics at ``spec.class_d`` at ``spec.class_points_per_decade`` eigenfrequencies per
    decade (at least ``spec.class_min_points``) spanning its band [Hz] (clipped to ``clip``, default ``spec.class_f_e``; a
    band outside it holds none)."""
    lo, hi = spec.class_f_e if clip is None else clip
    out = [Mechanics(J_sigma)]
    for v, (f_lo, f_hi) in bands.items():
        f_lo, f_hi = max(f_lo, lo), min(f_hi, hi)
        if f_lo <= f_hi:
            n = max(spec.class_min_points, math.ceil(spec.class_points_per_decade * math.log10(f_hi / f_lo)) + 1)
            f_es = np.geomspace(f_lo, f_hi, n) if f_hi > f_lo * spec.class_single_width else np.array([f_lo])
            out += [Mechanics(J_sigma, V_J=v, f_e=float(f), d=spec.class_d) for f in f_es]
    return out


@dataclass(frozen=True)
class F1Crossover:
    """F1's crossover ``w_c`` [rad/s] and its margins on the class's models; ``found``: they hold
    (else ``w_c`` is the lowest tried)."""

    w_c: float
    margins: Margins
    found: bool


def _f1_crossover(J: float, models: ModelSet, w_top: float, T_f: float, spec: ControllerSpec) -> F1Crossover:
    """The highest of ``spec.f1_steps`` crossovers from ``w_top`` down to ``spec.f1_w_c_min`` whose
    PI (``Kp = J w_c``, ``Ti = a_backlash / w_c``) keeps the margins on ``models``."""
    a = spec.a_backlash
    for w_c in np.geomspace(w_top, min(spec.f1_w_c_min, w_top), spec.f1_steps):
        m = models.margins(J * w_c, a / w_c, T_f, None)
        if m.meets(spec.min_phase_margin, spec.min_gain_margin_dB):
            return F1Crossover(float(w_c), m, True)
    w_low = min(spec.f1_w_c_min, w_top)
    return F1Crossover(w_low, models.margins(J * w_low, a / w_low, T_f, None), False)


def propose_cautious(J_sigma: float, drive: Any, spec: ControllerSpec | None = None, *,
                     bands: dict[float, tuple[float, float]] | None = None) -> ControllerProposal:
    """Fallback F1 after a refusal: a PI+lowpass on STEP 2's one-mass ``J_sigma`` (least squares on
    the whole record, the most robust figure of a test run) whose crossover is the highest of
    ``spec.f1_steps`` values (from the symmetric optimum down to ``spec.f1_w_c_min``) that keeps the
    guarantee's margins on the worst cases of the class: per inertia ratio, the eigenfrequencies
    ``bands[V_J] = (f_lo, f_hi)`` [Hz] that the measured test run allows (default: every ratio of
    ``spec.class_V_J`` over the SPEC envelope ``spec.class_f_e``), lightly damped
    (``spec.class_d``), each as it is and with the second-order current loop and the
    extra delay. ``Ti = a_backlash / w_c``. The loop is meant to be delivered as it is (its margins
    hold on every mechanic of the set), not tuned on a model the chain does not trust."""
    spec = spec or ControllerSpec()
    if not (isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0):
        raise ValueError(f"J_sigma: expected a finite number > 0, received {J_sigma!r}")
    bands = dict(bands) if bands is not None else {v: spec.class_f_e for v in spec.class_V_J}
    J = float(J_sigma)
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    drive_value(drive, "M_max")
    T_f = spec.speed_filter_samples * T_s
    a = spec.a_backlash
    w_top = 1.0 / (spec.a * _sum_time_constant(T_Ei, T_s, T_f))
    mechs = _class_mechanics(J, bands, spec)
    models = robust_models(mechs, drive, replace(spec, spread=0.0))
    mech = Mechanics(J)
    crossover = _f1_crossover(J, models, w_top, T_f, spec)
    w_c, m = crossover.w_c, crossover.margins
    warnings: tuple[str, ...] = ()
    if not crossover.found:
        warnings = (f"F1: no crossover down to {w_c:g} rad/s keeps the margins on the worst cases of the class "
                    f"(PM {m.phase_margin:.1f} deg, GM {m.gain_margin_dB:.1f} dB)",)
    Kp, Ti = J * w_c, a / w_c
    rule = (f"F1 identification refused: cautious PI on J_sigma = {J:.4g} kg m^2 alone; w_c = {w_c:.4g} rad/s, the highest "
            f"that keeps PM >= {spec.min_phase_margin:g} deg and GM >= {spec.min_gain_margin_dB:g} dB on {len(models.plants)} "
            f"worst-case models (one-mass, {_bands_text(bands, spec.class_f_e)}; d {spec.class_d:g}; each also with a 2nd-order current loop and "
            f"+{spec.extra_delay} sample delay); Kp = J_sigma w_c = {Kp:.4g} Nm s/rad, "
            f"Ti = {a:g} / w_c = {Ti:.4g} s")
    return ControllerProposal(_concept(T_f, None), Kp, Ti, T_f, None, loop_figures(mech, drive, Kp, Ti, T_f),
                              m, (rule,), warnings, "stiff", mech, models)


def _bands_text(bands: dict[float, tuple[float, float]], clip: tuple[float, float] = (0.0, math.inf)) -> str:
    """``V_J 0.2: f_e 5..500 Hz, ...`` of eigenfrequency bands (clipped to ``clip``)."""
    return ", ".join(f"V_J {v:g}: f_e {max(lo, clip[0]):.3g}..{min(hi, clip[1]):.3g} Hz" for v, (lo, hi) in bands.items()
                     if max(lo, clip[0]) <= min(hi, clip[1]))
