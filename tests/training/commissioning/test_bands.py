"""What a test run cannot exclude: the ringing a resonance shows in the measured speed (hand
values), F1's bands, the hidden resonances of a ``stiff`` answer and the guarantee over them (checked
on plants between the set's grid points, by the done-when's margins)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from training.commissioning import ControllerSpec, linear_plant, margins, propose_controller
from training.commissioning._bands import f1_bands, hidden_bands, ringing_amplitude

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20,
                        q_w=2 * math.pi / 2**20 / 2.5e-4)


def test_ringing_amplitude_by_hand():
    # V_J M / (J w) / sqrt(1 + (w T_Ei)^2) * sin(w T_s / 2) / (w T_s / 2) at 100 Hz
    w = 2 * math.pi * 100.0
    hand = 2.0 * 10.0 / (0.05 * w) / math.sqrt(1 + (w * 5e-4) ** 2) * math.sin(w * 1.25e-4) / (w * 1.25e-4)
    assert ringing_amplitude(np.array([100.0]), 2.0, 0.05, 10.0, DRIVE)[0] == pytest.approx(hand, rel=1e-12)


def test_hidden_bands_start_where_the_ringing_drops_below_resolution():
    entry = {"M_star": 20.0, "osc_quanta": 0.5, "f_osc": 0.0}
    bands, f_osc = hidden_bands(entry, 0.05, DRIVE, (0.2, 1.0, 5.0), f_lo=5.0, min_osc_quanta=2.0)
    assert f_osc is None and all(hi == pytest.approx(0.45 / DRIVE.T_s) for _, hi in bands.values())
    amp = math.sqrt(2) * 2.0 * DRIVE.q_w  # osc below the informative 2 q_w counts as 2 q_w
    for V_J, (lo, _) in bands.items():
        assert ringing_amplitude(np.array([lo * 1.02]), V_J, 0.05, 20.0, DRIVE)[0] < amp
        assert ringing_amplitude(np.array([lo / 1.05]), V_J, 0.05, 20.0, DRIVE)[0] >= amp
    assert bands[0.2][0] < bands[1.0][0] < bands[5.0][0]  # a larger inertia ratio rings more: visible higher up
    # a visible oscillation the stiff answer left out: its band, at the inertia ratio its amplitude allows
    seen, f_osc = hidden_bands({"M_star": 20.0, "osc_quanta": 3.0, "f_osc": 440.0}, 0.05, DRIVE, (0.2, 1.0, 5.0),
                               f_lo=5.0, min_osc_quanta=2.0)
    V_J = 4.0 * 3.0 * DRIVE.q_w / ringing_amplitude(np.array([440.0]), 1.0, 0.05, 20.0, DRIVE)[0]
    extra = [v for v in seen if v not in (0.2, 1.0, 5.0)]
    assert f_osc == 440.0 and extra == [pytest.approx(V_J)] and seen[extra[0]] == pytest.approx((440 / 1.2, 440 * 1.2))


def test_f1_band_widens_with_the_spectrum_resolution():
    e = {"osc_quanta": 10.0, "f_osc": 20.0, "longest_section": 0.5, "M_star": 5.0}
    band = f1_bands(e, 0.05, DRIVE, (1.0,), (5.0, 500.0), min_osc_quanta=2.0, osc_visible_ratio=20.0)[1.0]
    assert band == pytest.approx(((20 - 4) / 1.5, (20 + 4) * 1.5))  # 2 / 0.5 s = 4 Hz either side
    short = f1_bands({**e, "longest_section": 0.1}, 0.05, DRIVE, (1.0,), (5.0, 500.0), min_osc_quanta=2.0,
                     osc_visible_ratio=20.0)[1.0]
    assert short == pytest.approx((5.0, (20 + 20) * 1.5))  # 2 periods in a section: from the class's lowest


# the issue's misses as the study measured them: (J_sigma, the accepted run's M*, osc_quanta, f_osc)
# and the true plant (f_e, V_J, d): one read as stiff with a visible oscillation, one hidden (194 Hz)
MISSES = [((0.0288, 16.0, 3.26, 437.5), (439.3, 2.17, 0.054)), ((0.0735, 4.0, 3.83, 42.0), (193.6, 0.29, 0.007))]


@pytest.mark.parametrize("test, true", MISSES)
def test_stiff_answer_keeps_the_margins_on_resonances_it_cannot_exclude(test, true):
    """With the resonances the test cannot exclude in the guarantee, the delivered loop keeps PM >= 35
    deg, GM >= 5 dB on the true plants (SPEC current loop, and a 2nd-order one with one more sample
    of delay) that the design on J_sigma alone destabilizes."""
    spec = ControllerSpec()
    J, M_star, osc, f_osc = test
    bands, notch_at = hidden_bands({"M_star": M_star, "osc_quanta": osc, "f_osc": f_osc}, J, DRIVE, spec.class_V_J, f_lo=5.0,
                                   min_osc_quanta=2.0)
    plain = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec)
    prop = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec, hidden=bands, notch_at=notch_at)
    assert prop.meets(spec) and any(r.startswith("R7b") for r in prop.rules)
    plant = dict(zip(("f_e", "V_J", "d"), true), J_sigma=J)
    for damping, delay in ((None, 0), (1.0, 1)):
        m = margins(linear_plant(plant, DRIVE, current_loop_damping=damping, extra_delay=delay), prop.Kp, prop.Ti, prop.T_f, prop.notch)
        assert m.stable and m.phase_margin >= 35 and m.gain_margin_dB >= 5
    m = margins(linear_plant(plant, DRIVE, current_loop_damping=1.0, extra_delay=1), plain.Kp, plain.Ti, plain.T_f)
    assert not (m.stable and m.phase_margin >= 35 and m.gain_margin_dB >= 5)  # without them: the design on J_sigma misses


def test_two_runs_of_one_plant_allow_the_overlap_of_their_bands_and_both_where_they_disagree():
    from training.commissioning._bands import narrowed

    a = {0.2: (5.0, 76.3), 1.0: (5.0, 135.0), 5.0: (20.0, 30.0)}
    b = {0.2: (12.9, 61.9), 1.0: (12.9, 135.0), 5.0: (40.0, 50.0)}
    assert narrowed(a, b) == {0.2: (12.9, 61.9), 1.0: (12.9, 135.0), 5.0: (20.0, 50.0)}
    assert narrowed(a, {}) == a and narrowed({}, b) == b
