"""The identify page: one PNG per record that shows whether the identified model reproduces it.

Left, over time with the six test sections shaded and labelled: the measured motor speed and the
identified model's replay (:func:`model_speed`); the oscillating part ``w_osc`` (paper eq. 1:
the speed minus STEP 2's one-mass speed) of both; the current (or torque) with the torque
reference the sections imply. Below: the amplitude spectrum of ``w_osc`` with ``f_e`` and the
anti-resonance marked. Right: structure with the class probabilities, parameters with units and
their 90 % intervals (SPEC 4.1), quality figures, warnings and notes; below it each interval as a
bar relative to its value (:func:`draw_intervals`; where the maps carry no calibration, the text
says so in one line and no bars are drawn).
A record that failed gets a page with the reason (and its signals, where they could be read).
The record-on-the-maps page is :func:`maps_figure`.
"""

from __future__ import annotations

import math
import os
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import torch

import som_torch as st
from sim import (SECTION_NAMES, DriveConfig, Record, TwoMassParams, one_mass_stand_in, read_record, replay_speed,
                 two_mass_derived)
from training.errors import UserError, one_line
from training.figures._planes import PARAMETER_PLANES, draw_plane, unit_weights
from training.figures._style import (MARK, MEASURED, MODEL, new_figure, number, refuse_existing, require_matplotlib,
                                     save_png, with_unit)
from training.identification import (FEATURE_NAMES, INTERVAL_NAMES, PARAMETER_NAMES, PARAMETER_UNITS, Analysis,
                                     IdentificationFailure, IdentificationResult, Outcome, Parameters, TrainedMap,
                                     analyze, interval_text, torque_reference)

_SHADES = ("#fbe3c9", "#e4ecf7")  # alternate section shading
_TEXT_WIDTH = 58  # characters per line of the text box
#: The interval bars' axis: the interval over the reported value, clipped to this range (log scale).
INTERVAL_RATIO_RANGE = (1.0 / 3.0, 3.0)
NO_CALIBRATION = "90 % intervals: none (the maps carry no calibration)"


def model_speed(analysis: Analysis, parameters: Parameters) -> np.ndarray:
    """The identified model's motor speed ``N`` [rad/s] on the analysed record, as the refinement
    replays its candidates: driven open loop from rest by the torque reference rebuilt from the
    detected sections and ``M*`` (:func:`training.identification.torque_reference`), no torque
    limit, mean speed over each sample interval (:func:`sim.replay_speed`, unquantized). A result
    without an elastic part (``stiff``: no ``f_e``) runs as one mass: a shaft at the highest
    frequency the sampling resolves carrying 1 % of the inertia."""
    p = parameters
    elastic = p.f_e is not None and p.V_J is not None
    shaft = dict(V_J=p.V_J, f_e=p.f_e, d=p.d or 0.0) if elastic else one_mass_stand_in(analysis.T_s)
    row = dict(J_sigma=p.J_sigma, **shaft, backlash=p.backlash or 0.0, M_FC=p.M_FC or 0.0, mu_F=p.mu_F or 0.0)
    start, level = torque_reference(analysis.sections.bounds, analysis.M_star)
    drive = DriveConfig(M_max=1e9, T_Ei=analysis.T_Ei, T_s=analysis.T_s, encoder_counts=analysis.encoder_counts)
    w = replay_speed(TwoMassParams.from_dicts(row), drive, torch.as_tensor(start)[None], torch.as_tensor(level)[None],
                     len(analysis.fit.speed), quantize=False, dtype=torch.float64)
    return w[0].numpy()


def _in_sections(analysis: Analysis) -> np.ndarray:
    """Bool ``N``: the sample lies in one of the six sections."""
    lab = analysis.sections.labels()
    return (lab >= 1) & (lab <= 6)


