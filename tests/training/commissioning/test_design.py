"""Design by optimization (training/commissioning/_design.py): the optimizer against an independent
brute-force search on one exact model, the uncertainty set widened only by doubts on the elastic
values, a measured frequency response in place of the hidden resonances."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sim = pytest.importorskip("sim")

from training.commissioning import CommissioningConfig, ControllerSpec, NotchSpec, linear_plant, margins, propose_controller  # noqa: E402
from training.commissioning._bands import hidden_bands  # noqa: E402
from training.commissioning._chain import UNCERTAIN_CODES, ChainState, _propose, _uncertain  # noqa: E402
from training.commissioning._design import GAP_OPEN_MARGINS, elastic_doubts, optimize_loop  # noqa: E402
from training.commissioning._rules import uncertainty_set  # noqa: E402
from training.commissioning._frf import MeasuredResponse  # noqa: E402
from training.commissioning._loop import Mechanics, ModelSet, load_peak_dB  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from conftest import identification_result  # noqa: E402

DRIVE = SimpleNamespace(M_max=20.0, M_N=10.0, K_M=1.0, T_Ei=5e-4, T_s=2.5e-4, encoder_counts=2**20,
                        q_w=2 * math.pi / 2**20 / 2.5e-4)
ELASTIC = dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001)


def _brute_force(mech: Mechanics) -> float:
    """The largest first crossover of a grid of laws (Kp log-spaced, Ti w 1.5..10, T_f 0 or 2 T_s,
    no notch or one at f_0 of three shapes) that is stable with PM >= 45 deg, GM >= 6 dB and a
    load peak <= 6 dB on the one exact model (``margins``, ``load_peak_dB`` of the loop analysis)."""
    plant = linear_plant(mech, DRIVE)
    f_0 = mech.derived.w_0 / (2 * math.pi)
    notches = [None] + [NotchSpec(f_0, dz, dp) for dz, dp in ((0.05, 0.5), (0.2, 1.0), (0.1, 0.3))]
    best = 0.0
    for notch in notches:
        for T_f in (0.0, 2 * DRIVE.T_s):
            for ratio in (1.5, 2.5, 4.0, 6.0, 10.0):
                for w_r in np.geomspace(2000.0, 5.0, 45):  # descending: the first that holds is this shape's best
                    Kp, Ti = mech.J_sigma * w_r, ratio / w_r
                    m = margins(plant, Kp, Ti, T_f, notch)
                    if m.meets(45.0, 6.0) and load_peak_dB(plant, Kp, Ti, T_f, notch) <= 6.0:
                        best = max(best, m.w_c)
                        break
    return best


@pytest.mark.parametrize("mech", [Mechanics(0.05, V_J=1.0, f_e=30.0, d=0.03), Mechanics(0.05, V_J=4.0, f_e=230.0, d=0.01)])
def test_optimized_design_reaches_a_brute_force_search_on_one_model(mech):
    """On exact parameters (one model) the optimizer reaches at least 0.8 of an independent brute
    force's crossover, with PM >= 45 deg, GM >= 6 dB and a load peak <= 6 dB on that model."""
    plant = linear_plant(mech, DRIVE)
    loop = optimize_loop(ModelSet((plant,), ("exact",)), DRIVE, J_sigma=mech.J_sigma, notch_at=(mech.derived.w_0 / (2 * math.pi),),
                         d=mech.d, min_phase_margin=45.0, min_gain_margin_dB=6.0)
    m = margins(plant, loop.Kp, loop.Ti, loop.T_f, loop.notches)
    assert loop.found and m.meets(45.0, 6.0) and load_peak_dB(plant, loop.Kp, loop.Ti, loop.T_f, loop.notches) <= 6.0 + 1e-9
    assert m.w_c == pytest.approx(loop.w_c) and m.w_c >= 0.8 * _brute_force(mech)


def _with_finding(quantity: str, code: str = "outside_envelope"):
    """The elastic answer with one envelope finding on ``quantity`` and its warning."""
    result = identification_result("elastic", ELASTIC, warnings=((code, f"{quantity} is outside the drive envelope"),))
    if "outside_envelope" not in {f.name for f in dataclasses.fields(result.quality)}:
        pytest.skip("this identification reports no envelope findings")
    quality = dataclasses.replace(result.quality, outside_envelope={quantity: {"value": 0.1}})
    return dataclasses.replace(result, quality=quality)


