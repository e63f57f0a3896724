"""Systems over SPEC 3.1's drive envelope (issue 11): the sampler of drives, test runs and mechanics."""

import math

import pytest
import torch

from sim import EnvelopeRanges, PopulationRanges, sample_envelope, sample_population
from training.identification import SPEC_ENVELOPE


def test_the_reference_population_is_unchanged():
    """``sample_population`` draws what it drew before the envelope sampler existed (seed 1)."""
    p = sample_population(3, 1)
    assert p.J_sigma.tolist() == pytest.approx([0.0120069, 0.0195953, 0.0201730], rel=1e-5)
    assert torch.equal(sample_population(3, 1, PopulationRanges()).f_e, p.f_e)


def test_envelope_draws_stay_inside_spec_3_1():
    r = EnvelopeRanges(cell=4)
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
