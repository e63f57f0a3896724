"""Design by optimization: the speed loop of SPEC 8.1's structure (PI, speed low-pass, up to two
notches) with the largest crossover ``w_c`` that keeps, on every model of an uncertainty set, the
closed loop stable, the phase margin, the gain margin and the reference-to-load peak (SPEC 8.2).

:class:`UncertaintySet` is what the design must hold on: the identified mechanic and its plausible
spread, the current-loop and delay variants, the decoupled motor of a backlash plant, the
resonances a test run cannot exclude, or, where it was measured, the plant's frequency response.
:func:`optimize_loop` searches the law's parameters over it (the search is described there).

Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s], frequencies [Hz].
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from training._settings import AT_LEAST_ONE, COUNT, NON_NEGATIVE, POSITIVE, REAL_OR_INF, Interval, Values, check_settings
from training.errors import CommissioningError

from ._frf import MeasuredResponse
from ._law import MAX_NOTCHES, NotchSpec
from ._loop import (LinearPlant, Mechanics, ModelSet, closed_loop_matrices, controller_parts, drive_value, linear_plant,
                    load_transfer, margin_arrays)

__all__ = ["UncertaintySet", "MechanicsBounds", "GAP_OPEN_MARGINS", "BOUNDED_PARAMETERS", "DesignSearch", "SEARCH", "OptimizedLoop", "optimize_loop", "elastic_doubts",
           "measured_peaks", "trusted_response", "NON_ELASTIC_QUANTITIES"]

#: Quantities of the identification's envelope findings (``quality.outside_envelope``) that say
#: nothing about the elastic parameters: friction relative to the test's torque, the normalized
#: backlash, the torque levels
#: (torque and inertia scale together; they do not enter the maps' features). A finding on one of
#: these alone does not widen the set.
NON_ELASTIC_QUANTITIES: frozenset[str] = frozenset({"M_FC_over_M_star", "s_N", "M_N", "M_max_over_M_N", "M_star_over_M_max"})
#: The warning codes whose meaning rests on an envelope finding (which quantity: ``quality.outside_envelope``).
_ENVELOPE_CODES: frozenset[str] = frozenset({"outside_envelope", "drive_outside_training", "answer_outside_envelope"})


def elastic_doubts(result: Any, codes: Iterable[str]) -> list[str]:
    """Why the identified elastic values are uncertain: the warning codes of ``result`` in ``codes``
    (an envelope code only where a finding of ``result.quality.outside_envelope`` concerns more
    than :data:`NON_ELASTIC_QUANTITIES`), and ``outside_training`` where the quality says so."""
    findings = set(getattr(result.quality, "outside_envelope", None) or {})
    elastic_findings = bool(findings - NON_ELASTIC_QUANTITIES) or not findings
    why = sorted({w.code for w in result.warnings if w.code in set(codes)
                  and (w.code not in _ENVELOPE_CODES or elastic_findings)})
    if result.quality.outside_training and "outside_training" not in why:
        why.append("outside_training")
    return why


#: Rule R6: the phase [deg] and gain [dB] margins a backlash plant's decoupled motor keeps (the gap
#: open is a state the loop passes through: stable with room, so that it does not limit-cycle; the
#: guarantee's 45 deg and 6 dB there held plants above 100 Hz to a median 0.54 of the oracle, these
#: to 0.68; 15 deg and 1.5 dB limit-cycled on a drive: docs/commissioning.md, section 3).
GAP_OPEN_MARGINS: tuple[float, float] = (30.0, 3.0)

#: The parameters a :class:`MechanicsBounds` spans (those the design's models vary).
BOUNDED_PARAMETERS: tuple[str, ...] = ("J_sigma", "V_J", "f_e", "d", "J_M")


@dataclass(frozen=True)
class MechanicsBounds:
    """The ranges ``(low, high)`` an :class:`UncertaintySet` spans around the identified mechanic:
    ``J_sigma`` [kg m^2], ``V_J`` [-], ``f_e`` [Hz], ``d`` [-] and ``J_M`` [kg m^2] (the motor alone:
    a backlash plant's decoupled motor). Built from the identification's calibrated 90 % intervals
    (:meth:`from_intervals`, SPEC 4.1 and 8.2); ``widened`` says what rule R7c (:meth:`widen`) and a
    measured resonance (:meth:`placed`) made of them (empty: the intervals as they are). Checked on
    construction: finite, ``0 <= low <= high``, and a positive low end of ``J_sigma``, ``f_e`` and
    ``J_M``."""

    J_sigma: tuple[float, float]
    V_J: tuple[float, float]
    f_e: tuple[float, float]
    d: tuple[float, float]
    J_M: tuple[float, float]
    widened: str = ""

    def __post_init__(self) -> None:
        for name in BOUNDED_PARAMETERS:
            pair = getattr(self, name)
            try:
                low, high = (float(v) for v in pair)
            except (TypeError, ValueError):
                raise ValueError(f"bounds {name}: expected a pair (low, high), received {pair!r}") from None
            positive = name in ("J_sigma", "f_e", "J_M")
            if not (math.isfinite(low) and math.isfinite(high) and 0.0 <= low <= high and (low > 0 or not positive)):
                need = "0 < low" if positive else "0 <= low"
                raise ValueError(f"bounds {name}: expected finite {need} <= high, received ({low!r}, {high!r})")
            object.__setattr__(self, name, (low, high))

    @classmethod
    def from_intervals(cls, intervals: Any) -> MechanicsBounds:
        """The bounds of an identification's ``intervals`` (``intervals[name] -> (low, high)`` in SI:
        ``training.identification.Intervals``) over :data:`BOUNDED_PARAMETERS`."""
        try:
            return cls(**{name: tuple(intervals[name]) for name in BOUNDED_PARAMETERS})
        except (KeyError, TypeError) as err:
            raise ValueError(f"intervals: expected (low, high) for each of {list(BOUNDED_PARAMETERS)}: {err}") from None

    def placed(self, f_peak: float, spread: float, *, gap: bool = False) -> MechanicsBounds:
        """``f_e`` narrowed to the measured resonance ``f_peak`` [Hz] x(1 -+ ``spread``) where that
        lies inside the bounds (the frequency response places a resonance to a line's spacing; the
        test run's fit, to its calibrated interval); the bounds as they are where it does not. On a
        backlash plant (``gap``) from below only: the small-signal measurement sees the shaft
        softened by the gap (a resonance that falls with the amplitude), the closed gap's is higher."""
        low, high = max(self.f_e[0], f_peak * (1 - spread)), self.f_e[1] if gap else min(self.f_e[1], f_peak * (1 + spread))
        if not self.f_e[0] <= f_peak <= self.f_e[1] or (low, high) == self.f_e:
            return self
        note = f"f_e {'bounded from below' if gap else 'placed'} by the measured resonance at {f_peak:.4g} Hz (+-{spread:.0%})"
        return replace(self, f_e=(low, high), widened="; ".join(filter(None, (self.widened, note))))

    def widen(self, mechanics: Mechanics, spread: float, damping: float, why: str) -> MechanicsBounds:
        """Rule R7c on calibrated bounds: ``f_e`` and ``V_J`` span at least the identified value
        x(1 -+ ``spread``), ``d`` reaches down to at least the identified ``d`` x ``damping``; ``why``
        (one line) is kept in :attr:`widened`. A one-mass ``mechanics`` keeps the bounds as they are."""
        if not mechanics.two_mass:
            return self
        f, v, d = mechanics.f_e, mechanics.V_J, mechanics.d
        return replace(self, f_e=(min(self.f_e[0], f * (1 - spread)), max(self.f_e[1], f * (1 + spread))),
                       V_J=(min(self.V_J[0], v * (1 - spread)), max(self.V_J[1], v * (1 + spread))),
                       d=(min(self.d[0], d * damping), self.d[1]), widened=why)


def trusted_response(measured: MeasuredResponse, min_coherence: float) -> MeasuredResponse | None:
    """The measured response at the frequencies whose coherence reaches ``min_coherence`` (None: none)."""
    keep = np.asarray(measured.coherence) >= min_coherence
    if keep.sum() < 2:
        return None
    return MeasuredResponse(w=np.asarray(measured.w)[keep], G=np.asarray(measured.G)[keep],
                            coherence=np.asarray(measured.coherence)[keep], T_s=float(measured.T_s),
                            model=None if measured.model is None else np.asarray(measured.model)[keep],
                            resonances=measured.resonances)


def measured_peaks(measured: MeasuredResponse, J_sigma: float, *, min_ratio: float, most: int = MAX_NOTCHES) -> tuple[float, ...]:
    """Resonance peaks [Hz] the measured response shows: local maxima of ``|G| J_sigma w`` (the
    response over the one-mass inertia's, 1 where the plant moves as one mass) above ``min_ratio``,
    the ``most`` highest, lowest frequency first."""
    w = np.asarray(measured.w)
    ratio = np.abs(measured.G) * J_sigma * w
    inner = np.nonzero((ratio[1:-1] > ratio[:-2]) & (ratio[1:-1] >= ratio[2:]) & (ratio[1:-1] >= min_ratio))[0] + 1
    top = sorted(inner, key=lambda i: -ratio[i])[:most]
    return tuple(float(w[i] / (2 * math.pi)) for i in sorted(top))


#: How far [share] a resonance the measured frequency response places may lie from the line it peaks on.
MEASURED_F_SPREAD = 0.05

#: The measured response tells the current-loop variants apart where the pessimistic one lags the
#: nominal by at least this much [deg] (a few hundred Hz at 4 kHz: well above friction's lead) ...
VARIANT_CHECK_LAG_DEG = 30.0
#: ... on at least this many coherent lines.
VARIANT_CHECK_LINES = 5


class MeasuredMode(NamedTuple):
    """A resonance the measured response shows and a ``stiff`` answer lacks, fitted (rule R7d,
    :func:`training.commissioning._narrow.measured_mode`): found at ``w_r`` [rad/s]; the two-mass
    modes the measurement does not invalidate span ``f_e`` [Hz] (low, high) and the worst cases'
    ``V_J`` values, down to damping ``d``; from ``lines`` measured lines."""

    w_r: float
    f_e: tuple[float, float]
    V_J: tuple[float, ...]
    d: float
    lines: int


class Member(NamedTuple):
    """One mechanic of an :class:`UncertaintySet`: its ``mechanics``, ``label``, whether it is a
    ``hidden`` resonance (a worst case of what a test cannot exclude, not the identified plant),
    and whether it is ``transient`` (a state the plant passes through: the decoupled motor)."""

    mechanics: Mechanics
    label: str
    hidden: bool = False
    transient: bool = False


@dataclass(frozen=True)
class UncertaintySet:
    """The plants a design must hold on (SPEC 8.2's "every model of the uncertainty set").

    Where the identification reports calibrated intervals (SPEC 4.1), ``bounds`` (a
    :class:`MechanicsBounds` of them): the members span each interval of ``f_e``, ``V_J``, ``d``
    and ``J_sigma`` (a backlash plant's decoupled motor at the low end of ``J_M``), so that a
    narrow interval gives a narrow set. Without them (``bounds`` None: maps without a calibration)
    an interim set of documented relative half-widths (``f_e_spread``, ``V_J_spread``; ``d_scale``
    the damping's factors, low and high) around the identified ``mechanics``, and :meth:`describe`
    says so. ``doubts``: why it was widened (rule R7c). The
    identified mechanic is taken with the SPEC's first-order current loop, every member with
    ``current_loop_damping``'s second-order lag plus ``extra_delay`` samples of dead time (the
    hidden resonances with both). ``decoupled_motor``: a backlash
    plant's motor alone while the gap is open (one mass ``J_sigma / (1 + V_J)``, rule R6): a state
    the loop passes through, held to ``gap_open_margins`` (phase [deg], gain [dB]: stable with room,
    so that the loop does not limit-cycle) instead of the guarantee's margins, its load not counted.
    ``hidden``: resonances a test run cannot exclude (``V_J -> (f_lo, f_hi)`` [Hz], rule R7b,
    at damping ``hidden_d``), replaced by ``measured`` (the trusted part of the plant's measured
    frequency response) where there is one; a resonance the measurement found (and the model
    lacks) stays in the set at the same worst cases (each ``V_J`` of ``hidden``, ``hidden_d``) at
    its measured frequency x(1 -+ ``measured_f_spread``): the measurement places it, but its height
    and phase are not to be trusted (friction makes a small-signal measurement lead the plant).
    Its ratio of inertias is: where the measurement reaches above it, the measured over the
    one-mass model's magnitude there (:meth:`MeasuredResponse.inertia_ratio` over ``inertia_band``
    x the resonance: ``1 + V_J``) bounds the worst cases' ``V_J`` to ``inertia_factor`` x that
    ratio, less 1 (:meth:`measured_V_Js`). ``variant_lag_share``: where the measured response
    shows at most this share of the variant's extra phase lag (:meth:`variant_lag`), the drive
    follows the SPEC's first-order current loop and the members are taken without the variant
    (None: always with it). ``hidden_kept``: the measured response, coherent on too few of its lines
    to have shown a resonance where it is not, leaves :attr:`hidden` in the set beside it.
    """

    mechanics: Mechanics
    f_e_spread: float = 0.1
    V_J_spread: float = 0.25
    d_scale: tuple[float, float] = (0.5, 2.0)
    current_loop_damping: float = 1 / math.sqrt(2)
    extra_delay: int = 1
    decoupled_motor: bool = False
    hidden: dict[float, tuple[float, float]] | None = None
    hidden_d: float = 0.005
    hidden_points_per_decade: float = 8.0
    hidden_min_points: int = 5
    measured: MeasuredResponse | None = None
    measured_f_spread: float = MEASURED_F_SPREAD
    inertia_band: tuple[float, float] = (1.4, 2.5)
    inertia_factor: float = 1.5
    doubts: tuple[str, ...] = ()
    bounds: MechanicsBounds | None = None
    gap_open_margins: tuple[float, float] = GAP_OPEN_MARGINS
    variant_lag_share: float | None = None
    hidden_kept: bool = False
    measured_modes: tuple[MeasuredMode, ...] = ()

    def __post_init__(self) -> None:
        if self.bounds is not None and not isinstance(self.bounds, MechanicsBounds):
            raise TypeError(f"bounds: expected MechanicsBounds or None, received {type(self.bounds).__name__}")

    def spans(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, float]]:
        """The two-mass members' ``f_e`` values [Hz] (low, identified, high), ``V_J`` values and the
        damping's ``(low, high)`` (each at most 0.999): from :attr:`bounds`, else the interim spread."""
        m = self.mechanics
        if self.bounds is not None:
            b = self.bounds
            f_es, V_Js, (d_lo, d_hi) = (b.f_e[0], m.f_e, b.f_e[1]), (b.V_J[0], m.V_J, b.V_J[1]), b.d
        else:
            f_es = tuple(m.f_e * s for s in (1 - self.f_e_spread, 1.0, 1 + self.f_e_spread))
            V_Js = tuple(m.V_J * s for s in (1 - self.V_J_spread, 1.0, 1 + self.V_J_spread))
            d_lo, d_hi = (m.d * s for s in self.d_scale)
        return tuple(dict.fromkeys(f_es)), tuple(dict.fromkeys(V_Js)), (min(d_lo, 0.999), min(d_hi, 0.999))

    @property
    def keeps_hidden(self) -> bool:
        """Whether :attr:`hidden` is in the set: nothing measured, or a measurement that could not
        exclude them (:attr:`hidden_kept`)."""
        return bool(self.hidden) and (self.measured is None or self.hidden_kept)

    def decoupled_J(self) -> float:
        """The decoupled motor's inertia [kg m^2] (rule R6): the identified ``J_sigma / (1 + V_J)``, or
        the low end of :attr:`bounds`' ``J_M`` where that is lower (a lighter motor: more loop gain)."""
        m = self.mechanics
        J_M = m.J_sigma / (1.0 + m.V_J)
        return J_M if self.bounds is None else min(self.bounds.J_M[0], J_M)

    def members(self) -> list[Member]:
        """The mechanics of the set: the identified one first, the corners of ``f_e`` x ``V_J``
        (:meth:`spans`) at the low damping, the high damping at the identified ``f_e`` and ``V_J``,
        the ends of the ``J_sigma`` interval (with :attr:`bounds`; at the low damping), the decoupled
        motor, the hidden resonances (none where a response was measured)."""
        m = self.mechanics
        out = [Member(m, _label(m))]
        if m.two_mass:
            f_es, V_Js, (d_lo, d_hi) = self.spans()
            for f_e, V_J in itertools.product(f_es, V_Js):
                corner = replace(m, f_e=f_e, V_J=V_J, d=d_lo)
                out.append(Member(corner, _label(corner)))
            out.append(Member(replace(m, d=d_hi), _label(replace(m, d=d_hi))))
        if self.bounds is not None:
            low_d = {"d": self.spans()[2][0]} if m.two_mass else {}
            for J in dict.fromkeys(self.bounds.J_sigma):
                if J != m.J_sigma:
                    end = replace(m, J_sigma=J, **low_d)
                    out.append(Member(end, f"J_sigma {J:.4g} kg m^2, " + _label(end) if m.two_mass else _label(end)))
        if m.two_mass and self.decoupled_motor:
            out.append(Member(Mechanics(self.decoupled_J(), mu_F=m.mu_F), "decoupled motor (backlash gap open)", transient=True))
        if self.keeps_hidden:
            out += [Member(h, f"hidden resonance {_label(h)}", hidden=True)
                    for h in _hidden_mechanics(m.J_sigma, self.hidden, self.hidden_d, self.hidden_points_per_decade,
                                               self.hidden_min_points)]
        elif self.hidden:
            out += [Member(Mechanics(m.J_sigma, V_J=v, f_e=f, d=d), f"measured resonance's worst case f_e {f:.4g} Hz, V_J {v:.3g}, d {d:.3g}",
                           hidden=True)
                    for w in self.measured.resonances for f_es, V_Js, d in [self.measured_worst_cases(w)] for f in f_es for v in V_Js]
        return out

    def measured_worst_cases(self, w_r: float) -> tuple[tuple[float, ...], tuple[float, ...], float]:
        """The worst cases ``(f_e values [Hz], V_J values, d)`` of a resonance the measurement found
        at ``w_r`` [rad/s] (and the model lacks): where a mode was fitted to the measurement
        (:attr:`measured_modes`, rule R7d), the ends of its ``f_e`` and ``V_J`` and its lowest ``d``;
        else ``w_r`` x(1 -+ :attr:`measured_f_spread`), :meth:`measured_V_Js`, :attr:`hidden_d`."""
        f_r = w_r / (2 * math.pi)
        mode = next((mode for mode in self.measured_modes if mode.w_r == w_r), None)
        if mode is not None:
            return tuple(dict.fromkeys((mode.f_e[0], f_r, mode.f_e[1]))), mode.V_J, mode.d
        spread = self.measured_f_spread
        return (f_r * (1 - spread), f_r, f_r * (1 + spread)), self.measured_V_Js(w_r), self.hidden_d

    def measured_V_Js(self, w_r: float) -> tuple[float, ...]:
        """The worst cases' ``V_J`` of a resonance the measurement found at ``w_r`` [rad/s]: those of
        :attr:`hidden`, each at most ``inertia_factor`` x the measured ``1 + V_J``, less 1 (all of them
        where the measurement does not reach above the resonance, or where the identified mechanic
        has a resonance of its own: the measured over the model's magnitude then does not show the
        one it lacks)."""
        V_Js = tuple(self.hidden or ())
        one_mass = self.measured is not None and not self.mechanics.two_mass
        ratio = self.measured.inertia_ratio(w_r, self.inertia_band, 0.0) if one_mass else None
        if ratio is None:
            return V_Js
        cap = self.inertia_factor * max(ratio, 1.0) - 1.0
        return tuple(sorted({min(v, cap) for v in V_Js}))

    def models(self, drive: Any) -> ModelSet:
        """The :class:`ModelSet`: the identified mechanic as it is first (the design's nominal
        model), then every member with the second-order current loop and the extra delay (the
        pessimistic variant for the spread), the hidden resonances also as they are (a light
        resonance high up is gain-stabilized less by the first-order loop); the measured response last.
        Where the measured response shows the drive's loop as the SPEC's (:meth:`follows_nominal`),
        every member as it is, without the variant.
        The load peak counts on the identified mechanic's members, not on the hidden resonances:
        those sit at the envelope's lowest damping, a worst case for stability; a load held below
        6 dB there would bind any loop to a fiftieth of their anti-resonance, whatever the plant."""
        nominal = self.follows_nominal(drive)
        variant = {} if nominal else {"current_loop_damping": self.current_loop_damping, "extra_delay": self.extra_delay}
        suffix = "" if nominal else f", 2nd-order current loop, +{self.extra_delay} sample delay"
        plants, labels, checked, transient = [linear_plant(self.mechanics, drive)], [_label(self.mechanics)], [True], [False]
        for i, (mech, label, hidden, passing) in enumerate(self.members()):
            loops = [({}, label)] if i and hidden and not nominal else []
            if i or not nominal:  # the identified mechanic as it is is the first model already
                loops.append((variant, label + suffix))
            for loop, name in loops:
                plants.append(linear_plant(mech, drive, **loop))
                labels.append(name)
                checked.append(not hidden)
                transient.append(passing)
        return ModelSet(tuple(plants), tuple(labels), self.measured, tuple(checked), tuple(transient), self.gap_open_margins)

    def variant_lag(self, drive: Any) -> float | None:
        """The share of the pessimistic variant's extra phase lag (second-order current loop, extra
        delay) that the measured response shows over the identified mechanic's nominal response:
        the upper quartile of ``angle(G / G_nominal) / angle(G_variant / G_nominal)`` over the
        measured lines where the variant lags by at least :data:`VARIANT_CHECK_LAG_DEG` (about 1: the
        drive lags as the variant does; about 0 or below: as the SPEC's loop). The upper quartile,
        not the median: where the identified resonance is misplaced, the lines near it carry the
        model's error, not the drive's (a 448 Hz plant answered at 266 Hz on a drive with the
        variant: median 0.30, upper quartile 1.07). None: no measurement, or fewer than
        :data:`VARIANT_CHECK_LINES` such lines (the measurement does not reach where they differ)."""
        if self.measured is None:
            return None
        z = np.exp(1j * np.asarray(self.measured.w) * drive_value(drive, "T_s"))
        G_n = linear_plant(self.mechanics, drive).speed_response(z)
        G_v = linear_plant(self.mechanics, drive, current_loop_damping=self.current_loop_damping,
                           extra_delay=self.extra_delay).speed_response(z)
        lag = np.angle(G_v / G_n)
        where = lag <= -math.radians(VARIANT_CHECK_LAG_DEG)
        if where.sum() < VARIANT_CHECK_LINES:
            return None
        return float(np.quantile(np.angle(np.asarray(self.measured.G)[where] / G_n[where]) / lag[where], 0.75))

    def follows_nominal(self, drive: Any) -> bool:
        """Whether the measured response shows the drive's current loop as the SPEC's: at most
        :attr:`variant_lag_share` of the variant's extra lag (:meth:`variant_lag`)."""
        if self.variant_lag_share is None:
            return False
        share = self.variant_lag(drive)
        return share is not None and share <= self.variant_lag_share

    def describe(self, drive: Any = None) -> str:
        """One line: what the set holds."""
        m, b, parts = self.mechanics, self.bounds, []
        if b is not None:
            f_es, V_Js, (d_lo, d_hi) = self.spans()
            spans = (f"f_e {f_es[0]:.4g}..{f_es[-1]:.4g} Hz, V_J {V_Js[0]:.3g}..{V_Js[-1]:.3g}, d {d_lo:.3g}..{d_hi:.3g}, "
                     if m.two_mass else "")
            parts.append(f"{spans}J_sigma {b.J_sigma[0]:.4g}..{b.J_sigma[1]:.4g} kg m^2 (the identification's calibrated "
                         f"90 % intervals{'; ' + b.widened if b.widened else ''})")
        elif m.two_mass:
            parts.append(f"f_e +-{self.f_e_spread:.0%}, V_J +-{self.V_J_spread:.0%}, d x{self.d_scale[0]:g}..{self.d_scale[1]:g} "
                         "(the interim spread: the identification carries no calibrated intervals)")
        if m.two_mass and self.decoupled_motor:
            pm, gm = self.gap_open_margins
            parts.append(f"the decoupled motor {'J_sigma/(1+V_J)' if b is None else 'J_M'} = {self.decoupled_J():.4g} kg m^2 "
                         f"(gap open: PM >= {pm:g} deg, GM >= {gm:g} dB)")
        if self.keeps_hidden:
            parts.append("hidden resonances " + ", ".join(f"V_J {v:g}: {lo:.3g}..{hi:.3g} Hz" for v, (lo, hi) in self.hidden.items()))
        if self.measured is not None:
            parts.append(f"the measured response at {len(self.measured.w)} frequencies")
            if self.hidden and not self.hidden_kept and self.measured.resonances:
                for w in self.measured.resonances:
                    f_es, V_Js, d = self.measured_worst_cases(w)
                    fitted = any(mode.w_r == w for mode in self.measured_modes)
                    parts.append(f"the measured resonance at {w / (2 * math.pi):.4g} Hz{' fitted (R7d)' if fitted else ''}: "
                                 f"f_e {min(f_es):.4g}..{max(f_es):.4g} Hz, V_J {', '.join(f'{v:.3g}' for v in V_Js)}, d {d:.3g}")
        parts.append(self._loops_text(drive))
        return "; ".join(parts)

    def _loops_text(self, drive: Any) -> str:
        """What current loop the members carry (:meth:`describe`; ``drive`` None: not checked)."""
        share = None if drive is None or self.variant_lag_share is None else self.variant_lag(drive)
        if share is not None and share <= self.variant_lag_share:  # follows_nominal, the share said
            return (f"each with the SPEC's first-order current loop alone (the measured response shows {max(share, 0.0):.0%} "
                    f"of the extra lag of a 2nd-order loop with +{self.extra_delay} sample delay)")
        return f"each with a 2nd-order current loop (D {self.current_loop_damping:.3g}) +{self.extra_delay} sample delay"


