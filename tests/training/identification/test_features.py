"""Features of w_osc (training.identification._features): synthetic signals with known content, properties, a test run."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.signal import sawtooth

from test_sections import simulate_switching
from training.identification._features import (
    EIG_EDGES, EIG_NAMES, EXTRA_NAMES, STRUCT_NAMES, dominant_frequency, eigenfrequency_features,
    extra_features, structure_and_peaks, structure_features, zero_crossing_frequency,
)
from training.identification._one_mass import fit_one_mass
from training.identification._sections import detect_sections

T_S = 2.5e-4
BOUNDS = [(0, 1300), (1300, 2500), (2500, 4000), (4000, 5200), (5200, 6500), (6500, 8000)]


def _t(n=8000):
    return np.arange(n) * T_S


@pytest.mark.parametrize("f", [6.0, 12.0, 25.0, 40.0, 80.0, 150.0, 300.0, 480.0])
def test_sinusoid_peak_lands_in_its_bin(f):
    x = np.sin(2 * np.pi * f * _t() + 0.3)
    feat = eigenfrequency_features(x, T_S, BOUNDS)
    assert feat.shape == (26,)
    k = int(feat[25])
    # the bin of f, or a neighbour when f is within 5 % of an edge
    kt = int(np.searchsorted(EIG_EDGES, f) - 1)
    near_edge = min(abs(np.log(f / EIG_EDGES[kt])), abs(np.log(f / EIG_EDGES[kt + 1]))) < 0.05
    assert k == kt or (near_edge and abs(k - kt) == 1), (f, k, kt)
    assert 0 <= feat[:25].min() and feat[:25].max() > 0


def test_structure_of_sinusoid_and_triangle():
    for f in (9.0, 37.0, 120.0):
        s = structure_features(np.sin(2 * np.pi * f * _t()), T_S, BOUNDS)
        assert s.shape == (8,)
        assert s[0] == pytest.approx(1.0, abs=0.01)
        assert np.all(s[1:] < 0.02)
    tri = sawtooth(2 * np.pi * 37.0 * _t(), 0.5)
    s = structure_features(tri, T_S, BOUNDS)
    norm = np.sqrt(np.pi ** 4 / 96)  # energy of the triangle's odd harmonics 1/n^2
    assert s[0] == pytest.approx(1 / norm, abs=0.01)
    assert s[2] / s[0] == pytest.approx(1 / 9, rel=0.05)
    assert s[4] / s[0] == pytest.approx(1 / 25, rel=0.1)
    assert np.all(s[[1, 3, 5, 7]] < 0.01)


def test_frequency_estimators():
    x = np.sin(2 * np.pi * 53.0 * _t(4000)) + 0.05 * np.random.default_rng(0).standard_normal(4000)
    assert dominant_frequency(x, T_S) == pytest.approx(53.0, rel=0.01)
    assert zero_crossing_frequency(x, T_S) == pytest.approx(53.0, rel=0.02)
    assert dominant_frequency(np.zeros(100), T_S) == 0.0
    assert zero_crossing_frequency(np.ones(100), T_S) == 0.0


def test_amplitude_invariance():
    x = np.sin(2 * np.pi * 30 * _t()) * np.exp(-_t()) + 0.2 * np.sin(2 * np.pi * 90 * _t())
    for fn in (eigenfrequency_features, structure_features):
        a, b = fn(x, T_S, BOUNDS), fn(1e-3 * x, T_S, BOUNDS)
        assert np.allclose(a, b, atol=1e-9)


def test_component_names_match_the_feature_sizes():
    x = np.sin(2 * np.pi * 30 * _t())
    for fn, names in ((eigenfrequency_features, EIG_NAMES), (structure_features, STRUCT_NAMES),
                      (extra_features, EXTRA_NAMES)):
        assert fn(x, T_S, BOUNDS).shape == (len(names),)


def test_bad_input():
    with pytest.raises(ValueError, match="1-D"):
        eigenfrequency_features(np.zeros((2, 5)), T_S)
    with pytest.raises(ValueError, match="finite"):
        structure_features(np.array([0.0, np.nan, 1.0]), T_S)
    with pytest.raises(ValueError, match="T_s"):
        eigenfrequency_features(np.zeros(10), 0.0)


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(x=arrays(np.float64, st.integers(0, 600), elements=finite), k=st.integers(1, 6),
       scale=st.floats(min_value=1e-3, max_value=1e3))
def test_properties_finite_shape_scaling(x, k, scale):
    n = x.size
    edges = np.linspace(0, n, k + 1).astype(int)
    bounds = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a] or None
    if n == 0:
        bounds = None
    e = eigenfrequency_features(x, T_S, bounds)
    s = structure_features(x, T_S, bounds)
    z = extra_features(x, T_S, bounds, J_sigma=0.1, torque_steps=np.ones(k), speed_span=10.0)
    assert e.shape == (26,) and s.shape == (8,) and z.shape == (len(EXTRA_NAMES),)
    assert np.all(np.isfinite(e)) and np.all(np.isfinite(s)) and np.all(np.isfinite(z))
    assert np.all(e[:25] >= 0) and 0 <= e[25] <= 24
    assert np.all((s >= 0) & (s <= 1 + 1e-9))
    if n > 0:
        e2 = eigenfrequency_features(scale * x, T_S, bounds)
        s2 = structure_features(scale * x, T_S, bounds)
        assert np.allclose(e2[:25], e[:25], rtol=1e-6, atol=1e-6)
        assert np.allclose(s2, s, rtol=1e-6, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(x=arrays(np.float64, st.integers(0, 600), elements=finite), k=st.integers(1, 7),
       f=st.floats(min_value=5.0, max_value=1500.0))
def test_shared_peaks_give_the_same_features_bit_for_bit(x, k, f):
    # structure_and_peaks' section peaks, handed to extra_features, are exactly what it would find
    # itself: sections of any length (also below 8 samples), noise plus a sinusoid, constant runs
    x = x + 1e3 * np.sin(2 * np.pi * f * np.arange(x.size) * T_S)
    x[: x.size // 5] = 7.0
    edges = np.linspace(0, x.size, k + 1).astype(int)
    bounds = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a] or None
    if x.size == 0:
        bounds = None
    struct, peaks = structure_and_peaks(x, T_S, bounds)
    assert np.array_equal(struct, structure_features(x, T_S, bounds))
    opts = dict(J_sigma=0.1, torque_steps=np.ones(k), speed_span=10.0, structure=struct)
    assert np.array_equal(extra_features(x, T_S, bounds, peaks=peaks, **opts), extra_features(x, T_S, bounds, **opts))


@given(c=finite, n=st.integers(0, 300))
@settings(max_examples=30, deadline=None)
def test_constant_signals_give_zeros(c, n):
    x = np.full(n, c)
    assert not eigenfrequency_features(x, T_S).any()
    assert not structure_features(x, T_S).any()
    assert np.all(np.isfinite(extra_features(x, T_S)))


def test_test_run_eigenfrequency_bin_and_extras():
    f_e = 40.0
    rec = simulate_switching(J_sigma=0.03, V_J=2.0, f_e=f_e, d=0.02, M_FC=0.2, seed=1)
    split = detect_sections(rec)
    fit = fit_one_mass(rec.current, rec.speed, rec.meta["T_s"], sections=split)
    e = eigenfrequency_features(fit.w_osc, rec.meta["T_s"], split)
    k = int(e[25])
    assert EIG_EDGES[k] <= f_e <= EIG_EDGES[k + 1] or abs(np.searchsorted(EIG_EDGES, f_e) - 1 - k) <= 1
    s = structure_features(fit.w_osc, rec.meta["T_s"], split)
    assert s[0] > 0.8
    steps = np.diff(np.concatenate([[0.0], np.array([1, 0, -0.7, -1, 0, 0.7]) * 10.0]))
    z = extra_features(fit.w_osc, rec.meta["T_s"], split, J_sigma=fit.J_sigma, torque_steps=steps,
                       speed_span=float(np.ptp(rec.speed)), structure=s)
    assert 10 ** z[0] == pytest.approx(f_e, rel=0.05)
    assert 10 ** z[1] == pytest.approx(f_e, rel=0.05)
    assert 10 ** z[2] == pytest.approx(2.0, rel=0.25)  # V_J from the eq.-1 amplitude
    assert abs(z[5]) < 0.1 and abs(z[6]) < 0.1  # no backlash: frequency independent of torque


def test_backlash_raises_harmonics_and_shifts_frequency():
    kw = dict(J_sigma=0.03, V_J=2.0, f_e=40.0, d=0.02, M_FC=0.2, seed=1)
    out = []
    for bl in (0.0, 0.5):
        rec = simulate_switching(backlash_deg=bl, **kw)
        split = detect_sections(rec)
        fit = fit_one_mass(rec.current, rec.speed, rec.meta["T_s"], sections=split)
        out.append(extra_features(fit.w_osc, rec.meta["T_s"], split))
    assert out[1][4] > out[0][4]  # more harmonic content with backlash
