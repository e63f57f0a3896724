"""``twomass bench commission``: the oracle against independent references, the limit-cycle criterion,
the summary against hand-counted rows, and the command's bad input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import sim
from training.bench import run_target
from training.bench._commission import BenchRow, oscillates, summarize_rows
from training.bench._oracle import SEARCH, closed_loop_poles, notches_of, oracle, true_figures
from training.cli import main
from training.commissioning import Mechanics, NotchSpec, linear_plant, margins
from training.commissioning._loop import closed_loop_matrices
from training.errors import UserError

CONFIG = sim.DriveConfig()
#: A quick search: no polish, fewer shapes (the constraints as the bench's).
QUICK = replace(SEARCH, polish_evaluations=0, filter_samples=(0.0, 1.0), notch_depths=(0.1, 0.3))
#: A lightly damped two-mass plant whose resonance limits the loop without a notch.
ELASTIC = Mechanics(J_sigma=0.05, V_J=0.44, f_e=240.0, d=0.007, mu_F=0.001)


def test_one_mass_oracle_is_at_the_edge() -> None:
    """One mass: the reference keeps every constraint, and 5 % more gain breaks one."""
    plant = linear_plant(Mechanics(J_sigma=0.05), CONFIG)
    ref = oracle(plant, Mechanics(J_sigma=0.05), QUICK)
    figs = ref.figures
    assert figs.meets() and figs.phase_margin >= 45.0 and ref.notches == ()
    assert ref.w_c == pytest.approx(figs.w_c) and 100 < ref.w_c < 0.3 * math.pi / CONFIG.T_s
    higher = true_figures(plant, 1.05 * ref.Kp, ref.Ti, ref.T_f, None)
    assert higher.w_c > ref.w_c and not higher.meets()


def test_a_notch_raises_the_reference_on_a_resonant_plant() -> None:
    plant = linear_plant(ELASTIC, CONFIG)
    with_notch = oracle(plant, ELASTIC, QUICK)
    without = oracle(plant, ELASTIC, replace(QUICK, max_notches=0))
    assert with_notch.notches and not without.notches
    assert with_notch.figures.meets() and without.figures.meets()
    assert with_notch.w_c > 1.05 * without.w_c


@pytest.mark.parametrize("damping,delay", [(None, 0), (1 / math.sqrt(2), 1)])
def test_true_figures_agree_with_the_chains_margins(damping: float | None, delay: int) -> None:
    """The oracle's own loop evaluation against ``_loop.margins`` (another grid, other code) on single-notch
    laws, and its poles against the eigenvalues of ``closed_loop_matrices``."""
    plant = linear_plant(ELASTIC, CONFIG, current_loop_damping=damping, extra_delay=delay)
    laws = [(8.0, 0.04, 0.0, None), (20.0, 0.02, 2.5e-4, NotchSpec(240.0, 0.05, 0.5)),
            (30.0, 0.01, 5e-4, NotchSpec(200.0, 0.1, 0.3)), (60.0, 0.02, 0.0, NotchSpec(240.0, 0.02, 0.4))]
    for Kp, Ti, T_f, notch in laws:
        mine, chain = true_figures(plant, Kp, Ti, T_f, notch), margins(plant, Kp, Ti, T_f, notch)
        assert mine.stable == chain.stable
        assert mine.w_c == pytest.approx(chain.w_c, rel=2e-3)
        assert mine.phase_margin == pytest.approx(chain.phase_margin, abs=0.1)
        assert mine.gain_margin_dB == pytest.approx(chain.gain_margin_dB, abs=0.1)
        poles = np.sort_complex(closed_loop_poles(plant, Kp, Ti, T_f, notches_of(notch)))
        A = closed_loop_matrices(plant, Kp, Ti, T_f, notch)[0]
        assert np.abs(poles).max() == pytest.approx(np.abs(np.linalg.eigvals(A)).max(), abs=1e-6)


def test_load_peak_of_a_one_mass_p_loop_matches_the_closed_loop_by_hand() -> None:
    """One mass, no current-loop lag to speak of: the load is the motor, ``T_rL = C G / (1 + C G)``; a
    crossover far below the delays gives a first-order loop whose peak is 0 dB (no resonance)."""
    plant = linear_plant(Mechanics(J_sigma=0.05), CONFIG)
    figs = true_figures(plant, 0.05 * 10.0, 1e3, 0.0, None)  # Kp = J w_c: w_c = 10 rad/s, Ti huge
    assert figs.w_c == pytest.approx(10.0, rel=1e-2)
    assert figs.phase_margin == pytest.approx(90.0, abs=1.0) and abs(figs.load_peak_dB) < 0.1


def test_notches_normalize_to_a_tuple() -> None:
    n = NotchSpec(100.0)
    assert notches_of(None) == () and notches_of(n) == (n,) and notches_of((n, None)) == (n,) and notches_of([n, n]) == (n, n)
    with pytest.raises(TypeError, match="notch"):
        notches_of("100 Hz")


def test_limit_cycle_criterion() -> None:
    n, q_w, w_s = 4000, 0.024, 2.0
    t = np.arange(4 * n) * 2.5e-4
    rng = np.random.default_rng(1)
    dither = q_w * rng.integers(-1, 2, 4 * n)  # encoder dither: one quantum
    assert not oscillates(w_s + dither, n, w_s, q_w)
    sustained = 0.3 * np.sin(2 * math.pi * 30 * t)
    assert oscillates(dither + sustained, n, w_s, q_w)
    decaying = 0.3 * np.sin(2 * math.pi * 30 * t) * np.exp(-t / 0.05)
    assert not oscillates(dither + decaying, n, w_s, q_w)
    ramp = 0.5 * t  # a slow loop still settling: not an oscillation
    assert not oscillates(ramp + dither, n, w_s, q_w)


def _row(plant: int, structure: str, ratio: float, delivered: str = "model", pm: float = 50.0, backlash: float = 0.0,
         cycle: bool = False, within: bool = True, peak: float = 1.0) -> BenchRow:
    return BenchRow(plant=plant, drive="reference", structure=structure, f_e=50.0, V_J=1.0, backlash=backlash,
                    oracle_w_c=100.0, oracle_notches=0, delivered=delivered, refusal=None, fallback_reason=None,
                    stated_w_c=None, w_c=None if delivered == "none" else 100 * ratio, ratio=ratio,
                    phase_margin=None if delivered == "none" else pm, gain_margin_dB=None if delivered == "none" else 9.0,
                    load_peak_dB=peak, stable=None if delivered == "none" else True,
                    limit_cycle=None if delivered == "none" else cycle, within_limits=within)


def test_summary_counts_by_hand() -> None:
    rows = [_row(0, "stiff", 0.9), _row(1, "stiff", 0.7), _row(2, "elastic", 0.2, "F1", pm=70.0),
            _row(3, "elastic", 0.0, "none"), _row(4, "elastic_backlash", 0.6, backlash=0.01, cycle=True, pm=38.0),
            _row(5, "stiff", 1.0, within=False), _row(6, "stiff", 1.3, peak=9.0)]
    s = summarize_rows(rows, "reference")
    assert s.plants == 7 and s.median_ratio == pytest.approx(0.7)
    assert s.class_median_ratio == {"elastic": 0.1, "elastic_backlash": 0.6, "stiff": 0.95}
    assert s.at_least_floor == 5 and s.fallback == 1 and s.delivered == 6 and s.ringing == 1
    assert s.min_phase_margin == 38.0 and s.limit_cycles_backlash == 1 and s.within_limits == 6
    v = s.verdicts
    assert not v["median ratio >= 0.8"] and not v["no limit cycle on backlash plants"] and not v["load peak <= 6 dB"]
    assert not v["true PM >= 40 deg, GM >= 6 dB, stable"] and not v["every experiment inside the limits"]
    assert summarize_rows(rows, "2nd-order+delay").plants == 0


@pytest.mark.parametrize("argv,words", [(["--plants", "0"], "--plants"), (["--w-max", "-1"], "--w-max"),
                                        (["--only", "3,x"], "--only"), (["--plants", "2", "--only", "5"], "0..1")])
def test_bad_options_are_one_line_errors(argv: list[str], words: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(UserError, match=words):
        run_target("commission", argv)
    assert main(["bench", "commission", *argv]) != 0
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1