def _label(m: Mechanics) -> str:
    return (f"f_e {m.f_e:.3g} Hz, V_J {m.V_J:.3g}, d {m.d:.3g}" if m.two_mass else f"J_sigma {m.J_sigma:.3g}")


#: A band of hidden resonances no wider than this ratio is one eigenfrequency.
_SINGLE_WIDTH = 1.01


def _hidden_mechanics(J_sigma: float, bands: dict[float, tuple[float, float]], d: float, per_decade: float,
                      min_points: int) -> list[Mechanics]:
    """Two-mass mechanics on ``J_sigma`` at damping ``d``, per inertia ratio of ``bands`` at
    ``per_decade`` eigenfrequencies per decade (at least ``min_points``) across its band [Hz]."""
    out = []
    for v, (f_lo, f_hi) in bands.items():
        if f_lo <= f_hi:
            n = max(min_points, math.ceil(per_decade * math.log10(f_hi / f_lo)) + 1)
            f_es = np.geomspace(f_lo, f_hi, n) if f_hi > f_lo * _SINGLE_WIDTH else np.array([f_lo])
            out += [Mechanics(J_sigma, V_J=v, f_e=float(f), d=d) for f in f_es]
    return out


@dataclass(frozen=True)
class DesignSearch:
    """How :func:`optimize_loop` searches (every value documented: what and why)."""

    ti_ratios: tuple[float, ...] = (3.0, 7.0)
    """``Ti w_r`` tried (the PI's phase lag at the crossover ``atan(1/ratio)``: 18 and 8 deg); the smaller wins a tie."""
    filter_samples: tuple[float, ...] = (0.0, 2.0, 4.0, 8.0, 16.0)
    """Speed low-pass ``T_f`` tried, in samples (0: none; a low-pass gain-stabilizes resonances above the crossover:
    a stiff answer's hidden ones are held at 90 rad/s with 16 samples, 25 with 2)."""
    notch_depths: tuple[float, ...] = (0.05, 0.3)
    """Notch ``D_z`` tried (at least the mechanic's damping; the gain at the centre is ``D_z / D_p``)."""
    notch_widths: tuple[float, ...] = (0.2, 0.5, 1.2)
    """Notch ``D_p`` tried: narrow (0.2, the oracle's usual width: costs the least phase at the
    crossover, kept only where every model of the set allows it, e.g. a resonance the measurement
    placed within +-5 %) to wide (covers an uncertain resonance)."""
    notch_max_share: float = 0.4
    """Notches only below this share of the sampling frequency (resolvable, little warped)."""
    level_ratio: float = 1.25
    """The descending grid of target crossovers steps by this factor ..."""
    bisections: int = 4
    """... then this many bisections (in log) between the first feasible level and the one above."""
    keep_shapes: int = 12
    """Shapes carried into the bisection: the feasible ones with the most slack."""
    w_c_min: float = 0.5
    """The lowest target crossover [rad/s]."""
    max_load_peak_dB: float = 6.0
    """SPEC 8.2: the reference-to-load peak on every plant of the set [dB] (the load must not ring)."""

    def __post_init__(self) -> None:
        check_settings(self, {
            "ti_ratios": Values(POSITIVE, empty=False), "filter_samples": Values(NON_NEGATIVE, empty=False),
            "notch_depths": Values(POSITIVE, empty=False), "notch_widths": Values(POSITIVE, empty=False),
            "notch_max_share": Interval(0.0, 0.5, open_low=True, open_high=True), "level_ratio": Interval(1.0, open_low=True),
            "bisections": COUNT, "keep_shapes": AT_LEAST_ONE, "w_c_min": POSITIVE, "max_load_peak_dB": REAL_OR_INF},
            CommissioningError)


