"""Rule R7d (:mod:`training.commissioning._narrow`): the measured frequency response narrows the
set's intervals to the two-mass mechanics it does not invalidate; the truth stays inside, the
identified value too; a backlash answer's set is not narrowed; a resonance a stiff answer lacks is fitted."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("sim")

from training.commissioning import ControllerSpec, linear_plant, margins, propose_controller, uncertainty_set  # noqa: E402
from training.commissioning._design import MechanicsBounds  # noqa: E402
from training.commissioning._frf import MeasuredResponse  # noqa: E402
from training.commissioning._loop import Mechanics  # noqa: E402
from training.commissioning._narrow import NarrowSettings, measured_mode, narrowed_bounds, two_mass_response  # noqa: E402
from training.errors import CommissioningError  # noqa: E402

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20)
SPEC = ControllerSpec()
TRUE = Mechanics(0.05, V_J=1.0, f_e=320.0, d=0.02)
ANSWER = Mechanics(0.05, V_J=1.3, f_e=290.0, d=0.03)
WIDE = MechanicsBounds(J_sigma=(0.049, 0.051), V_J=(0.6, 2.2), f_e=(200.0, 450.0), d=(0.005, 0.08), J_M=(0.014, 0.032))


def _measured(true: Mechanics, *, coherence: float = 0.95, top: float = 0.9, **loop) -> MeasuredResponse:
    """The exact response of ``true`` on the drive (``loop``: its current-loop variant) on 150 log-spaced lines."""
    w = np.geomspace(2 * math.pi * 2.0, 0.99 * math.pi / DRIVE.T_s, 150)
    G = linear_plant(true, DRIVE, **loop).speed_response(np.exp(1j * w * DRIVE.T_s))
    return MeasuredResponse(w=w, G=G, coherence=np.where(w < top * math.pi / DRIVE.T_s, coherence, 0.5), T_s=DRIVE.T_s)


def _narrow(measured: MeasuredResponse | None, *, bounds: MechanicsBounds = WIDE, answer: Mechanics = ANSWER) -> MechanicsBounds:
    return narrowed_bounds(bounds, answer, measured, DRIVE, min_coherence=SPEC.min_coherence,
                           current_loop_damping=SPEC.current_loop_damping, extra_delay=SPEC.extra_delay)


def test_the_two_mass_response_by_hand():
    """J_sigma 0.05, V_J 1.5 (J_M 0.02, J_L 0.03), f_e 50 Hz, no damping: C_F = w_0^2 J_M J_L / J_sigma;
    the response is 1/(J_sigma s) far below the resonance, 1/(J_M s) far above, zero at the
    anti-resonance sqrt(C_F / J_L) and infinite at w_0."""
    J_M, J_L, w_0 = 0.02, 0.03, 2 * math.pi * 50.0
    C_F = w_0**2 * J_M * J_L / 0.05
    w = np.array([1.0, math.sqrt(C_F / J_L), 1e6])
    H = two_mass_response(w, 0.05, 1.5, 50.0, 0.0)
    assert H[0] * 1j * w[0] * 0.05 == pytest.approx(1.0, rel=1e-4)
    assert abs(H[1]) < 1e-9
    assert H[2] * 1j * w[2] * J_M == pytest.approx(1.0, rel=1e-4)
    assert abs(two_mass_response(np.array([w_0 * (1 + 1e-9)]), 0.05, 1.5, 50.0, 0.0)[0]) > 1e3


def test_the_measured_response_narrows_the_intervals_around_the_truth():
    """An answer at 290 Hz, V_J 1.3 with wide intervals; the plant (320 Hz, V_J 1.0, d 0.02) measured
    on 150 lines: f_e and V_J narrow to a fraction of their intervals, each holding the truth and the
    identified value, the damping's low end rises, and the note says so."""
    out = _narrow(_measured(TRUE))
    assert out.f_e[0] <= 290.0 and 320.0 <= out.f_e[1] <= 335.0
    assert out.V_J[0] <= 1.0 and 1.3 <= out.V_J[1] <= 1.4
    assert out.d[0] <= 0.02 <= out.d[1] and out.d[0] > WIDE.d[0]
    assert out.widened.startswith("R7d the measured response")
    assert (out.J_sigma, out.J_M) == (WIDE.J_sigma, WIDE.J_M)


