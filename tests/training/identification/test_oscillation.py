"""The eq.-1 oscillation fit recovers a known elastic mode exactly (noise-free, linear)."""

import math

import numpy as np
import pytest

from training.identification import _resonance
from training.identification._oscillation import fit_oscillation
from training.identification._resonance import zoh_responses

T_S = 2.5e-4


def _torque_steps(n_per: int = 1200) -> tuple[np.ndarray, np.ndarray]:
    levels = [10.0, 0.0, -7.0, -10.0, 0.0, 7.0]
    M = np.concatenate([np.full(n_per, v) for v in levels])
    bounds = np.array([[k * n_per, (k + 1) * n_per] for k in range(6)])
    return M, bounds


@pytest.mark.parametrize("f_0, d, gain", [(12.0, 0.02, 50.0), (47.0, 0.05, 120.0), (230.0, 0.01, 20.0)])
def test_recovers_frequency_damping_and_gain(f_0, d, gain):
    M, bounds = _torque_steps()
    w_osc = gain * zoh_responses(M, [f_0], [d], T_S)[0]
    w_osc += np.repeat(np.array([0.3, -0.2, 0.1, 0.0, 0.5, -0.4]), 1200)  # section offsets are nuisance
    fit = fit_oscillation(M, w_osc, bounds, T_S, f_guess=f_0 * 1.7)
    assert fit.f_0 == pytest.approx(f_0, rel=1e-3)
    assert fit.d == pytest.approx(d, rel=0.05)
    assert fit.gain == pytest.approx(gain, rel=1e-2)
    assert fit.r2 > 0.999


@pytest.fixture(params=["kernel", "lfilter"])
def path(request, monkeypatch):
    """Both implementations of the responses: the C kernel and scipy's lfilter (no kernel)."""
    _resonance._kernel.cache_clear()
    if request.param == "lfilter":
        monkeypatch.setenv("TWOMASS_NO_C_KERNEL", "1")
    elif _resonance._kernel() is None:
        pytest.skip("no C compiler")
    yield request.param
    _resonance._kernel.cache_clear()


def test_response_matches_the_continuous_step_response(path):
    # s/(s^2 + 2 d w0 s + w0^2) to a unit step: exp(-sigma t) sin(w_d t) / w_d at the samples
    f_0, d = np.array([40.0, 3.0, 400.0]), np.array([0.03, 0.2, 0.001])
    n = 400
    y = zoh_responses(np.ones(n), f_0, d, T_S)  # 3 x n
    w0 = 2 * math.pi * f_0[:, None]
    sigma, w_d = d[:, None] * w0, w0 * np.sqrt(1 - d[:, None] ** 2)
    t = np.arange(n) * T_S
    np.testing.assert_allclose(y, np.exp(-sigma * t) * np.sin(w_d * t) / w_d, atol=1e-12)


@pytest.mark.parametrize("K", [1, 7, 8, 9, 17])
def test_kernel_equals_lfilter(monkeypatch, K):
    """The kernel's K resonances side by side (8 at a time, the last group padded) give scipy's numbers."""
    rng = np.random.default_rng(K)
    M = np.concatenate([np.repeat(rng.standard_normal(12), 300), np.zeros(3000)])  # decays into the flush
    f_0, d = np.exp(rng.uniform(np.log(2.0), np.log(1500.0), K)), rng.uniform(0.001, 0.5, K)
    _resonance._kernel.cache_clear()
    if _resonance._kernel() is None:
        pytest.skip("no C compiler")
    fast = zoh_responses(M, f_0, d, T_S)
    monkeypatch.setenv("TWOMASS_NO_C_KERNEL", "1")
    _resonance._kernel.cache_clear()
    ref = zoh_responses(M, f_0, d, T_S)
    _resonance._kernel.cache_clear()
    assert fast.shape == ref.shape == (K, M.size)
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


def test_no_oscillation_gives_zeros():
    M, bounds = _torque_steps(200)
    fit = fit_oscillation(M, np.zeros_like(M), bounds, T_S, f_guess=30.0)
    assert (fit.f_0, fit.gain, fit.r2) == (0.0, 0.0, 0.0)


def test_shape_mismatch_is_rejected():
    with pytest.raises(ValueError, match="one length"):
        fit_oscillation(np.zeros(10), np.zeros(11), np.array([[0, 10]]), T_S, 10.0)