#: The search :func:`optimize_loop` uses by default.
SEARCH = DesignSearch()


@dataclass(frozen=True)
class OptimizedLoop:
    """:func:`optimize_loop`'s answer: the law (``Kp``, ``Ti``, ``T_f``, ``notches``) and its first
    crossover ``w_c`` [rad/s] on the nominal model; ``found`` whether every constraint holds on
    every model (else the lowest gain tried); the worst phase margin [deg], gain margin [dB],
    load peak [dB] over the set and the models they occur on; ``lowest_w_c`` the lowest first
    crossover over the set's models; ``limited_by``: what bounds ``w_c`` (the constraint, the
    model, one step above); ``evaluations``: law shapes x models evaluated."""

    Kp: float
    Ti: float
    T_f: float
    notches: tuple[NotchSpec, ...]
    w_c: float
    found: bool
    phase_margin: float
    gain_margin_dB: float
    load_peak_dB: float
    worst_model: str
    lowest_w_c: float
    limited_by: str
    evaluations: int


@dataclass
class _Model:
    """One model of the set as the search sees it: grid ``w``, ``z``, responses ``G``, ``G_L``
    (None: its load does not count), its plant (None: measured), label, the law's notch and
    low-pass responses on its grid per option, and whether it is a transient state
    (:attr:`ModelSet.transient`: held to the set's transient margins)."""

    label: str
    T_s: float
    w: np.ndarray
    z: np.ndarray
    G: np.ndarray
    G_L: np.ndarray | None
    plant: LinearPlant | None
    N: np.ndarray
    F: np.ndarray
    transient: bool = False
    kills: int = 0


