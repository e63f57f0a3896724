"""The commissioning page of one drive: test runs, the closed loop before and after tuning (motor
measured, load as the identified model estimates it), and the delivered loop's Bode plot with its
margins marked; and the page of the frequency response measured on the drive (beside the model)."""

from __future__ import annotations

from typing import Any

import numpy as np

from training.figures._style import MARK, MEASURED, MODEL, new_figure, with_unit

#: Names of the page's four panels, top to bottom (their titles start with them).
PANELS: tuple[str, ...] = ("test runs", "closed loop", "Bode |L|", "Bode phase")


def commission_figure(report: Any) -> Any:
    """The page of a :class:`training.commissioning.CommissioningReport` (a ``Figure``):

    1. every test run's measured motor speed, the limit ``w_max`` of the drive as dashed lines;
    2. the closed-loop experiment with the proposal (before tuning) and the delivered controller
       (after): measured motor speed, and where the mechanic is elastic the load speed the
       identified model estimates from it (dotted);
    3. and 4. the delivered loop's open-loop ``|L|`` and phase on the design model and on the
       guarantee's worst model, the crossover ``w_c``, the phase margin and the gain margin marked.
    Panels without data (a refusal ends before the closed loop) say so.
    """
    from training.commissioning import bode, load_estimate

    T_s = float(report.config.T_s)
    fig = new_figure(9.0, 12.0)
    ax_test, ax_loop, ax_mag, ax_phase = fig.subplots(4, 1)

    for i, rec in enumerate(report.excitation.records):
        ax_test.plot(np.arange(len(rec.speed)) * T_s, rec.speed, lw=0.8, label=f"run {i}")
    for sign in (1.0, -1.0):
        ax_test.axhline(sign * float(report.limits.w_max), color=MARK, ls="--", lw=0.8)
    ax_test.set_title(f"{PANELS[0]}: {report.name} (limit |w| <= {report.limits.w_max:g} rad/s dashed)", fontsize=9)
    ax_test.set_xlabel(with_unit("t", "s"))
    ax_test.set_ylabel(with_unit("w_M", "rad/s"))
    if report.excitation.records:
        ax_test.legend(fontsize=7)

    runs = [("before tuning (proposal)", report.runs[0] if report.runs else None, report.proposal),
            ("after tuning (delivered)", report.delivered_run, report.delivered)]
    for (label, run, proposal), colour in zip(runs, (MEASURED, MODEL)):
        if run is None:
            continue
        t = np.arange(len(run.speed)) * T_s
        ax_loop.plot(t, run.speed, color=colour, lw=0.9, label=f"motor, {label}")
        load = load_estimate(proposal.mechanics if proposal is not None else None, run.speed, T_s)
        if load is not None:
            ax_loop.plot(t, load, color=colour, ls=":", lw=0.9, label=f"load (model), {label}")
    ax_loop.set_title(f"{PANELS[1]}: speed steps and load disturbance on the drive", fontsize=9)
    ax_loop.set_xlabel(with_unit("t", "s"))
    ax_loop.set_ylabel(with_unit("w", "rad/s"))
    if ax_loop.lines:
        ax_loop.legend(fontsize=7)
    else:
        ax_loop.text(0.5, 0.5, "no closed-loop run (refused, no fallback)", ha="center", transform=ax_loop.transAxes)

    d = report.delivered
    if d is not None and d.models is not None:
        m = d.margins
        worst = d.models.plants[d.models.labels.index(m.model)] if m.model in d.models.labels else d.models.plants[0]
        for name, plant, colour in (("design model", d.models.plants[0], MEASURED), (f"worst: {m.model}", worst, MODEL)):
            b = bode(plant, d.Kp, d.Ti, d.T_f, d.notch)
            ax_mag.semilogx(b["w"], b["mag_dB"], color=colour, lw=0.9, label=name)
            ax_phase.semilogx(b["w"], b["phase_deg"], color=colour, lw=0.9, label=name)
        ax_mag.axhline(0.0, color="k", lw=0.5)
        ax_phase.axhline(-180.0, color="k", lw=0.5)
        for ax in (ax_mag, ax_phase):
            ax.axvline(m.w_c, color=MARK, ls="--", lw=0.8, label=f"w_c {m.w_c:.4g} rad/s")
        ax_phase.annotate(f"PM {m.phase_margin:.1f} deg", xy=(m.w_c, -180.0 + m.phase_margin), color=MARK, fontsize=8)
        ax_mag.set_title(f"{PANELS[2]}: delivered {d.concept}, PM {m.phase_margin:.1f} deg, "
                         f"GM {m.gain_margin_dB:.1f} dB (worst model)", fontsize=9)
        ax_phase.set_title(f"{PANELS[3]}", fontsize=9)
        ax_mag.legend(fontsize=7)
    else:
        ax_mag.set_title(f"{PANELS[2]}: no controller delivered", fontsize=9)
        ax_phase.set_title(f"{PANELS[3]}", fontsize=9)
    ax_mag.set_ylabel(with_unit("|L|", "dB"))
    ax_phase.set_ylabel(with_unit("phase L", "deg"))
    ax_phase.set_xlabel(with_unit("w", "rad/s"))
    return fig


