"""SPEC 1.1 real axes: constant load torque M_L0, motor friction M_FCM / mu_FM, the holding torque M_hold.

Exact solutions where the model has one (a stiff shaft makes one mass ``J_sigma``), the fast path
against its twin and against the event-restarted reference, and the zero terms against numbers
pinned from the simulator before SPEC 1.1 (so that every earlier result stays bit for bit)."""

import hashlib
import math

import numpy as np
import pytest
import torch

from _helpers import Profile
from sim import (ALL_PARAM_NAMES, PARAM_NAMES, DriveConfig, RealAxisRanges, TestSignalConfig, TwoMassParams,
                 iter_records, sample_envelope, sample_population, simulate, simulate_test)
from sim._drive import DriveLimits, Scenario, SimulatedDrive
from sim._integrate_fast import FastState
from sim._kernel import load_kernel
from sim.records import responses_to_records, validate

DRIVE = DriveConfig()


def _stiff(**kw) -> TwoMassParams:
    """A shaft stiff and damped enough that the two masses move as one ``J_sigma`` (0.05 kg m^2)."""
    base = dict(J_sigma=0.05, V_J=1.0, f_e=400.0, d=0.7, backlash=0.0, M_FC=0.0, mu_F=0.0)
    return TwoMassParams.from_dicts({**base, **kw})


#: The first 16 hex digits of the SHA-256 below, computed with the simulator of commit 3da875e.
PINNED = "49ac11124f279256"


def test_zero_real_axis_terms_give_the_numbers_of_before():
    """Pinned from the simulator before SPEC 1.1 (commit 3da875e): the fused test of four systems of
    the default population, float32 and float64, and the eager twin with an external load torque."""
    p = sample_population(4, 3)
    s = TestSignalConfig(M_star=10, w_max=30, timeout=0.3)
    digest = hashlib.sha256()
    for dtype in (torch.float32, torch.float64):
        r = simulate_test(p, DRIVE, s, dtype=dtype)
        for v in (r.speed, r.torque, r.torque_ref, r.length):
            digest.update(v.numpy().tobytes())
    r = simulate(p[:2], DRIVE, Profile([5.0, -5.0, 0.0], 100), 400, use_kernel=False,
                 load_torque=torch.tensor([-1.0, 1.0]))
    digest.update(r.speed.numpy().tobytes())
    digest.update(r.torque.numpy().tobytes())
    assert digest.hexdigest()[:16] == PINNED