def _notch_options(freqs: Sequence[float], d: float, T_s: float, search: DesignSearch) -> list[tuple[NotchSpec, ...]]:
    """No notch; one at each frequency of ``freqs`` [Hz] per depth and width; two (one per
    frequency, or a staggered pair around one) per depth and width."""
    f_ok = [f for f in freqs if 0 < f < search.notch_max_share / T_s]
    grid = [(max(dz, d), dp) for dz in search.notch_depths for dp in search.notch_widths if max(dz, d) < dp]
    out: list[tuple[NotchSpec, ...]] = [()]
    out += [(NotchSpec(f, dz, dp),) for f in f_ok for dz, dp in grid]
    pairs = list(itertools.combinations(f_ok, 2)) or [(f / 1.15, min(f * 1.15, 0.999 * search.notch_max_share / T_s)) for f in f_ok[:1]]
    out += [(NotchSpec(a, dz, dp), NotchSpec(b, dz, dp)) for a, b in pairs[:1] for dz, dp in grid]
    return out


def _shapes(notch_options: list[tuple[NotchSpec, ...]], search: DesignSearch) -> list[tuple[int, int, int]]:
    """Every (ti_ratio, filter, notch option) index triple, in the order a tie is decided: fewer
    notches, smaller ``Ti w_c``, less filter first."""
    return sorted(itertools.product(range(len(search.ti_ratios)), range(len(search.filter_samples)), range(len(notch_options))),
                  key=lambda s: (len(notch_options[s[2]]), s[0], s[1], s[2]))


