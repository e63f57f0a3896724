"""Speed-controller law (SPEC 8.1 contract), the loop analysis and margins, the proposal rules."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from training.commissioning import (ControllerSpec, PISpeedLaw, linear_plant, loop_figures, margins, propose_cautious,
                                    propose_controller)
from training.commissioning._loop import closed_loop_matrices, constant_input_response

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20)
ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=20.0, d=0.02)


def _run_law(law, plant, n, w_ref=1.0):
    """The law on the linear plant, sample by sample, in the drive's timing (M_ref from k+1)."""
    x, u, w, out = np.zeros(plant.Ad.shape[0]), 0.0, 0.0, []
    law.reset()
    for _ in range(n):
        out.append(w)
        M = law.step(w, w_ref)
        dphi = plant.Cd @ x + plant.Dd * u
        x = plant.Ad @ x + plant.Bd * u
        u, w = M, dphi / plant.T_s
    return np.array(out)


@pytest.mark.parametrize("delay", [0, 1])
def test_law_matches_linear_closed_loop_model(delay):
    """The law on the plant == the closed-loop matrices behind the margins (incl. an extra delay)."""
    big = SimpleNamespace(**{**DRIVE.__dict__, "M_max": 1e9})
    plant = linear_plant(ELASTIC, big, current_loop_damping=0.7 if delay else None, extra_delay=delay)
    law = PISpeedLaw(2.0, 0.05, T_s=big.T_s, M_max=big.M_max, T_f=5e-4)
    w = _run_law(law, plant, 600)
    A, b_r, _, c, _ = closed_loop_matrices(plant, 2.0, 0.05, 5e-4, None)
    np.testing.assert_allclose(w, constant_input_response(A, b_r, c, 600), rtol=1e-9, atol=1e-12)


def test_law_is_batched_clamped_and_reports_its_params():
    law = PISpeedLaw(np.array([0.5, 2.0, 8.0]), 0.05, T_s=DRIVE.T_s, M_max=DRIVE.M_max)
    out = law.step(np.zeros(3), 5.0)
    assert out.shape == (3,) and np.abs(out).max() <= DRIVE.M_max
    for _ in range(200):  # anti-windup: a long saturation leaves the integrator bounded
        law.step(np.zeros(3), 5.0)
    assert np.abs(law._I).max() <= DRIVE.M_max + 1e-12
    single = PISpeedLaw(2.0, 0.05, T_s=DRIVE.T_s, M_max=DRIVE.M_max)
    assert isinstance(single.step(0.0, 1.0), float) and single.params["Kp"] == 2.0 and single.params["notch"] is None
    with pytest.raises(ValueError):
        PISpeedLaw(-1.0, 0.05, T_s=DRIVE.T_s, M_max=20.0)


def test_phase_margin_matches_symmetric_optimum_analytically():
    """Small T_s: SO with a=2 on 1/(J s (1 + s T)) has PM = atan(a) - atan(1/a), less the sampled
    loop's 2 T_s of delay (computation, hold, speed by difference)."""
    T = 1e-3
    drive = SimpleNamespace(M_max=20.0, T_Ei=T, T_s=1e-5, encoder_counts=2**20)
    J, a = 0.1, 2.0
    f = loop_figures({"J_sigma": J}, drive, J / (a * T), a * a * T)
    pm = math.degrees(math.atan(a) - math.atan(1 / a) - 2 * drive.T_s / (a * T))
    assert f["phase_margin"] == pytest.approx(pm, abs=0.1)
    assert f["w_c"] == pytest.approx(1 / (a * T), rel=0.01)
    assert f["stable"] == 1.0


def test_gain_margin_of_a_pure_gain_loop_is_exact():
    """Doubling the gain takes 6.02 dB off the gain margin; the margin's loop is unstable beyond it."""
    plant = linear_plant({"J_sigma": 0.05}, DRIVE)
    g1 = margins(plant, 20.0, 1.0).gain_margin_dB
    g2 = margins(plant, 40.0, 1.0).gain_margin_dB
    assert g1 - g2 == pytest.approx(20 * math.log10(2), abs=0.05)
    over = 20.0 * 10 ** (g1 / 20) * 1.05
    assert margins(plant, over, 1.0).stable is False


