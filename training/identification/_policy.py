"""The identifier's decisions for one record, as named rules over typed values with their own
settings (:class:`IdentificationPolicy`):

- :data:`REFINED_WHEN`: which maps' answers the refinement sees (any rule that holds);
- :func:`angle_checked_when`: which refined stiff results are checked for a gap in the motor's angle;
- :func:`refinement_stands`: whether the refinement's class replaces the maps' one;

and SPEC's class rule on a two-mass model of the record's drive (:func:`spec_class`), which both
the maps' answer and the refined one are classed by.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from sim import STRUCTURE_CLASSES, class_index, two_mass_derived
from training._settings import POSITIVE, SHARE, check_settings
from training.identification._analysis import Analysis
from training.identification._envelope import Finding
from training.identification._limits import backlash_negligible, speed_resolution
from training.identification._refine import Refined

#: The classes with a backlash (their width is identified).
BACKLASH_CLASSES = ("elastic_backlash", "stiff_backlash")


@dataclass(frozen=True)
class IdentificationPolicy:
    """The thresholds of the identifier's decisions (each checked to lie in its range)."""

    #: rms of ``w_osc`` [speed quanta] from which the oscillation shows above the quantization.
    visible_quanta: float = 1.0
    #: the structure map's probability of ``stiff`` below which a stiff answer is refined too.
    stiff_sure: float = 0.6
    #: :attr:`Refined.evidence` below which the refinement's class does not replace the maps' one.
    class_evidence: float = 15.0
    #: the refined model's residual (of the oscillation's rms) above which its fit is called partial.
    partial_fit_residual: float = 0.7
    #: relative distance to a class threshold within which the neighbouring class is about as likely.
    class_margin: float = 0.25
    #: the largest damping the maps' answer gives (the ``f_e`` map's read-out clipped to ``[0, this]``).
    damping_cap: float = 0.9
    #: the smallest ``s_N`` the refinement starts from (its coordinate is ``log10 s_N``).
    start_s_N_floor: float = 1e-3
    #: the refinement's model carries STEP 2's constant torque ``M_0`` as a load torque ``M_L0`` (SPEC 1.1,
    #: held at rest, the gap closed on the loaded side) only where it reaches this share of ``M*`` and
    #: ``load_torque_sigmas`` of its standard deviation: an axis without one starts with its gap open
    #: (measured on the reference drive's default population: carrying every fitted offset, down to
    #: 1e-4 M*, cost 10 points of the backlash widths within 30 %).
    load_torque_floor: float = 0.005
    load_torque_sigmas: float = 3.0
    #: the share of ``w_osc``'s variance the oscillation fit must explain for a stiff answer to name
    #: the mode its record shows (``Quality.stiff_mode_Hz``): at and above it, every such fit on the
    #: matrix drives' records put the mode within 2 % of the true one.
    mode_fit_r2: float = 0.3

    def __post_init__(self) -> None:
        check_settings(self, {
            "visible_quanta": POSITIVE, "stiff_sure": SHARE, "class_evidence": POSITIVE, "partial_fit_residual": POSITIVE,
            "class_margin": SHARE, "damping_cap": SHARE, "start_s_N_floor": POSITIVE, "mode_fit_r2": SHARE,
            "load_torque_floor": SHARE, "load_torque_sigmas": POSITIVE})


@dataclass(frozen=True)
class MapsAnswer:
    """What the maps say about one record, before the refinement: the structure and its
    probabilities, ``f_e`` [Hz], ``V_J``, ``d``, the structure map's and the backlash map's
    ``s_N`` (on the record's own ``M_N``: :func:`s_N_on_record`), each map's recall distance
    over its training 99 % quantile, and ``f_e_flat`` [Hz]: the ``f_e`` map's units' own weights
    where its local linear read-out gives ``f_e`` (the refinement explores around both)."""

    structure: str
    probabilities: dict[str, float]
    f_e: float
    V_J: float
    d: float
    s_N: float
    s_N_backlash: float
    distance_ratio: dict[str, float]
    f_e_flat: float | None = None

    @property
    def used(self) -> tuple[str, ...]:
        """The maps whose recall this answer rests on."""
        return (("structure",) + (("f_e", "V_J") if self.structure != "stiff" else ())
                + (("backlash",) if self.structure in BACKLASH_CLASSES else ()))

    @property
    def outside_training(self) -> bool:
        return any(self.distance_ratio[name] > 1.0 for name in self.used)


def second_f_e_start(answer: MapsAnswer) -> float | None:
    """The ``f_e`` [Hz] the refinement's exploration also starts from (:attr:`RefineProblem.f_e_other`):
    the ``f_e`` map's units' own weights, unless the maps answer ``stiff_backlash``. On a coarse,
    slowly sampled drive the map's local read-out can put an elastic record's ``f_e`` 1.3-2.5x too
    high (beyond the exploring grid) where the units' weights do not. Where the maps answer
    ``stiff_backlash`` the gap hides ``f_e``, the windows barely tell it, and a second start lets
    models far below the true ``f_e`` win (``docs/identification.md``, "Explore")."""
    return None if answer.structure == "stiff_backlash" else answer.f_e_flat


# -- which answers are refined ------------------------------------------------------------------
#: A rule on one record: its analysis, the maps' answer, the envelope's findings on its drive.
RecordRule = Callable[[Analysis, MapsAnswer, Sequence[Finding], IdentificationPolicy], bool]


def _not_stiff(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
               policy: IdentificationPolicy) -> bool:
    """An elastic or backlash answer: the refinement fits its parameters on the record."""
    return answer.structure != "stiff"


