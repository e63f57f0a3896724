"""The self-commissioning chain end to end: stiff and elastic plants, refusal, limits, command."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.cli import main  # noqa: E402
from training.commissioning import (REFUSAL_RULES, CommissioningConfig, ExcitationLimits, commission,  # noqa: E402
                                    summarize, summary_text)

DRIVE = sim.DriveConfig()
FAST = CommissioningConfig(tune_evaluations=8, max_samples=600)
LIMITS = ExcitationLimits(w_limit=100.0, travel_limit=100.0)
STIFF = dict(J_sigma=0.05, V_J=0.5, f_e=400.0, d=0.05, backlash=0.0, M_FC=0.1, mu_F=0.001)
ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


def _plant(params):
    return sim.TwoMassParams.from_dicts(params)


def _shipped_identifier():
    """The shipped maps; skip (with the reason) while they do not match the toolkit's features
    (between a feature change and the retraining of the maps)."""
    from som_torch import CheckpointError
    from training.identification import Identifier

    try:
        return Identifier.load()
    except CheckpointError as err:
        pytest.skip(f"shipped maps not loadable: {err}")


def _check_accepted(rep):
    assert rep.permission.allowed, rep.permission.reason
    assert rep.proposal is not None and rep.tuning is not None
    assert rep.plant_costs["tuned"] <= rep.plant_costs["proposal"]
    assert rep.checks["stable"] and rep.checks["within_limits"] and rep.checks["tuned_not_worse"]
    assert rep.figures["after"]["settling_time"] < math.inf
    json.dumps(rep.to_dict())  # JSON-able
    text = rep.to_text()
    for part in ("1 test signal", "2 identification", "3 validation", "5 proposal", "6 tuned", "before", "after"):
        assert part in text


def test_chain_on_a_stiff_plant(stub):
    """One-mass identification (no V_J, f_e): validation uses the one-mass stand-in, then the
    symmetric optimum, tuning and the final choice on the (slightly elastic) plant."""
    ident = stub("stiff", {"J_sigma": 0.05, "M_FC": 0.1, "mu_F": 0.001, "V_J": None, "f_e": None, "d": None, "backlash": 0.0})
    rep = commission(_plant(STIFF), DRIVE, LIMITS, identifier=ident, config=FAST)
    assert rep.validation.passed and rep.validation.nrmse < 0.05
    assert rep.proposal.structure == "stiff" and any(r.startswith("R2") for r in rep.proposal.rules)
    _check_accepted(rep)


def test_chain_with_the_shipped_maps_accepts_soundly_or_refuses_with_a_reason():
    """The real identifier (provisional maps): no truth reaches it; the outcome is either a
    refusal that names its rule or an accepted, stable, not-worse tuned loop."""
    ident = _shipped_identifier()
    seen, seen_results = [], []
    real = ident.identify
    ident.identify = lambda record: (seen.append(record), seen_results.append(real(record)), seen_results[-1])[2]
    rep = commission(_plant(STIFF), DRIVE, LIMITS, identifier=ident, config=replace(FAST, seed=1))
    assert seen and "truth" not in seen[0].meta and "truth" not in rep.record.meta
    assert rep.identification is seen_results[0]  # kept as the identifier answered it
    assert rep.identification.parameters.J_sigma == pytest.approx(STIFF["J_sigma"], rel=0.05)
    assert rep.checks["within_limits"]
    if rep.refused:
        assert rep.permission.rule in REFUSAL_RULES and rep.permission.reason.startswith(rep.permission.rule)
    else:
        _check_accepted(rep)


def test_chain_on_an_elastic_plant_with_exact_identification(stub):
    """An identifier that knows the plant: validation passes, the elastic rules and the tuning run."""
    ident = stub("elastic", ELASTIC)
    rep = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=ident, config=FAST)
    assert ident.records and "truth" not in ident.records[0].meta
    assert rep.validation.nrmse < 0.01 and rep.validation.osc_nrmse is not None and rep.validation.osc_nrmse < 0.1
    assert any(r.startswith("R3") for r in rep.proposal.rules)
    _check_accepted(rep)


def test_wrong_identification_is_refused_with_the_reason(stub):
    """Deliberately wrong parameters (f_e x 3, J_sigma x 1.5): validation fails, nothing is proposed
    (without the fallback); the JSON report writes inf as null."""
    ident = stub("elastic", ELASTIC, f_e=3.0, J_sigma=1.5)
    rep = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=ident, config=replace(FAST, fallback_evaluations=0))
    assert not rep.validation.passed
    assert rep.refused and rep.permission.rule == "V3" and rep.validation.reason in rep.permission.reason
    assert rep.proposal is None and rep.tuning is None and rep.controller is None and rep.improvement is None
    assert "REFUSED" in rep.to_text() and rep.permission.reason in rep.to_text()
    d = rep.to_dict()
    assert d["permission"]["allowed"] is False and d["permission"]["rule"] == "V3" and d["proposal"] is None
    d = replace(rep, checks={**rep.checks, "peak_speed": math.inf}, timings={"total": -math.inf}).to_dict()
    assert d["checks"]["peak_speed"] is None and d["timings"]["total"] is None
    json.dumps(d, allow_nan=False)


def test_refusal_ends_with_the_cautious_fallback_tuned_on_the_plant(stub):
    """The same wrong identification with the fallback F1: a PI on J_sigma alone, searched on the
    plant, ends with a stable loop that is not worse than its start; the refusal is still reported."""
    ident = stub("elastic", ELASTIC, f_e=3.0, J_sigma=1.5)
    rep = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=ident, config=replace(FAST, fallback_evaluations=8))
    assert rep.refused and rep.permission.rule == "V3" and rep.fallback
    assert any(r.startswith("F1") for r in rep.proposal.rules)
    assert rep.proposal.Kp == pytest.approx(1.5 * ELASTIC["J_sigma"] * 3.0)  # J_sigma as identified, w_c 3 rad/s
    assert rep.controller is not None and rep.tuning.n_evaluations <= 8 + 1  # scipy counts the start too
    assert rep.checks["stable"] and rep.checks["tuned_not_worse"] and rep.checks["within_limits"]
    text = rep.to_text()
    assert "REFUSED" in text and "5 fallback F1" in text and "evaluations on the plant" in text
    assert rep.to_dict()["fallback"] is True
    with pytest.raises(ValueError, match="fallback_evaluations"):
        replace(FAST, fallback_evaluations=-1)
    with pytest.raises(ValueError, match="validation_mode"):
        replace(FAST, validation_mode="guess")


def test_identifier_error_is_refused_by_V1():
    """An error the identifier raises ends the chain with rule V1 (no fallback: no J_sigma)."""
    class Failing:
        def identify(self, record):
            raise ValueError("no test run found\nsecond line")

    rep = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=Failing(), config=FAST)
    assert rep.permission.rule == "V1" and rep.validation is None and rep.controller is None
    assert not rep.identification.ok and rep.identified_structure is None and rep.outside_training is None
    assert "2 identification failed: no test run found" in rep.to_text()
    assert rep.to_dict()["identification"] == {"error": "no test run found"}
    summary = summarize([rep, rep], 1.0)  # refusals counted by rule code
    assert summary["refused_by_rule"] == {"V1": 2} and summary["structure_correct"] == 0
    assert "(V1 2)" in summary_text(summary)


def test_outside_training_is_refused(stub):
    """V4 with the commissioning's bound on the map distances; its reading is its own field, the
    identifier's ``quality.outside_training`` keeps its meaning."""
    ident = stub("elastic", ELASTIC, outside_training=True, ratios={"f_e": 4.0})
    rep = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=ident, config=replace(FAST, fallback_evaluations=0))
    assert rep.refused and rep.permission.rule == "V4" and "f_e 4.00" in rep.permission.reason
    assert rep.outside_training is True and rep.to_dict()["assessment"]["outside_training"] is True
    # the default bound is 3 x the training 99 % quantile; a looser one lets the same result through
    rep2 = commission(_plant(ELASTIC), DRIVE, LIMITS, identifier=ident,
                      config=replace(FAST, max_map_distance_ratio=5.0, tune=False))
    assert rep2.permission.allowed and rep2.tuning is None and rep2.plant_costs["tuned"] == rep2.plant_costs["proposal"]
    assert rep2.outside_training is False and rep2.identification.quality.outside_training is True
    assert "validation_error" not in rep2.to_dict()["identification"]["quality"]


