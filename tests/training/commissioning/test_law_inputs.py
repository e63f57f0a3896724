"""PISpeedLaw: bad settings name the argument; torch tensors are taken like numpy arrays."""

import numpy as np
import pytest
import torch

from training.commissioning import PISpeedLaw


def test_step_takes_torch_tensors_as_numpy_does():
    a, b = PISpeedLaw(np.array([1.0, 2.0]), 0.02, T_s=2.5e-4, M_max=20.0), PISpeedLaw(np.array([1.0, 2.0]), 0.02, T_s=2.5e-4, M_max=20.0)
    for w, r in ((0.0, 5.0), (1.5, 5.0), (3.25, -2.0)):
        assert np.array_equal(a.step(w, r), b.step(torch.tensor(w, dtype=torch.float64), torch.tensor(r)))
    assert PISpeedLaw(1.0, 0.02, T_s=2.5e-4, M_max=20.0).step(1.0, torch.tensor(5.0)) == pytest.approx(4.05)


@pytest.mark.parametrize("kw, err, name", [(dict(T_s=None), TypeError, "T_s"), (dict(M_max=True), TypeError, "M_max"),
                                           (dict(T_s="1e-4"), TypeError, "T_s"), (dict(M_max=-1.0), ValueError, "M_max"),
                                           (dict(T_s=float("nan")), ValueError, "T_s")])
def test_bad_settings_name_the_argument(kw, err, name):
    with pytest.raises(err, match=f"^{name}: expected a finite number > 0"):
        PISpeedLaw(1.0, 0.02, **{"T_s": 2.5e-4, "M_max": 20.0, **kw})


def test_bad_step_inputs_name_the_argument():
    law = PISpeedLaw(1.0, 0.02, T_s=2.5e-4, M_max=20.0)
    with pytest.raises(TypeError, match="^w_ref: "):
        law.step(1.0, None)  # would be NaN
    with pytest.raises(TypeError, match="^w_meas: "):
        law.step("fast", 1.0)