def _prepare(models: ModelSet, T_s: float, notch_options: list[tuple[NotchSpec, ...]], search: DesignSearch) -> list[_Model]:
    """Each model's grid and responses, with the notch and low-pass options' responses on it."""
    T_fs = np.array(search.filter_samples) * T_s
    out = []
    for i, (plant, label, (w, G, G_L)) in enumerate(zip(models.plants, models.labels, models.responses())):
        z = np.exp(1j * w * plant.T_s)
        out.append(_Model(label, T_s, w, z, G, G_L if models.load_counts(i) else None, plant,
                          np.array([controller_parts(T_s, z, notch=n)["notch"] for n in notch_options]),
                          controller_parts(T_s, z, T_f=T_fs[:, None])["lowpass"], models.is_transient(i)))
    if models.measured is not None:
        m = models.measured
        z = np.exp(1j * m.w * m.T_s)
        out.append(_Model(ModelSet.MEASURED, T_s, m.w, z, m.G, None, None,
                          np.array([controller_parts(T_s, z, notch=n)["notch"] for n in notch_options]),
                          controller_parts(T_s, z, T_f=T_fs[:, None])["lowpass"]))
    return out


@dataclass(frozen=True)
class _Check:
    """The constraints of a batch of shapes on one model: ``ok`` per shape, and the figures."""

    ok: np.ndarray
    pm: np.ndarray
    gm: np.ndarray
    peak: np.ndarray
    w_c: np.ndarray


