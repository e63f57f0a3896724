"""A stiff answer says which mode its record still shows, and why it leaves it out."""

from __future__ import annotations

import pytest

from sim import TwoMassParams, iter_records
from training.identification import Identifier


@pytest.fixture(scope="module")
def answers():
    """A 450 Hz shaft on the reference drive (w_e T_Ei 1.4: stiff by the class rule, yet visible in the
    speed) and a 30 Hz elastic one."""
    plants = TwoMassParams.from_dicts([
        dict(J_sigma=0.015, V_J=1.6, f_e=450.0, d=0.036, backlash=0.0, M_FC=0.16, mu_F=0.0005),
        dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash=0.0, M_FC=0.2, mu_F=0.001)])
    records = sorted(iter_records(plants, seed=1), key=lambda r: r.name)
    ident = Identifier.load()
    return [ident.identify(r) for r in records]


def test_a_stiff_answer_names_the_mode_above_the_current_loop(answers):
    stiff = answers[0]
    assert stiff.structure == "stiff"
    assert stiff.quality.stiff_mode_Hz == pytest.approx(450.0, rel=0.02)
    assert stiff.quality.stiff_mode_note.startswith("a mode near 45")
    assert "above the current loop's bandwidth" in stiff.quality.stiff_mode_note
    assert "stiff_mode_Hz" in stiff.to_dict()["quality"]


def test_an_elastic_answer_has_no_stiff_mode(answers):
    elastic = answers[1]
    assert elastic.structure == "elastic"
    assert elastic.quality.stiff_mode_Hz is None and "stiff_mode_Hz" not in elastic.to_dict()["quality"]