#: Names of the frequency-response page's three panels, top to bottom (their titles start with them).
FRF_PANELS: tuple[str, ...] = ("measured |G|", "measured phase", "coherence")


def frf_figure(report: Any) -> Any:
    """The frequency-response page of a report with a measured response (``report.measured``; a
    ``Figure``): the plant's torque-to-speed ``|G|`` and phase measured on the drive beside the
    identified model's on the same lines, the resonances the model lacks marked, and the
    coherence per line with the threshold the resonance search uses."""
    from training.commissioning import FRF_SETTINGS

    m = report.measured
    if m is None:
        raise ValueError(f"report {report.name!r}: no measured frequency response to draw")
    f = m.w / (2 * np.pi)
    fig = new_figure(9.0, 10.0)
    ax_mag, ax_phase, ax_coh = fig.subplots(3, 1, sharex=True)
    curves = [("measured", m.G, MEASURED)] + ([("identified model", m.model, MODEL)] if m.model is not None else [])
    for label, G, colour in curves:
        ax_mag.semilogx(f, 20 * np.log10(np.maximum(np.abs(G), 1e-300)), color=colour, lw=0.9, label=label)
        ax_phase.semilogx(f, np.degrees(np.unwrap(np.angle(G))), color=colour, lw=0.9, label=label)
    for r in m.resonances:
        for ax in (ax_mag, ax_phase):
            ax.axvline(r / (2 * np.pi), color=MARK, ls="--", lw=0.8)
    found = ", ".join(f"{r / (2 * np.pi):.4g} Hz" for r in m.resonances) or "none"
    ax_mag.set_title(f"{FRF_PANELS[0]}: {report.name}, torque reference -> motor speed (resonances the model lacks: "
                     f"{found}, dashed)", fontsize=9)
    ax_phase.set_title(FRF_PANELS[1], fontsize=9)
    ax_coh.semilogx(f, m.coherence, color=MEASURED, lw=0.9)
    ax_coh.axhline(FRF_SETTINGS.min_coherence, color=MARK, ls="--", lw=0.8)
    ax_coh.set_ylim(0.0, 1.05)
    ax_coh.set_title(f"{FRF_PANELS[2]}: share of the measured speed the multisine explains "
                     f"(resonances searched above {FRF_SETTINGS.min_coherence:g})", fontsize=9)
    ax_mag.set_ylabel(with_unit("|G|", "dB"))
    ax_phase.set_ylabel(with_unit("phase G", "deg"))
    ax_coh.set_ylabel(with_unit("coherence", "1"))
    ax_coh.set_xlabel(with_unit("f", "Hz"))
    ax_mag.legend(fontsize=7)
    return fig