def test_parameters_default_to_zero_and_check_their_range():
    p = sample_population(3, 0)
    for n in ("M_L0", "M_FCM", "mu_FM"):
        assert torch.equal(getattr(p, n), torch.zeros(3, dtype=torch.float64))
    assert not p.real_axis and list(p.to_dicts()[0]) == list(PARAM_NAMES)
    q = _stiff(M_L0=-2.0, M_FCM=0.1, mu_FM=0.01)
    assert q.real_axis and list(q.to_dicts()[0]) == list(ALL_PARAM_NAMES)
    assert float(q.M_hold) == -2.0 and float(q.reshape(1)[0].M_L0) == -2.0
    truth = q.reshape(1).truth(DRIVE, 10.0)[0]
    assert (truth["M_L0"], truth["M_FCM"], truth["mu_FM"]) == (-2.0, 0.1, 0.01)
    for bad in ({"M_FCM": -0.1}, {"mu_FM": -1e-3}, {"M_L0": math.inf}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            _stiff(**bad)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_stiff_axis_with_load_torque_and_motor_viscous_friction_follows_the_closed_form(dtype):
    """Held at M_L0, then M_ref = M: ``J w' + mu_FM w = M_M(t) - M_L0``, ``M_M`` the current loop's
    first-order step from ``M_L0`` to ``M``: ``w = dM/mu (1 - e^{-a t}) + C (e^{-t/T} - e^{-a t})``,
    ``a = mu/J``, ``C = -dM / (J (a - 1/T))``."""
    J, M_L0, mu, M, T = 0.05, 2.0, 0.05, 6.0, DRIVE.T_Ei
    p = _stiff(M_L0=M_L0, mu_FM=mu)
    r = simulate(p.reshape(1), DRIVE, Profile([M], 1), 2000, dtype=dtype, return_states=True)
    t = np.arange(2000) * DRIVE.T_s - DRIVE.T_s  # the reference applies from sample 1
    t = np.clip(t, 0.0, None)
    a, dM = mu / J, M - M_L0
    w = dM / mu * (1 - np.exp(-a * t)) - dM / (J * (a - 1 / T)) * (np.exp(-t / T) - np.exp(-a * t))
    got = r.states["w_M"][0].double().numpy()
    assert float(r.torque[0, 0]) == M_L0  # the first sample shows the holding torque
    tol = 2e-4 if dtype == torch.float64 else 2e-3
    assert np.abs(got - w).max() < tol * w.max(), np.abs(got - w).max()
    assert np.abs(r.states["w_L"][0].double().numpy() - w).max() < tol * w.max()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("backlash", [0.0, 0.01])
def test_held_axis_stays_at_rest(dtype, backlash):
    """Held by M_hold = M_L0 (no friction anywhere: nothing else holds it), the axis stays put."""
    p = TwoMassParams.from_dicts({"J_sigma": 0.05, "V_J": 2.0, "f_e": 40.0, "d": 0.02, "backlash": backlash,
                                  "M_L0": -3.0}).reshape(1)
    r = simulate(p, DRIVE, Profile([-3.0], 1), 4000, dtype=dtype, return_states=True)
    assert float(r.speed.abs().max()) == 0.0  # not one encoder count in 1 s
    assert float(r.states["w_M"].abs().max()) < 0.01 * DRIVE.q_w
    x = FastState.held(p, torch.float64)
    assert float(x.dphi[0]) == -3.0 / float(p.C_F[0]) - backlash / 2 and float(x.M_M[0]) == -3.0
    # without the hold, the load torque turns it (M_L0 < 0 drives it forward; a check that the test can fail)
    free = simulate(p, DRIVE, Profile([0.0], 1), 400, dtype=dtype)
    assert float(free.speed.max()) > 10 * DRIVE.q_w


def test_motor_coulomb_friction_decelerates_a_coasting_motor_at_M_FCM_over_J_and_holds_it():
    J, M_FCM = 0.05, 1.0
    p = _stiff(M_FCM=M_FCM).reshape(1)
    # 5 Nm for 0.1 s, then 0: the motor coasts down at M_FCM / J_sigma, stops (after 0.4 s), and sticks
    r = simulate(p, DRIVE, Profile([5.0] * 400 + [0.0] * 4000, 1), 3000, dtype=torch.float64, return_states=True)
    w = r.states["w_M"][0].numpy()
    k0, k1 = 500, 900  # M_M has decayed (60 T_Ei after the step), the motor still runs
    assert w[k1] > 1.0
    slope = (w[k1] - w[k0]) / ((k1 - k0) * DRIVE.T_s)
    assert slope == pytest.approx(-M_FCM / J, rel=1e-6)
    stop = k1 + int(np.argmax(w[k1:] <= 0))
    assert stop > k1 and (w[stop:] == 0).all()  # stuck: exactly at rest
    assert np.abs(r.states["w_L"][0].numpy()[stop + 400:]).max() < 1e-6  # the load's shaft swing has died out
    # the stop time of the closed form: the speed at k1 over the deceleration
    assert stop * DRIVE.T_s == pytest.approx(k1 * DRIVE.T_s + w[k1] * J / M_FCM, abs=2 * DRIVE.T_s)


def test_motor_sticks_inside_the_backlash_below_M_FCM_and_slides_above():
    """Inside the gap the shaft carries nothing (M_S = 0): the motor sticks while |M_M| <= M_FCM, and
    slides at ``(M_M - M_FCM) / J_M`` above (reference path: its stick/slip events are exact)."""
    M_FCM, J_M, T = 1.0, 0.025, DRIVE.T_Ei
    p = TwoMassParams.from_dicts({"J_sigma": 0.05, "V_J": 1.0, "f_e": 50.0, "d": 0.05, "backlash": 0.2,
                                  "M_FCM": M_FCM}).reshape(1)
    below = simulate(p, DRIVE, Profile([0.9], 1), 40, method="reference", return_states=True)
    assert (below.states["w_M"] == 0).all()
    r = simulate(p, DRIVE, Profile([1.5], 1), 40, method="reference", return_states=True)
    t = np.clip(np.arange(40) * DRIVE.T_s - DRIVE.T_s, 0.0, None)
    t0 = T * math.log(3.0)  # M_M = 1.5 (1 - e^{-t/T}) reaches M_FCM
    w = np.where(t > t0, (0.5 * (t - t0) - 1.5 * T * (1 / 3 - np.exp(-t / T))) / J_M, 0.0)
    assert np.abs(r.states["w_M"][0].numpy() - w).max() < 1e-7 * w.max()
    assert float(r.states["dphi"][0].abs().max()) < 0.1  # still inside the gap (half width 0.1 rad)
    fast = simulate(p, DRIVE, Profile([1.5], 1), 40, dtype=torch.float64, return_states=True)
    assert np.abs(fast.states["w_M"][0].numpy() - w).max() < 2e-3 * w.max()


def _combinations() -> TwoMassParams:
    t = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    return TwoMassParams(J_sigma=t(0.05, 0.02, 0.05, 0.03, 0.04), V_J=t(1.0, 2.0, 0.5, 1.5, 1.0),
                         f_e=t(30.0, 80.0, 50.0, 40.0, 60.0), d=t(0.02, 0.05, 0.03, 0.04, 0.02),
                         backlash=torch.deg2rad(t(0.5, 0.0, 0.2, 0.0, 0.3)), M_FC=t(0.3, 0.0, 0.2, 0.5, 0.0),
                         mu_F=t(0.002, 0.0, 0.001, 0.0, 0.003), M_L0=t(1.5, -1.0, 0.0, 0.0, -0.5),
                         M_FCM=t(0.0, 0.0, 0.3, 0.2, 0.4), mu_FM=t(0.0, 0.002, 0.0, 0.001, 0.002))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("around_hold", [True, False])
def test_kernel_equals_its_eager_twin_with_the_new_terms(dtype, around_hold):
    if load_kernel() is None:
        pytest.skip("no C kernel")
    p = _combinations()
    s = TestSignalConfig(M_star=5.0, w_max=10.0, timeout=0.2)
    # the first two alone: no motor Coulomb friction in the batch (the twin skips the motor's stop rule)
    for q in (p, p[:2]):
        a = simulate_test(q, DRIVE, s, dtype=dtype, around_hold=around_hold, chunk_samples=300)
        b = simulate_test(q, DRIVE, s, dtype=dtype, around_hold=around_hold, use_kernel=False)
        for k in ("speed", "torque", "torque_ref", "section", "length", "timed_out"):
            assert torch.equal(getattr(a, k), getattr(b, k)), k
    a = simulate_test(p, DRIVE, s, dtype=dtype, around_hold=around_hold, chunk_samples=300)
    hold = p.M_L0.to(dtype)
    assert torch.equal(a.torque_ref[:, 0], hold)  # held before the test
    if around_hold:  # the tail runs at M_hold too
        assert torch.equal(a.M_hold, p.M_L0) and torch.equal(a.torque_ref[:, 1], (5.0 + hold))
    else:
        assert a.M_hold is None and torch.equal(a.torque_ref[:, 1], torch.full((5,), 5.0, dtype=dtype))


def test_fast_path_agrees_with_reference_with_the_new_terms():
    """Five combinations of M_L0, M_FCM, mu_FM with and without backlash and load friction. At the
    default substeps as tests/sim/test_sim_reference.py (2 % of each state's range there, on one
    system; these reach 2.7 %, the same systems without the new terms 1.8 %: the stick/slip and
    contact decisions once per substep), 3 counts of encoder speed; at 64 substeps within 0.3 %
    (the fast path converges to the reference)."""
    p = _combinations()
    ctl = Profile([5.0, -5.0, 0.0, 2.0], 30)
    ref = simulate(p, DRIVE, ctl, 120, method="reference", return_states=True)
    for substeps, tol in ((None, 3e-2), (64, 3e-3)):
        fast = simulate(p, DRIVE, ctl, 120, return_states=True, substeps=substeps, dtype=torch.float64)
        for k in ("w_M", "w_L", "dphi", "M_M"):
            a, b = fast.states[k], ref.states[k]
            err = (a - b).abs().max(-1).values / b.abs().max(-1).values
            assert float(err.max()) < tol, (substeps, k, err.tolist())
        assert float(((fast.speed - ref.speed).abs() / DRIVE.q_w).max()) <= 3
        # both see the motors with Coulomb friction stuck for a while
        assert int((ref.states["w_M"][2:] == 0).sum()) > 3 and int((fast.states["w_M"][2:] == 0).sum()) > 3


def test_records_say_M_hold_only_when_the_levels_ran_around_it():
    p = _combinations()
    s = TestSignalConfig(M_star=5.0, w_max=20.0, timeout=0.5)
    recs = {r.name: r for r in iter_records(p, DRIVE, s)}
    assert [recs[f"sys{i:05d}"].info.M_hold for i in range(5)] == [1.5, -1.0, None, None, -0.5]
    assert recs["sys00000"].info.truth["M_L0"] == 1.5 and recs["sys00002"].info.truth["M_FCM"] == 0.3
    plain = {r.name: r for r in iter_records(p, DRIVE, s, around_hold=False)}
    assert all("M_hold" not in r.meta for r in plain.values())
    resp = simulate_test(p, DRIVE, s, dtype=torch.float64)
    assert [r.meta.get("M_hold") for r in responses_to_records(resp, p, DRIVE, s)] == [1.5, -1.0, None, None, -0.5]
    rec = validate(recs["sys00000"])
    rec.meta["M_hold"] = "1"
    with pytest.raises(ValueError, match="M_hold"):
        validate(rec)


def test_simulated_drive_starts_held_and_holds_in_closed_loop():
    class Zero:
        params: dict = {}

        def reset(self):
            pass

        def step(self, w_meas, w_ref):
            return 0.0

    plant = {"J_sigma": 0.05, "V_J": 1.0, "f_e": 40.0, "d": 0.05, "M_L0": 2.0, "mu_FM": 0.001}
    drive = SimulatedDrive(plant)
    limits = DriveLimits(w_max=50.0, travel=20.0)
    rec = drive.run_closed_loop(Zero(), Scenario(np.zeros(800), np.zeros(800)), limits)
    assert rec.meta["M_hold"] == 2.0 and np.abs(rec.speed).max() == 0.0
    assert np.allclose(rec.torque_ref, 2.0)
    test = drive.run_test(5.0, 20.0, limits)
    assert test.meta["M_hold"] == 2.0 and test.torque_ref[0] == 2.0 and test.torque_ref[1] == 7.0
    stopped = drive.run_test(5.0, 20.0, DriveLimits(w_max=5.0, travel=20.0))  # passes 5 rad/s: stops, holds
    assert stopped.meta["aborted"] and stopped.meta["M_hold"] == 2.0 and stopped.torque_ref[-1] == 2.0
    assert "M_hold" not in SimulatedDrive({k: v for k, v in plant.items() if k != "M_L0"}).run_test(
        5.0, 20.0, limits).meta


def test_real_axis_population_adds_the_parts_and_keeps_the_rest():
    p = sample_population(4000, 7)
    q = sample_population(4000, 7, real_axis=True)
    assert all(torch.equal(getattr(p, n), getattr(q, n)) for n in PARAM_NAMES)
    M_star = TestSignalConfig().M_star
    has_L0, has_FCM = q.M_L0 != 0, q.M_FCM != 0
    assert 0.45 < float(has_L0.double().mean()) < 0.55 and 0.45 < float(has_FCM.double().mean()) < 0.55
    assert float(q.M_L0.abs().max()) <= 0.15 * M_star and float(q.M_L0.max()) > 0.14 * M_star
    assert float(q.M_L0.min()) < -0.14 * M_star
    assert float(q.M_FCM.max()) <= 0.03 * M_star and float(q.M_FCM.max()) > 0.029 * M_star
    assert float(q.mu_FM.max()) <= 0.002 and float(q.mu_FM.max()) > 0.00195 and float(q.mu_FM.min()) >= 0
    # independent draws: the parts are uncorrelated
    assert abs(float(torch.corrcoef(torch.stack([has_L0.double(), has_FCM.double()]))[0, 1])) < 0.05
    half = sample_population(50, 1, real_axis=RealAxisRanges(M_L0_share=1.0, M_FCM_share=0.0))
    assert bool((half.M_L0 != 0).all()) and bool((half.M_FCM == 0).all())
    with pytest.raises(TypeError, match="real_axis"):
        sample_population(5, 1, real_axis="yes")  # type: ignore[arg-type]
    env = sample_envelope(64, 3, real_axis=True)
    M_star_env = torch.tensor([s.M_star for _, s in env.cases])[env.cell]
    assert float((env.params.M_L0.abs() / M_star_env).max()) <= 0.15


def test_replay_starts_held_and_its_kernel_equals_the_twin_with_the_new_terms():
    from sim import replay_speed

    p = _combinations()
    start = torch.tensor([[0, 100, 300]] * 5, dtype=torch.int32)
    level = torch.stack([p.M_L0, p.M_L0 + 4.0, p.M_L0 - 4.0], -1)
    if load_kernel() is not None:
        a = replay_speed(p, DRIVE, start, level, 500)
        b = replay_speed(p, DRIVE, start, level, 500, use_kernel=False)
        assert torch.equal(a, b)
    held = replay_speed(p, DRIVE, start[:, :1], level[:, :1], 400, dtype=torch.float64)
    # held by M_hold = M_L0: within one count (the motor angle starts on a count's edge, where a
    # rounding-size motion of 1e-18 rad reads as one count)
    assert float(held.abs().max()) <= DRIVE.q_w * (1 + 1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_blocks_with_and_without_motor_friction_equal_the_twin(dtype):
    """The kernel runs a block of 32 systems with the motor's friction only where one of them has it;
    the twin decides for the whole batch: the same numbers either way."""
    if load_kernel() is None:
        pytest.skip("no C kernel")
    p = sample_population(40, 9)
    mu_FM = torch.zeros(40, dtype=torch.float64)
    mu_FM[36:] = 0.002
    M_FCM = torch.zeros(40, dtype=torch.float64)
    M_FCM[38:] = 0.2
    q = TwoMassParams(**{**{n: getattr(p, n) for n in PARAM_NAMES}, "mu_FM": mu_FM, "M_FCM": M_FCM})
    ctl = Profile([5.0, -5.0, 0.0], 60)
    a = simulate(q, DRIVE, ctl, 240, dtype=dtype, return_states=True)
    b = simulate(q, DRIVE, ctl, 240, dtype=dtype, return_states=True, use_kernel=False)
    for k in ("w_M", "w_L", "dphi", "M_M", "phi_M"):
        assert torch.equal(a.states[k], b.states[k]), k
    plain = simulate(p, DRIVE, ctl, 240, dtype=dtype, return_states=True)
    assert torch.equal(plain.states["w_M"][:32], a.states["w_M"][:32])  # the first block: SPEC 1's numbers
    assert not torch.equal(plain.states["w_M"][36:], a.states["w_M"][36:])
