"""Tests of the IV4 baseline (training/evaluation/_iv4.py): exactness, consistency, two-mass conversion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import trapezoid
from scipy.linalg import expm
from scipy.signal import lfilter

from training.evaluation._iv4 import arx, identify_iv4, iv4, mean_torque, two_mass_from_discrete

T_S = 2.5e-4


# ----------------------------------------------------------------------------- helpers


def _prbs(n: int, seed: int, hold: int = 1) -> np.ndarray:
    """+-1 pseudo-random binary sequence, each value held ``hold`` samples."""
    rng = np.random.default_rng(seed)
    return np.repeat(np.sign(rng.standard_normal(n // hold + 1)), hold)[:n]


def _two_mass_matrices(J_sigma: float, V_J: float, f_e: float, d: float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous state space, states (w_M, w_L, dphi, phi_M), input M_M; no backlash/friction."""
    J_M = J_sigma / (1 + V_J)
    J_L = J_sigma - J_M
    w_0 = 2 * np.pi * f_e / np.sqrt(1 - d * d)
    C_F = w_0**2 * J_M * J_L / J_sigma
    D_F = 2 * d * C_F / w_0
    A = np.array(
        [
            [-D_F / J_M, D_F / J_M, -C_F / J_M, 0.0],
            [D_F / J_L, -D_F / J_L, C_F / J_L, 0.0],
            [1.0, -1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
        ]
    )
    B = np.array([1.0 / J_M, 0.0, 0.0, 0.0])
    return A, B


def _zoh(A: np.ndarray, B: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n] = A, B
    E = expm(M * T)
    return E[:n, :n], E[:n, n]


def _simulate_zoh(A: np.ndarray, B: np.ndarray, u: np.ndarray, T: float) -> np.ndarray:
    """States at the sample instants for a held input ``u[k]`` over ``[kT, (k+1)T]``; shape N x n."""
    Ad, Bd = _zoh(A, B, T)
    x = np.zeros(A.shape[0])
    out = np.empty((u.size, A.shape[0]))
    for k in range(u.size):
        out[k] = x
        x = Ad @ x + Bd * u[k]
    return out


def _spec_test_linear(
    J_sigma: float, V_J: float, f_e: float, d: float, *, seed: int, M_star: float = 10.0, w_max: float = 100.0
) -> tuple[np.ndarray, np.ndarray]:
    """SPEC sec. 2 switching test signal on the linear plant with SPEC sec. 1 drive and sensors.

    Current loop T_Ei = 0.5 ms, encoder 2**20 counts (speed = quantised-angle difference / T_s),
    measured current (K_M = 1) with 0.01 A white noise. Returns (current [A], speed [rad/s]).
    A stand-in for ``sim.simulate_test`` restricted to the backlash- and friction-free case.
    """
    T_Ei, q = 5e-4, 2 * np.pi / 2**20
    A4, B4 = _two_mass_matrices(J_sigma, V_J, f_e, d)
    A = np.zeros((5, 5))  # states (M_M, w_M, w_L, dphi, phi_M), input M_ref
    A[0, 0] = -1.0 / T_Ei
    A[1:, 1:] = A4
    A[1:, 0] = B4
    B = np.array([1.0 / T_Ei, 0, 0, 0, 0])
    Ad, Bd = _zoh(A, B, T_S)
    levels = {1: M_star, 2: 0.0, 3: -0.7 * M_star, 4: -M_star, 5: 0.0, 6: 0.7 * M_star}
    x, phi_prev = np.zeros(5), 0.0
    section, k_sec, len_I, len_IV, tail = 1, 0, 0, 0, -1
    n_timeout, n_tail = int(10.0 / T_S), int(0.05 / T_S)
    speed, torque = [], []
    while tail < n_tail:
        phi_q = np.floor(x[4] / q) * q
        w_m, phi_prev = (phi_q - phi_prev) / T_S, phi_q
        speed.append(w_m)
        torque.append(x[0])
        if tail < 0:
            k_sec += 1
            end = k_sec >= n_timeout or {
                1: w_m >= w_max,
                2: k_sec >= len_I or w_m <= 0.2 * w_max,
                3: w_m <= 0,
                4: w_m <= -w_max,
                5: k_sec >= len_IV or w_m >= -0.2 * w_max,
                6: w_m >= 0,
            }[section]
            if end:
                len_I = k_sec if section == 1 else len_I
                len_IV = k_sec if section == 4 else len_IV
                section, k_sec = section + 1, 0
                tail = 0 if section == 7 else -1
        else:
            tail += 1
        M_ref = levels[section] if tail < 0 else 0.0
        x = Ad @ x + Bd * M_ref
    rng = np.random.default_rng(seed)
    current = np.asarray(torque) + 0.01 * rng.standard_normal(len(torque))
    return current, np.asarray(speed)


def _rel(a: float, b: float) -> float:
    return abs(a / b - 1.0)


# ----------------------------------------------------------------------------- (a) exactness


@pytest.mark.parametrize(
    "A, B",
    [
        (np.array([1.0, -1.5, 0.7]), np.array([0.0, 1.0, 0.5])),
        (np.array([1.0, -2.2, 1.61, -0.378]), np.array([0.0, 0.3, -0.2, 0.05])),
    ],
)
def test_exact_recovery_noise_free(A: np.ndarray, B: np.ndarray) -> None:
    u = _prbs(3000, seed=1)
    y = lfilter(B, A, u)
    na, nb = A.size - 1, B.size - 1
    for model in (iv4(u, y, na, nb, 1), arx(u, y, na, nb, 1)):
        np.testing.assert_allclose(model.A, A, atol=1e-8)
        np.testing.assert_allclose(model.B, B, atol=1e-8)
    assert iv4(u, y, na, nb, 1).converged


def test_exact_recovery_with_exog() -> None:
    """An extra static regressor (an offset ramp) is estimated with the model, exactly."""
    A, B, c = np.array([1.0, -1.5, 0.7]), np.array([0.0, 1.0, 0.5]), 0.3
    u = _prbs(3000, seed=6)
    E = np.sin(np.arange(3000) / 50.0)[:, None]
    y = lfilter([1.0], A, lfilter(B, [1.0], u) + c * E[:, 0])
    r = iv4(u, y, 2, 2, 1, exog=E)
    np.testing.assert_allclose(r.A, A, atol=1e-8)
    np.testing.assert_allclose(r.B, B, atol=1e-8)
    np.testing.assert_allclose(r.exog_coef, [c], atol=1e-8)
    np.testing.assert_allclose(r.simulate(u, E), y, atol=1e-8)


# ----------------------------------------------------------------------------- (b) consistency


@pytest.mark.parametrize("C, D, sigma", [([1.0], [1.0, -0.9], 0.5), ([1.0, 0.5], [1.0], 1.0)])
def test_iv4_consistent_where_arx_is_biased(C: list[float], D: list[float], sigma: float) -> None:
    A, B = np.array([1.0, -1.5, 0.7]), np.array([0.0, 1.0, 0.5])
    theta_true = np.concatenate([A[1:], B[1:]])
    n = 20000
    u = _prbs(n, seed=2)
    v = sigma * lfilter(C, D, np.random.default_rng(3).standard_normal(n))  # coloured output noise
    y = lfilter(B, A, u) + v
    err_iv4 = np.linalg.norm(iv4(u, y, 2, 2, 1).theta - theta_true)
    err_arx = np.linalg.norm(arx(u, y, 2, 2, 1).theta - theta_true)
    assert err_iv4 < 0.02, err_iv4
    assert err_arx > 0.05, err_arx
    assert err_arx > 5 * err_iv4, (err_arx, err_iv4)


# ----------------------------------------------------------------------------- (c) conversion


@pytest.mark.parametrize("f_e", [5.0, 30.0, 120.0, 500.0])
def test_conversion_of_exact_zoh_models(f_e: float) -> None:
    """The three model outputs of an exactly ZOH-sampled two-mass system convert back exactly."""
    J_sigma, V_J, d = 0.05, 2.0, 0.05
    Ac, Bc = _two_mass_matrices(J_sigma, V_J, f_e, d)
    Ad, Bd = _zoh(Ac, Bc, T_S)
    # resonance polynomial (without the integrators) from the exact discrete poles
    p = np.exp(T_S * np.linalg.eigvals(Ac[:3, :3]))
    p = p[np.abs(p - 1.0) > 1e-9]
    A2 = np.real(np.poly(p))
    # Markov parameters of speed and angle -> numerators B = A_full * h
    n = 6
    h_w, h_phi, x = np.zeros(n), np.zeros(n), Bd.copy()
    for k in range(1, n):
        h_w[k], h_phi[k] = x[0], x[3]
        x = Ad @ x
    A_w = np.convolve(A2, [1.0, -1.0])
    A_phi = np.convolve(A_w, [1.0, -1.0])
    B_speed = np.convolve(A_w, h_w)[:4]
    B_angle = np.convolve(A_phi, h_phi)[:5]
    cases = [
        (A_w, B_speed, "speed"),
        (A2, B_speed, "speed_difference"),
        (A2, B_angle, "angle"),
        (A2, B_angle / T_S, "mean_speed_difference"),
    ]
    for A, B, output in cases:
        r = two_mass_from_discrete(A, B, T_S, output=output)
        assert r.valid, (output, r.reason)
        tol = 1e-4 if output == "speed" else 1e-6  # "speed" re-estimates the integrator pole
        assert _rel(r.f_e, f_e) < 1e-6, (output, r.f_e)
        assert _rel(r.V_J, V_J) < tol, (output, r.V_J)
        assert _rel(r.J_sigma, J_sigma) < tol, (output, r.J_sigma)
        assert abs(r.d - d) < 1e-6, (output, r.d)


def test_identify_linear_two_mass_rich_excitation() -> None:
    """(c) ZOH-exact simulation, multi-level random held torque, white speed noise: all within 1 %."""
    J_sigma, V_J, f_e, d = 0.03, 1.5, 40.0, 0.03
    rng = np.random.default_rng(4)
    n = 20000
    torque = np.repeat(rng.choice([-5.0, -2.0, 0.0, 2.0, 5.0], n // 8 + 1), 8)[:n]
    torque -= np.mean(torque)  # keep the speed bounded
    Ac, Bc = _two_mass_matrices(J_sigma, V_J, f_e, d)
    states = _simulate_zoh(Ac, Bc, torque, T_S)
    speed = states[:, 0] + 1e-3 * rng.standard_normal(n)  # high SNR
    r = identify_iv4(torque, speed, T_S, torque_is_reference=True, speed_is_mean=False).estimate
    assert r.valid, r.reason
    assert _rel(r.f_e, f_e) < 0.01, r.f_e
    assert _rel(r.V_J, V_J) < 0.01, r.V_J
    assert _rel(r.J_sigma, J_sigma) < 0.01, r.J_sigma


# ----------------------------------------------------------------------------- (d) SPEC test signal


@pytest.mark.parametrize(
    "J_sigma, V_J, f_e, d",
    [(0.044, 1.77, 30.5, 0.011), (0.023, 3.39, 64.6, 0.011), (0.040, 0.41, 116.8, 0.066), (0.032, 0.74, 6.4, 0.009)],
)
def test_identify_spec_test_signal_linear_plant(J_sigma: float, V_J: float, f_e: float, d: float) -> None:
    """SPEC test signal on an elastic plant without backlash (own linear simulator): within 10 %."""
    current, speed = _spec_test_linear(J_sigma, V_J, f_e, d, seed=5)
    r = identify_iv4(current * 1.0, speed, T_S, T_Ei=5e-4).estimate  # torque = K_M * current, K_M = 1
    assert r.valid, r.reason
    assert _rel(r.f_e, f_e) < 0.10, r.f_e
    assert _rel(r.V_J, V_J) < 0.10, r.V_J
    assert _rel(r.J_sigma, J_sigma) < 0.10, r.J_sigma


def _colleague_response(M_FC: float, mu_F: float):  # -> (torque [Nm], speed [rad/s], drive)
    sim = pytest.importorskip("sim")
    if not hasattr(sim, "simulate_test"):
        pytest.skip("sim.simulate_test is not available yet")
    import torch

    values = dict(J_sigma=0.044, V_J=1.77, f_e=30.5, d=0.011, backlash=0.0, M_FC=M_FC, mu_F=mu_F)
    params = sim.TwoMassParams(**{k: torch.tensor([v], dtype=torch.float64) for k, v in values.items()})
    drive = sim.DriveConfig()
    resp = sim.simulate_test(params, drive, sim.TestSignalConfig(), seed=0, dtype=torch.float64)
    n = int(resp.length[0])
    return resp.current[0, :n].numpy() * drive.K_M, resp.speed[0, :n].numpy(), drive


def test_identify_with_colleague_simulator() -> None:
    """(d) SPEC test signal through ``sim.simulate_test``, elastic, no backlash: within 10 %."""
    torque, speed, drive = _colleague_response(0.0, 0.0)
    r = identify_iv4(torque, speed, drive.T_s, T_Ei=drive.T_Ei).estimate
    assert _rel(r.f_e, 30.5) < 0.10, r.f_e
    assert _rel(r.V_J, 1.77) < 0.10, r.V_J
    assert _rel(r.J_sigma, 0.044) < 0.10, r.J_sigma


def test_identify_with_load_friction() -> None:
    """Load Coulomb + viscous friction: the friction regressors keep IV4 within 10 %; without
    them the linear model is off (shows the check can fail)."""
    torque, speed, drive = _colleague_response(0.4, 0.004)
    r = identify_iv4(torque, speed, drive.T_s, T_Ei=drive.T_Ei).estimate
    assert _rel(r.f_e, 30.5) < 0.10, r.f_e
    assert _rel(r.V_J, 1.77) < 0.10, r.V_J
    assert _rel(r.J_sigma, 0.044) < 0.10, r.J_sigma
    bare = identify_iv4(torque, speed, drive.T_s, T_Ei=drive.T_Ei, friction=False).estimate
    errs = [_rel(getattr(bare, k), v) for k, v in (("f_e", 30.5), ("V_J", 1.77), ("J_sigma", 0.044))]
    assert not all(np.isfinite(e) and e < 0.10 for e in errs), errs


# ----------------------------------------------------------------------------- pieces and checks


def test_mean_torque_rebuilds_the_interval_mean() -> None:
    """Exact interval mean of M_M behind a first-order current loop, from the samples or the reference."""
    T_Ei = 5e-4
    ref = np.repeat([0.0, 10.0, -7.0, 0.0, 3.0], 7)
    a = np.exp(-T_S / T_Ei)
    M = np.concatenate([[0.0], lfilter([1 - a], [1, -a], ref)])[:-1]  # M_M(k)
    # reference: fine-grid integration of the exponential within each interval
    fine = np.linspace(0, T_S, 2001)
    truth = np.array(
        [trapezoid(ref[k] + (M[k] - ref[k]) * np.exp(-fine / T_Ei), fine) / T_S for k in range(ref.size - 1)]
    )
    np.testing.assert_allclose(mean_torque(M, T_S, T_Ei), truth, atol=1e-7)
    np.testing.assert_allclose(mean_torque(ref, T_S, T_Ei, is_reference=True), truth, atol=1e-7)
    # the plain samples would be off by much more: the check can fail
    assert np.max(np.abs(M[:-1] - truth)) > 1.0


def test_no_resonance_is_reported_not_raised() -> None:
    r = two_mass_from_discrete([1.0, -1.2, 0.35], [0.0, 1e-3, 1e-3, 1e-4], T_S, output="speed_difference")
    assert not r.valid and np.isnan(r.f_e) and "resonance" in r.reason


def test_input_checks() -> None:
    u, y = np.zeros(500), np.zeros(500)
    with pytest.raises(ValueError, match="same length"):
        iv4(u, y[:-1], 2, 2)
    with pytest.raises(ValueError, match="na"):
        iv4(u, y, -1, 2)
    with pytest.raises(TypeError, match="nb"):
        arx(u, y, 2, 2.5)
    with pytest.raises(ValueError, match="1-D"):
        iv4(np.zeros((10, 2)), np.zeros((10, 2)), 1, 1)
    with pytest.raises(ValueError, match="finite"):
        iv4(np.full(500, np.nan), y, 1, 1)
    with pytest.raises(ValueError, match="at least"):
        iv4(u[:20], y[:20], 2, 2)
    with pytest.raises(ValueError, match="T_s"):
        two_mass_from_discrete([1.0, -1.9, 0.95], [0.0, 1.0, 1.0], 0.0, output="speed_difference")
    with pytest.raises(ValueError, match="output"):
        two_mass_from_discrete([1.0, -1.9, 0.95], [0.0, 1.0, 1.0], T_S, output="torque")
    with pytest.raises(ValueError, match="order"):
        two_mass_from_discrete([1.0, -1.9, 0.95], [0.0, 1.0, 1.0], T_S, output="speed")
    with pytest.raises(ValueError, match="T_Ei"):
        identify_iv4(u, y, T_S, T_Ei=-1.0)


def test_conversion_with_current_loop() -> None:
    """Model from the held torque reference through the current loop: T_Ei put back exactly."""
    J_sigma, V_J, f_e, d, T_Ei = 0.02, 0.8, 60.0, 0.04, 5e-4
    A4, B4 = _two_mass_matrices(J_sigma, V_J, f_e, d)
    A = np.zeros((5, 5))
    A[0, 0] = -1.0 / T_Ei
    A[1:, 1:] = A4
    A[1:, 0] = B4
    Bc = np.array([1.0 / T_Ei, 0, 0, 0, 0])
    Ad, Bd = _zoh(A, Bc, T_S)
    p = np.exp(T_S * np.linalg.eigvals(A4[:3, :3]))
    A2 = np.real(np.poly(p[np.abs(p - 1.0) > 1e-9]))
    A_full = np.convolve(np.convolve(A2, [1.0, -1.0]), [1.0, -np.exp(-T_S / T_Ei)])
    h, x = np.zeros(6), Bd.copy()
    for k in range(1, 6):
        h[k] = x[1]  # w_M
        x = Ad @ x
    B = np.convolve(A_full, h)[:5]
    r = two_mass_from_discrete(A2, B, T_S, output="speed_difference", T_Ei=T_Ei)
    assert _rel(r.f_e, f_e) < 1e-6 and _rel(r.V_J, V_J) < 1e-6 and _rel(r.J_sigma, J_sigma) < 1e-6, r
    wrong = two_mass_from_discrete(A2, B[:4], T_S, output="speed_difference")  # ignoring the loop
    assert not (np.isfinite(wrong.V_J) and _rel(wrong.V_J, V_J) < 1e-3)
