"""Speed-controller law (batched, contract) and the proposal rules, on the exact linear model."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from training.commissioning import ControllerSpec, LinearRunner, PISpeedController, linear_plant, loop_figures, propose_controller
from training.commissioning._loop import closed_loop_matrices, constant_input_response

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20)
ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=20.0, d=0.02)


def test_controller_law_matches_linear_closed_loop_model():
    """The torch controller on the linear plant == the closed-loop matrices behind the figures."""
    big = SimpleNamespace(**{**DRIVE.__dict__, "M_max": 1e9})
    n = 600
    ctrl = PISpeedController(2.0, 0.05, T_s=big.T_s, M_max=big.M_max, T_f=5e-4, w_ref=1.0)
    w = LinearRunner(ELASTIC, big).run(ctrl, n, None, 1)[0].numpy()
    A, b_r, _, c = closed_loop_matrices(linear_plant(ELASTIC, big), 2.0, 0.05, 5e-4, None)
    ref = constant_input_response(A, b_r, c, n)
    np.testing.assert_allclose(w, ref, rtol=1e-9, atol=1e-12)


def test_controller_is_batched_and_clamped():
    Kp = torch.tensor([0.5, 2.0, 8.0])
    ctrl = PISpeedController(Kp, 0.05, T_s=DRIVE.T_s, M_max=DRIVE.M_max, w_ref=5.0)
    batched = LinearRunner(ELASTIC, DRIVE).run(ctrl, 300, None, 3)
    for i, kp in enumerate(Kp.tolist()):
        single = LinearRunner(ELASTIC, DRIVE).run(PISpeedController(kp, 0.05, T_s=DRIVE.T_s, M_max=DRIVE.M_max, w_ref=5.0), 300, None, 1)
        torch.testing.assert_close(batched[i], single[0])
    ctrl.reset((3,))
    out = ctrl.step(0, torch.zeros(3))
    assert out.shape == (3,) and float(out.abs().max()) <= DRIVE.M_max
    # anti-windup: a long saturation leaves the integrator bounded by M_max
    for k in range(200):
        out = ctrl.step(k, torch.zeros(3))
    assert float(ctrl._I.abs().max()) <= DRIVE.M_max + 1e-12
    with pytest.raises(ValueError):
        ctrl.reset((4,))
    with pytest.raises(ValueError):
        PISpeedController(-1.0, 0.05, T_s=DRIVE.T_s, M_max=20.0)


def test_phase_margin_matches_symmetric_optimum_analytically():
    """Continuous limit (tiny T_s): SO with a=2 on 1/(J s (1 + s T)) has PM = atan(a) - atan(1/a)."""
    T = 1e-3
    drive = SimpleNamespace(M_max=20.0, T_Ei=T, T_s=1e-6, encoder_counts=2**20)
    J, a = 0.1, 2.0
    f = loop_figures({"J_sigma": J}, drive, J / (a * T), a * a * T, n_freq=4000)
    pm = math.degrees(math.atan(a) - math.atan(1 / a))
    assert f["phase_margin"] == pytest.approx(pm, abs=0.5)
    assert f["w_c"] == pytest.approx(1 / (a * T), rel=0.03)
    assert f["stable"] == 1.0


def test_stiff_proposal_is_symmetric_optimum_with_margins():
    p = propose_controller("stiff", {"J_sigma": 0.05}, DRIVE)
    T_sigma = DRIVE.T_Ei + 2 * DRIVE.T_s + DRIVE.T_s
    assert p.Kp == pytest.approx(0.05 / (3 * T_sigma))
    assert p.Ti == pytest.approx(9 * T_sigma)
    f = p.figures
    assert f["stable"] == 1.0 and f["phase_margin"] >= 45 and f["gain_margin_dB"] >= 6
    for key in ("w_c", "bandwidth", "overshoot_pct", "rise_time", "settling_time"):
        assert math.isfinite(f[key])


def test_elastic_rules_bandwidth_limits_and_backlash():
    spec = ControllerSpec()
    ela = propose_controller("elastic", ELASTIC, DRIVE, spec)
    w_A = 2 * math.pi * 20.0 / math.sqrt(1 - 0.02**2) / math.sqrt(2.0)
    assert ela.figures["w_c"] <= 0.6 * w_A  # R3: V_J = 1 -> w_c <= 0.5 w_A (+ crossover read-out)
    assert ela.figures["stable"] == 1.0 and ela.figures["phase_margin"] >= spec.min_phase_margin
    assert any(r.startswith("R3") for r in ela.rules)
    # small inertia ratio: a more aggressive design relative to w_A
    small = propose_controller("elastic", {**ELASTIC, "V_J": 0.3}, DRIVE)
    large = propose_controller("elastic", {**ELASTIC, "V_J": 4.0}, DRIVE)
    def rel(p, V):
        return p.figures["w_c"] / (2 * math.pi * 20.0 / math.sqrt(1 + V))
    assert rel(small, 0.3) > rel(large, 4.0)
    # backlash: lower gain and a limit-cycle warning
    bl = propose_controller("stiff_backlash", {"J_sigma": 0.05, "backlash": 0.01}, DRIVE)
    st = propose_controller("stiff", {"J_sigma": 0.05}, DRIVE)
    assert bl.Kp < st.Kp and any("limit cycle" in w for w in bl.warnings)


def test_proposal_input_checks():
    with pytest.raises(ValueError):
        propose_controller("wobbly", {"J_sigma": 0.05}, DRIVE)
    with pytest.raises(ValueError):
        propose_controller("elastic", {"J_sigma": 0.05}, DRIVE)
    with pytest.raises(ValueError):
        propose_controller("stiff", {"J_sigma": -1.0}, DRIVE)
    with pytest.raises(TypeError):
        propose_controller("stiff", {"J_sigma": "heavy"}, DRIVE)