def _run(result) -> SimpleNamespace:
    """What :func:`_propose` reads of a chain run (an elastic answer: no hidden resonances)."""
    return SimpleNamespace(settings=CommissioningConfig(), result=result, config=DRIVE, state=ChainState(),
                           excitation=None)


def test_a_friction_only_warning_does_not_widen_the_set():
    """The issue's 30 Hz plant: a friction finding (friction 10 % of the test's M*) says nothing of
    f_e, V_J, d: no R7c, the same design as without the warning (its notch kept); a finding on f_e
    widens the set (R7c) and costs crossover."""
    friction = _with_finding("M_FC_over_M_star")
    assert _uncertain(friction) == [] and elastic_doubts(friction, UNCERTAIN_CODES) == []
    plain = _propose(_run(identification_result("elastic", ELASTIC)))
    kept = _propose(_run(friction))
    assert plain.notches and kept.notches == plain.notches and kept.figures["w_c"] == pytest.approx(plain.figures["w_c"])
    assert not any(r.startswith("R7c") for r in kept.rules)
    f_e = _with_finding("f_e")
    assert _uncertain(f_e) == ["outside_envelope"]
    wide = _propose(_run(f_e))
    assert wide.rules[0].startswith("R7c") and wide.figures["w_c"] < plain.figures["w_c"]


def _measured(plant, noise: float, seed: int = 0) -> MeasuredResponse:
    """The plant's response on the 2 Hz grid of a 0.5 s multisine period up to Nyquist, with relative complex noise."""
    w = 2 * math.pi * np.arange(2.0, 0.49 / DRIVE.T_s, 2.0)
    G = plant.speed_response(np.exp(1j * w * DRIVE.T_s))
    rng = np.random.default_rng(seed)
    G = G * (1 + noise * (rng.standard_normal(len(w)) + 1j * rng.standard_normal(len(w))))
    coherence = np.where(w < 0.9 * math.pi / DRIVE.T_s, 0.95, 0.5)
    return MeasuredResponse(w=w, G=G, coherence=coherence, T_s=DRIVE.T_s)


def test_a_measured_response_replaces_the_hidden_resonances():
    """A stiff answer whose plant has a real 400 Hz mode (V_J 0.5, d 0.01) the test could not show:
    with its measured response the set holds the measurement instead of the hidden resonances, a
    notch may sit at the measured peak, the loop is faster than with the hidden resonances and
    keeps PM >= 45 deg, GM >= 6 dB on the true plant."""
    J = 0.05
    true = Mechanics(J, V_J=0.5, f_e=400.0, d=0.01)
    spec = ControllerSpec()
    bands, _ = hidden_bands({"M_star": 10.0, "osc_quanta": 0.5, "f_osc": 0.0}, J, DRIVE, spec.class_V_J, f_lo=5.0, min_osc_quanta=2.0)
    hidden = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec, hidden=bands)
    meas = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec, hidden=bands, measured=_measured(linear_plant(true, DRIVE), 0.01))
    assert meas.models.measured is not None and not any(lab.startswith("hidden") for lab in meas.models.labels)
    assert any(r.startswith("R7b the measured frequency response replaces") for r in meas.rules)
    assert any(r.startswith("R4") and "measured peak" in r for r in meas.rules)
    m = margins(linear_plant(true, DRIVE), meas.Kp, meas.Ti, meas.T_f, meas.notch)
    assert m.meets(45.0 - 1.0, 6.0 - 0.2) and meas.figures["w_c"] > hidden.figures["w_c"]


