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

import numpy as np

import sim

from ._law import NotchSpec, PISpeedLaw
from ._loop import Margins, Mechanics, ModelSet, drive_value, loop_figures, mechanics_from, model_set

__all__ = ["ControllerSpec", "ControllerProposal", "propose_controller", "propose_cautious", "robust_models"]


@dataclass(frozen=True)
class ControllerSpec:
    """Design requirements and rule constants (see docs/commissioning.md, "Controller rules").

    ``a``: symmetric-optimum ratio (``w_c = 1/(a T_sigma)``, ``Ti = a^2 T_sigma``; 2 = classic
    SO, 37 deg; 3 = 53 deg). ``a_backlash``: the same for backlash structures (lower gain).
    ``anti_resonance_ratio``: ``w_c <= ratio(V_J) * w_A`` as ``(V_J_small, ratio_small,
    ratio_mid, V_J_large, ratio_large)``. ``speed_filter_samples``: low-pass ``T_f`` in samples
    (0: none). ``allow_notch``: try a notch at the resonance when the elastic bandwidth limit costs
    more than ``notch_gain_factor``.

    The guarantee (rule R7; every delivered loop): ``min_phase_margin`` [deg] and
    ``min_gain_margin_dB`` on every model of :func:`robust_models`: the identified mechanic as it
    is and with ``f_e``, ``V_J`` x (1 -+ ``spread``), each with the current loop as a second-order
    lag of damping ``current_loop_damping`` and ``extra_delay`` more samples of dead time; the gain
    is lowered by ``backoff`` (at most ``max_backoff_steps`` times) until the margins hold.

    Fallback F1 (:func:`propose_cautious`): the worst case of the class over ``class_V_J`` (inertia
    ratios) and the eigenfrequency band the test run allows (inside ``class_f_e`` [Hz], the SPEC
    envelope) at damping ``class_d``, ``class_points_per_decade`` eigenfrequencies per decade of a
    band (a lightly damped resonance is narrow; its worst case moves smoothly); the highest crossover of ``f1_steps`` log-spaced values from
    the symmetric optimum down to ``f1_w_c_min`` [rad/s] that keeps the margins; ``Ti = a_backlash / w_c``.
    """

    a: float = 3.0
    a_backlash: float = 4.0
    anti_resonance_ratio: tuple[float, float, float, float, float] = (0.5, 1.0, 0.5, 2.0, 0.3)
    min_phase_margin: float = 40.0
    min_gain_margin_dB: float = 6.0
    spread: float = 0.3
    current_loop_damping: float = 1 / math.sqrt(2)
    extra_delay: int = 1
    backoff: float = 0.8
    max_backoff_steps: int = 30
    speed_filter_samples: float = 1.0
    allow_notch: bool = True
    notch_gain_factor: float = 3.0
    class_f_e: tuple[float, float] = (5.0, 500.0)
    class_V_J: tuple[float, ...] = (0.2, 1.0, 5.0)
    class_d: float = 0.005
    class_points_per_decade: float = 8.0
    f1_steps: int = 40
    f1_w_c_min: float = 1.0


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


