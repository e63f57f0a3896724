"""Speed-controller law (SPEC 8.1 contract), the loop analysis and margins, the proposal rules."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from training.commissioning import (ControllerSpec, NotchSpec, PISpeedLaw, linear_plant, loop_figures, margins, propose_cautious,
                                    propose_controller)
from training.commissioning._loop import closed_loop_matrices, constant_input_response, load_peak_dB, reference_to_load

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


TWO_NOTCHES = (NotchSpec(20.0, 0.05, 0.5), NotchSpec(300.0, 0.1, 0.7))


@pytest.mark.parametrize("delay, notch", [(0, None), (1, None), (0, TWO_NOTCHES[0]), (1, TWO_NOTCHES)])
def test_law_matches_linear_closed_loop_model(delay, notch):
    """The law on the plant == the closed-loop matrices behind the margins (incl. an extra delay,
    one notch and two in series)."""
    big = SimpleNamespace(**{**DRIVE.__dict__, "M_max": 1e9})
    plant = linear_plant(ELASTIC, big, current_loop_damping=0.7 if delay else None, extra_delay=delay)
    law = PISpeedLaw(2.0, 0.05, T_s=big.T_s, M_max=big.M_max, T_f=5e-4, notch=notch)
    w = _run_law(law, plant, 600)
    A, b_r, _, c, _ = closed_loop_matrices(plant, 2.0, 0.05, 5e-4, notch)
    np.testing.assert_allclose(w, constant_input_response(A, b_r, c, 600), rtol=1e-9, atol=1e-12)


def test_two_notches_in_the_law_params_and_in_series():
    law = PISpeedLaw(2.0, 0.05, T_s=DRIVE.T_s, M_max=20.0, notch=TWO_NOTCHES)
    assert law.notches == TWO_NOTCHES and law.notch == TWO_NOTCHES[0]
    assert law.params["notch"] == {"f_n": 20.0, "D_z": 0.05, "D_p": 0.5} and len(law.params["notches"]) == 2
    assert PISpeedLaw(2.0, 0.05, T_s=DRIVE.T_s, M_max=20.0).params["notches"] == []
    with pytest.raises(ValueError, match="^notch: expected at most 2"):
        PISpeedLaw(2.0, 0.05, T_s=DRIVE.T_s, M_max=20.0, notch=TWO_NOTCHES + TWO_NOTCHES[:1])
    with pytest.raises(TypeError, match="^notch: "):
        PISpeedLaw(2.0, 0.05, T_s=DRIVE.T_s, M_max=20.0, notch={"f_n": 20.0})


@pytest.mark.parametrize("delay", [0, 1])
def test_load_peak_is_the_closed_loop_state_space_response(delay):
    """T_rL = C N G_L / (1 + C N F G) (the loop's formula) equals c_L (zI - A)^-1 b_r of the closed-loop
    matrices (the law's own sample) to 1e-9, with two notches; its peak is the load peak."""
    plant = linear_plant(ELASTIC, DRIVE, current_loop_damping=0.7 if delay else None, extra_delay=delay)
    w = np.geomspace(1.0, 0.99 * math.pi / DRIVE.T_s, 300)
    T_rL = reference_to_load(plant, 2.0, 0.05, 5e-4, TWO_NOTCHES, w=w)
    A, b_r, _, _, c_L = closed_loop_matrices(plant, 2.0, 0.05, 5e-4, TWO_NOTCHES)
    z = np.exp(1j * w * DRIVE.T_s)
    ss = np.array([c_L @ np.linalg.solve(zk * np.eye(len(A)) - A, b_r) for zk in z])
    np.testing.assert_allclose(T_rL, ss, rtol=1e-9, atol=1e-12)
    assert load_peak_dB(plant, 2.0, 0.05, 5e-4, TWO_NOTCHES) == pytest.approx(20 * math.log10(np.abs(ss).max()), abs=0.02)


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


def test_stiff_proposal_beats_the_symmetric_optimum_with_guaranteed_margins():
    """On one mass the optimized loop is faster than the symmetric optimum (a = 3: w_c = 1/(3 T_sigma))
    and keeps PM >= 45 deg, GM >= 6 dB on its set, its phase margin within a degree of the bound
    (the crossover is pushed to it)."""
    p = propose_controller("stiff", {"J_sigma": 0.05}, DRIVE)
    T_sigma = DRIVE.T_Ei + 2 * DRIVE.T_s + DRIVE.T_s
    assert p.figures["w_c"] > 1.3 / (3 * T_sigma) and p.rules[-1].startswith("R5")
    assert p.meets(ControllerSpec()) and 45 <= p.margins.phase_margin <= 46.5 and p.margins.gain_margin_dB >= 6


@pytest.mark.parametrize("mech", [dict(J_sigma=0.05, V_J=4.0, f_e=230.0, d=0.01), dict(J_sigma=0.05, V_J=1.0, f_e=100.0, d=0.01),
                                  ELASTIC])
def test_every_proposal_keeps_the_margins_on_the_spread_with_the_extra_lags(mech):
    """The guarantee: PM >= 45 deg, GM >= 6 dB and the load peak <= 6 dB on f_e x 0.9..1.1, V_J x
    0.75..1.25 at half the damping with a 2nd-order current loop and one extra sample of delay (the
    interim set), checked here model by model."""
    p = propose_controller("elastic", mech, DRIVE)
    for f in (0.9, 1.0, 1.1):
        for v in (0.75, 1.0, 1.25):
            m = {**mech, "f_e": mech["f_e"] * f, "V_J": mech["V_J"] * v, "d": mech["d"] / 2}
            plant = linear_plant(m, DRIVE, current_loop_damping=1 / math.sqrt(2), extra_delay=1)
            mg = margins(plant, p.Kp, p.Ti, p.T_f, p.notch)
            assert mg.stable and mg.phase_margin >= 45 - 0.5 and mg.gain_margin_dB >= 6 - 0.1, (f, v, mg)
            assert load_peak_dB(plant, p.Kp, p.Ti, p.T_f, p.notch) <= 6.1


def test_backlash_design_holds_on_the_decoupled_motor():
    """A backlash plant's loop keeps the margins on the motor alone (J_sigma / (1 + V_J): the gain x
    (1 + V_J) while the gap is open), checked here on that one-mass plant."""
    bl = propose_controller("elastic_backlash", {**ELASTIC, "backlash": 0.01}, DRIVE)
    assert any(lab.startswith("decoupled motor") for lab in bl.models.labels) and any("limit cycle" in w for w in bl.warnings)
    motor = linear_plant({"J_sigma": ELASTIC["J_sigma"] / (1 + ELASTIC["V_J"])}, DRIVE)
    mg = margins(motor, bl.Kp, bl.Ti, bl.T_f, bl.notch)
    assert mg.stable and mg.phase_margin >= 45 - 0.5 and mg.gain_margin_dB >= 6 - 0.1
    assert bl.meets(ControllerSpec()) and bl.limited_by


def test_fallback_F1_crossover_follows_the_band_the_test_allows():
    """F1 is as fast as the worst case of its band allows: a narrow band around a soft 8 Hz mode
    gives a useful loop, and every worst-case model keeps the margins."""
    narrow = propose_cautious(0.05, DRIVE, bands={v: (6.0, 10.0) for v in (0.2, 1.0, 5.0)})
    assert narrow.figures["w_c"] > 10 and narrow.meets(ControllerSpec())
    assert narrow.rules[0].startswith("F1") and "V_J 5: f_e 6..10 Hz" in narrow.rules[0]
    stiff_only = propose_cautious(0.05, DRIVE, bands={})
    assert stiff_only.figures["w_c"] > narrow.figures["w_c"]


def test_F1_states_the_lowest_crossover_over_its_set():
    """F1 never states a crossover a plant of its set does not have: its w_c is the lowest first
    crossover over the set (hand-checked model by model), and a true plant inside the band, between
    the set's grid points, has at least about that much."""
    f1 = propose_cautious(0.05, DRIVE, bands={v: (6.0, 10.0) for v in (0.2, 1.0, 5.0)})
    each = [margins(p, f1.Kp, f1.Ti, f1.T_f, f1.notch).w_c for p in f1.models.plants]
    assert f1.figures["w_c"] == pytest.approx(min(each), rel=1e-9) and f1.figures["w_c"] < f1.figures["w_c_nominal"]
    for true in (dict(V_J=4.0, f_e=7.3, d=0.02), dict(V_J=0.5, f_e=9.1, d=0.01)):
        plant = linear_plant({"J_sigma": 0.05, **true}, DRIVE)
        assert margins(plant, f1.Kp, f1.Ti, f1.T_f).w_c >= 0.95 * f1.figures["w_c"]


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
