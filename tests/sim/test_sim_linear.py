"""Linear case (no backlash, no friction) against the exact matrix-exponential solution."""

import math

import torch

from _helpers import Profile
from sim import DriveConfig, TwoMassParams, encoder_count, simulate


def _exact(p: TwoMassParams, drive: DriveConfig, M_ref: list[float], n: int) -> torch.Tensor:
    """States [w_M, w_L, dphi, M_M, phi_M] at the samples for a piecewise-constant reference."""
    J_M, J_L, C_F, D_F = (float(v) for v in (p.J_M, p.J_L, p.C_F, p.D_F))
    A = torch.tensor([[-D_F / J_M, D_F / J_M, -C_F / J_M, 1 / J_M, 0, 0],
                      [D_F / J_L, -D_F / J_L - float(p.mu_F) / J_L, C_F / J_L, 0, 0, 0],
                      [1, -1, 0, 0, 0, 0],
                      [0, 0, 0, -1 / drive.T_Ei, 0, 1 / drive.T_Ei],
                      [1, 0, 0, 0, 0, 0],
                      [0, 0, 0, 0, 0, 0]], dtype=torch.float64)
    Phi = torch.linalg.matrix_exp(A * drive.T_s)
    x = torch.zeros(6, dtype=torch.float64)
    out = []
    for k in range(n):
        out.append(x[:5].clone())
        x[5] = M_ref[k]
        x = Phi @ x
    return torch.stack(out, -1)


def test_linear_step_matches_matrix_exponential():
    drive = DriveConfig()
    p = TwoMassParams(J_sigma=0.05, V_J=1.5, f_e=40.0, d=0.03, backlash=0.0, M_FC=0.0, mu_F=0.002)
    n = 800
    ctl = Profile([10.0], 10**9)
    r = simulate(p, drive, ctl, n, dtype=torch.float64, return_states=True)
    # reference applied: 0 over the first interval, then 10 Nm (a step at t = T_s)
    ref = _exact(p, drive, [0.0] + [10.0] * (n - 1), n)
    for i, name in enumerate(("w_M", "w_L", "dphi", "M_M", "phi_M")):
        got = r.states[name]
        err = float((got - ref[i]).abs().max() / ref[i].abs().max())
        assert err < 1e-6, (name, err)


def test_encoder_exact_to_one_count_in_float32_over_hundreds_of_radians():
    drive = DriveConfig()
    p = TwoMassParams(J_sigma=0.01, V_J=1.0, f_e=60.0, d=0.05, backlash=0.0, M_FC=0.0, mu_F=0.0)
    n = 1500  # 0.375 s at 20 Nm: ~ 140 rad
    ctl = Profile([20.0], 10**9)
    r = simulate(p, drive, ctl, n, dtype=torch.float32, return_states=True)
    exact = _exact(p, drive, [0.0] + [20.0] * (n - 1), n)[4]
    assert float(exact[-1]) > 120
    counts = encoder_count(r.states["phi_M"], drive)
    diff = (counts - encoder_count(exact, drive)).abs()
    assert float(diff.max()) <= 1
    # measured speed is the count difference per sample
    w = torch.diff(counts, prepend=counts[:1]) * drive.q_w
    assert torch.equal(r.speed, w.to(torch.float32))
    assert math.isclose(drive.q_w, 2 * math.pi / (drive.encoder_counts * drive.T_s))


