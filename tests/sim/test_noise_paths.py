"""The current noise of a simulated record does not depend on which path ran (C kernel or torch twin)."""

import numpy as np
import torch
import pytest

import sim
from sim._kernel import load_kernel


@pytest.mark.skipif(load_kernel() is None, reason="the C kernel is not available here")
def test_iter_records_same_noise_on_both_paths():
    params = sim.TwoMassParams.from_dicts([dict(J_sigma=0.01, V_J=1.0, f_e=60.0, d=0.05),
                                           dict(J_sigma=0.02, V_J=0.5, f_e=120.0, d=0.1, backlash=0.002)])
    signal = sim.TestSignalConfig(M_star=10.0, w_max=20.0)
    fast, twin = (list(sim.iter_records(params, signal=signal, seed=7, use_kernel=k)) for k in (True, False))
    for a, b in zip(fast, twin):
        assert a.name == b.name and len(a) == len(b)
        # same arithmetic, same noise draw: far below the noise itself (0.01 A; two draws differ by ~0.014 A rms)
        assert np.abs(a.current - b.current).max() < 1e-4
        assert a.meta["timed_out"] == b.meta["timed_out"]


def test_simulate_test_noise_and_iter_records_order_are_as_documented():
    """docs/simulator.md, "Order and current noise": one n x N draw for simulate_test (input order);
    iter_records in ascending expected duration, noise from default_rng(seed + index)."""
    p = sim.TwoMassParams.from_dicts([dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.05),
                                      dict(J_sigma=0.01, V_J=2.0, f_e=60.0, d=0.05)])
    signal, drive = sim.TestSignalConfig(w_max=20.0), sim.DriveConfig()
    r = sim.simulate_test(p, drive, signal, seed=5)
    noise = torch.randn(r.speed.shape, generator=torch.Generator().manual_seed(5), dtype=r.torque.dtype)
    for i, L in enumerate(r.length.tolist()):
        assert torch.equal(r.current[i, :L], r.torque[i, :L] / drive.K_M + drive.current_noise_std * noise[i, :L])
    recs = list(sim.iter_records(p, drive, signal, seed=5))
    assert [x.name for x in recs] == ["sys00001", "sys00000"]  # the lighter system's test is shorter
    for x, i in zip(recs, (1, 0)):
        L = int(r.length[i])
        own = np.random.default_rng(5 + i).standard_normal(L, dtype=np.float32).astype(np.float64)
        assert np.array_equal(x.current, r.torque[i, :L].double().numpy() / drive.K_M + drive.current_noise_std * own)