def test_a_drive_with_the_pessimistic_current_loop_is_matched_too():
    """Measured on a drive with the set's pessimistic loop (2nd-order current loop, +1 sample): the
    variant's fit counts, and the truth stays inside."""
    out = _narrow(_measured(TRUE, current_loop_damping=SPEC.current_loop_damping, extra_delay=SPEC.extra_delay))
    assert out.f_e[0] <= 320.0 <= out.f_e[1] < 400.0 and out.V_J[0] <= 1.0 <= out.V_J[1] < 2.0


def test_a_backlash_answer_is_not_narrowed():
    """At the measurement's small amplitude a gap rattles and the load sticks: the set of a backlash
    answer keeps its intervals (placed by a peak at most), the drive given or not."""
    answer = dict(J_sigma=0.05, V_J=1.3, f_e=290.0, d=0.03, mu_F=0.0)
    gap = uncertainty_set(answer, SPEC, structure="elastic_backlash", bounds=WIDE, measured=_measured(TRUE), drive=DRIVE)
    assert "R7d" not in gap.describe(DRIVE) and gap.bounds.V_J == WIDE.V_J and gap.bounds.d == WIDE.d


def test_an_answer_that_may_have_missed_a_gap_is_not_narrowed():
    """The identification's calibrated probability of a backlash class at the threshold (50 %) or
    above: no R7d, neither the intervals (the peak still places f_e) nor a stiff answer's measured
    resonance; below it, R7d."""
    answer = dict(J_sigma=0.05, V_J=1.3, f_e=290.0, d=0.03, mu_F=0.0)
    limit = SPEC.narrow.max_gap_probability
    doubtful = uncertainty_set(answer, SPEC, structure="elastic", bounds=WIDE, measured=_measured(TRUE), drive=DRIVE,
                               gap_probability=limit)
    assert "R7d" not in doubtful.describe(DRIVE) and (doubtful.bounds.V_J, doubtful.bounds.d) == (WIDE.V_J, WIDE.d)
    sure = uncertainty_set(answer, SPEC, structure="elastic", bounds=WIDE, measured=_measured(TRUE), drive=DRIVE,
                           gap_probability=0.5 * limit)
    assert "R7d" in sure.describe(DRIVE)
    measured = replace(_measured(Mechanics(0.05, V_J=0.5, f_e=400.0, d=0.02)), resonances=(2 * math.pi * 400.0,))
    bands = {v: (5.0, 0.45 / DRIVE.T_s) for v in SPEC.class_V_J}
    assert uncertainty_set({"J_sigma": 0.05}, SPEC, hidden=bands, measured=measured, drive=DRIVE,
                           gap_probability=limit).measured_modes == ()


def test_without_evidence_the_bounds_stay():
    """No measurement, a one-mass answer, or too few trusted lines in the band: the bounds as they are."""
    assert _narrow(None) is WIDE
    assert _narrow(_measured(TRUE), answer=Mechanics(0.05)) is WIDE
    assert _narrow(_measured(TRUE, top=0.02)) is WIDE  # coherent only far below the resonance


def test_a_measurement_unlike_every_two_mass_mechanic_narrows_little():
    """A plant the grid cannot reproduce (a second mode at 900 Hz on top of the two-mass one): the
    misfit left at the best mechanic widens the region; the truth's f_e and V_J stay inside."""
    base = _measured(TRUE)
    z = np.exp(1j * base.w * DRIVE.T_s)
    extra = linear_plant(Mechanics(0.05, V_J=0.3, f_e=900.0, d=0.01), DRIVE).speed_response(z)
    extra = extra / linear_plant(Mechanics(0.05), DRIVE).speed_response(z)
    out = _narrow(MeasuredResponse(w=base.w, G=base.G * extra, coherence=base.coherence, T_s=DRIVE.T_s))
    assert out.f_e[0] <= 320.0 <= out.f_e[1] and out.V_J[0] <= 1.0 <= out.V_J[1]


def test_the_set_narrowed_gives_a_faster_loop_that_keeps_its_margins_on_the_true_plant():
    """uncertainty_set with the drive's config narrows (R7d in its description); without it not. The
    design on the narrowed set is faster and keeps PM >= 45 deg, GM >= 6 dB on the true plant."""
    measured = _measured(TRUE)
    answer = dict(J_sigma=0.05, V_J=1.3, f_e=290.0, d=0.03, mu_F=0.0)
    wide = uncertainty_set(answer, SPEC, structure="elastic", bounds=WIDE, measured=measured)
    narrow = uncertainty_set(answer, SPEC, structure="elastic", bounds=WIDE, measured=measured, drive=DRIVE)
    assert "R7d" in narrow.describe(DRIVE) and "R7d" not in wide.describe(DRIVE)
    slow = propose_controller("elastic", answer, DRIVE, SPEC, uncertainty=wide)
    fast = propose_controller("elastic", answer, DRIVE, SPEC, uncertainty=narrow)
    assert fast.figures["w_c"] > 1.1 * slow.figures["w_c"]
    assert margins(linear_plant(TRUE, DRIVE), fast.Kp, fast.Ti, fast.T_f, fast.notch).meets(45.0 - 1.0, 6.0 - 0.2)


