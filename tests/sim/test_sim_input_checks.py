"""Bad inputs to the simulator raise one-line errors naming the argument; valid ones are kept safe."""

import numpy as np
import pytest
import torch

import sim

ONE = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.05, backlash=0.0, M_FC=0.1, mu_F=0.001)


@pytest.mark.parametrize("name", ["chunk_samples", "chunk_systems"])
@pytest.mark.parametrize("value", [0, -1, 2.5, True])
def test_chunks_must_be_ints_of_at_least_one(name, value):
    # chunk_samples=0 used to loop forever; chunk_systems=0 failed in range()
    with pytest.raises(ValueError, match=f"^{name}: expected an int >= 1"):
        sim.simulate_test(sim.TwoMassParams(**ONE), **{name: value})


def test_simulate_test_names_its_bad_arguments():
    p = sim.TwoMassParams(**ONE)
    with pytest.raises(TypeError, match="^signal: expected TestSignalConfig"):
        sim.simulate_test(p, signal={"M_star": 5.0})
    with pytest.raises(TypeError, match="^drive: expected DriveConfig"):
        sim.simulate_test(p, drive={})
    with pytest.raises(ValueError, match="^seed: expected an int"):
        sim.simulate_test(p, seed=None)
    with pytest.raises(ValueError, match="^seed: expected an int in"):
        sim.simulate_test(p, seed=2**70)
    empty = sim.TwoMassParams(**{**ONE, "J_sigma": torch.empty(0)})
    with pytest.raises(ValueError, match="^params: expected at least one system"):
        sim.simulate_test(empty)


def test_params_keep_a_copy_of_the_callers_tensor():
    js = torch.tensor([0.1, 0.2], dtype=torch.float64)
    arr = np.array([1.0, 2.0])
    p = sim.TwoMassParams(**{**ONE, "J_sigma": js, "V_J": arr})
    J_M = p.J_M.clone()
    js[0], arr[0] = -5.0, -7.0
    assert p.J_sigma.tolist() == [0.1, 0.2] and p.V_J.tolist() == [1.0, 2.0]
    assert torch.equal(p.J_M, J_M)


@pytest.mark.parametrize("value", [True, torch.tensor([True, False]), np.array(False), [True, 1.0]])
def test_params_refuse_bools(value):
    with pytest.raises(TypeError, match="^TwoMassParams.J_sigma: .*bool"):
        sim.TwoMassParams(**{**ONE, "J_sigma": value})


@pytest.mark.parametrize("cls", [sim.DriveConfig, sim.TestSignalConfig])
def test_settings_take_any_real_number_type_and_refuse_bools_and_strings(cls):
    name = "T_s" if cls is sim.DriveConfig else "M_star"
    for v in (np.float32(0.25), np.float64(0.25), np.int64(1)):
        got = getattr(cls(**{name: v}), name)
        assert type(got) in (int, float) and got == v  # stored as a Python number (JSON, float64 arithmetic)
    for v in (True, "0.25", None):
        with pytest.raises(TypeError, match=f"^{cls.__name__}.{name}: expected a finite number"):
            cls(**{name: v})


def test_from_dicts_refuses_both_parameter_sets():
    with pytest.raises(ValueError, match="system 0: expected either .* received both"):
        sim.TwoMassParams.from_dicts({"J_sigma": 0.1, "V_J": 1, "f_e": 30, "J_M": 0.3, "J_L": 0.3, "C_F": 100.0})
    with pytest.raises(ValueError, match="system 0: expected either"):  # D_F would be ignored
        sim.TwoMassParams.from_dicts({"J_sigma": 0.1, "V_J": 1, "f_e": 30, "D_F": 0.1})
    with pytest.raises(ValueError, match=r"system 0: missing keys \['J_L', 'C_F'\]"):
        sim.TwoMassParams.from_dicts({"J_M": 0.3})