def test_a_response_coherent_on_too_few_lines_leaves_the_hidden_resonances_in_the_set():
    """The same plant measured coherently only below 150 Hz (a gap rattling at the measurement's small
    amplitude, friction): the response could not have shown the 400 Hz mode, so it does not replace
    the resonances the test cannot exclude; they stay beside it and the loop keeps its margins on the
    true plant. Replacing them (the share asked 0) gives a loop that does not."""
    J = 0.05
    true = Mechanics(J, V_J=0.5, f_e=400.0, d=0.01)
    spec = ControllerSpec()
    bands, _ = hidden_bands({"M_star": 10.0, "osc_quanta": 0.5, "f_osc": 0.0}, J, DRIVE, spec.class_V_J, f_lo=5.0, min_osc_quanta=2.0)
    full = _measured(linear_plant(true, DRIVE), 0.01)
    low = replace(full, coherence=np.where(full.w < 2 * math.pi * 150.0, 0.95, 0.5))
    assert low.coherent_share(spec.min_coherence) < spec.min_coherent_share <= full.coherent_share(spec.min_coherence)
    kept = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec, hidden=bands, measured=low)
    assert kept.models.measured is not None and any(lab.startswith("hidden") for lab in kept.models.labels)
    assert any(r.startswith("R7b the measured frequency response is coherent on too few lines") for r in kept.rules)
    assert margins(linear_plant(true, DRIVE), kept.Kp, kept.Ti, kept.T_f, kept.notch).meets(45.0 - 1.0, 6.0 - 0.2)
    trusting = propose_controller("stiff", {"J_sigma": J}, DRIVE, replace(spec, min_coherent_share=0.0), hidden=bands,
                                  measured=low)
    assert not any(lab.startswith("hidden") for lab in trusting.models.labels)
    assert not margins(linear_plant(true, DRIVE), trusting.Kp, trusting.Ti, trusting.T_f, trusting.notch).meets(40.0, 6.0)


def test_a_measured_resonance_keeps_its_worst_cases_where_the_measurement_understates_it():
    """The measurement places a resonance but may understate it (friction makes a small-signal
    measurement lead the plant): a stiff answer whose 440 Hz mode (V_J 2, d 0.005) was measured
    as a mild one (V_J 0.3, d 0.05) gets worst-case members at the measured frequency (each V_J of
    the hidden bands, d 0.005, f +-5 %), none elsewhere, and keeps PM >= 45 deg and GM >= 6 dB on
    the true plant (held to the measurement alone, the loop is unstable there)."""
    J = 0.05
    true = Mechanics(J, V_J=2.0, f_e=440.0, d=0.005)
    mild = Mechanics(J, V_J=0.3, f_e=440.0, d=0.05)
    spec = ControllerSpec()
    bands, _ = hidden_bands({"M_star": 10.0, "osc_quanta": 0.5, "f_osc": 0.0}, J, DRIVE, spec.class_V_J, f_lo=5.0, min_osc_quanta=2.0)
    measured = replace(_measured(linear_plant(mild, DRIVE), 0.0), resonances=(2 * math.pi * 440.0,))
    prop = propose_controller("stiff", {"J_sigma": J}, DRIVE, spec, hidden=bands, measured=measured)
    worst = [lab for lab in prop.models.labels if lab.startswith("measured resonance's worst case")]
    assert worst and all(418.0 - 1 <= float(lab.split("f_e ")[1].split(" Hz")[0]) <= 462.0 + 1 for lab in worst)
    assert {float(lab.split("V_J ")[1].split(",")[0]) for lab in worst} == set(bands)
    m = margins(linear_plant(true, DRIVE), prop.Kp, prop.Ti, prop.T_f, prop.notch)
    assert m.stable and m.meets(45.0 - 1.0, 6.0 - 0.2)


def test_a_transient_member_is_held_to_its_own_margins_and_its_load_does_not_count():
    """A hand-made set: a one-mass plant and, as a transient state, its motor alone (a quarter of
    the inertia: four times the loop gain). The set's margins are the lasting plant's; the transient
    one only has to keep ``transient_margins`` (else ``stable`` False, named), its load peak is -inf."""
    lasting, light = linear_plant(Mechanics(0.05), DRIVE), linear_plant(Mechanics(0.0125), DRIVE)
    Kp, Ti = 0.05 * 300.0, 7 / 300.0
    alone, gap = margins(lasting, Kp, Ti), margins(light, Kp, Ti)
    assert gap.stable and 15.0 < gap.phase_margin < alone.phase_margin - 10  # the light one is closer to the edge
    labels = ("lasting", "gap open")
    relaxed = ModelSet((lasting, light), labels, transient=(False, True), transient_margins=(15.0, 1.5))
    m = relaxed.margins(Kp, Ti)
    assert m.stable and m.phase_margin == pytest.approx(alone.phase_margin) and m.gain_margin_dB == pytest.approx(alone.gain_margin_dB)
    strict = ModelSet((lasting, light), labels, transient=(False, True), transient_margins=(gap.phase_margin + 1.0, 0.0))
    assert not strict.margins(Kp, Ti).stable and strict.margins(Kp, Ti).model == "gap open"
    peaks = relaxed.load_peaks_dB(Kp, Ti)
    assert math.isfinite(peaks[0]) and peaks[1] == -math.inf
    plain = ModelSet((lasting, light), labels)
    assert plain.margins(Kp, Ti).phase_margin == pytest.approx(gap.phase_margin)


