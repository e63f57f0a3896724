"""Training data over SPEC 3.1's drive envelope (issue 11): the sampler of drives, test runs and
mechanics, the dataset's drive columns, and the maps' stored envelope."""

import math

import numpy as np
import pytest
import torch

from sim import DriveConfig, EnvelopeRanges, PopulationRanges, TestSignalConfig, sample_envelope, sample_population
from training.identification import SPEC_ENVELOPE, TARGETS, Envelope, trained_envelope
from training.learning import GenerateConfig, generate, load_dataset


def test_the_reference_population_is_unchanged():
    """``sample_population`` draws what it drew before the envelope sampler existed (seed 1)."""
    p = sample_population(3, 1)
    assert p.J_sigma.tolist() == pytest.approx([0.0120069, 0.0195953, 0.0201730], rel=1e-5)
    assert torch.equal(sample_population(3, 1, PopulationRanges()).f_e, p.f_e)


def test_envelope_draws_stay_inside_spec_3_1():
    r = EnvelopeRanges(cell=4, reference_share=0.0)
    s = sample_envelope(400, 2, r)
    assert len(s.cases) == 100 and s.cell.tolist()[:9] == [0, 0, 0, 0, 1, 1, 1, 1, 2]
    M_star = torch.tensor([c[1].M_star for c in s.cases], dtype=torch.float64)[s.cell]
    w_max = torch.tensor([c[1].w_max for c in s.cases], dtype=torch.float64)[s.cell]
    tau = s.params.J_sigma * w_max / M_star
    assert tau.min() >= 0.02 * (1 - 1e-9) and tau.max() <= 5.0 * (1 + 1e-9)
    assert float((s.params.M_FC / M_star).max()) <= 0.05
    for drive, signal in s.cases:
        assert SPEC_ENVELOPE["T_s"][0] <= drive.T_s <= SPEC_ENVELOPE["T_s"][1]
        assert SPEC_ENVELOPE["T_Ei"][0] <= drive.T_Ei <= SPEC_ENVELOPE["T_Ei"][1]
        assert 12 <= math.log2(drive.encoder_counts) <= 24 and math.log2(drive.encoder_counts).is_integer()
        assert 1.5 <= drive.M_max / drive.M_N <= 4.0 and signal.M_star <= drive.M_max
        assert 0.1 <= drive.M_N <= 1000.0 and drive.current_noise_std / signal.M_star <= 0.05
    bits = {int(math.log2(d.encoder_counts)) for d, _ in s.cases}
    assert {12, 24} <= bits  # both ends drawn
    assert torch.equal(sample_envelope(400, 2, r).params.f_e, s.params.f_e)
    with pytest.raises(ValueError, match="cell"):
        EnvelopeRanges(cell=0)


def test_a_share_of_the_cells_runs_the_reference_drive_and_test():
    r = EnvelopeRanges(cell=2, reference_share=0.5)
    s = sample_envelope(800, 5, r)
    on_ref = torch.tensor([drive == DriveConfig() and signal == TestSignalConfig() for drive, signal in s.cases])
    assert 0.4 < float(on_ref.float().mean()) < 0.6
    tau = s.params.J_sigma * torch.tensor([sig.w_max / sig.M_star for _, sig in s.cases], dtype=torch.float64)[s.cell]
    ref = on_ref[s.cell]
    assert float(tau[ref].min()) >= 0.1 * (1 - 1e-9) and float(tau[ref].max()) <= 2.0 * (1 + 1e-9)
    assert float(tau[~ref].min()) < 0.1  # the others span the envelope's time scales
    # without reference cells, the other draws are the same as with them
    none = sample_envelope(800, 5, EnvelopeRanges(cell=2, reference_share=0.0))
    assert torch.equal(none.params.f_e, s.params.f_e) and not any(d == DriveConfig() for d, _ in none.cases)
    with pytest.raises(ValueError, match="reference_share"):
        EnvelopeRanges(reference_share=1.5)


def test_an_envelope_dataset_stores_each_systems_drive(tmp_path):
    config = GenerateConfig(n=6, seed=4, shard_size=4,
                            envelope=EnvelopeRanges(cell=3, time_scale=(0.02, 0.05), reference_share=0.0))
    ds = load_dataset(generate(tmp_path / "ds", config, workers=1))
    sample = sample_envelope(6, 4, config.envelope)
    for i in range(6):
        drive, signal = sample.cases[int(sample.cell[i])]
        assert ds.truth["M_star"][i] == pytest.approx(signal.M_star)
        assert ds.truth["T_s"][i] == pytest.approx(drive.T_s) and ds.truth["M_N"][i] == pytest.approx(drive.M_N)
        assert ds.truth["w_e_T_Ei"][i] == pytest.approx(ds.truth["w_e"][i] * drive.T_Ei)
    assert ds.ok.all()
    # the backlash target is the gap's torque over the test's M*: the same for any M_N
    s_star = TARGETS["log10_s_star"](ds.truth, ds.features)
    expect = np.log10(np.maximum(ds.truth["s_N"] * ds.truth["M_N"] / ds.truth["M_star"], 1e-4))
    np.testing.assert_allclose(s_star, expect)
    # the trained ranges a map's metadata gives (the maps of such data carry dataset.envelope)
    env = trained_envelope({"dataset": {"envelope": ds.config["envelope"]}})
    assert env.trained["T_s"] == (62.5e-6, 1e-3) and env.trained["encoder_counts"] == (2.0**12, 2.0**24)
    assert env.trained["time_scale"] == (0.02, 0.05)
    assert Envelope.from_dict(env.to_dict()) == env


def test_generate_says_why_the_analysis_rejected_a_system(tmp_path, capsys):
    """A motor that cannot break away (Coulomb friction above M*) gives no test run: the summary names
    the reason; the reasons live beside the shards, outside their sha256."""
    from training.commands import generate as command
    from training.learning import GenerateConfig, generate, load_dataset, rejection_reasons

    config = GenerateConfig(n=2, seed=3, shard_size=2, ranges=PopulationRanges(M_FC=(20.0, 30.0)))
    generate(tmp_path / "stuck", config, workers=1)
    reasons = rejection_reasons(tmp_path / "stuck")
    assert sorted(reasons) == [0, 1] and all(reasons.values())
    dataset = load_dataset(tmp_path / "stuck")
    assert not dataset.ok.any()
    (tmp_path / "stuck" / "shard_00000.rejected.json").unlink()
    assert load_dataset(tmp_path / "stuck").sha256 == dataset.sha256 and rejection_reasons(tmp_path / "stuck") == {}
    lines = command.summary(tmp_path / "stuck")
    assert "2 systems, 0 analysed, 2 rejected" in lines[0] and len(lines) == 1  # the reasons' file was removed
    generate(tmp_path / "more", GenerateConfig(n=5, seed=3, shard_size=5, ranges=PopulationRanges(M_FC=(20.0, 30.0))),
             workers=1)
    lines = command.summary(tmp_path / "more")
    assert lines[1] == f"  rejected system 0: {rejection_reasons(tmp_path / 'more')[0]}"
    assert len(lines) == 5 and lines[4].startswith("  ... 2 more in")
