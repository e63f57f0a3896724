"""Fast path vs the torchdiffeq reference on nonlinear systems (backlash, stiction)."""

import torch

from _helpers import Profile
from sim import DriveConfig, TwoMassParams, simulate

# stated tolerance (docs/simulator.md): with the default 4 substeps the fast path stays within
# 2 % of each state's range of the event-restarted dopri5 solution, encoder speed within 3 counts
TOL = 2e-2


def test_fast_path_agrees_with_reference_on_backlash_and_stiction():
    drive = DriveConfig()
    p = nonlinear_pair()[:1]  # backlash 0.5 deg, M_FC 0.3 Nm
    ctl = Profile([5.0, -5.0, 0.0, 2.0], 30)
    ref = simulate(p, drive, ctl, 120, method="reference", return_states=True)
    fast = simulate(p, drive, ctl, 120, return_states=True)
    for k in ("w_M", "w_L", "dphi", "M_M"):
        a, b = fast.states[k].double(), ref.states[k]
        err = (a - b).abs().max(-1).values / b.abs().max(-1).values
        assert float(err.max()) < TOL, (k, err.tolist())
    assert float(((fast.speed.double() - ref.speed).abs() / drive.q_w).max()) <= 3
    # both see the load stuck for a while (stiction really holds)
    assert int((ref.states["w_L"] == 0).sum()) > 10 and int((fast.states["w_L"] == 0).sum()) > 10



def nonlinear_pair() -> TwoMassParams:
    t = torch.tensor
    return TwoMassParams(J_sigma=t([0.05, 0.02]), V_J=t([1.0, 2.0]), f_e=t([30.0, 80.0]), d=t([0.02, 0.05]),
                         backlash=torch.deg2rad(t([0.5, 0.2])), M_FC=t([0.3, 0.5]), mu_F=t([0.002, 0.001]))