BACKLASH = dict(J_sigma=0.107, V_J=0.64, f_e=436.0, d=0.073, backlash=0.006, M_FC=0.3, mu_F=0.0025)


def _backlash_design(gap_open_margins: tuple[float, float]):
    from training.commissioning._design import UncertaintySet
    from training.commissioning._loop import mechanics_from

    u = UncertaintySet(mechanics_from(BACKLASH), decoupled_motor=True, gap_open_margins=gap_open_margins)
    models = u.models(DRIVE)
    loop = optimize_loop(models, DRIVE, J_sigma=BACKLASH["J_sigma"], notch_at=(436.0,), d=0.073, min_phase_margin=45.0,
                         min_gain_margin_dB=6.0)
    return u, models, loop


def test_the_gap_open_state_costs_less_bandwidth_and_keeps_its_margins():
    """R6 holds a backlash plant's decoupled motor to its own margins (stable with room), not to the
    guarantee's: a 436 Hz shaft gets a faster loop, the decoupled motor keeps the gap-open margins
    (PM >= 30 deg, GM >= 3 dB) on its pessimistic current loop, and every lasting model keeps the guarantee."""
    _, strict_models, strict = _backlash_design((45.0, 6.0))
    u, models, loop = _backlash_design(GAP_OPEN_MARGINS)
    assert GAP_OPEN_MARGINS == (30.0, 3.0) and u.gap_open_margins == GAP_OPEN_MARGINS
    assert strict.found and loop.found and loop.w_c > 1.2 * strict.w_c
    each = models.each(loop.Kp, loop.Ti, loop.T_f, loop.notches)
    gap = [m for i, m in enumerate(each) if models.is_transient(i)]
    assert len(gap) == 1 and gap[0].meets(*GAP_OPEN_MARGINS) and not gap[0].meets(45.0, 6.0)
    assert models.margins(loop.Kp, loop.Ti, loop.T_f, loop.notches).meets(45.0, 6.0)
    assert loop.phase_margin >= 45.0 and loop.gain_margin_dB >= 6.0  # reported over the lasting models only


def test_the_faster_backlash_loop_does_not_limit_cycle_on_the_nonlinear_plant():
    """The loop designed with the gap-open margins runs on the simulator's nonlinear plant (backlash,
    Coulomb friction): steps from rest and a disturbance torque, no sustained oscillation
    (the bench's criterion, :func:`training.bench._commission.oscillates`)."""
    from training.bench._commission import limit_cycle_scenario, oscillates
    from training.commissioning import PISpeedLaw

    _, _, loop = _backlash_design(GAP_OPEN_MARGINS)
    drive = sim.SimulatedDrive(BACKLASH)
    config, limits = drive.config, sim.DriveLimits(w_max=20.0, travel=5.0)
    law = PISpeedLaw(loop.Kp, loop.Ti, T_s=config.T_s, M_max=config.M_max, T_f=loop.T_f, notch=loop.notches or None)
    scenario, n, w_s = limit_cycle_scenario(loop.w_c, loop.Kp, limits, config)
    record = drive.run_closed_loop(law, scenario, limits)
    q_w = 2 * math.pi / (config.encoder_counts * config.T_s)
    assert not record.meta.get("aborted") and not oscillates(np.asarray(record.speed, dtype=float), n, w_s, q_w)


