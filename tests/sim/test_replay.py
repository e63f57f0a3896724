"""Open-loop replay (sim.replay): the record's own reference reproduces it; kernel = eager twin."""

import pytest
import torch

from sim import DriveConfig, TestSignalConfig, sample_population, simulate_test
from sim._kernel import load_kernel
from sim.replay import replay_speed

DRIVE = DriveConfig()


def _segments(torque_ref: torch.Tensor, lengths: torch.Tensor, K: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Run-length segments ``n x K`` of each padded ``torque_ref`` row (padded with far starts)."""
    starts, levels = [], []
    for tr, L in zip(torque_ref, lengths.tolist()):
        tr = tr[:L]
        change = torch.nonzero(tr[1:] != tr[:-1]).reshape(-1) + 1
        st = torch.cat([torch.tensor([0]), change])
        pad = K - len(st)
        starts.append(torch.cat([st, torch.full((pad,), 2**30)]))
        levels.append(torch.cat([tr[st], torch.zeros(pad)]))
    return torch.stack(starts), torch.stack(levels)


@pytest.fixture(scope="module")
def runs():
    p = sample_population(60, seed=4)
    p = p[p.J_sigma < 0.03][:4]  # short tests
    resp = simulate_test(p, DRIVE, TestSignalConfig(w_max=40.0))
    return p, resp


def test_replaying_the_recorded_reference_reproduces_the_measured_speed_exactly(runs):
    p, resp = runs
    start, level = _segments(resp.torque_ref, resp.length, 10)
    N = int(resp.length.max())
    w = replay_speed(p, DRIVE, start, level, N, substeps=resp.substeps)
    for i, L in enumerate(resp.length.tolist()):
        assert torch.equal(w[i, :L], resp.speed[i, :L])


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: only the eager path exists")
@pytest.mark.parametrize("quantize", [True, False])
def test_kernel_equals_eager_twin(runs, quantize):
    p, resp = runs
    start, level = _segments(resp.torque_ref, resp.length, 10)
    a = replay_speed(p, DRIVE, start, level, 600, quantize=quantize, substeps=2)
    b = replay_speed(p, DRIVE, start, level, 600, quantize=quantize, substeps=2, use_kernel=False)
    assert torch.allclose(a, b, rtol=0, atol=1e-5 * float(a.abs().max()))
    if quantize:
        assert torch.equal(a, b)


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: only the eager path exists")
def test_kernel_equals_eager_twin_when_each_system_switches_at_its_own_samples():
    # 40 systems (a full block of 32 and a partial one), each with its own switching samples:
    # segments of 0, 1 and many samples, a last segment that starts past the end
    p = sample_population(40, seed=9)
    g = torch.Generator().manual_seed(3)
    gaps = torch.randint(0, 40, (40, 6), generator=g)
    gaps[::7, 2] = 0
    gaps[::5, 3] = 1
    start = torch.cat([torch.zeros(40, 1, dtype=torch.int64), gaps.cumsum(-1)], dim=1)  # 40 x 7, ascending
    start[::9, -1] = 2**30
    level = 10.0 * (2.0 * torch.rand(40, 7, generator=g) - 1.0)
    a = replay_speed(p, DRIVE, start, level, 300, substeps=2)
    b = replay_speed(p, DRIVE, start, level, 300, substeps=2, use_kernel=False)
    assert torch.equal(a, b)


def test_unquantized_speed_is_the_mean_of_the_encoder_speed(runs):
    p, resp = runs
    start, level = _segments(resp.torque_ref, resp.length, 10)
    q = replay_speed(p, DRIVE, start, level, 2000)
    u = replay_speed(p, DRIVE, start, level, 2000, quantize=False)
    # the encoder's speed is the mean speed up to one count per sample, and the counts telescope:
    # the summed speeds differ by less than one count (plus float32 rounding of the speeds)
    assert float((q - u).abs().max()) <= 1.01 * DRIVE.q_w
    assert float((q.double().cumsum(-1) - u.double().cumsum(-1)).abs().max()) <= 1.5 * DRIVE.q_w


def test_bad_shapes_are_rejected(runs):
    p, _ = runs
    with pytest.raises(ValueError, match="expected 4 x K"):
        replay_speed(p, DRIVE, torch.zeros(3, 2, dtype=torch.int32), torch.zeros(3, 2), 10)
    with pytest.raises(ValueError, match="n_samples"):
        replay_speed(p, DRIVE, torch.zeros(4, 2, dtype=torch.int32), torch.zeros(4, 2), 0)
