"""The controller rules (knowledge base, docs/commissioning.md "Controller rules"): turn an
identified structure and parameters into the SPEC 8.1 speed law (PI, speed low-pass, up to two
notches) with the largest crossover that keeps the guarantee on every model of the uncertainty set
(:mod:`training.commissioning._design`), or the cautious fallback F1.

:func:`propose_controller` applies :data:`CONTROLLER_RULES` in order, each a named function over
the typed inputs (:class:`DesignInputs`) and the design so far (:class:`Design`):

    R6 backlash: the decoupled motor -> R7/R7b/R7c/R7d the guarantee's model set -> R4 notch frequencies
    -> R5 the crossover maximized over the law's parameters

Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s].
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import sim
from training._settings import NON_NEGATIVE, POSITIVE, Constraint, InstanceOf, Interval, Pair, Values, check_settings
from training.errors import CommissioningError

from ._design import (GAP_OPEN_MARGINS, MEASURED_F_SPREAD, SEARCH, DesignSearch, MechanicsBounds, OptimizedLoop, UncertaintySet,
                      measured_peaks, optimize_loop, trusted_response)
from ._frf import MeasuredResponse
from ._law import NotchSpec, PISpeedLaw
from ._loop import Margins, Mechanics, ModelSet, Notches, drive_value, loop_figures, mechanics_from
from ._narrow import NARROW_SETTINGS, NarrowSettings, measured_mode, narrowed_bounds

__all__ = ["ControllerSpec", "ControllerProposal", "DesignInputs", "Design", "CONTROLLER_RULES", "propose_controller",
           "propose_cautious", "robust_models", "uncertainty_set"]


@dataclass(frozen=True)
class ControllerSpec:
    """Design requirements and rule settings (docs/commissioning.md, "Controller rules"); checked
    on construction.

    The guarantee (every delivered loop): ``min_phase_margin``, ``min_gain_margin_dB`` and the
    reference-to-load peak ``search.max_load_peak_dB`` on every model of the uncertainty set
    (:class:`training.commissioning._design.UncertaintySet`): the identified mechanic and its
    spread (the identification's calibrated intervals where it has them, else the interim
    half-widths ``f_e_spread``, ``V_J_spread`` and damping factors ``d_scale``), each with the SPEC's current loop and with a second-order lag of damping
    ``current_loop_damping`` plus ``extra_delay`` samples of dead time (the latter left out where a
    measured frequency response shows the SPEC's loop, ``variant_lag_share``).

    Fallback F1 (:func:`propose_cautious`): the worst case of the class over ``class_V_J`` and the
    eigenfrequency band the test run allows (inside ``class_f_e``) at damping ``class_d``.
    """

    min_phase_margin: float = 45.0
    """The design's phase margin on every model of the set [deg] (SPEC 8.2 asks 45 of the reference and 40 of the delivered loop on the true plant)."""
    min_gain_margin_dB: float = 6.0
    """The design's gain margin on every model of the set [dB]."""
    f_e_spread: float = 0.1
    """Interim relative half-width of ``f_e``, for an identification without calibrated intervals (docs/results/report.md: the identification's ``f_e`` error has std 6.0 %, 99 % within 30 %)."""
    V_J_spread: float = 0.25
    """Interim relative half-width of ``V_J`` (docs/results/report.md: std 5.4 %; the maps alone 34 %)."""
    d_scale: tuple[float, float] = (0.5, 2.0)
    """Interim factors on the identified damping ``d`` (docs/results/report.md: median error 1.8 %, std 80 %)."""
    current_loop_damping: float = 1 / math.sqrt(2)
    """Damping of the current loop as a second-order lag in the set's pessimistic models."""
    extra_delay: int = 1
    """Samples of dead time the set's pessimistic models add."""
    variant_lag_share: float = 1 / 3
    """Where the plant's frequency response was measured and shows at most this share of the
    pessimistic variant's extra phase lag (upper quartile over the coherent lines where that lag reaches
    30 deg), the drive's current loop is the SPEC's: the set is taken without the variant."""
    min_coherence: float = 0.8
    """A measured frequency response counts where its coherence reaches this."""
    min_coherent_share: float = 0.5
    """R7b: the measured response replaces the resonances the test cannot exclude only where at least
    this share of its lines counts (``min_coherence``); below it (a gap rattling at the measurement's
    small amplitude, friction) it could not have shown them, and they stay in the set beside it."""
    peak_ratio: float = 2.0
    """A measured resonance peak: the response this many times the one-mass inertia's (6 dB); a notch may sit there."""
    search: DesignSearch = SEARCH
    """How the design searches the law's parameters (:class:`training.commissioning._design.DesignSearch`)."""
    narrow: NarrowSettings = NARROW_SETTINGS
    """R7d: how a measured frequency response narrows the set's intervals (:mod:`training.commissioning._narrow`)."""
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
    gap_open_phase_margin: float = GAP_OPEN_MARGINS[0]
    """R6: the phase margin [deg] the decoupled motor of a backlash plant keeps: a state the loop
    passes through while the gap is open, held stable with room (no limit cycle), not to the
    guarantee's margins (docs/commissioning.md, section 3) ..."""
    gap_open_gain_margin_dB: float = GAP_OPEN_MARGINS[1]
    """R6: ... and its gain margin [dB]."""

    def __post_init__(self) -> None:
        check_settings(self, _SPEC_CONSTRAINTS, CommissioningError)


_SPEC_CONSTRAINTS: dict[str, Constraint] = {
    "min_phase_margin": Interval(0.0, 90.0), "min_gain_margin_dB": NON_NEGATIVE,
    "f_e_spread": Interval(0.0, 1.0, open_high=True), "V_J_spread": Interval(0.0, 1.0, open_high=True),
    "d_scale": Pair(POSITIVE), "current_loop_damping": POSITIVE, "extra_delay": Interval(0, integer=True),
    "variant_lag_share": Interval(0.0, 1.0),
    "min_coherence": Interval(0.0, 1.0), "min_coherent_share": Interval(0.0, 1.0), "peak_ratio": POSITIVE, "search": InstanceOf(DesignSearch),
    "narrow": InstanceOf(NarrowSettings),
    "class_d": NON_NEGATIVE, "class_points_per_decade": POSITIVE, "class_min_points": Interval(1, integer=True),
    "class_f_e": Pair(POSITIVE), "class_V_J": Values(POSITIVE, empty=False), "gap_open_phase_margin": Interval(0.0, 90.0),
    "gap_open_gain_margin_dB": NON_NEGATIVE,
}


#: The load peak is read on the frequency grid (0.2 % steps at a resonance): a gain set the tuning
#: moved keeps the 6 dB within this much [dB], below what the grid resolves of a light resonance.
LOAD_PEAK_TOLERANCE_DB: float = 0.1


@dataclass(frozen=True)
class ControllerProposal:
    """A speed-controller concept and its parameters, with the expected figures and the rules used.

    ``concept``: "PI", "PI+lowpass", "PI+notch", "PI+lowpass+notch" (x2 for two notches). ``Kp``
    [Nm s/rad], ``Ti`` [s], ``T_f`` [s] (speed low-pass, 0 = none), ``notches`` (in series;
    :attr:`notch` is the law's argument). ``figures``: :func:`loop_figures` on the model the design
    assumes (``w_c`` there: the crossover the proposal states); ``margins``: the worst
    :class:`Margins` over ``models`` (the guarantee's set); ``load_peak_dB``: the worst
    reference-to-load peak over the set's plants; ``lowest_w_c``: the lowest crossover over the
    set; ``limited_by``: what bounds the crossover; ``rules``: the rule lines (each starts with
    its code). ``M_hold`` [Nm]: the holding torque (SPEC 1.1), where the law's integrator starts on
    the drive (the identified constant load torque ``M_L0``; 0 on an axis without one): a drive that
    holds the axis adds it to the law's output (its feedforward), one that loads the law starts the
    integrator there. The linear design does not see it (a constant torque does not change the loop).
    """

    concept: str
    Kp: float
    Ti: float
    T_f: float
    notches: tuple[NotchSpec, ...]
    figures: dict[str, float]
    margins: Margins
    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    structure: str = "stiff"
    mechanics: Mechanics | None = field(default=None, repr=False)
    models: ModelSet | None = field(default=None, repr=False)
    load_peak_dB: float = math.nan
    lowest_w_c: float = math.nan
    limited_by: str = ""
    max_load_peak_dB: float = SEARCH.max_load_peak_dB
    M_hold: float = 0.0

    @property
    def notch(self) -> Notches:
        """The law's notch argument: None, the one notch, or the tuple of two."""
        return None if not self.notches else (self.notches[0] if len(self.notches) == 1 else self.notches)

    def law(self, config: Any, *, Kp: Any = None, Ti: Any = None, T_f: Any = None) -> PISpeedLaw:
        """The SPEC 8.1 law on the drive ``config`` (gains overridable, e.g. by arrays ``B``)."""
        return PISpeedLaw(self.Kp if Kp is None else Kp, self.Ti if Ti is None else Ti,
                          T_s=drive_value(config, "T_s"), M_max=drive_value(config, "M_max"),
                          T_f=self.T_f if T_f is None else T_f, notch=self.notches)

    def meets(self, spec: ControllerSpec) -> bool:
        """The guarantee: ``spec``'s margins on every model of the set, and the load peak where known."""
        peak_ok = not self.load_peak_dB > self.max_load_peak_dB + LOAD_PEAK_TOLERANCE_DB
        return self.margins.meets(spec.min_phase_margin, spec.min_gain_margin_dB) and peak_ok

    def with_gains(self, config: Any, Kp: float, Ti: float, T_f: float, rule: str) -> ControllerProposal:
        """A copy with new gains, new figures, margins and load peak, and one more rule line."""
        return replace(self, Kp=Kp, Ti=Ti, T_f=T_f, figures=loop_figures(self.mechanics, config, Kp, Ti, T_f, self.notch),
                       margins=self.models.margins(Kp, Ti, T_f, self.notch),
                       load_peak_dB=float(self.models.load_peaks_dB(Kp, Ti, T_f, self.notch).max()),
                       rules=self.rules + (rule,))

    def to_dict(self) -> dict[str, Any]:
        m = self.margins
        each = [{"f_n": n.f_n, "D_z": n.D_z, "D_p": n.D_p} for n in self.notches]
        return {
            "concept": self.concept, "structure": self.structure, "Kp": self.Kp, "Ti": self.Ti, "T_f": self.T_f,
            "notch": each[0] if each else None, "notches": each, "figures": dict(self.figures),
            "margins": {"phase_margin": m.phase_margin, "gain_margin_dB": m.gain_margin_dB, "w_c": m.w_c,
                        "stable": m.stable, "worst_model": m.model},
            "load_peak_dB": _finite_or_none(self.load_peak_dB), "lowest_w_c": _finite_or_none(self.lowest_w_c),
            "limited_by": self.limited_by, "M_hold": self.M_hold,
            "rules": list(self.rules), "rule_codes": [r.split(" ", 1)[0] for r in self.rules], "warnings": list(self.warnings),
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def uncertainty_set(mechanics: Any, spec: ControllerSpec, *, structure: str = "stiff",
                    hidden: dict[float, tuple[float, float]] | None = None, measured: MeasuredResponse | None = None,
                    spread: float | None = None, damping: float | None = None, doubts: tuple[str, ...] = (),
                    bounds: MechanicsBounds | None = None, drive: Any = None, gap_probability: float = 0.0) -> UncertaintySet:
    """The :class:`UncertaintySet` of ``spec`` around ``mechanics``: spanning ``bounds`` (the
    identification's calibrated intervals, :meth:`MechanicsBounds.from_intervals`), or without them
    ``spec``'s interim spread; ``spread`` and ``damping`` (rule R7c) widen ``f_e`` and ``V_J`` to at
    least that relative half-width and the damping's low end to at most ``damping`` x the identified
    ``d`` (on either); a backlash ``structure`` adds the decoupled motor (R6); ``hidden`` (R7b)
    unless ``measured`` (its trusted part, coherence >= ``spec.min_coherence``); a measured
    resonance inside the bounds' ``f_e`` places them (:meth:`MechanicsBounds.placed`; from below
    only on a backlash plant) and, given the ``drive``'s config, narrows them to the mechanics the
    measured response does not invalidate (rule R7d, :func:`training.commissioning._narrow.narrowed_bounds`; not a backlash answer's),
    or fits the resonances it found to a one-mass answer (:func:`training.commissioning._narrow.measured_mode`);
    R7d only where ``gap_probability`` (the identification's calibrated probability of a backlash
    class) is below ``spec.narrow.max_gap_probability``."""
    m = mechanics_from(mechanics)
    trusted = trusted_response(measured, spec.min_coherence) if measured is not None else None
    fit_drive = drive if gap_probability < spec.narrow.max_gap_probability else None  # R7d's: None, no R7d
    wide = 0.0 if spread is None else spread
    d_low = spec.d_scale[0] if damping is None else min(spec.d_scale[0], damping)
    if bounds is not None and (spread is not None or damping is not None):
        bounds = bounds.widen(m, wide, 1.0 if damping is None else damping,
                              f"R7c widened to f_e, V_J +-{wide:.0%} and d from x{1.0 if damping is None else damping:g} at least")
    if bounds is not None and trusted is not None and m.two_mass:
        bounds = _measured_bounds(bounds, m, trusted, fit_drive, spec, gap=structure in BACKLASH_CLASSES)
    u = UncertaintySet(m, f_e_spread=max(spec.f_e_spread, wide), V_J_spread=max(spec.V_J_spread, wide),
                       d_scale=(d_low, spec.d_scale[1]), bounds=bounds,
                       current_loop_damping=spec.current_loop_damping, extra_delay=spec.extra_delay,
                       decoupled_motor=structure in BACKLASH_CLASSES and m.two_mass, hidden=hidden, hidden_d=spec.class_d,
                       hidden_points_per_decade=spec.class_points_per_decade, hidden_min_points=spec.class_min_points,
                       measured=trusted, doubts=doubts, variant_lag_share=spec.variant_lag_share,
                       gap_open_margins=(spec.gap_open_phase_margin, spec.gap_open_gain_margin_dB),
                       hidden_kept=measured is not None and measured.coherent_share(spec.min_coherence) < spec.min_coherent_share)
    return u if fit_drive is None else _fitted_modes(u, fit_drive, spec)


def _measured_bounds(bounds: MechanicsBounds, m: Mechanics, trusted: MeasuredResponse, drive: Any, spec: ControllerSpec, *,
                     gap: bool) -> MechanicsBounds:
    """A two-mass answer's bounds with the trusted measured response: placed by its highest peak
    (:meth:`MechanicsBounds.placed`), then, given the ``drive``'s config and without a ``gap``,
    narrowed to the mechanics it does not invalidate (R7d). A gap's small-signal response is not the
    plant's: the load sticks, the gap rattles, and the resonance reads anywhere (docs/commissioning.md, 3b)."""
    peak = measured_peaks(trusted, m.J_sigma, min_ratio=spec.peak_ratio, most=1)
    bounds = bounds.placed(peak[0], MEASURED_F_SPREAD, gap=gap) if peak else bounds
    if drive is None or gap:
        return bounds
    return narrowed_bounds(bounds, m, trusted, drive, min_coherence=spec.min_coherence, current_loop_damping=spec.current_loop_damping,
                           extra_delay=spec.extra_delay, settings=spec.narrow)


def _fitted_modes(u: UncertaintySet, drive: Any, spec: ControllerSpec) -> UncertaintySet:
    """R7d for a one-mass answer: the resonances the trusted measurement found, where it replaced
    the hidden ones, each fitted (:func:`measured_mode`) for the set's worst cases."""
    m, trusted = u.mechanics, u.measured
    if trusted is None or m.two_mass or not u.hidden or u.keeps_hidden:
        return u
    modes = (measured_mode(w, m, trusted, drive, V_J=(min(V_Js), max(V_Js)), d=(spec.class_d, spec.narrow.mode_damping),
                           f_spread=MEASURED_F_SPREAD, min_coherence=spec.min_coherence, current_loop_damping=spec.current_loop_damping,
                           extra_delay=spec.extra_delay, settings=spec.narrow)
             for w in trusted.resonances for V_Js in [u.measured_V_Js(w)] if V_Js)
    return replace(u, measured_modes=tuple(mode for mode in modes if mode is not None))


def robust_models(mechanics: Any, config: Any, spec: ControllerSpec, *,
                  hidden: dict[float, tuple[float, float]] | None = None) -> ModelSet:
    """The guarantee's model set of one identified mechanic (:func:`uncertainty_set`'s models)."""
    return uncertainty_set(mechanics, spec, hidden=hidden).models(config)


#: The structures with a gap (SPEC 1): R6's decoupled motor, R7d's exception.
BACKLASH_CLASSES: tuple[str, ...] = ("elastic_backlash", "stiff_backlash")


@dataclass(frozen=True)
class DesignInputs:
    """What the controller rules design from: the identified ``structure`` and ``mechanics``, the
    drive (``T_s``, ``T_Ei``), the settings, the :class:`UncertaintySet` the guarantee holds on,
    and a resonance the test showed that a ``stiff`` answer left out (``notch_at`` [Hz])."""

    structure: str
    mechanics: Mechanics
    drive: Any
    T_s: float
    T_Ei: float
    spec: ControllerSpec
    uncertainty: UncertaintySet
    notch_at: float | None = None

    @property
    def elastic(self) -> bool:
        return self.structure in ("elastic", "elastic_backlash")

    @property
    def backlash(self) -> bool:
        return self.structure in BACKLASH_CLASSES


@dataclass(frozen=True)
class Design:
    """The design as the rules so far made it: R7's ``models``, R4's notch frequencies
    ``notch_at`` [Hz], R5's optimized ``loop`` and the ``chosen`` proposal; the rule lines and
    warnings."""

    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    models: ModelSet | None = None
    notch_at: tuple[float, ...] = ()
    loop: OptimizedLoop | None = None
    chosen: ControllerProposal | None = None

    def noted(self, rule: str, **changes: Any) -> Design:
        """With ``changes`` and one more rule line."""
        return replace(self, rules=self.rules + (rule,), **changes)


def r6_backlash(inputs: DesignInputs, design: Design) -> Design:
    """R6, runs for a backlash structure: the decoupled motor (one mass ``J_sigma / (1 + V_J)``: the
    loop's gain x (1 + V_J) while the gap is open) is in the guarantee's set, so that the loop does
    not limit-cycle; a warning to check the loop at low speed."""
    if not inputs.backlash:
        return design
    warning = ("backlash: integral action with backlash can cause a limit cycle around standstill; check the closed loop at "
               "low speed",)
    if not inputs.uncertainty.decoupled_motor:
        return design.noted("R6 backlash: no inertia ratio identified, the decoupled motor is not in the set",
                            warnings=design.warnings + warning)
    m = inputs.mechanics
    pm, gm = inputs.uncertainty.gap_open_margins
    return design.noted(f"R6 backlash: the decoupled motor J_sigma/(1+V_J) = {m.J_sigma / (1 + m.V_J):.4g} kg m^2 "
                        f"(gain x {1 + m.V_J:.3g} while the gap is open) in the guarantee's set, kept stable with PM >= {pm:g} deg, "
                        f"GM >= {gm:g} dB", warnings=design.warnings + warning)


def r7_model_set(inputs: DesignInputs, design: Design) -> Design:
    """R7, runs always: the guarantee's model set from the uncertainty set (R7b: with the resonances a
    test cannot exclude, or the measured frequency response in their place)."""
    u = inputs.uncertainty
    models = u.models(inputs.drive)
    design = design.noted(f"R7 the guarantee's set ({len(models.plants) + (models.measured is not None)} models): {u.describe(inputs.drive)}",
                          models=models)
    if u.keeps_hidden:
        lead = ("R7b resonances the test cannot exclude" if u.measured is None else "R7b the measured frequency response is "
                "coherent on too few lines to exclude resonances: those the test cannot exclude stay")
        design = design.noted(f"{lead} in the guarantee: {_bands_text(u.hidden)} (d {u.hidden_d:g})")
    elif u.hidden:
        design = design.noted("R7b the measured frequency response replaces the resonances the test cannot exclude")
    return design


def r4_notch_frequencies(inputs: DesignInputs, design: Design) -> Design:
    """R4, runs when a resonance is known: the notch frequencies the search may use: the identified
    resonance ``f_0`` (two-mass), the visible oscillation a ``stiff`` answer left out, the peaks
    of the measured frequency response."""
    m, u, spec = inputs.mechanics, inputs.uncertainty, inputs.spec
    found = []
    if m.two_mass:
        found.append(("the identified resonance", m.derived.w_0 / (2 * math.pi)))
    if inputs.notch_at is not None:
        found.append(("the test's visible oscillation", inputs.notch_at))
    if u.measured is not None:
        found += [("a measured peak", f) for f in measured_peaks(u.measured, m.J_sigma, min_ratio=spec.peak_ratio)]
    if not found:
        return design
    freqs = tuple(dict.fromkeys(round(f, 6) for _, f in found))
    return design.noted("R4 notch frequencies " + ", ".join(f"{f:.4g} Hz ({what})" for what, f in found), notch_at=freqs)


def _concept(T_f: float, notches: tuple[NotchSpec, ...]) -> str:
    return "PI" + ("+lowpass" if T_f > 0 else "") + "".join("+notch" for _ in notches)


def _notches_text(notches: tuple[NotchSpec, ...]) -> str:
    return ", ".join(f"notch {n.f_n:.4g} Hz (D_z {n.D_z:.3g}, D_p {n.D_p:.3g})" for n in notches) or "no notch"


def r5_optimize(inputs: DesignInputs, design: Design) -> Design:
    """R5, runs always: the crossover maximized over ``Kp``, ``Ti``, ``T_f`` and up to two notches at
    R4's frequencies, subject to stability, the margins and the load peak on every model of R7's
    set (:func:`training.commissioning._design.optimize_loop`)."""
    spec, mech, models = inputs.spec, inputs.mechanics, design.models
    loop = optimize_loop(models, inputs.drive, J_sigma=mech.J_sigma, notch_at=design.notch_at, d=mech.d, min_phase_margin=spec.min_phase_margin,
                         min_gain_margin_dB=spec.min_gain_margin_dB, search=spec.search)
    proposal = _proposal(inputs.structure, mech, inputs.drive, models, loop, spec, design.rules, design.warnings)
    line = (f"R5 optimized: w_c {loop.w_c:.4g} rad/s (lowest over the set {loop.lowest_w_c:.4g}), Kp {loop.Kp:.4g} Nm s/rad, "
            f"Ti {loop.Ti:.4g} s, T_f {loop.T_f:.3g} s, {_notches_text(loop.notches)}; "
            f"worst of the set PM {loop.phase_margin:.1f} deg, GM {loop.gain_margin_dB:.1f} dB, load peak "
            f"{loop.load_peak_dB:.1f} dB; limited by {loop.limited_by}")
    proposal = replace(proposal, rules=proposal.rules + (line,))
    if not loop.found:
        m = proposal.margins
        proposal = replace(proposal, warnings=proposal.warnings + (
            f"margins not reached (PM {m.phase_margin:.1f} deg, GM {m.gain_margin_dB:.1f} dB, load peak {loop.load_peak_dB:.1f} dB, "
            f"stable={m.stable}, worst model: {m.model})",))
    return replace(design, loop=loop, chosen=proposal)


def _proposal(structure: str, mech: Mechanics, drive: Any, models: ModelSet, loop: OptimizedLoop, spec: ControllerSpec,
              rules: tuple[str, ...], warnings: tuple[str, ...]) -> ControllerProposal:
    """The optimized loop as a :class:`ControllerProposal` (figures on ``mech``, margins over ``models``)."""
    figures = loop_figures(mech, drive, loop.Kp, loop.Ti, loop.T_f, loop.notches)
    return ControllerProposal(_concept(loop.T_f, loop.notches), loop.Kp, loop.Ti, loop.T_f, loop.notches, figures,
                              models.margins(loop.Kp, loop.Ti, loop.T_f, loop.notches), rules, warnings, structure, mech, models,
                              loop.load_peak_dB, loop.lowest_w_c, loop.limited_by, spec.search.max_load_peak_dB)


#: The controller rules :func:`propose_controller` applies, in this order.
CONTROLLER_RULES: tuple[Callable[[DesignInputs, Design], Design], ...] = (
    r6_backlash,
    r7_model_set,
    r4_notch_frequencies,
    r5_optimize,
)


def propose_controller(
    structure: str,
    params: Mapping[str, Any] | Any,
    drive: Any,
    spec: ControllerSpec | None = None,
    *,
    hidden: dict[float, tuple[float, float]] | None = None,
    notch_at: float | None = None,
    measured: MeasuredResponse | None = None,
    uncertainty: UncertaintySet | None = None,
) -> ControllerProposal:
    """Propose a speed controller from the identified structure and parameters (:data:`CONTROLLER_RULES`).

    Args:
        structure: one of :data:`sim.STRUCTURE_CLASSES`.
        params: identified parameters (dict or one-system TwoMassParams), at least ``J_sigma``;
            ``V_J`` and ``f_e`` for the elastic structures.
        drive: DriveConfig (``T_s``, ``T_Ei``, ``M_max``).
        spec: rule settings and margin requirements.
        hidden: for a ``stiff`` answer (or one whose oscillation the model does not reproduce), the
            resonances the test cannot exclude (``V_J -> (f_lo, f_hi)`` [Hz],
            :func:`training.commissioning._bands.hidden_bands`): rule R7b adds them to the set;
            ``notch_at`` [Hz]: a resonance the test showed (R4: a notch may sit there).
        measured: the plant's frequency response measured on the drive: its trusted part is a
            model of the set and replaces ``hidden``; its peaks are notch frequencies.
        uncertainty: the set to hold on (default: :func:`uncertainty_set` of ``spec`` around ``params``).

    Returns a :class:`ControllerProposal` whose ``figures`` come from the exact sampled linear
    model (delays included) and whose margins and load peak hold on every model of the set where
    the search found such a law (else a warning says so).
    """
    spec = spec or ControllerSpec()
    if structure not in sim.STRUCTURE_CLASSES:
        raise ValueError(f"structure: expected one of {sim.STRUCTURE_CLASSES}, received {structure!r}")
    mech = mechanics_from(params)
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    drive_value(drive, "M_max")
    if structure in ("elastic", "elastic_backlash") and not mech.two_mass:
        raise ValueError(f"structure {structure!r} needs V_J and f_e, received V_J={mech.V_J}, f_e={mech.f_e}")
    if uncertainty is None:
        uncertainty = uncertainty_set(mech, spec, structure=structure, hidden=hidden, measured=measured)
    inputs = DesignInputs(structure, uncertainty.mechanics, drive, T_s, T_Ei, spec, uncertainty, notch_at)
    design = Design()
    for rule in CONTROLLER_RULES:
        design = rule(inputs, design)
    return design.chosen


def propose_cautious(J_sigma: float, drive: Any, spec: ControllerSpec | None = None, *,
                     bands: dict[float, tuple[float, float]] | None = None) -> ControllerProposal:
    """Fallback F1 after a refusal: a law on an inertia the caller trusts (``J_sigma``), no notch,
    optimized (:func:`training.commissioning._design.optimize_loop`) over the worst cases of the
    class: the one-mass ``J_sigma`` and, per inertia ratio, the eigenfrequencies ``bands[V_J] =
    (f_lo, f_hi)`` [Hz] the measured test run allows (default: every ratio of ``spec.class_V_J``
    over the SPEC envelope ``spec.class_f_e``), lightly damped (``spec.class_d``), each as it is
    and with the second-order current loop and the extra delay. The crossover it states
    (``figures["w_c"]``) is the lowest over that set: the one it guarantees. It is meant to be
    delivered as it is, not tuned on a model the chain does not trust."""
    spec = spec or ControllerSpec()
    if not (isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0):
        raise ValueError(f"J_sigma: expected a finite number > 0, received {J_sigma!r}")
    bands = dict(bands) if bands is not None else {v: spec.class_f_e for v in spec.class_V_J}
    J = float(J_sigma)
    drive_value(drive, "T_s"), drive_value(drive, "T_Ei"), drive_value(drive, "M_max")
    mech = Mechanics(J)
    models = UncertaintySet(mech, hidden=_clipped(bands, spec.class_f_e), hidden_d=spec.class_d,
                            hidden_points_per_decade=spec.class_points_per_decade, hidden_min_points=spec.class_min_points,
                            current_loop_damping=spec.current_loop_damping, extra_delay=spec.extra_delay).models(drive)
    loop = optimize_loop(models, drive, J_sigma=J, min_phase_margin=spec.min_phase_margin, min_gain_margin_dB=spec.min_gain_margin_dB,
                         search=spec.search)
    proposal = _proposal("stiff", mech, drive, models, loop, spec, (), ())
    stated = min(loop.lowest_w_c, proposal.figures["w_c"]) if math.isfinite(loop.lowest_w_c) else proposal.figures["w_c"]
    figures = {**proposal.figures, "w_c_nominal": proposal.figures["w_c"], "w_c": stated, "f_c": stated / (2 * math.pi)}
    warnings: tuple[str, ...] = ()
    if not loop.found:
        warnings = (f"F1: no crossover keeps the margins on the worst cases of the class (PM {loop.phase_margin:.1f} deg, "
                    f"GM {loop.gain_margin_dB:.1f} dB)",)
    rule = (f"F1 identification refused: cautious law on J_sigma = {J:.4g} kg m^2 alone; w_c = {stated:.4g} rad/s, the lowest "
            f"crossover over {len(models.plants)} worst-case models (one-mass, {_bands_text(bands, spec.class_f_e)}; "
            f"d {spec.class_d:g}; each also with a 2nd-order current loop and +{spec.extra_delay} sample delay) that all keep "
            f"PM >= {spec.min_phase_margin:g} deg, GM >= {spec.min_gain_margin_dB:g} dB and a load peak <= "
            f"{spec.search.max_load_peak_dB:g} dB (on J_sigma: {proposal.figures['w_c']:.4g} rad/s); Kp = {loop.Kp:.4g} Nm s/rad, "
            f"Ti = {loop.Ti:.4g} s, T_f = {loop.T_f:.3g} s; limited by {loop.limited_by}")
    return replace(proposal, figures=figures, rules=(rule,), warnings=warnings)


def _clipped(bands: dict[float, tuple[float, float]], clip: tuple[float, float]) -> dict[float, tuple[float, float]]:
    """``bands`` clipped to ``clip`` [Hz]; a band outside it is left out."""
    out = {v: (max(lo, clip[0]), min(hi, clip[1])) for v, (lo, hi) in bands.items()}
    return {v: b for v, b in out.items() if b[0] <= b[1]}


def _bands_text(bands: dict[float, tuple[float, float]], clip: tuple[float, float] = (0.0, math.inf)) -> str:
    """``V_J 0.2: f_e 5..500 Hz, ...`` of eigenfrequency bands (clipped to ``clip``)."""
    return ", ".join(f"V_J {v:g}: f_e {max(lo, clip[0]):.3g}..{min(hi, clip[1]):.3g} Hz" for v, (lo, hi) in bands.items()
                     if max(lo, clip[0]) <= min(hi, clip[1]))