def test_a_limit_cycle_on_the_drive_designs_again_with_the_guarantees_margins_on_the_decoupled_motor(monkeypatch):
    """Stage ``try`` with the drive's verdicts stubbed: the first design's candidates limit-cycle, so
    the chain designs again with the decoupled motor held to 45 deg and 6 dB (a slower loop, R6 says
    why) and runs its candidates; a design whose candidates only do not settle is not designed again."""
    from training.commissioning import _chain

    answer = identification_result("elastic_backlash", BACKLASH)
    tried: list = []

    def candidates(run, plan, kind):
        tried.append(plan.proposal)
        verdict = "limit_cycle" if len(tried) == 1 else None
        return [SimpleNamespace(verdict=verdict, settled=verdict is None, usable=verdict is None, cost=1.0)]

    monkeypatch.setattr(_chain, "_run_candidates", candidates)
    monkeypatch.setattr(_chain, "_plan_loop", lambda run, proposal: SimpleNamespace(proposal=proposal))
    run = SimpleNamespace(settings=CommissioningConfig(), result=answer, config=DRIVE, excitation=None,
                          state=_chain.ChainState(), lap=lambda *a: None, say=lambda *a: None, warned=[], name="plant")
    run.warn = lambda code, text: run.warned.append(code)
    run.state.design = SimpleNamespace(proposal=_propose(run))
    first = run.state.design.proposal
    _chain._try_design(run)
    second = run.state.design.proposal
    assert run.state.gap_open_cycled and len(tried) == 2 and run.state.design_trial.chosen == 0 and not run.warned
    assert second.rules[0].startswith("R6 a loop with the decoupled motor at the gap-open margins limit-cycled")
    assert any("kept stable with PM >= 45 deg, GM >= 6 dB" in r for r in second.rules)
    assert any("kept stable with PM >= 30 deg, GM >= 3 dB" in r for r in first.rules)
    assert second.figures["w_c"] < first.figures["w_c"]
    tried.clear()
    monkeypatch.setattr(_chain, "_run_candidates", lambda run, plan, kind: tried.append(1) or [SimpleNamespace(
        verdict="slow", settled=False, usable=False, cost=1.0)])
    again = SimpleNamespace(**{**vars(run), "state": _chain.ChainState(), "warned": []})
    again.warn = lambda code, text: again.warned.append(code)
    again.state.design = SimpleNamespace(proposal=first)
    _chain._try_design(again)
    assert tried == [1] and not again.state.gap_open_cycled and again.warned == ["loop_not_settled"]


def test_no_redesign_where_the_measured_response_is_unlike_the_model(monkeypatch):
    """A measurement whose gain near the crossover is 0.39 x the model's (``loop_unlike_model``: a
    wrong answer, or a backlash gap open at the measurement's small amplitude) is no basis for a
    redesign: the first design stays, and the reason says why (a redesign of the study's likely-wrong
    ``stiff`` answer for a 21 Hz shaft with a 0.016 rad gap reaches 575 rad/s and true PM 35 deg)."""
    from training.commissioning import _chain

    called = []
    monkeypatch.setattr(_chain, "_propose", lambda run: called.append(1))
    run = SimpleNamespace(settings=CommissioningConfig(), state=_chain.ChainState(measured=object(), measured_unlike=0.387))
    _chain._redesign(run)
    assert not called and run.state.redesign is None and "0.387 x the identified model's" in run.state.redesign_reason


def test_a_placed_resonance_gets_a_narrow_notch_where_the_set_allows_it():
    """A resonance known within +-5 % (the measured response's placement): the default search,
    which tries the narrow notch width 0.2, reaches a higher crossover than the wide widths alone
    (0.5, 1.2), with a narrow notch, and keeps PM >= 45 deg, GM >= 6 dB, load peak <= 6 dB on every
    model of the set."""
    from training.commissioning._design import SEARCH

    mechs = [Mechanics(0.016, V_J=1.0, f_e=150.0 * k, d=0.02) for k in (1.0, 0.95, 1.05)]
    models = ModelSet(tuple(linear_plant(m, DRIVE) for m in mechs), ("nominal", "low", "high"))

    def design(search):
        return optimize_loop(models, DRIVE, J_sigma=0.016, notch_at=(mechs[0].derived.w_0 / (2 * math.pi),), d=0.02,
                             min_phase_margin=45.0, min_gain_margin_dB=6.0, search=search)

    narrow, wide = design(SEARCH), design(replace(SEARCH, notch_widths=(0.5, 1.2)))
    assert 0.2 in SEARCH.notch_widths and narrow.found and wide.found
    assert narrow.w_c > 1.15 * wide.w_c  # measured: 390 against 323 rad/s
    assert min(n.D_p for n in narrow.notches) == pytest.approx(0.2)
    for plant in models.plants:
        m = margins(plant, narrow.Kp, narrow.Ti, narrow.T_f, narrow.notches)
        assert m.meets(45.0, 6.0) and load_peak_dB(plant, narrow.Kp, narrow.Ti, narrow.T_f, narrow.notches) <= 6.0 + 1e-9