@pytest.mark.parametrize("limits", [ExcitationLimits(w_limit=6.0, travel_limit=1.5, M_star_max=5.0),
                                    ExcitationLimits(w_limit=40.0, travel_limit=4.0)])
def test_limits_never_exceeded_over_the_chain(limits, stub, monkeypatch):
    plant = dict(J_sigma=0.2, V_J=2.0, f_e=15.0, d=0.02, backlash=0.001, M_FC=0.3, mu_F=0.0)
    runs = []
    import training.commissioning._chain as cm

    inner = cm.sim_test_runner

    def recording(params, drive, seed=0):
        run = inner(params, drive, seed=seed)

        def wrapped(signal):
            resp = run(signal)
            runs.append((signal, resp))
            return resp

        return wrapped

    monkeypatch.setattr(cm, "sim_test_runner", recording)
    rep = commission(_plant(plant), DRIVE, limits, identifier=stub("elastic_backlash", plant), config=replace(FAST, tune=False))
    M_cap = min(DRIVE.M_max, limits.M_star_max or math.inf)
    assert len(runs) == len(rep.excitation.log) >= 2
    for signal, resp in runs:
        n = int(resp.length.reshape(-1)[0])
        w = resp.speed.reshape(-1)[:n].double().numpy()
        assert signal.M_star <= M_cap + 1e-12
        assert np.abs(resp.torque_ref.reshape(-1)[:n].double().numpy()).max() <= M_cap + 1e-6
        assert np.abs(w).max() <= limits.w_limit
        assert np.abs(np.cumsum(w) * DRIVE.T_s).max() <= limits.travel_limit
    assert rep.checks["within_limits"]