def _check(model: _Model, Kp: np.ndarray, ti: np.ndarray, fi: np.ndarray, ni: np.ndarray, w_c: float,
           search: DesignSearch, pm_min: float, gm_min: float) -> _Check:
    """Phase and gain margins and the load peak of the shapes (``Kp``, indices into the options) on ``model``."""
    Ti = np.asarray(search.ti_ratios)[ti] / w_c
    C = Kp[:, None] * controller_parts(model.T_s, model.z, Ti=Ti[:, None])["pi"] * model.N[ni]
    L = C * model.F[fi] * model.G
    pm, gm, wc = margin_arrays(L, model.w)
    if model.G_L is not None:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            peak = 20 * np.log10(np.abs(load_transfer(C, model.F[fi], model.G, model.G_L)).max(axis=-1))
    else:
        peak = np.full(len(Kp), -np.inf)
    ok = (pm >= pm_min) & (gm >= gm_min) & (peak <= search.max_load_peak_dB)
    return _Check(ok, pm, gm, peak, wc)


@dataclass
class _Context:
    """What every level of the search shares: the models, the options, the nominal plant, the bounds."""

    models: list[_Model]
    notch_options: list[tuple[NotchSpec, ...]]
    shapes: np.ndarray  # (S, 3) indices: ti_ratio, filter, notch option
    J_sigma: float
    T_s: float
    search: DesignSearch
    pm_min: float
    gm_min: float
    transient_margins: tuple[float, float] = (0.0, 0.0)
    evaluations: int = 0

    def required(self, model: _Model) -> tuple[float, float]:
        """The phase [deg] and gain [dB] margins ``model`` must keep."""
        return self.transient_margins if model.transient else (self.pm_min, self.gm_min)

    def law(self, shape: np.ndarray, w_c: float) -> tuple[float, float, float, tuple[NotchSpec, ...]]:
        """``(Kp, Ti, T_f, notches)`` of one shape at the target crossover ``w_c``."""
        Kp = float(self.gains(shape[None], w_c)[0])
        ti, fi, ni = (int(i) for i in shape)
        return Kp, self.search.ti_ratios[ti] / w_c, self.search.filter_samples[fi] * self.T_s, self.notch_options[ni]

    def gains(self, shapes: np.ndarray, w_r: float) -> np.ndarray:
        """``Kp`` per shape at the rigid-body crossover ``w_r``: ``J_sigma w_r`` (the crossover of the
        one mass ``J_sigma``; the same for every shape, so that a level is one gain)."""
        return np.full(len(shapes), self.J_sigma * w_r)


