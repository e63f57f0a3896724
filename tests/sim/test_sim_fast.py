"""Fixed-step path: kernel vs eager twin, batch vs loop, stiction, backlash gap, the six sections."""

import math

import pytest
import torch

from _helpers import Profile
from sim import (DriveConfig, SwitchingController, TestSignalConfig, TwoMassParams, sample_population, simulate,
                 simulate_test)
from sim._kernel import load_kernel

DRIVE = DriveConfig()
NEVER = torch.iinfo(torch.int32).max


def _light(n: int, seed: int) -> TwoMassParams:
    p = sample_population(40 * n, seed)
    return p[p.J_sigma < 0.014][:n]  # short tests (~1 s)


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: only the eager path exists")
def test_kernel_and_eager_twin_give_identical_records():
    p = _light(2, 5)
    sig = TestSignalConfig(w_max=25.0)  # a short test: the eager twin is slow
    a = simulate_test(p, DRIVE, sig)
    b = simulate_test(p, DRIVE, sig, use_kernel=False)
    for k in ("speed", "torque", "torque_ref", "section", "length", "timed_out", "current"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


def test_batch_equals_loop_over_single_systems():
    p = _light(6, 9).reshape(2, 3)
    batch = simulate_test(p, DRIVE, seed=0)
    assert batch.speed.shape[:2] == (2, 3)
    for i in range(2):
        for j in range(3):
            one = simulate_test(p[i, j], DRIVE, seed=0)
            L = int(one.length)
            assert int(batch.length[i, j]) == L
            assert torch.equal(batch.speed[i, j, :L], one.speed[:L])
            assert torch.equal(batch.torque[i, j, :L], one.torque[:L])
            assert torch.equal(batch.section[i, j, :L], one.section[:L])


def test_stiction_holds_the_load_below_M_FC_and_releases_above():
    p = TwoMassParams(J_sigma=torch.tensor([0.05, 0.05]), V_J=1.0, f_e=30.0, d=0.05, backlash=0.0,
                      M_FC=0.5, mu_F=0.001)
    n = 800
    # a 0.2 Nm step overshoots to at most 0.4 Nm of shaft torque on a stuck load: below M_FC
    r = simulate(p, DRIVE, _Split([0.2, 0.7]), n, return_states=True)
    w_L = r.states["w_L"]
    assert torch.all(w_L[0] == 0)  # the load never moves
    assert float(w_L[1].abs().max()) > 0.1  # 0.7 Nm > M_FC: it slides
    # while stuck, the motor settles where the shaft carries the motor torque
    C_F = float(p.C_F[0])
    assert float(r.states["dphi"][0, -400:].mean()) == pytest.approx(0.2 / C_F, rel=0.05)


class _Split:
    def __init__(self, levels):
        self.levels = levels

    def reset(self, batch_shape):
        self.shape = batch_shape

    def step(self, k, w):
        return torch.tensor(self.levels, dtype=torch.float32)


def test_motor_crosses_the_gap_freely_with_M_M_over_J_M():
    s_deg = 1.0
    p = TwoMassParams(J_sigma=0.05, V_J=2.0, f_e=50.0, d=0.05, backlash=math.radians(2 * s_deg), M_FC=0.3, mu_F=0.0)
    r = simulate(p, DRIVE, Profile([4.0], 10**9), 120, dtype=torch.float64, return_states=True)
    dphi, w_M, M_M, w_L = (r.states[k] for k in ("dphi", "w_M", "M_M", "w_L"))
    s = float(p.s)
    gap = dphi.abs() < s
    last = int((~gap).nonzero().min()) - 1  # last sample before the first contact
    assert last > 20
    # in the gap no shaft torque: w_M(t) = M_ref/J_M (tau - T_Ei (1 - exp(-tau/T_Ei))), tau = t - T_s
    tau = (torch.arange(last + 1, dtype=torch.float64) - 1).clamp(min=0) * DRIVE.T_s
    expect = 4.0 / float(p.J_M) * (tau - DRIVE.T_Ei * (1 - torch.exp(-tau / DRIVE.T_Ei)))
    rel = (w_M[1: last + 1] - expect[1:]).abs().max() / expect.abs().max()
    assert float(rel) < 1e-6
    assert torch.all(w_L[: last + 1] == 0)  # no shaft torque: the load rests
    assert bool((dphi.abs() > s).any())  # and the motor reaches the other side


def test_six_sections_in_order_end_at_rest_and_position_returns():
    p = TwoMassParams(J_sigma=0.01, V_J=1.0, f_e=200.0, d=0.1, backlash=0.0, M_FC=0.0, mu_F=0.0)
    r = simulate_test(p, DRIVE, TestSignalConfig(M_star=10.0, w_max=100.0))
    L = int(r.length)
    sec = r.section[:L]
    changes = sec[1:] != sec[:-1]
    order = [int(sec[0])] + sec[1:][changes].tolist()
    assert order == [1, 2, 3, 4, 5, 6, 0]
    assert int((sec == 0).sum()) == TestSignalConfig().n_tail(DRIVE)
    assert not bool(r.timed_out.any())
    w = r.speed[:L].double()
    assert float(w.max()) >= 100.0 and float(w.min()) <= -100.0
    assert abs(float(w[sec == 0].mean())) < 0.01 * 100.0  # at rest within 1 % of w_max
    # the encoder angle is the sum of the measured speeds (exact counts)
    phi = torch.cumsum(w, 0) * DRIVE.T_s
    assert float(phi[-1].abs()) < 0.02 * float(phi.abs().max())  # symmetric plant: back near zero
    assert bool(r.section[L:].eq(-1).all())


def test_timeouts_are_flagged():
    p = TwoMassParams(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.05, backlash=0.0, M_FC=0.0, mu_F=0.0)
    r = simulate_test(p, DRIVE, TestSignalConfig(M_star=1.0, w_max=100.0, timeout=0.05))
    assert bool(r.timed_out[0]) and int(r.length) <= 6 * 200 + 200 + 1


def test_bad_arguments():
    p = _light(1, 3)
    with pytest.raises(ValueError, match="method"):
        simulate_test(p, DRIVE, method="euler")
    with pytest.raises(TypeError, match="dtype"):
        simulate_test(p, DRIVE, dtype=torch.float16)
    with pytest.raises(ValueError, match="n_samples"):
        simulate(p, DRIVE, Profile([1.0], 1), 0)




@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: only the eager path exists")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_eager_twin_and_kernel_share_the_state_layout(dtype: torch.dtype) -> None:
    # the two paths hand the state (compensations included) to each other: any mix of eager and
    # kernel samples gives the numbers of the kernel alone, and the eager results are plain tensors
    from sim._integrate_fast import FastParams, FastState, advance, default_substeps

    p = TwoMassParams(J_sigma=torch.tensor([0.02, 0.05, 0.03]), V_J=2.0, f_e=torch.tensor([40.0, 20.0, 60.0]),
                      d=0.05, backlash=torch.tensor([0.003, 0.0, 0.01]), M_FC=torch.tensor([0.2, 0.5, 0.0]),
                      mu_F=0.001)
    fp = FastParams.build(p, DRIVE, default_substeps(p, DRIVE), dtype, torch.tensor([0.1, -0.2, 0.0]))
    g = torch.Generator().manual_seed(3)
    refs = (torch.randn(60, 3, generator=g) * 2).to(dtype)
    states = []
    for kernel_on in (lambda k: True, lambda k: k % 3 != 1, lambda k: False):
        x = FastState.zeros(3, dtype)
        for k in range(60):
            x.M_ref = refs[k].contiguous()
            advance(x, fp, use_kernel=kernel_on(k))
        states.append(x)
    for x in states[1:]:
        for name in ("w_M", "w_L", "dphi", "M_M", "phi", "comp"):
            assert torch.equal(getattr(x, name), getattr(states[0], name)), name
    last = states[2]
    assert last.comp.shape == (4, 3) and bool(last.comp.ne(0).any())
    assert not any(getattr(last, name).is_inference() for name in ("w_M", "w_L", "dphi", "M_M", "phi", "comp"))


@pytest.mark.parametrize("use_kernel", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_decayed_motor_torque_ends_at_zero_not_in_subnormals(dtype: torch.dtype, use_kernel: bool) -> None:
    # at zero reference the current loop's lag decays as exp(-t / T_Ei): below TORQUE_FLOOR (1e-30 Nm)
    # it is 0 with its compensation, never a subnormal number (each costs the CPU a microcode assist).
    # Hand count: after 10 samples at 1 Nm, M_M = 1 - exp(-5) = 0.9933 (T_s / T_Ei = 0.5); at 0 Nm it
    # falls below 1e-30 once k / 2 > ln(0.9933e30) = 69.07, at the 139th sample
    from sim._integrate_fast import TORQUE_FLOOR, FastParams, FastState, advance

    if use_kernel and load_kernel() is None:
        pytest.skip("no C compiler: only the eager path exists")
    p = TwoMassParams(J_sigma=torch.tensor([0.02, 0.05]), V_J=2.0, f_e=torch.tensor([40.0, 20.0]), d=0.05,
                      backlash=torch.tensor([0.003, 0.0]), M_FC=0.2, mu_F=0.001)
    fp = FastParams.build(p, DRIVE, 4, dtype)
    x = FastState.zeros(2, dtype)
    torque = []
    for k in range(300):
        x.M_ref = torch.full((2,), 1.0 if k < 10 else 0.0, dtype=dtype)
        advance(x, fp, use_kernel=use_kernel)
        torque.append(x.M_M.clone())
    M = torch.stack(torque)  # 300 x 2, after each sample
    assert not bool(((M != 0) & (M.abs() < TORQUE_FLOOR)).any())
    first_zero = (M == 0).to(torch.int8).argmax(0) - 9  # zero-reference samples until M_M is 0
    assert first_zero.tolist() == [139, 139]
    assert bool((M[200:] == 0).all()) and bool((x.comp[3] == 0).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_controller_decides_at_each_threshold_inclusively(dtype: torch.dtype) -> None:
    # one system per section, its speed exactly at the section's threshold (ends) and one quantum
    # short of it (goes on): I w >= w_max, II w <= 0.2 w_max, III w <= 0, IV w <= -w_max,
    # V w >= -0.2 w_max, VI w >= 0 (SPEC 2)
    sig = TestSignalConfig(M_star=10.0, w_max=100.0)
    thr = torch.tensor([100.0, 20.0, 0.0, -100.0, -20.0, 0.0], dtype=dtype)
    inward = torch.tensor([-1.0, 1.0, 1.0, 1.0, -1.0, -1.0], dtype=dtype) * 0.25  # short of the threshold
    for w, ends in ((thr, True), (thr + inward, False)):
        ctl = SwitchingController(sig, DRIVE, dtype)
        ctl.reset((6,))
        ctl.sec = torch.arange(1, 7, dtype=torch.int32)
        ctl.cnt = torch.full((6,), 3, dtype=torch.int32)
        ctl.limit = torch.full((6,), 1000, dtype=torch.int32)  # II and V not over by time
        M = ctl.step(10, w)
        expect_sec = torch.arange(1, 7, dtype=torch.int32) + int(ends)
        assert torch.equal(ctl.sec, expect_sec)
        assert torch.equal(ctl.cnt, torch.full((6,), 0 if ends else 4, dtype=torch.int32))
        levels = torch.tensor([0.0, 10.0, 0.0, -7.0, -10.0, 0.0, 7.0, 0.0], dtype=dtype)
        assert torch.equal(M, levels[expect_sec.long()])
        assert torch.equal(ctl.length, torch.zeros(6, dtype=torch.int32))
        assert not bool(ctl.timed_out.any())
    # by time: II after as many samples as I lasted, V as IV, the tail after n_tail; a timeout sets
    # the section's bit; the limits start with the section
    ctl = SwitchingController(sig, DRIVE, dtype)
    ctl.reset((6,))
    ctl.sec = torch.tensor([1, 2, 4, 5, 6, 3], dtype=torch.int32)
    ctl.cnt = torch.tensor([6, 6, 8, 8, 4, sig.n_timeout(DRIVE) - 1], dtype=torch.int32)
    ctl.limit[1], ctl.limit[3] = 7, 9
    w = torch.tensor([100.0, 50.0, -100.0, -50.0, 0.0, 50.0], dtype=dtype)  # I, IV, VI end by speed
    ctl.step(41, w)
    assert ctl.sec.tolist() == [2, 3, 5, 6, 7, 4]
    assert ctl.limit.tolist() == [7, NEVER, 9, NEVER, sig.n_tail(DRIVE), NEVER]
    assert ctl.timed_out.tolist() == [[False] * 6] * 5 + [[False, False, True, False, False, False]]
    ctl.cnt[4] = sig.n_tail(DRIVE) - 1
    ctl.step(42, w)
    assert ctl.sec[4] == 8 and ctl.length.tolist() == [0, 0, 0, 0, 43, 0]


def test_simulated_plant_interface_matches_simulate():
    from sim import Plant, SimulatedPlant

    p = TwoMassParams(J_sigma=torch.tensor([0.02, 0.05]), V_J=2.0, f_e=40.0, d=0.05, backlash=0.003, M_FC=0.2, mu_F=0.001)
    ctl = Profile([3.0, -2.0], 25)
    ref = simulate(p, DRIVE, ctl, 100)
    plant = SimulatedPlant(p, DRIVE)
    assert isinstance(plant, Plant)
    ctl.reset(p.batch_shape)
    speeds, M = [], torch.zeros(2)
    for k in range(100):
        w = plant.measure()
        speeds.append(w)
        M_next = ctl.step(k, w)
        plant.apply(M)
        M = M_next
    assert torch.equal(torch.stack(speeds, -1), ref.speed)