@pytest.mark.parametrize("mech", [Mechanics(0.05), Mechanics(0.05, V_J=1.0, f_e=120.0, d=0.03)], ids=["stiff", "elastic"])
def test_the_measured_phase_tells_the_drives_current_loop(mech):
    """The set's pessimistic variant (2nd-order current loop, +1 sample delay) stays where the
    measured response lags as it does and is left out where the response follows the SPEC's
    first-order loop; a drive with only one of its two parts (here the extra sample: about half
    the extra lag) and a measurement that does not reach where the two differ keep it. The loop
    designed without it is faster and keeps its margins on the plant that was measured."""
    spec = ControllerSpec()
    nominal_plant = linear_plant(mech, DRIVE)
    variant_plant = linear_plant(mech, DRIVE, current_loop_damping=spec.current_loop_damping, extra_delay=spec.extra_delay)
    structure = "elastic" if mech.two_mass else "stiff"
    params = dataclasses.asdict(mech) if mech.two_mass else {"J_sigma": mech.J_sigma}
    designs = {}
    for name, plant in (("nominal", nominal_plant), ("variant", variant_plant)):
        measured = _measured(plant, 0.01)
        u = uncertainty_set(params, spec, structure=structure, measured=measured)
        share = u.variant_lag(DRIVE)
        assert share == pytest.approx(0.0 if name == "nominal" else 1.0, abs=0.1)
        assert u.follows_nominal(DRIVE) == (name == "nominal")
        labels = u.models(DRIVE).labels
        assert any("2nd-order" in lab for lab in labels) == (name == "variant")
        prop = propose_controller(structure, params, DRIVE, spec, measured=measured)
        m = margins(plant, prop.Kp, prop.Ti, prop.T_f, prop.notch)
        assert m.stable and m.meets(45.0 - 0.5, 6.0 - 0.2)
        designs[name] = prop.figures["w_c"]
    assert designs["nominal"] > 1.2 * designs["variant"]  # measured: 632 against 499 rad/s stiff, 300 against 163 elastic
    delayed = uncertainty_set(params, spec, structure=structure, measured=_measured(linear_plant(mech, DRIVE, extra_delay=1), 0.01))
    assert 0.4 < delayed.variant_lag(DRIVE) < 0.7 and not delayed.follows_nominal(DRIVE)
    low = _measured(nominal_plant, 0.01)
    keep = low.w < 2 * math.pi * 100.0  # the measurement ends at 100 Hz: the loops hardly differ there
    low = MeasuredResponse(w=low.w[keep], G=low.G[keep], coherence=low.coherence[keep], T_s=low.T_s)
    u = uncertainty_set(params, spec, structure=structure, measured=low)
    assert u.variant_lag(DRIVE) is None and not u.follows_nominal(DRIVE)



def test_a_misplaced_resonance_does_not_hide_the_drives_lag():
    """The response the chain measured on the bench study's variant plant 1 (a 448 Hz shaft, drive
    with a 2nd-order current loop and +1 sample delay, answered elastic at 266 Hz): near the two
    resonances the measured over the model's phase carries the model's error, not the drive's (the
    lines' median share 0.30 would drop the variant; the loop designed so kept PM 37 deg on the true
    plant). The upper quartile keeps it."""
    data = np.loadtxt(Path(__file__).parent / "data" / "variant_plant1_frf.csv", delimiter=",", comments="#", skiprows=2)
    measured = MeasuredResponse(w=data[:, 0], G=data[:, 1] + 1j * data[:, 2], coherence=data[:, 3], T_s=DRIVE.T_s)
    answer = dict(J_sigma=0.0833, V_J=0.259, f_e=266.0, d=0.17)
    u = uncertainty_set(answer, ControllerSpec(), structure="elastic", measured=measured)
    assert u.variant_lag(DRIVE) > 0.9 and not u.follows_nominal(DRIVE)  # measured: 1.07