def test_stiff_proposal_is_symmetric_optimum_with_guaranteed_margins():
    p = propose_controller("stiff", {"J_sigma": 0.05}, DRIVE)
    T_sigma = DRIVE.T_Ei + 2 * DRIVE.T_s + DRIVE.T_s
    assert p.Kp == pytest.approx(0.05 / (3 * T_sigma)) and p.Ti == pytest.approx(9 * T_sigma)
    assert p.meets(ControllerSpec()) and p.margins.phase_margin >= 40 and p.margins.gain_margin_dB >= 6


@pytest.mark.parametrize("mech", [dict(J_sigma=0.05, V_J=4.0, f_e=230.0, d=0.01), dict(J_sigma=0.05, V_J=1.0, f_e=100.0, d=0.01),
                                  ELASTIC])
def test_every_proposal_keeps_the_margins_on_the_spread_with_the_extra_lags(mech):
    """The guarantee: PM >= 40 deg, GM >= 6 dB on f_e, V_J x 0.7..1.3 with a 2nd-order current loop and
    one extra sample of delay, checked here model by model."""
    p = propose_controller("elastic", mech, DRIVE)
    for f in (0.7, 1.0, 1.3):
        for v in (0.7, 1.0, 1.3):
            m = {**mech, "f_e": mech["f_e"] * f, "V_J": mech["V_J"] * v}
            mg = margins(linear_plant(m, DRIVE, current_loop_damping=1 / math.sqrt(2), extra_delay=1), p.Kp, p.Ti, p.T_f, p.notch)
            assert mg.stable and mg.phase_margin >= 40 - 0.5 and mg.gain_margin_dB >= 6 - 0.1, (f, v, mg)


def test_elastic_rules_bandwidth_limits_and_backlash():
    ela = propose_controller("elastic", ELASTIC, DRIVE)
    w_A = 2 * math.pi * 20.0 / math.sqrt(1 - 0.02**2) / math.sqrt(2.0)
    assert ela.figures["w_c"] <= 0.6 * w_A and any(r.startswith("R3") for r in ela.rules)
    bl = propose_controller("stiff_backlash", {"J_sigma": 0.05, "backlash": 0.01}, DRIVE)
    st = propose_controller("stiff", {"J_sigma": 0.05}, DRIVE)
    assert bl.Kp < st.Kp and any("limit cycle" in w for w in bl.warnings)


def test_fallback_F1_crossover_follows_the_band_the_test_allows():
    """F1 is as fast as the worst case of its band allows: a narrow band around a soft 8 Hz mode
    gives a useful loop, and every worst-case model keeps the margins."""
    narrow = propose_cautious(0.05, DRIVE, bands={v: (6.0, 10.0) for v in (0.2, 1.0, 5.0)})
    assert narrow.figures["w_c"] > 30 and narrow.meets(ControllerSpec())
    assert narrow.rules[0].startswith("F1") and "V_J 5: f_e 6..10 Hz" in narrow.rules[0]
    stiff_only = propose_cautious(0.05, DRIVE, bands={})
    assert stiff_only.figures["w_c"] > narrow.figures["w_c"]


def test_proposal_input_checks():
    with pytest.raises(ValueError):
        propose_controller("wobbly", {"J_sigma": 0.05}, DRIVE)
    with pytest.raises(ValueError):
        propose_controller("elastic", {"J_sigma": 0.05}, DRIVE)
    with pytest.raises(ValueError):
        propose_controller("stiff", {"J_sigma": -1.0}, DRIVE)
    with pytest.raises(TypeError):
        propose_controller("stiff", {"J_sigma": "heavy"}, DRIVE)
    with pytest.raises(ValueError):
        propose_cautious(float("nan"), DRIVE)