def test_command_reports_and_rejects_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["commission", "--params", str(bad)]) == 2
    assert "invalid JSON" in capsys.readouterr().err
    good = tmp_path / "plant.json"
    good.write_text(json.dumps({**STIFF, "name": "stiff1"}))
    assert main(["commission", "--params", str(good), "--w-limit", "0"]) == 2
    err = capsys.readouterr().err
    assert "--w-limit" in err and len(err.strip().splitlines()) == 1
    for change, words in (({"J_sigmaa": 1.0}, "unknown keys"), ({"d": 1.5}, "TwoMassParams.d")):
        wrong = tmp_path / "wrong.json"
        wrong.write_text(json.dumps({**STIFF, **change}))
        assert main(["commission", "--params", str(wrong)]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1
    _shipped_identifier()
    out_json = tmp_path / "out.json"
    out_json.write_text("keep me")
    assert main(["commission", "--params", str(good), "--no-tune", "--no-progress", "--json", str(out_json)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err and out_json.read_text() == "keep me"
    assert main(["commission", "--params", str(good), "--no-tune", "--no-progress", "--json", str(out_json),
                 "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert "== commissioning stiff1 ==" in out and "1 test signal" in out
    data = json.loads(out_json.read_text())
    assert data["reports"][0]["name"] == "stiff1" and data["summary"] is None
    assert list(tmp_path.glob(".out.json.*")) == []  # no temporary file left


def test_spectral_oscillation_check_tolerates_small_and_flags_large_frequency_errors():
    """The chain's oscillation check (osc_metric="spectrum") is phase-insensitive: 3 % f_e error
    passes where the sample-by-sample error is larger; f_e x 2 and f_e / 2 fail."""
    from training.commissioning import validate_model

    plant = _plant(ELASTIC)
    sig = sim.TestSignalConfig(M_star=10.0, w_max=50.0)
    rec = sim.responses_to_records(sim.simulate_test(plant, DRIVE, sig, seed=3), plant.reshape(1), DRIVE, sig)[0]

    def err(metric, **change):
        p = {**ELASTIC, **change}
        return validate_model(p, DRIVE, rec, mode="switching", osc_metric=metric).osc_nrmse

    assert err("spectrum") < 0.05
    assert err("spectrum", f_e=ELASTIC["f_e"] * 1.03) < 0.5
    assert err("spectrum", f_e=ELASTIC["f_e"] * 2) > 0.5
    assert err("spectrum", f_e=ELASTIC["f_e"] / 2) > 0.5
    assert err("time", f_e=ELASTIC["f_e"] * 1.03) > err("spectrum", f_e=ELASTIC["f_e"] * 1.03)
    with pytest.raises(ValueError):
        validate_model(ELASTIC, DRIVE, rec, osc_metric="wavelet")