def _shade_sections(ax: Any, t: np.ndarray, analysis: Analysis, *, labels: bool) -> None:
    """Shade sections I..VI (and mark the tail) over time ``t``; with ``labels``, name them on top."""
    bounds = analysis.sections.bounds.tolist()
    tail = analysis.sections.tail
    spans = [(name, a, b) for name, (a, b) in zip(SECTION_NAMES, bounds)]
    if tail[1] > tail[0]:
        spans.append(("tail", *tail))
    for k, (name, a, b) in enumerate(spans):
        t0, t1 = t[a], t[min(b, len(t) - 1)]
        ax.axvspan(t0, t1, color=_SHADES[k % 2] if name != "tail" else "0.93", zorder=0, linewidth=0)
        if labels:
            ax.text(0.5 * (t0 + t1), 1.01, name, transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                    fontsize=9, fontweight="bold")


def _reference(analysis: Analysis, n: int) -> np.ndarray:
    """The rebuilt torque reference ``N`` [Nm]."""
    start, level = torque_reference(analysis.sections.bounds, analysis.M_star)
    return level[np.searchsorted(start, np.arange(n), side="right") - 1]


def _spectrum(x: np.ndarray, T_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided amplitude spectrum of ``x`` (``2 |X_k| / N``), frequencies above 0 [Hz]."""
    X = 2.0 * np.abs(np.fft.rfft(x)) / max(len(x), 1)
    f = np.fft.rfftfreq(len(x), T_s)
    return f[1:], X[1:]


def anti_resonance(parameters: Parameters) -> float | None:
    """Anti-resonance of the motor-side response [Hz]: ``sqrt(C_F / J_L) / 2 pi`` (the load
    oscillating against a held motor); None without an elastic part."""
    p = parameters
    if p.f_e is None or p.V_J is None or p.J_sigma is None:
        return None
    dv = two_mass_derived(p.J_sigma, p.V_J, p.f_e, p.d or 0.0)
    return math.sqrt(dv.C_F / dv.J_L) / (2.0 * math.pi)


def _current(record: Record) -> tuple[np.ndarray, str, float | None]:
    """The drive signal shown: the current [A], else the torque [Nm]; and the factor from torque
    to that signal (``1 / K_M``; None where the record gives no ``K_M`` for its current)."""
    if record.current is not None:
        K_M = record.meta.get("K_M")
        return (np.asarray(record.current, dtype=np.float64), with_unit("motor current i", "A"),
                1.0 / float(K_M) if K_M else None)
    return record.motor_torque, with_unit("motor torque M", "Nm"), 1.0


def _text(result: IdentificationResult, a: Analysis, n: int) -> str:
    """The text box: the record, structure, parameters with units, quality figures, warnings."""
    q = result.quality
    lines = [f"record: {n} samples, T_s {number(a.T_s * 1e6)} us, T_Ei {number(a.T_Ei * 1e3)} ms, "
             f"{a.encoder_counts} counts/rev, M* {number(a.M_star, 3)} Nm"
             + (" (estimated)" if a.sections.M_star_estimated else ""), "",
             f"structure: {result.structure}"]
    if q.maps_structure is not None and q.maps_structure != result.structure:
        lines.append(f"  (maps said {q.maps_structure})")
    calibrated = q.answer_probability is not None
    lines.append(("  P(class), calibrated: " if calibrated else "  P(class), the structure map's (uncalibrated): ")
                 + ", ".join(f"{c} {v:.2f}" for c, v in q.structure_probabilities.items()))
    if calibrated:
        lines.append(f"  P(answer right) {q.answer_probability:.2f} (class; f_e, V_J, J_sigma in 30 %)")
    iv = result.intervals
    lines += ["", "parameters (reported)" + ("" if iv is None else ", 90 % interval")]
    for name in PARAMETER_NAMES:
        value = getattr(result.parameters, name)
        row = f"  {name:9} {number(value):>10}  {PARAMETER_UNITS[name]:8}"
        lines.append((row + " " + interval_text(name, value, iv[name])) if iv is not None else row.rstrip())
    if iv is None:
        lines.append("  " + NO_CALIBRATION)
    lines += ["", "quality"]
    lines.append("  map distance / training 99 % quantile:")
    lines.append("    " + ", ".join(f"{n} {v:.2f}" for n, v in q.map_distance_ratio.items()))
    lines.append(f"  oscillation {number(q.osc_quanta, 3)} speed quanta rms")
    lines.append(f"  eq.-1 fit R^2 {number(q.oscillation_fit_r2, 3)}, one-mass residual "
                 f"{number(100.0 * q.one_mass_rel_residual, 2)} %")
    if q.refine_residual is not None:
        lines.append(f"  refine residual {number(q.refine_residual, 3)} (maps' answer "
                     f"{number(q.refine_start_residual, 3)})")
    est = q.maps_estimate
    lines.append(f"  maps' answer: f_e {number(est.get('f_e'))} Hz, V_J {number(est.get('V_J'), 3)}, "
                 f"s_N {number(est.get('s_N'), 3)}")
    if q.section_flags:
        lines.append("  sections: " + "; ".join(q.section_flags))
    lines += ["", "warnings" + ("" if result.warnings else ": none")]
    lines += [f"  [{w.code}] {w.text}" for w in result.warnings]
    if result.notes:
        lines += ["", "notes (the intervals carry them): " + ", ".join(dict.fromkeys(w.code for w in result.notes))]
    return "\n".join(textwrap.fill(ln, _TEXT_WIDTH, subsequent_indent="      ", drop_whitespace=False)
                     if len(ln) > _TEXT_WIDTH else ln for ln in lines)


def identify_figure(record: Record, result: IdentificationResult, analysis: Analysis | None = None) -> Any:
    """The identify page of one identified record (a ``matplotlib`` figure, 16 x 12 in).
    ``analysis``: :func:`training.identification.analyze` of ``record`` (computed when not given)."""
    a = analysis if analysis is not None else analyze(record)
    t = np.asarray(record.t, dtype=np.float64)
    w_model = model_speed(a, result.parameters)
    inside = _in_sections(a)
    osc_model = np.where(inside, w_model - a.fit.w_bar, 0.0)
    one_mass = result.parameters.f_e is None
    fig = new_figure(16.0, 12.0)
    gs = fig.add_gridspec(4, 2, width_ratios=(2.2, 1.15))
    ax_w = fig.add_subplot(gs[0, 0])
    ax_o = fig.add_subplot(gs[1, 0], sharex=ax_w)
    ax_i = fig.add_subplot(gs[2, 0], sharex=ax_w)
    ax_f = fig.add_subplot(gs[3, 0])
    right = gs[:, 1].subgridspec(2, 1, height_ratios=(3.3, 1.0), hspace=0.15)
    ax_t = fig.add_subplot(right[0])
    ax_c = fig.add_subplot(right[1])
    model_label = "identified model, replayed" + (" (one mass)" if one_mass else "")
    for ax, labels in ((ax_w, True), (ax_o, False), (ax_i, False)):
        _shade_sections(ax, t, a, labels=labels)
    ax_w.plot(t, record.speed, color=MEASURED, linewidth=0.8, label="measured")
    ax_w.plot(t, w_model, color=MODEL, linewidth=1.0, linestyle="--", label=model_label)
    ax_w.set_ylabel(with_unit("motor speed w_M", "rad/s"))
    ax_o.plot(t, a.fit.w_osc, color=MEASURED, linewidth=0.8, label="measured w_osc")
    ax_o.plot(t, osc_model, color=MODEL, linewidth=1.0, label="model's w_osc")
    ax_o.set_ylabel(with_unit("w_osc = w_M - one-mass speed", "rad/s"))
    signal, label, per_Nm = _current(record)
    ax_i.plot(t, signal, color=MEASURED, linewidth=0.6, label="measured")
    if per_Nm is not None:
        ax_i.plot(t, _reference(a, len(t)) * per_Nm, color=MODEL, linewidth=1.0, linestyle="--",
                  label="test signal rebuilt from the sections")
    ax_i.set_ylabel(label)
    ax_i.set_xlabel(with_unit("time t", "s"))
    for ax in (ax_w, ax_o, ax_i):
        ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
        ax.grid(alpha=0.3)
    _draw_spectrum(ax_f, a, result, osc_model)
    ax_t.axis("off")
    ax_t.text(0.0, 1.0, _text(result, a, len(t)), transform=ax_t.transAxes, va="top", ha="left", family="monospace",
              fontsize=8.5)
    draw_intervals(ax_c, result)
    fig.suptitle(f"{result.record or record.name}: identified {result.structure}", fontsize=12, fontweight="bold")
    return fig


def draw_intervals(ax: Any, result: IdentificationResult) -> None:
    """Each parameter's 90 % interval as a bar over the reported value (log axis, clipped to
    :data:`INTERVAL_RATIO_RANGE`; a clipped end is marked by a triangle, the value by a dot at 1),
    one row per parameter of :data:`INTERVAL_NAMES` top down, the line labelled ``"<name>
    interval"``; a parameter reported 0 or not at all gets no bar, only its interval in words.
    Without intervals (uncalibrated maps; the text box says so) the axes stay empty and hidden."""
    if result.intervals is None:  # the text box says so
        ax.axis("off")
        return
    lo_x, hi_x = INTERVAL_RATIO_RANGE
    names = list(INTERVAL_NAMES)
    for k, name in enumerate(names):
        y = len(names) - 1 - k
        value = getattr(result.parameters, name)
        low, high = result.intervals[name]
        if value is None or value <= 0.0:
            ax.text(1.0, y, f"{interval_text(name, value, (low, high))} {PARAMETER_UNITS[name]}", ha="center",
                    va="center", fontsize=7)
            continue
        a, b = low / value, high / value
        ax.plot([min(max(a, lo_x), hi_x), max(min(b, hi_x), lo_x)], [y, y], color=MODEL, linewidth=4.0,
                solid_capstyle="butt", label=f"{name} interval")
        ax.plot([1.0], [y], "o", color=MEASURED, markersize=3)
        if a < lo_x:
            ax.plot([lo_x], [y], "<", color=MODEL, markersize=5)
        if b > hi_x:
            ax.plot([hi_x], [y], ">", color=MODEL, markersize=5)
    ax.set_xscale("log")
    ax.set_xlim(lo_x / 1.08, hi_x * 1.08)
    ax.set_xticks([1 / 3, 0.5, 0.8, 1.0, 1.25, 2.0, 3.0], ["1/3", "0.5", "0.8", "1", "1.25", "2", "3"])
    ax.minorticks_off()
    ax.set_yticks(range(len(names)), names[::-1], fontsize=7)
    ax.set_ylim(-0.7, len(names) - 0.3)
    ax.axvline(1.0, color="0.6", linewidth=0.8, zorder=0)
    ax.set_xlabel("90 % interval / reported value", fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(alpha=0.3, axis="x")


def _draw_spectrum(ax: Any, a: Analysis, result: IdentificationResult, osc_model: np.ndarray) -> None:
    f, X = _spectrum(a.fit.w_osc, a.T_s)
    _, Xm = _spectrum(osc_model, a.T_s)
    keep = f >= 1.0
    ax.loglog(f[keep], np.maximum(X[keep], 1e-12), color=MEASURED, linewidth=0.7, label="measured w_osc")
    ax.loglog(f[keep], np.maximum(Xm[keep], 1e-12), color=MODEL, linewidth=0.9, label="model's w_osc")
    p = result.parameters
    if p.f_e is not None:
        ax.axvline(p.f_e, color=MARK, linestyle="--", linewidth=1.0, label=f"f_e = {number(p.f_e)} Hz")
    f_a = anti_resonance(p)
    if f_a is not None:
        ax.axvline(f_a, color="tab:blue", linestyle=":", linewidth=1.2, label=f"anti-resonance f_a = {number(f_a)} Hz")
    peak = X[keep].max(initial=0.0)
    if peak > 0:
        ax.set_ylim(peak * 1e-4, peak * 3.0)
    ax.set_xlabel(with_unit("frequency f", "Hz"))
    ax.set_ylabel(with_unit("amplitude |W_osc(f)|", "rad/s"))
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.grid(alpha=0.3, which="both")


def failure_figure(error: str, record: Record | None = None, name: str | None = None) -> Any:
    """The page of a record that could not be identified: the reason, and its measured speed and
    current where the record could be read (12 x 7 in)."""
    fig = new_figure(12.0, 7.0 if record is not None else 3.0)
    title = f"{name or (record.name if record is not None else 'record')}: not identified"
    fig.suptitle(title, fontsize=12, fontweight="bold", color=MARK)
    wrapped = textwrap.fill(f"reason: {error}", 110)
    if record is None:
        ax = fig.add_subplot()
        ax.axis("off")
        ax.text(0.0, 0.8, wrapped, transform=ax.transAxes, va="top", fontsize=11)
        return fig
    ax_w, ax_i = fig.subplots(2, 1, sharex=True)
    t = np.asarray(record.t, dtype=np.float64)
    ax_w.plot(t, record.speed, color=MEASURED, linewidth=0.8)
    ax_w.set_ylabel(with_unit("motor speed w_M", "rad/s"))
    ax_w.set_title(wrapped, fontsize=10, loc="left")
    try:
        signal, label, _ = _current(record)
        ax_i.plot(t, signal, color=MEASURED, linewidth=0.6)
        ax_i.set_ylabel(label)
    except ValueError as err:  # no current/torque or no K_M: say so where the signal would be
        ax_i.text(0.5, 0.5, one_line(err), transform=ax_i.transAxes, ha="center")
    ax_i.set_xlabel(with_unit("time t", "s"))
    for ax in (ax_w, ax_i):
        ax.grid(alpha=0.3)
    return fig


def best_match(trained: TrainedMap, features: np.ndarray, member: int = 0) -> int:
    """The unit of ensemble member ``member`` that best matches the record's feature vector
    ``features`` (``F``, :data:`training.identification.FEATURE_NAMES`), as the recall finds it."""
    cols = [FEATURE_NAMES.index(f) for f in trained.spec.features]
    r = st.recall(trained.som, torch.as_tensor(np.asarray(features, dtype=np.float64)[cols])[None])
    unit = int(r.units.reshape(-1)[member])
    if unit < 0:  # som_torch's "no match": not one active feature is finite
        raise ValueError(f"features: no finite value among the {trained.spec.name} map's features")
    return unit


def plane_values(symbol: str, unit_value: float, result: IdentificationResult | None,
                 member: int = 0) -> list[tuple[str, float | None]]:
    """The values of a plane's quantity that a panel of the maps page names, each with what it is:
    ``"best unit (member k)"``, the record's best match unit on one ensemble member; ``"maps"``,
    the maps' answer, the ensemble's estimate before the refinement (where the maps estimate the
    quantity); and ``"reported"``, the value the identification answers (``parameters``; for
    ``s_N`` the refined ``quality.refined_s_N``, else the maps' value, which is then reported)."""
    out: list[tuple[str, float | None]] = [(f"best unit (member {member + 1})", unit_value)]
    if result is None:
        return out
    q = result.quality
    maps = q.maps_estimate.get(symbol)
    answer = (q.refined_s_N if q.refined_s_N is not None else maps) if symbol == "s_N" else getattr(result.parameters, symbol)
    if maps is not None:
        out.append(("maps", maps))
    return out + [("reported", answer)]


def maps_figure(analysis: Analysis, maps: dict[str, TrainedMap], result: IdentificationResult | None = None, *,
                member: int = 0, name: str | None = None) -> Any:
    """The record on the maps: per map (of :data:`PARAMETER_PLANES`) the parameter its units
    store, with lines of constant value (paper Figs. 7-8) and the record's best match (ensemble
    member ``member``) marked; each panel names the recall distance over the map's training 99 %
    quantile and the quantity's values, each labelled (:func:`plane_values`: the best unit's, the
    maps' answer, and the value the identification reports) (14 x 11 in)."""
    names = [n for n in PARAMETER_PLANES if n in maps]
    fig = new_figure(14.0, 11.0)
    cols = 2
    rows = max(1, math.ceil(len(names) / cols))
    for k, map_name in enumerate(names):
        trained, plane = maps[map_name], PARAMETER_PLANES[map_name]
        ax = fig.add_subplot(rows, cols, k + 1)
        values = plane.values(unit_weights(trained, member))
        unit = best_match(trained, analysis.features, member)
        draw_plane(ax, trained.som.grid, values, label=with_unit(plane.label, plane.unit), log=True, contours=True,
                   mark=unit, mark_label="record's best match")
        r, c = divmod(unit, trained.som.grid.cols)
        dist = result.quality.map_distance_ratio.get(map_name) if result is not None else None
        unit_text = "" if plane.unit == "-" else f" {plane.unit}"
        said = "; ".join(f"{what} {number(v, 3)}{unit_text}"
                         for what, v in plane_values(plane.symbol, float(values[unit]), result, member))
        ax.set_title(f"{map_name} map (member {member + 1} of {trained.som.batch_shape.numel()}): best match row {r}, "
                     f"column {c}, distance / 99 % quantile {number(dist, 2)}\n{plane.symbol}: {said}", fontsize=9)
    fig.suptitle(f"{name or (result.record if result is not None else None) or 'record'} on the maps",
                 fontsize=12, fontweight="bold")
    return fig


def identify_pages(outcome: Outcome, folder: str | os.PathLike[str], *, record: Record | None = None,
                   maps: dict[str, TrainedMap] | None = None, name: str | None = None,
                   overwrite: bool = False) -> list[Path]:
    """Write the pages of one outcome into ``folder``: ``<name>.png`` (the identify page, or the
    failure page) and, for an identified record with ``maps``, ``<name>_maps.png`` (the record on
    the maps). ``record``: the record (read from ``outcome.record`` when not given); ``name``:
    default the record file's stem. Existing files are replaced only with ``overwrite``.
    Returns the paths written."""
    folder = Path(folder)
    if record is None and outcome.record is not None:
        try:
            record = read_record(outcome.record)
        except (ValueError, OSError):
            record = None  # the failure page says why without the signals
    stem = name or (Path(outcome.record).stem if outcome.record else record.name if record is not None else "record")
    if isinstance(outcome, IdentificationFailure):
        return [save_png(failure_figure(outcome.error, record, outcome.record or stem), folder / f"{stem}.png",
                         overwrite=overwrite)]
    if record is None:
        raise ValueError(f"identify_pages: the record of {outcome.record!r} cannot be read; pass record=")
    analysis = analyze(record)
    written = [save_png(identify_figure(record, outcome, analysis), folder / f"{stem}.png", overwrite=overwrite)]
    if maps:
        written.append(save_png(maps_figure(analysis, maps, outcome, name=outcome.record or stem),
                                folder / f"{stem}_maps.png", overwrite=overwrite))
    return written


def page_names(records: list[str]) -> dict[str, str]:
    """A distinct file stem per record path: its stem, or ``<stem>_2``, ``_3``, ... where its pages
    ``<name>.png`` or ``<name>_maps.png`` would be another record's (two records in different
    folders with one name; records ``x`` and ``x_maps``)."""
    out: dict[str, str] = {}
    taken: set[str] = set()  # the page stems given out
    for rec in records:
        stem = Path(rec).stem if Path(rec).suffix.lower() in (".csv", ".json") else Path(rec).name
        name, k = stem, 1
        while name in taken or f"{name}_maps" in taken:
            k += 1
            name = f"{stem}_{k}"
        taken.update((name, f"{name}_maps"))
        out[rec] = name
    return out


class PageWriter:
    """Writes the pages of each outcome into ``folder`` as it comes (:func:`identify_pages`,
    ``<name>.png`` and ``<name>_maps.png``, names by :func:`page_names` of ``records``). Refuses,
    on creation, pages that exist already (unless ``overwrite``). Calling it with an outcome
    writes its pages and returns the outcome; a page that cannot be written is reported through
    ``report`` (one line) and the outcome still returned."""

    def __init__(self, folder: str | os.PathLike[str], records: list[str], maps: dict[str, TrainedMap] | None, *,
                 overwrite: bool = False, report: Any = None) -> None:
        require_matplotlib()
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise UserError(f"--plot: expected a folder, received the file {str(self.folder)!r}")
        self.names = page_names(records)
        self.maps, self.overwrite, self.report = maps, overwrite, report
        refuse_existing([self.folder / f"{n}{s}.png" for n in self.names.values() for s in ("", "_maps")], overwrite)
        self.written: list[Path] = []

    def __call__(self, outcome: Outcome) -> Outcome:
        name = self.names.get(outcome.record) if outcome.record is not None else None
        try:
            self.written += identify_pages(outcome, self.folder, maps=self.maps, name=name, overwrite=self.overwrite)
        except (ValueError, OSError) as err:
            if self.report is None:
                raise
            self.report(f"page of {outcome.record} not written: {one_line(err)}")
        return outcome
