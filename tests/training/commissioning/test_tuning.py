"""Nelder-Mead fine-tuning on the closed loop: known optimum, never worse than the proposal."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from training.commissioning import (ControllerSpec, LinearRunner, SimRunner, closed_loop_cost, make_scenario,
                                    propose_controller, tune_controller)
from training.commissioning._tuning import evaluate_gains

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20)
ONE_MASS = {"J_sigma": 0.02}


@pytest.fixture(scope="module")
def setup():
    prop = propose_controller("stiff", ONE_MASS, DRIVE, ControllerSpec(speed_filter_samples=0.0))
    # a small step: no candidate of the searched range reaches the torque limit (linear problem)
    sc = make_scenario(prop, DRIVE, w_step=0.02 * DRIVE.M_max / prop.Kp, settle_factor=15.0)
    return prop, sc, LinearRunner(ONE_MASS, DRIVE)


def test_nelder_mead_finds_the_grid_optimum(setup):
    prop, sc, runner = setup
    # brute force: 21 x 21 log grid, one batched closed-loop run
    g = torch.linspace(-math.log(3), math.log(3), 21, dtype=torch.float64)
    KK, TT = torch.meshgrid(prop.Kp * torch.exp(g), prop.Ti * torch.exp(g), indexing="ij")
    cost, _, _ = evaluate_gains(runner, prop, DRIVE, sc, KK.reshape(-1), TT.reshape(-1))
    i = int(cost.argmin())
    Kp_g, Ti_g, c_g = float(KK.reshape(-1)[i]), float(TT.reshape(-1)[i]), float(cost[i])
    assert 0 < i // 21 < 20 and 0 < i % 21 < 20, "grid optimum on the border: widen the grid"
    res = tune_controller(prop, runner, DRIVE, scenario=sc, max_evaluations=60, min_phase_margin=None)
    step = math.log(3) / 10  # one grid cell in log units
    assert abs(math.log(res.controller.Kp / Kp_g)) <= 1.5 * step
    assert abs(math.log(res.controller.Ti / Ti_g)) <= 1.5 * step
    assert res.cost_tuned <= c_g * 1.001
    assert res.cost_tuned <= res.cost_proposal
    assert res.stable and res.n_evaluations <= 62


def test_tuning_never_worse_and_reports_figures(setup):
    prop, _, runner = setup
    res = tune_controller(prop, runner, DRIVE, max_evaluations=20)
    assert res.cost_tuned <= res.cost_proposal
    assert len(res.history) >= 1 and res.history[0]["cost"] == pytest.approx(res.cost_proposal)
    for figs in (res.figures_before, res.figures_after):
        for key in ("rise_time", "overshoot_pct", "settling_time", "load_dip", "cost"):
            assert key in figs and math.isfinite(figs[key])
    assert res.figures_after["cost"] == pytest.approx(res.cost_tuned)
    assert res.stable and res.controller.figures["stable"] == 1.0


def test_unstable_candidate_gets_a_large_finite_cost(setup):
    prop, sc, runner = setup
    cost, terms, speed = evaluate_gains(runner, prop, DRIVE, sc, torch.tensor([prop.Kp, prop.Kp * 50]),
                                        torch.tensor([prop.Ti, prop.Ti]))
    assert math.isfinite(float(cost[1])) and float(cost[1]) >= sc.unstable_cost
    assert float(cost[0]) < 100 and terms["unstable"].tolist() == [0.0, 1.0]
    with pytest.raises(ValueError):
        closed_loop_cost(speed[:, :, :10], sc)


def test_sim_runner_agrees_with_linear_model_and_tuning_on_sim_never_worse():
    """Same timing conventions as the simulator; a short search on the nonlinear plant."""
    sim = pytest.importorskip("sim")
    if not hasattr(sim, "simulate") or not hasattr(sim, "TwoMassParams"):
        pytest.skip("sim.simulate not available yet")
    drive = sim.DriveConfig()
    params = dict(J_sigma=0.05, V_J=0.5, f_e=200.0, d=0.05, backlash=0.0, M_FC=0.0, mu_F=0.0)
    prop = propose_controller("stiff", params, drive)
    sc = make_scenario(prop, drive, settle_factor=10.0)
    sim_runner = SimRunner(sim.TwoMassParams.from_dicts(params), drive)
    c_lin, _, w_lin = evaluate_gains(LinearRunner(params, drive), prop, drive, sc, torch.tensor([prop.Kp]), torch.tensor([prop.Ti]))
    c_sim, _, w_sim = evaluate_gains(sim_runner, prop, drive, sc, torch.tensor([prop.Kp]), torch.tensor([prop.Ti]))
    # the linear model has no encoder: the difference stays within a few speed quanta
    assert float((w_lin - w_sim).abs().max()) <= 5 * drive.q_w
    assert float(c_sim) == pytest.approx(float(c_lin), rel=0.05)
    res = tune_controller(prop, sim_runner, drive, scenario=sc, max_evaluations=3)
    assert res.cost_tuned <= res.cost_proposal and res.stable
