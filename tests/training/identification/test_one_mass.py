"""STEP 2 one-mass fit (training.identification._one_mass): exact one-mass data, the test run, and the EMPS benchmark."""

from __future__ import annotations

import numpy as np
import pytest

from test_sections import simulate_switching
from training.identification._one_mass import OneMassFit, _osc_pairs, _SectionDesign, fit_one_mass, speed_from_position
from training.identification._sections import detect_sections

EMPS_REF = {"J_sigma": 95.1089, "mu_F": 203.5034, "M_FC": 20.3935}


def _one_mass_exact(J=0.05, M_FC=0.3, mu_F=0.002, M_0=0.1, T_s=1e-3, n=6000):
    """Exact solution of J dw/dt = M - mu_F w - M_FC sign(w) - M_0 under piecewise-constant torque."""
    rng = np.random.default_rng(0)
    levels = rng.choice([-8.0, -5.0, 0.0, 5.0, 8.0], size=n // 300)
    M = np.repeat(levels, 300)
    w = np.zeros(n)
    v = 0.0
    for k in range(1, n):
        # zero-order hold over [k-1, k]: exact exponential while the sign stays (small T_s)
        s = np.sign(v) if v != 0 else np.sign(M[k - 1] - M_0)
        if v == 0 and abs(M[k - 1] - M_0) <= M_FC:
            v = 0.0
        else:
            a = mu_F / J
            u = (M[k - 1] - M_FC * s - M_0)
            v_new = v * np.exp(-a * T_s) + u / mu_F * (1 - np.exp(-a * T_s))
            v = 0.0 if v != 0 and np.sign(v_new) != np.sign(v) else v_new
        w[k] = v
    # torque sample k-1 acts over [k-1, k]; shift so sample k carries the mean torque of its interval
    return M, w


@pytest.mark.parametrize("method", ["integral", "trajectory", "derivative"])
def test_exact_one_mass_recovered(method):
    M, w = _one_mass_exact()
    Mc = np.concatenate([[M[0]], M[:-1]])  # torque applied during the interval ending at sample k
    fit = fit_one_mass(Mc, w, 1e-3, method=method)
    assert isinstance(fit, OneMassFit)
    tol = 0.03 if method == "derivative" else 0.01
    assert fit.J_sigma == pytest.approx(0.05, rel=tol)
    assert fit.M_FC == pytest.approx(0.3, abs=0.03)
    assert fit.M_0 == pytest.approx(0.1, abs=0.03)


@pytest.mark.parametrize("case", [
    dict(elastic=False, J_sigma=0.05, M_FC=0.3, mu_F=0.003),
    dict(J_sigma=0.03, V_J=2.0, f_e=40.0, M_FC=0.2, d=0.02),
    dict(J_sigma=0.1, V_J=0.3, f_e=300.0, M_FC=0.1, mu_F=0.004),
    dict(J_sigma=0.2, V_J=1.0, f_e=5.0, M_FC=0.0, mu_F=0.0),
])
def test_test_run_fit_and_w_osc(case):
    rec = simulate_switching(seed=2, **case)
    split = detect_sections(rec)
    fit = fit_one_mass(rec.current * rec.meta["K_M"], rec.speed, rec.meta["T_s"], sections=split)
    assert fit.J_sigma == pytest.approx(case["J_sigma"], rel=0.02)
    assert fit.M_FC == pytest.approx(case["M_FC"], abs=0.05)
    assert len(fit.sections) == 6
    assert fit.w_osc.shape == rec.speed.shape
    # w_osc is what w_bar leaves; for a rigid plant only quantization (~1 quantum) remains
    q_w = 2 * np.pi / (rec.meta["encoder_counts"] * rec.meta["T_s"])
    inside = split.labels() > 0
    inside &= split.labels() < 7
    assert np.allclose(fit.w_bar[inside] + fit.w_osc[inside], rec.speed[inside])
    if case.get("elastic", True) is False:
        assert max(s.osc_rms for s in fit.sections) < 2 * q_w


def test_w_osc_holds_the_elastic_oscillation():
    rec = simulate_switching(J_sigma=0.03, V_J=2.0, f_e=40.0, d=0.02, M_FC=0.2, seed=1)
    split = detect_sections(rec)
    fit = fit_one_mass(rec.current, rec.speed, rec.meta["T_s"], sections=split)
    a, b = split.bounds[0]
    seg = fit.w_osc[a:b]
    # paper eq. 1: amplitude V_J*M*/(J_sigma*w_0) after the step of M*
    w0 = 2 * np.pi * 40.0 / np.sqrt(1 - 0.02 ** 2)
    expected = 2.0 * 10.0 / (0.03 * w0)
    per = int(round(1 / (40.0 * rec.meta["T_s"])))
    assert 0.5 * np.ptp(seg[:per]) == pytest.approx(expected, rel=0.1)
    spec = np.abs(np.fft.rfft(seg - seg.mean()))
    f = np.fft.rfftfreq(seg.size, rec.meta["T_s"])
    assert abs(f[np.argmax(spec)] - 40.0) < 2.0 / (seg.size * rec.meta["T_s"]) + 1.0


def test_rejects_bad_input():
    with pytest.raises(ValueError, match="1-D"):
        fit_one_mass(np.zeros((3, 3)), np.zeros(9), 1e-3)
    with pytest.raises(ValueError, match="samples like torque"):
        fit_one_mass(np.zeros(100), np.zeros(99), 1e-3)
    with pytest.raises(ValueError, match="T_s"):
        fit_one_mass(np.zeros(100), np.arange(100.0), 0.0)
    with pytest.raises(ValueError, match="constant"):
        fit_one_mass(np.ones(100), np.ones(100), 1e-3)
    with pytest.raises(ValueError, match="speed or position"):
        fit_one_mass(np.ones(100), None, 1e-3)
    with pytest.raises(ValueError, match=r"method: expected 'auto' or one of \['derivative', 'integral', 'trajectory'\], "
                                         r"received 'magic'"):
        fit_one_mass(np.ones(100), np.arange(100.0), 1e-3, method="magic")
    with pytest.raises(ValueError, match="sections"):
        fit_one_mass(np.ones(100), np.arange(100.0), 1e-3, sections=[(50, 200)])


@pytest.fixture(scope="module")
def emps(shared_dir):
    from scipy.io import loadmat

    path = shared_dir / "data" / "emps" / "DATA_EMPS.mat"
    if not path.is_file():
        pytest.skip(f"EMPS data not found at {path}")
    d = loadmat(path)
    t = d["t"].ravel()
    force = (d["gtau"] * d["vir"]).ravel()
    return force, d["qm"].ravel(), float(t[1] - t[0])


@pytest.mark.parametrize("method", ["integral", "derivative"])
def test_emps_reference_within_3_percent(emps, method):
    force, qm, T_s = emps
    fit = fit_one_mass(force, None, T_s, position=qm, method=method, offset=True)
    got = {"J_sigma": fit.J_sigma, "mu_F": fit.mu_F, "M_FC": fit.M_FC}
    for key, ref in EMPS_REF.items():
        assert got[key] == pytest.approx(ref, rel=0.03), (key, got[key], ref)
    assert fit.M_0 == pytest.approx(-3.1648, rel=0.1)


def test_emps_speed_from_position_matches(emps):
    force, qm, T_s = emps
    v = speed_from_position(qm, T_s)
    fit = fit_one_mass(force, v, T_s)
    assert fit.J_sigma == pytest.approx(EMPS_REF["J_sigma"], rel=0.03)


def _sim_api():
    """The ``sim`` package's test-run API (package exports, else its modules), or skip while absent."""
    import types

    sim = pytest.importorskip("sim")
    names = ("simulate_test", "TwoMassParams", "DriveConfig", "TestSignalConfig")
    if all(hasattr(sim, n) for n in names):
        return sim
    try:  # sim is built in parallel; its modules may exist before the package exports them
        from sim.params import DriveConfig, TwoMassParams
        from sim.plant import simulate_test
        from sim._signal import TestSignalConfig
    except ImportError as exc:
        pytest.skip(f"sim lacks the test-run API yet ({exc})")
    return types.SimpleNamespace(simulate_test=simulate_test, TwoMassParams=TwoMassParams,
                                 DriveConfig=DriveConfig, TestSignalConfig=TestSignalConfig)


def test_integration_with_sim_simulate_test():
    """sim.simulate_test -> sections (vs the true column) -> one-mass fit -> eigenfrequency bin."""
    import torch

    from training.identification._features import EIG_EDGES, eigenfrequency_features

    sim = _sim_api()
    truth = {"J_sigma": [0.05, 0.03, 0.1], "V_J": [1.0, 2.0, 0.5], "f_e": [300.0, 40.0, 20.0],
             "d": [0.05, 0.02, 0.03], "backlash": [0.0, 0.0, 0.0], "M_FC": [0.3, 0.2, 0.1],
             "mu_F": [0.002, 0.001, 0.004]}
    params = sim.TwoMassParams(**{k: torch.tensor(v, dtype=torch.float64) for k, v in truth.items()})
    drive, signal = sim.DriveConfig(), sim.TestSignalConfig()
    resp = sim.simulate_test(params, drive, signal, seed=0)
    for i in range(3):
        L = int(resp.length[i])
        speed = resp.speed[i, :L].double().numpy()
        current = resp.current[i, :L].double().numpy()
        section = resp.section[i, :L].numpy()
        split = detect_sections(speed=speed, torque=current * drive.K_M, T_s=drive.T_s, T_Ei=drive.T_Ei)
        true = np.array([[np.flatnonzero(section == k)[0], np.flatnonzero(section == k)[-1] + 1] for k in range(1, 7)])
        assert np.abs(split.bounds - true).max() <= 2, (i, split.bounds, true)
        ref = detect_sections(speed=speed, torque=current, T_s=drive.T_s,
                              torque_ref=resp.torque_ref[i, :L].double().numpy())
        assert np.array_equal(ref.bounds, true)
        fit = fit_one_mass(current * drive.K_M, speed, drive.T_s, sections=split)
        assert fit.J_sigma == pytest.approx(truth["J_sigma"][i], rel=0.03)
        assert fit.M_FC == pytest.approx(truth["M_FC"][i], abs=0.05)
        if truth["f_e"][i] <= 100.0:  # clearly elastic (w_e*T_Ei < 1, r_osc >> 1)
            k = int(eigenfrequency_features(fit.w_osc, drive.T_s, split)[25])
            kt = int(np.searchsorted(EIG_EDGES, truth["f_e"][i]) - 1)
            assert abs(k - kt) <= 1, (i, k, kt)


def test_integration_with_sim_records(tmp_path):
    """sim records (CSV round trip, section and torque_ref columns dropped) -> sections -> fit."""
    import torch

    sim = _sim_api()
    if not all(hasattr(sim, n) for n in ("Record", "responses_to_records", "write_record", "read_record")):
        pytest.skip("sim lacks the record API yet")
    truth = {"J_sigma": [0.04], "V_J": [1.5], "f_e": [30.0], "d": [0.03], "backlash": [0.0], "M_FC": [0.25],
             "mu_F": [0.002]}
    params = sim.TwoMassParams(**{k: torch.tensor(v, dtype=torch.float64) for k, v in truth.items()})
    drive, signal = sim.DriveConfig(), sim.TestSignalConfig()
    resp = sim.simulate_test(params, drive, signal, seed=1)
    rec = sim.responses_to_records(resp, params, drive, signal)[0]
    bare = sim.Record(t=rec.t, speed=rec.speed, meta=dict(rec.meta), current=rec.current)
    path = tmp_path / "run.csv"
    sim.write_record(path, bare)
    back = sim.read_record(path)
    split = detect_sections(back)
    true = np.array([[np.flatnonzero(rec.section == k)[0], np.flatnonzero(rec.section == k)[-1] + 1]
                     for k in range(1, 7)])
    assert np.abs(split.bounds - true).max() <= 2
    torque = back.current * back.meta["K_M"] if back.torque is None else back.torque
    fit = fit_one_mass(torque, back.speed, float(back.meta["T_s"]), sections=split)
    assert fit.J_sigma == pytest.approx(0.04, rel=0.03)
    assert fit.M_FC == pytest.approx(0.25, abs=0.05)
    assert not fit.warnings


def test_section_design_equals_its_dense_matrix() -> None:
    """The trajectory fit's structured Gram matrix and products equal those of the dense regressor
    matrix built independently (dense columns, a 0/1 column per section, a sin/cos pair per section)."""
    rng = np.random.default_rng(0)
    bounds = [(0, 50), (60, 130), (130, 171)]
    lengths = np.array([b - a for a, b in bounds])
    n, K = int(lengths.sum()), len(bounds)
    D, y, O = rng.standard_normal((n, 4)), rng.standard_normal(n), _osc_pairs(bounds, 1e-3, 37.0, (0.05,))[0]
    E, Oc = np.zeros((n, K)), np.zeros((n, 2 * K))
    for k, (a, L) in enumerate(zip(np.cumsum(lengths) - lengths, lengths)):
        E[a:a + L, k] = 1.0
        Oc[a:a + L, 2 * k:2 * k + 2] = O[a:a + L]
    for design, X in ((_SectionDesign(D, lengths), np.hstack([D, E])),
                      (_SectionDesign(D, lengths, O), np.hstack([D, E, Oc]))):
        theta = rng.standard_normal(X.shape[1])
        np.testing.assert_allclose(design.gram(), X.T @ X, rtol=0, atol=1e-12)
        np.testing.assert_allclose(design.rmatvec(y), X.T @ y, rtol=0, atol=1e-12)
        np.testing.assert_allclose(design.matvec(theta), X @ theta, rtol=0, atol=1e-12)
