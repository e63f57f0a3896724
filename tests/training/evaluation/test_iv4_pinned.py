"""IV4's answers on a few simulated test runs, pinned: the conversion and its typed result must give
the numbers it gave as a dict of re-derived values. ``C_F`` and ``D_F`` come from
``sim.two_mass_derived`` (``w_0`` from ``f_e`` and ``d``, ``C_F = w_0^2 J_M J_L / J_sigma``) where they
were ``w_A^2 J_L``: the same quantities in another order of operations, equal within 1e-12."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import sim
from training.evaluation import iv4_result
from training.evaluation._iv4 import identify_iv4, two_mass_from_discrete

nan = math.nan
_PLANT = dict(J_sigma=0.044, V_J=1.77, f_e=30.5, d=0.011, backlash=0.0)
#: case -> (plant parameters, friction regressors)
CASES = {
    "elastic": (dict(_PLANT, M_FC=0.0, mu_F=0.0), True),
    "friction": (dict(_PLANT, M_FC=0.4, mu_F=0.004), True),
    "friction_bare": (dict(_PLANT, M_FC=0.4, mu_F=0.004), False),
    "backlash": (dict(J_sigma=0.023, V_J=3.39, f_e=64.6, d=0.011, backlash=0.002, M_FC=0.1, mu_F=0.001), True),
}
#: case -> (estimate, iterations, converged, A, B): the values before the typed result
PINNED = {
    "elastic": (dict(J_sigma=0.044000865189297696, V_J=1.7744041182881944, f_e=30.5006065521121, d=0.011056646807834117, w_0=191.6526780224978, w_A=115.06150013954122, J_M=0.015859573196008014, J_L=0.028141291993289682, C_F=372.56675252756594, D_F=0.04298754431759594, integrator_pole=1.0, noise_variance=0.00014092872539514772),
               3, True, [1.0, -1.9966470259264733, 0.9989410431055757], [0.0, 0.015754043999828823, -0.031489261294987234, 0.01574825122738472]),
    "friction": (dict(J_sigma=0.043987931960632026, V_J=1.8051612383245503, f_e=30.493708299508548, d=0.012646358068469138, w_0=191.61294292622821, w_A=114.40524263980129, J_M=0.015681070791818325, J_L=0.0283068611688137, C_F=370.49603789680805, D_F=0.04890510512117185, integrator_pole=1.0, noise_variance=0.00014346497132287412),
               6, True, [1.0, -1.99649623885329, 0.9987891307509829], [0.0, 0.01593439383519801, -0.031845397977901646, 0.015924035511737666]),
    "friction_bare": (dict(J_sigma=nan, V_J=nan, f_e=nan, d=nan, w_0=nan, w_A=nan, J_M=nan, J_L=nan, C_F=nan, D_F=nan, integrator_pole=nan, noise_variance=0.00029906520286113403),
               10, False, [1.0, -1.9733522401650196, 0.9733517695495434], [0.0, 0.017719355753211666, -0.035292951898519484, 0.017573589726701668]),
    "backlash": (dict(J_sigma=0.02299840019599007, V_J=3.451119323808764, f_e=62.02770596476233, d=0.04181400178498719, w_0=390.07272361061655, w_A=184.88895350703956, J_M=0.0051668801761779425, J_L=0.017831520019812128, C_F=609.5513452922428, D_F=0.13068220102225822, integrator_pole=1.0, noise_variance=0.0002991341234949925),
               10, False, [1.0, -1.9824142929584367, 0.9918779130626838], [0.0, 0.048173571105201846, -0.09615554120882108, 0.04808484269501258]),
}
_REORDERED = ("C_F", "D_F")  # derived in sim.two_mass_derived's order of operations


def _record(values: dict[str, float]) -> sim.Record:
    params = sim.TwoMassParams(**{k: torch.tensor([v], dtype=torch.float64) for k, v in values.items()})
    drive, signal = sim.DriveConfig(), sim.TestSignalConfig()
    response = sim.simulate_test(params, drive, signal, seed=0, dtype=torch.float64)
    return sim.responses_to_records(response, params, drive, signal)[0]


@pytest.mark.parametrize("case", sorted(CASES))
def test_iv4_answers_are_pinned(case: str) -> None:
    values, friction = CASES[case]
    record = _record(values)
    torque = record.current * sim.DriveConfig().K_M
    result = identify_iv4(torque, record.speed, record.T_s, T_Ei=record.info.T_Ei, friction=friction)
    estimate, iterations, converged, A, B = PINNED[case]
    for key, value in estimate.items():
        got = getattr(result.estimate, key) if key != "noise_variance" else result.noise_variance
        if math.isnan(value):
            assert math.isnan(got), (key, got)
        elif key in _REORDERED:
            assert math.isclose(got, value, rel_tol=1e-12), (key, got, value)
        else:
            assert got == value, (key, got, value)
    valid = not math.isnan(estimate["J_sigma"])
    assert result.estimate.valid == valid
    assert result.estimate.reason == ("" if valid else "no complex pole pair (no resonance in the model)")
    assert (result.iterations, result.converged, result.T_model) == (iterations, converged, record.T_s)
    assert result.A.tolist() == A and result.B.tolist() == B
    assert not valid or result.estimate.f_0 == result.estimate.w_0 / (2 * np.pi)
    if friction:  # the study's row holds the same four parameters
        row = iv4_result(record)
        assert [row[k] for k in ("J_sigma", "V_J", "f_e", "d")] == [estimate[k] for k in ("J_sigma", "V_J", "f_e", "d")]
        assert (row["valid"], row["iterations"], row["converged"]) == (True, iterations, converged)


def test_no_resonance_is_an_invalid_estimate() -> None:
    estimate = two_mass_from_discrete([1.0, -1.2, 0.35], [0.0, 1e-3, 1e-3, 1e-4], 2.5e-4, output="speed_difference")
    assert not estimate.valid and estimate.reason == "no complex pole pair (no resonance in the model)"
    assert all(math.isnan(getattr(estimate, k)) for k in ("J_sigma", "V_J", "f_e", "d", "J_M", "C_F", "integrator_pole"))