@dataclass(frozen=True)
class _Level:
    """One rigid-body crossover's outcome (``w_c``: the level): the shapes (indices into the
    context's) that keep every constraint (``feasible``, most slack first), the stable one with
    the highest first crossover on the nominal model (``chosen``, None: none; ``crossover`` its
    crossover [rad/s]), and per shape the first failing model and constraint (``why``)."""

    w_c: float
    feasible: np.ndarray
    chosen: int | None
    why: dict[int, str]
    crossover: float = math.nan


def _slack(chk: _Check, pm_min: float, gm_min: float, max_peak: float) -> np.ndarray:
    """How far the shapes keep from the constraints (in units of 10 deg, 3 dB, 3 dB)."""
    return np.minimum(np.minimum((chk.pm - pm_min) / 10.0, (chk.gm - gm_min) / 3.0), (max_peak - chk.peak) / 3.0)


def _failure(chk: _Check, i: int, pm_min: float, gm_min: float, max_peak: float, label: str) -> str:
    """Which constraint shape ``i`` of ``chk`` misses on the model ``label``, in words."""
    if not chk.pm[i] >= pm_min:
        return f"PM {chk.pm[i]:.1f} deg < {pm_min:g} on {label}"
    if not chk.gm[i] >= gm_min:
        return f"GM {chk.gm[i]:.1f} dB < {gm_min:g} on {label}"
    return f"load peak {chk.peak[i]:.1f} dB > {max_peak:g} on {label}"


def _stable(ctx: _Context, shape: np.ndarray, w_c: float) -> str | None:
    """None when the closed loop of ``shape`` at ``w_c`` is stable on every plant of the set, else
    the first plant it is not stable on."""
    Kp, Ti, T_f, notches = ctx.law(shape, w_c)
    for m in ctx.models:
        if m.plant is not None:
            A = closed_loop_matrices(m.plant, Kp, Ti, T_f, notches)[0]
            if not np.abs(np.linalg.eigvals(A)).max() < 1.0:
                return f"unstable on {m.label}"
    return None