@pytest.mark.parametrize("field, value", [("confidence", 1.0), ("floor", 0.0), ("points", 2), ("band", (0.5,)), ("top", 0.6)])
def test_bad_settings_are_refused_in_one_line(field, value):
    with pytest.raises(CommissioningError, match=field):
        NarrowSettings(**{field: value})


def test_a_resonance_a_stiff_answer_lacks_is_fitted_and_its_worst_cases_narrow():
    """A stiff answer (J_sigma 0.05) whose plant has a 400 Hz mode (V_J 0.5, d 0.02) the measurement
    found on lines 2.3 % apart: the fitted mode spans the truth's f_e within 2 %, its worst cases' V_J
    run from at most 0.5 to at most 1.5 (the fit's high end, 1.5 x in 1 + V_J; not the class's 5),
    its damping lies below 0.02 and above the class's 0.005; the set with the drive holds those worst
    cases and says so."""
    true = Mechanics(0.05, V_J=0.5, f_e=400.0, d=0.02)
    measured = replace(_measured(true), resonances=(2 * math.pi * 400.0,))
    mode = measured_mode(2 * math.pi * 400.0, Mechanics(0.05), measured, DRIVE, V_J=(0.2, 5.0), d=(0.005, 0.2), f_spread=0.05,
                         min_coherence=SPEC.min_coherence, current_loop_damping=SPEC.current_loop_damping, extra_delay=SPEC.extra_delay)
    assert mode is not None and 392.0 <= mode.f_e[0] <= 400.0 <= mode.f_e[1] <= 408.0
    assert min(mode.V_J) <= 0.5 <= max(mode.V_J) <= 1.5
    assert 0.005 < mode.d <= 0.02
    bands = {v: (5.0, 0.45 / DRIVE.T_s) for v in SPEC.class_V_J}
    fitted = uncertainty_set({"J_sigma": 0.05}, SPEC, hidden=bands, measured=measured, drive=DRIVE)
    assert fitted.measured_modes == (mode,) and "fitted (R7d)" in fitted.describe(DRIVE)
    assert uncertainty_set({"J_sigma": 0.05}, SPEC, hidden=bands, measured=measured).measured_modes == ()


@pytest.mark.parametrize("true_V_J, measured_V_J", [(0.5, 0.5), (2.0, 1.0)])
def test_a_fitted_resonance_gives_a_faster_loop_that_keeps_its_margins_also_where_the_measurement_understates_it(
        true_V_J, measured_V_J):
    """The loop designed with the fitted mode is faster than with the unfitted worst cases (the class's
    V_J capped by the plateau, d 0.005) and keeps PM >= 45 deg, GM >= 6 dB on the true plant, also
    where the measurement understates 1 + V_J by a third (a mode of V_J 2 measured as 1)."""
    J = 0.05
    measured = replace(_measured(Mechanics(J, V_J=measured_V_J, f_e=400.0, d=0.01)), resonances=(2 * math.pi * 400.0,))
    bands = {v: (5.0, 0.45 / DRIVE.T_s) for v in SPEC.class_V_J}
    slow = propose_controller("stiff", {"J_sigma": J}, DRIVE, SPEC,
                              uncertainty=uncertainty_set({"J_sigma": J}, SPEC, hidden=bands, measured=measured))
    fast = propose_controller("stiff", {"J_sigma": J}, DRIVE, SPEC,
                              uncertainty=uncertainty_set({"J_sigma": J}, SPEC, hidden=bands, measured=measured, drive=DRIVE))
    assert fast.figures["w_c"] > 1.1 * slow.figures["w_c"]
    true = linear_plant(Mechanics(J, V_J=true_V_J, f_e=400.0, d=0.01), DRIVE)
    assert margins(true, fast.Kp, fast.Ti, fast.T_f, fast.notch).meets(45.0 - 1.0, 6.0 - 0.2)