def propose_controller(
    structure: str,
    params: Mapping[str, Any] | Any,
    drive: Any,
    spec: ControllerSpec | None = None,
    *,
    hidden: dict[float, tuple[float, float]] | None = None,
    notch_at: float | None = None,
) -> ControllerProposal:
    """Propose a speed controller from the identified structure and parameters (rules R1-R7).

    Args:
        structure: one of :data:`sim.STRUCTURE_CLASSES`.
        params: identified parameters (dict or one-system TwoMassParams), at least ``J_sigma``;
            ``V_J`` and ``f_e`` for the elastic structures.
        drive: DriveConfig (``T_s``, ``T_Ei``, ``M_max``).
        spec: rule constants and margin requirements.
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
    models = robust_models(mech, drive, spec, hidden=hidden)
    if hidden:
        rules.append(f"R7b resonances the test cannot exclude in the guarantee: {_bands_text(hidden)} (d {spec.class_d:g})")
    prop = ControllerProposal(concept, Kp, Ti, T_f, notch, loop_figures(mech, drive, Kp, Ti, T_f, notch),
                              models.margins(Kp, Ti, T_f, notch), tuple(rules), tuple(warnings), structure, mech, models)
    # R4b: a notch that does not help is dropped again
    if notch is not None and not prop.meets(spec):
        Kp, Ti = mech.J_sigma * w_lim, max(a / w_lim, a * a * T_sigma)
        prop = replace(prop, concept=concept.replace("+notch", ""), notch=None, figures=loop_figures(mech, drive, Kp, Ti, T_f, None),
                       margins=models.margins(Kp, Ti, T_f, None), Kp=Kp, Ti=Ti,
                       rules=prop.rules + (f"R4b notch did not meet the margins: dropped, w_c = {w_lim:.4g} rad/s",))
    best = _back_off(prop, drive, spec)
    if not best.figures["w_c"] >= 0.5 * prop.figures["w_c"]:
        if mech.two_mass:
            best = _alternatives(prop, best, drive, spec, mech.derived.w_0 / (2 * math.pi), max(mech.d, 0.05), (0.0,))
        elif hidden:
            best = _alternatives(prop, best, drive, spec, notch_at, 0.05, (0.0, 2 * T_f, 4 * T_f))
    return best


def _alternatives(prop: ControllerProposal, best: ControllerProposal, drive: Any, spec: ControllerSpec, f_0: float | None,
                  D_z: float, filters: tuple[float, ...]) -> ControllerProposal:
    """R8: when R7 had to lower the crossover below half of the design's, the same design with the
    speed low-pass ``T_f`` of ``filters`` (0: none) instead of its own, with a wide notch at the
    resonance ``f_0`` [Hz] (``D_p = 1``: the spread of ``f_e`` stays inside it), or both, each
    through R7; the highest crossover that keeps the margins wins."""
    T_s = drive_value(drive, "T_s")
    notch = NotchSpec(f_n=f_0, D_z=D_z, D_p=1.0) if f_0 is not None and f_0 < 0.4 / T_s else None
    tried = {(prop.T_f, prop.notch)}
    for T_f, nt in [(T_f, nt) for T_f in (*filters, prop.T_f) for nt in (prop.notch, notch)]:
        if (T_f, nt) in tried:
            continue
        tried.add((T_f, nt))
        concept = "PI" + ("+lowpass" if T_f > 0 else "") + ("+notch" if nt is not None else "")
        what = (f"speed low-pass T_f {T_f:.3g} s" if T_f > 0 else "no speed low-pass") + \
            (f", notch at {nt.f_n:.4g} Hz (D_z {nt.D_z:.3g}, D_p {nt.D_p:g})" if nt is not None else "")
        alt = replace(prop, concept=concept, T_f=T_f, notch=nt, margins=prop.models.margins(prop.Kp, prop.Ti, T_f, nt),
                      figures=loop_figures(prop.mechanics, drive, prop.Kp, prop.Ti, T_f, nt), rules=prop.rules + (f"R8 alternative: {what}",))
        alt = _back_off(alt, drive, spec)
        if alt.meets(spec) and (not best.meets(spec) or alt.figures["w_c"] > best.figures["w_c"]):
            best = alt
    return best


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
    decade (at least 5) spanning its band [Hz] (clipped to ``clip``, default ``spec.class_f_e``; a
    band outside it holds none)."""
    lo, hi = spec.class_f_e if clip is None else clip
    out = [Mechanics(J_sigma)]
    for v, (f_lo, f_hi) in bands.items():
        f_lo, f_hi = max(f_lo, lo), min(f_hi, hi)
        if f_lo <= f_hi:
            n = max(5, math.ceil(spec.class_points_per_decade * math.log10(f_hi / f_lo)) + 1)
            f_es = np.geomspace(f_lo, f_hi, n) if f_hi > f_lo * 1.01 else np.array([f_lo])
            out += [Mechanics(J_sigma, V_J=v, f_e=float(f), d=spec.class_d) for f in f_es]
    return out


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
    w_top = 1.0 / (spec.a * (T_Ei + 2.0 * T_s + T_f))
    mechs = _class_mechanics(J, bands, spec)
    models = robust_models(mechs, drive, replace(spec, spread=0.0))
    mech = Mechanics(J)
    chosen = None
    for w_c in np.geomspace(w_top, min(spec.f1_w_c_min, w_top), spec.f1_steps):
        m = models.margins(J * w_c, a / w_c, T_f, None)
        if m.meets(spec.min_phase_margin, spec.min_gain_margin_dB):
            chosen = (float(w_c), m)
            break
    warnings: tuple[str, ...] = ()
    if chosen is None:
        w_c = min(spec.f1_w_c_min, w_top)
        chosen = (w_c, models.margins(J * w_c, a / w_c, T_f, None))
        warnings = (f"F1: no crossover down to {w_c:g} rad/s keeps the margins on the worst cases of the class "
                    f"(PM {chosen[1].phase_margin:.1f} deg, GM {chosen[1].gain_margin_dB:.1f} dB)",)
    w_c, m = chosen
    Kp, Ti = J * w_c, a / w_c
    rule = (f"F1 identification refused: cautious PI on J_sigma = {J:.4g} kg m^2 alone; w_c = {w_c:.4g} rad/s, the highest "
            f"that keeps PM >= {spec.min_phase_margin:g} deg and GM >= {spec.min_gain_margin_dB:g} dB on {len(models.plants)} "
            f"worst-case models (one-mass, {_bands_text(bands, spec.class_f_e)}; d {spec.class_d:g}; each also with a 2nd-order current loop and "
            f"+{spec.extra_delay} sample delay); Kp = J_sigma w_c = {Kp:.4g} Nm s/rad, "
            f"Ti = {a:g} / w_c = {Ti:.4g} s")
    return ControllerProposal("PI" + ("+lowpass" if T_f > 0 else ""), Kp, Ti, T_f, None, loop_figures(mech, drive, Kp, Ti, T_f),
                              m, (rule,), warnings, "stiff", mech, models)


def _bands_text(bands: dict[float, tuple[float, float]], clip: tuple[float, float] = (0.0, math.inf)) -> str:
    """``V_J 0.2: f_e 5..500 Hz, ...`` of eigenfrequency bands (clipped to ``clip``)."""
    return ", ".join(f"V_J {v:g}: f_e {max(lo, clip[0]):.3g}..{min(hi, clip[1]):.3g} Hz" for v, (lo, hi) in bands.items()
                     if max(lo, clip[0]) <= min(hi, clip[1]))