def _level(ctx: _Context, candidates: np.ndarray, w_c: float) -> _Level:
    """The ``candidates`` (indices into ``ctx.shapes``) at the rigid-body crossover ``w_c``: each model
    in turn (the one that rejected most so far first) drops the shapes that miss a constraint on
    it; the survivors, in the order of preference, are checked for closed-loop stability."""
    s, max_peak = ctx.search, ctx.search.max_load_peak_dB
    shapes = ctx.shapes[candidates]
    Kp = ctx.gains(shapes, w_c)
    alive = np.ones(len(candidates), dtype=bool)
    slack, crossover = np.full(len(candidates), np.inf), np.full(len(candidates), np.nan)
    why: dict[int, str] = {}
    for model in sorted(ctx.models, key=lambda m: -m.kills):
        idx = np.nonzero(alive)[0]
        if not len(idx):
            break
        sub = shapes[idx]
        pm_min, gm_min = ctx.required(model)
        chk = _check(model, Kp[idx], sub[:, 0], sub[:, 1], sub[:, 2], w_c, s, pm_min, gm_min)
        ctx.evaluations += len(idx)
        slack[idx] = np.minimum(slack[idx], _slack(chk, pm_min, gm_min, max_peak))
        if model is ctx.models[0]:
            crossover[idx] = chk.w_c
        for j in np.nonzero(~chk.ok)[0]:
            why[int(candidates[idx[j]])] = _failure(chk, j, pm_min, gm_min, max_peak, model.label)
        model.kills += int((~chk.ok).sum())
        alive[idx[~chk.ok]] = False
    ok = np.nonzero(alive)[0]
    chosen = None
    # the highest nominal crossover first; a tie to the order of preference (candidates index it)
    for i in sorted(ok, key=lambda i: (-np.round(np.nan_to_num(crossover[i]), 6), candidates[i])):
        unstable = _stable(ctx, ctx.shapes[candidates[i]], w_c)
        if unstable is None:
            chosen = int(candidates[i])
            break
        why[int(candidates[i])] = unstable
        alive[i] = False
    feasible = candidates[np.nonzero(alive)[0][np.argsort(-slack[alive])]]
    return _Level(w_c, feasible, chosen, why, float(crossover[list(candidates).index(chosen)]) if chosen is not None else math.nan)


def _search(ctx: _Context, w_top: float) -> tuple[_Level | None, _Level | None]:
    """The descending grid of target crossovers from ``w_top`` to the first level with a stable
    feasible shape, then bisection (in log) between it and the level above on the shapes with most
    slack. Returns the best feasible level and the infeasible one just above it (None: the top
    itself was feasible, or nothing was)."""
    s = ctx.search
    every = np.arange(len(ctx.shapes))
    w_c, above = w_top, None
    while w_c >= s.w_c_min:
        level = _level(ctx, every, w_c)
        if level.chosen is not None:
            break
        above, w_c = level, w_c / s.level_ratio
    else:
        return None, above
    if above is None:
        return level, None
    for _ in range(s.bisections):
        mid = math.sqrt(level.w_c * above.w_c)
        keep = np.union1d(level.feasible[:s.keep_shapes], [level.chosen])
        trial = _level(ctx, keep, mid)
        if trial.chosen is not None:
            level = trial
        else:
            above = trial
    return level, above


def optimize_loop(models: ModelSet, drive: Any, *, J_sigma: float, notch_at: Sequence[float] = (), d: float = 0.0,
                  min_phase_margin: float, min_gain_margin_dB: float, search: DesignSearch = SEARCH) -> OptimizedLoop:
    """The law with the largest first crossover on ``models``' first (nominal) model that keeps, on
    every model of the set, the closed loop stable, PM >= ``min_phase_margin``, GM >=
    ``min_gain_margin_dB`` and, on the plants whose load counts (:attr:`ModelSet.load_checked`),
    the reference-to-load peak <= ``search.max_load_peak_dB``.

    The search: the gain ``Kp = J_sigma w_r`` descends by ``search.level_ratio`` from the
    rigid-body crossover ``w_r = 1.5 / (T_Ei + 2 T_s)`` (above what the current loop and the
    sampling allow); per level every shape (``Ti = ratio / w_r`` over ``search.ti_ratios``,
    ``T_f`` of ``search.filter_samples``, no notch, one notch at each of ``notch_at`` [Hz] or two,
    over ``search.notch_depths`` (at least ``d``) and ``search.notch_widths``) is held against the
    constraints model by model (the one that rejected most so far first), vectorized over the
    shapes; the first level with a stable feasible shape ends the descent, ``search.bisections``
    bisections in log between it and the level above refine it on the ``search.keep_shapes``
    shapes with most slack. At the final level the stable feasible shape with the highest first
    crossover on the nominal model wins (a tie: fewer notches, the smaller ``Ti w_r``, the
    smaller ``T_f``).
    """
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    notch_options = _notch_options(notch_at, d, T_s, search)
    shapes = np.array(_shapes(notch_options, search), dtype=np.int64)
    ctx = _Context(_prepare(models, T_s, notch_options, search), notch_options, shapes, J_sigma, T_s, search,
                   min_phase_margin, min_gain_margin_dB, models.transient_margins)
    best, above = _search(ctx, 1.5 / (T_Ei + 2 * T_s))
    found = best is not None
    w_r = best.w_c if found else search.w_c_min
    shape = shapes[best.chosen] if found else shapes[0]
    Kp, Ti, T_f, notches = ctx.law(shape, w_r)
    lasting = [m for i, m in enumerate(models.each(Kp, Ti, T_f, notches)) if not models.is_transient(i)]
    peaks = models.load_peaks_dB(Kp, Ti, T_f, notches)
    worst = min(lasting, key=lambda m: (m.stable, min(m.phase_margin - min_phase_margin, m.gain_margin_dB - min_gain_margin_dB)))
    crossovers = [m.w_c for m in lasting if math.isfinite(m.w_c)]
    if not found:
        limited = "no gain down to the search's lowest keeps the constraints"
    elif above is None:
        limited = "the search's highest gain (the current loop and the sampling)"
    else:
        limited = f"Kp x {above.w_c / best.w_c:.3g}: " + above.why.get(int(best.chosen), "every shape misses a constraint")
    return OptimizedLoop(Kp, Ti, T_f, notches, lasting[0].w_c, found, min(m.phase_margin for m in lasting),
                         min(m.gain_margin_dB for m in lasting), float(peaks.max(initial=-math.inf)), worst.model,
                         min(crossovers, default=math.nan), limited, ctx.evaluations)