def _oscillation_shows(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
                       policy: IdentificationPolicy) -> bool:
    """The oscillation shows above the quantization: near the ``w_e T_Ei = 1`` threshold the maps'
    ``f_e`` decides the class."""
    return analysis.osc_quanta >= policy.visible_quanta


def _drive_outside_training(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
                            policy: IdentificationPolicy) -> bool:
    """The drive lies outside the maps' training (or the envelope): their stiff verdict is unproven."""
    return bool(findings)


def _speed_may_hide_backlash(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
                             policy: IdentificationPolicy) -> bool:
    """The drive's speed could hide a backlash from the features: the replay still sees the gap crossings."""
    return hides_backlash(analysis)


def _unsure_of_stiff(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
                     policy: IdentificationPolicy) -> bool:
    """The structure map itself is unsure of ``stiff``."""
    return answer.probabilities["stiff"] < policy.stiff_sure


#: The maps' answer of a record is refined when any of these holds.
REFINED_WHEN: tuple[RecordRule, ...] = (_not_stiff, _oscillation_shows, _drive_outside_training,
                                        _speed_may_hide_backlash, _unsure_of_stiff)


def refined_when(analysis: Analysis, answer: MapsAnswer, findings: Sequence[Finding],
                 policy: IdentificationPolicy) -> bool:
    """Whether the refinement sees this record (:data:`REFINED_WHEN`)."""
    return any(rule(analysis, answer, findings, policy) for rule in REFINED_WHEN)


def angle_checked_when(analysis: Analysis, answer: MapsAnswer, result_structure: str) -> bool:
    """Whether a refined record's result is checked for a gap in the motor's angle: a ``stiff``
    result on STEP 2's trusted fit, where the record's speed could hide a backlash or the
    refinement dropped the maps' gap."""
    return (result_structure == "stiff" and not analysis.fit.warnings
            and (hides_backlash(analysis) or answer.structure in BACKLASH_CLASSES))


def refinement_stands(maps_structure: str, refined_structure: str, refined: Refined,
                      policy: IdentificationPolicy) -> bool:
    """Whether the refinement's answer replaces the maps' one: it keeps their class, or the record
    shows its better fit (:attr:`Refined.evidence`), or it replaced STEP 2's one-mass values."""
    return (refined_structure == maps_structure or refined.evidence >= policy.class_evidence
            or refined.J_sigma is not None)


# -- the record's own scales ---------------------------------------------------------------------
def s_N_on_record(analysis: Analysis, log10_s_star: float) -> float:
    """The record's ``s_N = s C_F / M_N`` from a map's ``log10_s_star``, ``s* = s C_F / M*`` (the
    gap's torque over the test's torque: what the speed shows), by the record's ``M*`` and ``M_N``."""
    return 10.0 ** log10_s_star * analysis.M_star / analysis.M_N


def hides_backlash(analysis: Analysis) -> bool:
    """Whether the record's speed could hide a backlash that matters on a stiff shaft
    (:func:`._limits.speed_resolution`, :func:`._limits.backlash_negligible`): the angle may still
    show it."""
    J_sigma = abs(analysis.fit.J_sigma)
    return speed_resolution(analysis.q_w, J_sigma, analysis.M_star) > backlash_negligible(analysis.M_N, analysis.T_Ei,
                                                                                         J_sigma)


@dataclass(frozen=True)
class ClassModel:
    """A two-mass model of which SPEC's class rule speaks, with the label that names it in a warning."""

    J_sigma: float
    V_J: float
    f_e: float
    d: float
    s_N: float
    label: str = ""


def class_quantities(analysis: Analysis, J_sigma: float, V_J: float, f_e: float, d: float,
                     s_N: float) -> dict[str, float]:
    """The quantities of SPEC's class rule (:data:`sim.CLASS_THRESHOLDS`) of a two-mass model on the
    record's drive: ``s_N``, ``w_e T_Ei`` and ``r_osc = V_J M* / (J_sigma w_0 q_w)``."""
    derived = two_mass_derived(J_sigma, V_J, f_e, d)
    return {"s_N": s_N, "w_e_T_Ei": derived.w_e * analysis.T_Ei,
            "r_osc": V_J * analysis.M_star / (J_sigma * derived.w_0 * analysis.q_w)}


def spec_class(analysis: Analysis, J_sigma: float, V_J: float, f_e: float, d: float, s_N: float) -> str:
    """SPEC's class (:func:`sim.class_index`) of a two-mass model on the record's drive."""
    return STRUCTURE_CLASSES[int(class_index(**class_quantities(analysis, J_sigma, V_J, f_e, d, s_N)))]


def held_torque(analysis: Analysis, policy: IdentificationPolicy) -> float:
    """The load torque ``M_L0`` [Nm] the refinement's model carries: :attr:`Analysis.M_L0` where the
    record ran around a holding torque, or where STEP 2's fit is trusted (no warning) and its
    constant torque significant (:attr:`IdentificationPolicy.load_torque_floor`); else 0 (an
    untrusted fit's offset is its model error: on soft shafts whose sections hold few periods,
    0.3-0.9 Nm on axes without any, which cost ``J_sigma`` 25-75 % where the model carried it)."""
    if analysis.drive.M_hold != 0.0:
        return analysis.M_L0
    significant = abs(analysis.fit.M_0) > load_torque_threshold(analysis, policy)
    return analysis.M_L0 if significant and not analysis.fit.warnings else 0.0


def load_torque_threshold(analysis: Analysis, policy: IdentificationPolicy) -> float:
    """[Nm] the smallest constant torque of STEP 2's fit that :func:`held_torque` carries."""
    return max(policy.load_torque_floor * analysis.M_star, policy.load_torque_sigmas * analysis.fit.std[3])
