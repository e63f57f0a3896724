"""Does the confidence of an answer mean what it says (SPEC 4.1)? Scored on the drive study's rows
(:func:`training.evaluation.drive_rows`, :func:`~training.evaluation.envelope_rows`), whose ``som``
part holds the answer's :func:`~training.evaluation._drives.confidence_columns`.

* **coverage** of each parameter's 90 % interval: the share of systems whose true value lies in
  ``[low, high]`` (inclusive; a true 0, a backlash-free system, is inside where ``low <= 0``),
  overall, per reported class (the Mondrian cells the calibration conditions on), per true class,
  per drive and per reported class x drive cell of at least :data:`MIN_CELL` systems;
* the **median relative half-width** ``(high - low) / 2 / |truth|`` of each interval, per drive;
* the **expected calibration error** (top label, :data:`BINS` equal-width bins) of the reported
  class's probability against "class right", and of ``answer_probability`` against "answer
  right" (:mod:`training.evaluation._answers`), with their reliability tables;
* the **warned shares**: of the right answers those with a warning, of the wrong ones those with none.

Failed analyses are no answers: left out and counted. Answers without a calibration (``intervals``
``None``; ``answer_probability`` ``None``) are left out of what needs it and counted
("uncalibrated").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from training.evaluation._answers import score_rows
from training.evaluation._report import markdown_table
from training.identification import INTERVAL_NAMES

#: The nominal coverage of an interval (SPEC 4.1) and what the study accepts: overall per parameter
#: within :data:`COVERAGE_BAND` percent, in every listed cell at least :data:`CELL_COVERAGE_MIN`.
LEVEL = 0.9
COVERAGE_BAND = (85.0, 95.0)
CELL_COVERAGE_MIN = 80.0

#: Fewest systems of a class x drive cell the table lists (smaller cells say little about coverage).
MIN_CELL = 30

#: Bins of the calibration error and the reliability diagram (equal width over 0..1), and the
#: largest calibration error SPEC 4.1 accepts.
BINS = 10
ECE_MAX = 0.05

#: SPEC 4.1's warning bounds [%]: right answers with a warning, wrong answers with none.
RIGHT_WARNED_MAX, WRONG_UNWARNED_MAX = 10.0, 1.0

#: The parameters whose half-widths the markdown shows per drive (the JSON holds every one).
HALF_WIDTH_SHOWN: tuple[str, ...] = ("f_e", "V_J", "J_sigma", "backlash")

#: The name of the row of all drives together.
ALL = "all"


def _percent(k: int, n: int) -> float | None:
    return 100.0 * k / n if n else None


@dataclass(frozen=True)
class Coverage:
    """``covered`` of ``n`` systems with an interval and a known truth hold the truth inside."""

    n: int
    covered: int

    @property
    def percent(self) -> float | None:
        return _percent(self.covered, self.n)

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "covered": self.covered, "percent": self.percent}


@dataclass(frozen=True)
class CoverageCell:
    """A reported class x drive cell: ``n`` calibrated answers, and each parameter's coverage."""

    structure: str
    drive: str
    n: int
    coverage: dict[str, Coverage]


@dataclass(frozen=True)
class CoverageTable:
    """Coverage of each parameter's interval (module docstring). ``by_*``: group -> parameter ->
    :class:`Coverage`; ``cells``: the reported class x drive cells of at least :data:`MIN_CELL`
    calibrated answers (``n_small_cells`` more were smaller and are left out); ``n_uncalibrated``
    answers had no intervals (``n_calibrated`` had), ``n_failed`` analyses no answer."""

    parameters: tuple[str, ...]
    overall: dict[str, Coverage]
    by_reported_class: dict[str, dict[str, Coverage]]
    by_true_class: dict[str, dict[str, Coverage]]
    by_drive: dict[str, dict[str, Coverage]]
    cells: tuple[CoverageCell, ...]
    n_small_cells: int
    n_calibrated: int
    n_uncalibrated: int
    n_failed: int

    def worst_cell(self, parameter: str) -> CoverageCell | None:
        """The listed cell of the lowest coverage of ``parameter`` (``None`` where none is listed)."""
        listed = [c for c in self.cells if c.coverage[parameter].n]  # percent is a number in these
        return min(listed, key=lambda c: c.coverage[parameter].covered / c.coverage[parameter].n) if listed else None


@dataclass(frozen=True)
class Reliability:
    """Predicted probability against observed frequency in ``len(count)`` equal-width bins over
    0..1 (bin ``k``: ``[k/B, (k+1)/B)``, the last one closed): per bin the answers, their mean
    probability and the share of them right (``None`` in an empty bin); ``ece`` = ``sum_k n_k / n
    |mean_p_k - observed_k|`` (``None`` without answers)."""

    count: tuple[int, ...]
    mean_p: tuple[float | None, ...]
    observed: tuple[float | None, ...]

    @property
    def n(self) -> int:
        return sum(self.count)

    @property
    def edges(self) -> tuple[float, ...]:
        return tuple(k / len(self.count) for k in range(len(self.count) + 1))

    @property
    def ece(self) -> float | None:
        if not self.n:
            return None
        return sum(c / self.n * abs(p - o) for c, p, o in zip(self.count, self.mean_p, self.observed)
                   if c and p is not None and o is not None)

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "ece": self.ece, "edges": list(self.edges), "count": list(self.count),
                "mean_p": list(self.mean_p), "observed": list(self.observed)}


@dataclass(frozen=True)
class ProbabilityCalibration:
    """A probability's :class:`Reliability` over ``reliability.n`` answers; ``n_uncalibrated``
    answers gave none. For the class probabilities also: ``n_not_summing`` answers whose four
    probabilities do not sum to 1 (within 1e-6), ``n_not_argmax`` whose reported class is not the
    most probable (``None`` for ``answer_probability``)."""

    reliability: Reliability
    n_uncalibrated: int
    n_not_summing: int | None = None
    n_not_argmax: int | None = None

    def to_dict(self) -> dict[str, Any]:
        out = {"reliability": self.reliability.to_dict(), "ece": self.reliability.ece,
               "n_uncalibrated": self.n_uncalibrated}
        if self.n_not_summing is not None:
            out.update(n_not_summing=self.n_not_summing, n_not_argmax=self.n_not_argmax)
        return out


@dataclass(frozen=True)
class WarnedShares:
    """Of ``n_right`` right answers ``n_right_warned`` carry a warning; of ``n_wrong`` wrong ones
    ``n_wrong_unwarned`` carry none (``n_failed`` analyses gave no answer and count in neither)."""

    n_right: int
    n_right_warned: int
    n_wrong: int
    n_wrong_unwarned: int
    n_failed: int

    @property
    def right_warned(self) -> float | None:
        """[%] of the right answers with a warning."""
        return _percent(self.n_right_warned, self.n_right)

    @property
    def wrong_unwarned(self) -> float | None:
        """[%] of the wrong answers with no warning."""
        return _percent(self.n_wrong_unwarned, self.n_wrong)

    def to_dict(self) -> dict[str, Any]:
        return {"n_right": self.n_right, "n_right_warned": self.n_right_warned, "right_warned": self.right_warned,
                "n_wrong": self.n_wrong, "n_wrong_unwarned": self.n_wrong_unwarned,
                "wrong_unwarned": self.wrong_unwarned, "n_failed": self.n_failed}


@dataclass(frozen=True)
class Check:
    """One of SPEC 4.1's targets: ``passed`` (``None`` where nothing could be measured) and the figures."""

    name: str
    passed: bool | None
    detail: str


@dataclass(frozen=True)
class ConfidenceReport:
    """Everything :func:`confidence_markdown` writes: coverage, half-widths (drive or :data:`ALL`
    -> parameter -> median, ``None`` without intervals), the class and answer calibration, the warned
    shares, and SPEC 4.1's checks."""

    coverage: CoverageTable
    half_widths: dict[str, dict[str, float | None]]
    structure: ProbabilityCalibration
    answer: ProbabilityCalibration
    warned: WarnedShares
    checks: tuple[Check, ...]

    def to_dict(self) -> dict[str, Any]:
        cov = self.coverage
        return {
            "level": LEVEL, "parameters": list(cov.parameters), "n_calibrated": cov.n_calibrated,
            "n_uncalibrated": cov.n_uncalibrated,
            "n_failed": cov.n_failed,
            "coverage": {"overall": cov.overall, "by_reported_class": cov.by_reported_class,
                         "by_true_class": cov.by_true_class, "by_drive": cov.by_drive,
                         "cells": [{"structure": c.structure, "drive": c.drive, "n": c.n, "coverage": c.coverage}
                                   for c in cov.cells],
                         "min_cell": MIN_CELL, "n_small_cells": cov.n_small_cells},
            "median_relative_half_width": self.half_widths, "structure_probability": self.structure,
            "answer_probability": self.answer, "warned": self.warned,
            "checks": [{"name": c.name, "passed": c.passed, "detail": c.detail} for c in self.checks]}


# --- the figures -------------------------------------------------------------------------------------------


def _answered(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if r["som"]["error"] is None]


def _interval_hits(rows: Sequence[dict[str, Any]], parameters: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(has, inside)``, bool ``N x P``: the answer has an interval of the parameter and its truth
    is known; the truth lies in ``[low, high]``. Rows without intervals have none."""
    has = np.zeros((len(rows), len(parameters)), dtype=bool)
    inside = np.zeros_like(has)
    for i, r in enumerate(rows):
        intervals = r["som"].get("intervals")
        if intervals is None:
            continue
        for j, name in enumerate(parameters):
            bounds, truth = intervals.get(name), r["truth"].get(name)
            if bounds is None or truth is None or not math.isfinite(float(truth)):
                continue
            low, high = (float(b) for b in bounds)
            if not low <= high:  # NaN too
                raise ValueError(f"intervals: expected low <= high, received {name} [{low!r}, {high!r}]")
            has[i, j] = True
            inside[i, j] = low <= float(truth) <= high
    return has, inside


def _coverages(has: np.ndarray, inside: np.ndarray, mask: np.ndarray, parameters: Sequence[str]) -> dict[str, Coverage]:
    return {name: Coverage(int(has[mask, j].sum()), int((has & inside)[mask, j].sum()))
            for j, name in enumerate(parameters)}


def coverage_table(rows_by_drive: Mapping[str, Sequence[dict[str, Any]]],
                   parameters: Sequence[str] = INTERVAL_NAMES) -> CoverageTable:
    """Coverage of the 90 % intervals of ``parameters`` (module docstring) over the rows of each
    drive (drive name -> rows)."""
    failed = sum(len(rows) - len(_answered(rows)) for rows in rows_by_drive.values())
    rows = [r for d in rows_by_drive.values() for r in _answered(d)]
    drive = np.array([name for name, d in rows_by_drive.items() for _ in _answered(d)], dtype=str)
    calibrated = np.array([r["som"].get("intervals") is not None for r in rows], dtype=bool)
    has, inside = _interval_hits(rows, parameters)
    reported = np.array([str(r["som"]["structure"]) for r in rows], dtype=str)
    true = np.array([r["truth"]["structure"] for r in rows], dtype=str)
    group = lambda labels: {k: _coverages(has, inside, labels == k, parameters)  # noqa: E731
                            for k in sorted(set(labels[calibrated].tolist()))}
    cells, small = [], 0
    for cls in sorted(set(reported[calibrated].tolist())):
        for name in rows_by_drive:
            mask = calibrated & (reported == cls) & (drive == name)
            if not mask.any():
                continue
            if mask.sum() < MIN_CELL:
                small += 1
                continue
            cells.append(CoverageCell(cls, name, int(mask.sum()), _coverages(has, inside, mask, parameters)))
    return CoverageTable(tuple(parameters), _coverages(has, inside, np.ones(len(rows), dtype=bool), parameters),
                         group(reported), group(true),
                         {name: _coverages(has, inside, drive == name, parameters) for name in rows_by_drive},
                         tuple(cells), small, int(calibrated.sum()), int((~calibrated).sum()), failed)


def median_half_width(rows: Sequence[dict[str, Any]], parameter: str) -> float | None:
    """The median of ``(high - low) / 2 / |truth|`` of ``parameter``'s intervals over ``rows``
    (systems whose truth is 0 or unknown, and answers without intervals, left out; ``None`` where
    none is left)."""
    widths = []
    for r in _answered(rows):
        intervals, truth = r["som"].get("intervals"), r["truth"].get(parameter)
        bounds = None if intervals is None else intervals.get(parameter)
        if bounds is None or truth is None or not math.isfinite(float(truth)) or float(truth) == 0.0:
            continue
        widths.append(0.5 * (float(bounds[1]) - float(bounds[0])) / abs(float(truth)))
    return float(np.median(widths)) if widths else None


def reliability(p: np.ndarray, hit: np.ndarray, bins: int = BINS) -> Reliability:
    """The :class:`Reliability` of probabilities ``p`` (``N``, in 0..1) against outcomes ``hit``
    (bool ``N``: the event happened) in ``bins`` equal-width bins."""
    p, hit = np.asarray(p, dtype=float), np.asarray(hit)
    if p.ndim != 1 or p.shape != hit.shape:
        raise ValueError(f"reliability: expected p and hit of one length N, received shapes {p.shape}, {hit.shape}")
    if hit.dtype != bool:
        raise TypeError(f"reliability: expected hit as booleans, received dtype {hit.dtype}")
    if not (np.isfinite(p).all() and ((p >= 0.0) & (p <= 1.0)).all()):
        raise ValueError("reliability: expected probabilities in 0..1, received values outside (or NaN)")
    if bins < 1:
        raise ValueError(f"reliability: expected bins >= 1, received {bins}")
    k = np.minimum(np.floor(p * bins).astype(int), bins - 1)  # p = 1 in the last bin
    count = np.bincount(k, minlength=bins)
    mean = lambda x: tuple(float(x[k == b].mean()) if count[b] else None for b in range(bins))  # noqa: E731
    return Reliability(tuple(int(c) for c in count), mean(p), mean(hit.astype(float)))


def expected_calibration_error(p: np.ndarray, hit: np.ndarray, bins: int = BINS) -> float:
    """Top-label expected calibration error of probabilities ``p`` against outcomes ``hit``
    (:class:`Reliability`'s ``ece``); ``ValueError`` without any answer."""
    ece = reliability(p, hit, bins).ece
    if ece is None:
        raise ValueError("expected_calibration_error: expected at least one probability, received none")
    return ece


def structure_calibration(rows: Sequence[dict[str, Any]], bins: int = BINS) -> ProbabilityCalibration:
    """The reported class's probability against "class right", over the answers of ``rows``
    (answers without probabilities counted as uncalibrated)."""
    rows = _answered(rows)
    score = score_rows(rows)
    keep = np.array([bool(r["som"].get("probabilities")) for r in rows], dtype=bool)
    kept = [r["som"] for r, k in zip(rows, keep) if k]
    if any(som["structure"] not in som["probabilities"] for som in kept):
        raise ValueError("probabilities: expected one for the reported class, received none for some answer")
    p = np.array([float(som["probabilities"][som["structure"]]) for som in kept])
    not_summing = sum(abs(sum(som["probabilities"].values()) - 1.0) > 1e-6 for som in kept)
    not_argmax = sum(som["probabilities"][som["structure"]] < max(som["probabilities"].values()) for som in kept)
    return ProbabilityCalibration(reliability(p, score.class_right[keep], bins), int((~keep).sum()), int(not_summing),
                       int(not_argmax))


def answer_calibration(rows: Sequence[dict[str, Any]], bins: int = BINS) -> ProbabilityCalibration:
    """``answer_probability`` against "answer right" (:mod:`training.evaluation._answers`) over the
    answers of ``rows`` (``None``: uncalibrated, counted)."""
    rows = _answered(rows)
    score = score_rows(rows)
    keep = np.array([r["som"].get("answer_probability") is not None for r in rows], dtype=bool)
    p = np.array([float(r["som"]["answer_probability"]) for r, k in zip(rows, keep) if k])
    return ProbabilityCalibration(reliability(p, ~score.wrong[keep], bins), int((~keep).sum()))


def warned_shares(rows: Sequence[dict[str, Any]]) -> WarnedShares:
    """Of the right answers of ``rows`` those with a warning, of the wrong ones those without."""
    score = score_rows(rows)
    right, wrong = ~score.wrong & ~score.failed, score.wrong & ~score.failed
    return WarnedShares(int(right.sum()), int((right & score.warned).sum()), int(wrong.sum()),
                        int((wrong & ~score.warned).sum()), int(score.failed.sum()))


def _checks(cov: CoverageTable, structure: ProbabilityCalibration, answer: ProbabilityCalibration, warned: WarnedShares) -> tuple[Check, ...]:
    lo, hi = COVERAGE_BAND
    out = []
    for name in cov.parameters:
        c = cov.overall[name]
        out.append(Check(f"{name}: coverage {lo:g}..{hi:g} %", None if c.percent is None else lo <= c.percent <= hi,
                         f"{_fmt(c.percent)} % of {c.n}" if c.n else "no intervals"))
        worst = cov.worst_cell(name)
        w = None if worst is None else worst.coverage[name]
        out.append(Check(f"{name}: every class x drive cell >= {CELL_COVERAGE_MIN:g} %",
                         None if w is None or w.percent is None else w.percent >= CELL_COVERAGE_MIN,
                         f"no cell of n >= {MIN_CELL}" if worst is None else
                         f"lowest {_fmt(w.percent)} % of {w.n} ({worst.structure} x {worst.drive})"))
    for what, cal in (("class probability", structure), ("answer_probability", answer)):
        ece = cal.reliability.ece
        out.append(Check(f"{what}: ECE <= {ECE_MAX:g}", None if ece is None else ece <= ECE_MAX,
                         "no probabilities" if ece is None else f"{_fmt(ece, 3)} over {cal.reliability.n}"))
    out.append(Check(f"right answers warned <= {RIGHT_WARNED_MAX:g} %",
                     None if warned.right_warned is None else warned.right_warned <= RIGHT_WARNED_MAX,
                     f"{_fmt(warned.right_warned)} % of {warned.n_right}" if warned.n_right else "no right answers"))
    out.append(Check(f"wrong answers unwarned <= {WRONG_UNWARNED_MAX:g} %",
                     None if warned.wrong_unwarned is None else warned.wrong_unwarned <= WRONG_UNWARNED_MAX,
                     f"{_fmt(warned.wrong_unwarned)} % of {warned.n_wrong}" if warned.n_wrong else "no wrong answers"))
    return tuple(out)


def confidence_report(rows_by_drive: Mapping[str, Sequence[dict[str, Any]]],
                      parameters: Sequence[str] = INTERVAL_NAMES, bins: int = BINS) -> ConfidenceReport:
    """Every figure of the module docstring over the rows of each drive (drive name -> rows; the
    drive :data:`ALL` is reserved for all of them together)."""
    if ALL in rows_by_drive:
        raise ValueError(f"rows_by_drive: the drive name {ALL!r} is reserved for all drives together")
    every = [r for rows in rows_by_drive.values() for r in rows]
    widths = {name: {p: median_half_width(rows, p) for p in parameters} for name, rows in rows_by_drive.items()}
    widths[ALL] = {p: median_half_width(every, p) for p in parameters}
    cov = coverage_table(rows_by_drive, parameters)
    structure, answer = structure_calibration(every, bins), answer_calibration(every, bins)
    warned = warned_shares(every)
    return ConfidenceReport(cov, widths, structure, answer, warned, _checks(cov, structure, answer, warned))


# --- markdown, JSON and the reliability diagram ----------------------------------------------------------------


def _fmt(x: float | None, digits: int = 1) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _cov(c: Coverage) -> str:
    return f"{_fmt(c.percent)} ({c.n})" if c.n else "n/a"


def _coverage_lines(title: str, groups: Mapping[str, Mapping[str, Coverage]], parameters: Sequence[str]) -> list[str]:
    rows = [[name, *(_cov(g[p]) for p in parameters)] for name, g in groups.items()]
    return [f"### {title}", "", *markdown_table(["", *parameters], rows), ""]


def confidence_markdown(report: ConfidenceReport, command: str, descriptions: Mapping[str, str] | None = None,
                        title: str = "Confidence of the answers", figure: str | None = None,
                        figure_note: str = "") -> str:
    """The report in markdown (``descriptions``: drive name -> the drive in words; ``figure``: the
    reliability diagram's file name, or ``figure_note``: why there is none)."""
    cov, names = report.coverage, report.coverage.parameters
    descriptions = descriptions or {}
    lines = [f"# {title}", "", f"Made by `{command}`.", "",
             f"{cov.n_calibrated} answers with intervals, {cov.n_uncalibrated} without "
             f"(uncalibrated maps), {cov.n_failed} failed analyses (left out).", "", "## SPEC 4.1 checks", ""]
    lines += markdown_table(["check", "result", "figures"],
                            [[c.name, "PASS" if c.passed else "FAIL" if c.passed is False else "n/a", c.detail]
                             for c in report.checks])
    lines += ["", f"## Coverage of the {100 * LEVEL:g} % intervals", "",
              f"Percent of the systems whose true value lies inside (n: answers with an interval). Target "
              f"{COVERAGE_BAND[0]:g}..{COVERAGE_BAND[1]:g} % overall, >= {CELL_COVERAGE_MIN:g} % in every class x drive "
              "cell. A true 0 (no backlash) is inside where the interval starts at 0.", ""]
    lines += _coverage_lines("Overall", {ALL: cov.overall}, names)
    lines += _coverage_lines("Per reported class (the calibration's cells)", cov.by_reported_class, names)
    lines += _coverage_lines("Per true class", cov.by_true_class, names)
    lines += _coverage_lines("Per drive", {f"{d}: {descriptions[d]}" if descriptions.get(d) else d: g
                                           for d, g in cov.by_drive.items()}, names)
    lines += _coverage_lines(f"Per reported class x drive (cells of n >= {MIN_CELL}; {cov.n_small_cells} smaller "
                             "cells left out)", {f"{c.structure} x {c.drive}": c.coverage for c in cov.cells}, names)
    lines += ["## Median relative half-width", "",
              "(high - low) / 2 / |true value| (systems whose true value is 0 left out); every parameter in the JSON.",
              ""]
    shown = [p for p in HALF_WIDTH_SHOWN if p in names]
    lines += markdown_table(["drive", *shown], [[d, *(_fmt(w[p], 3) for p in shown)]
                                                for d, w in report.half_widths.items()])
    lines += ["", "## ProbabilityCalibration of the probabilities", "",
              f"Expected calibration error (top label, {BINS} equal-width bins; target <= {ECE_MAX:g}): the reported "
              "class's probability against \"class right\", answer_probability against \"answer right\" (not wrong: "
              "class right, an elastic answer within E_30, J_sigma within 30 %).", ""]
    rows = []
    for what, cal in (("class probability", report.structure), ("answer_probability", report.answer)):
        rows.append([what, _fmt(cal.reliability.ece, 3), str(cal.reliability.n), str(cal.n_uncalibrated),
                     "n/a" if cal.n_not_summing is None else str(cal.n_not_summing),
                     "n/a" if cal.n_not_argmax is None else str(cal.n_not_argmax)])
    lines += markdown_table(["probability", "ECE", "n", "uncalibrated", "not summing to 1", "reported not argmax"],
                            rows)
    cls, ans = report.structure.reliability, report.answer.reliability
    lines += ["", "Reliability (per bin of the predicted probability: answers, their mean probability, the share "
              "right):", ""]
    lines += markdown_table(["bin", "class: n", "mean p", "observed", "answer: n", "mean p", "observed"],
                            [[f"{cls.edges[k]:.1f}..{cls.edges[k + 1]:.1f}",
                              *(x for rel in (cls, ans) for x in (str(rel.count[k]), _fmt(rel.mean_p[k], 3),
                                                                  _fmt(rel.observed[k], 3)))]
                             for k in range(len(cls.count))])
    w = report.warned
    lines += ["", "## Warnings", "",
              f"Right answers with a warning: {_fmt(w.right_warned)} % of {w.n_right} (target <= "
              f"{RIGHT_WARNED_MAX:g} %); wrong answers with none: {_fmt(w.wrong_unwarned)} % of {w.n_wrong} (target <= "
              f"{WRONG_UNWARNED_MAX:g} %); {w.n_failed} failed analyses left out.", ""]
    if figure:
        lines += [f"![reliability]({figure})", ""]
    if figure_note:
        lines += [figure_note, ""]
    return "\n".join(lines)


def reliability_figure(report: ConfidenceReport) -> Any:
    """The reliability diagrams (a ``matplotlib.figure.Figure``): per panel (the class probability,
    ``answer_probability``) the observed frequency of each bin over its mean predicted probability,
    the diagonal of perfect calibration, and each bin's count."""
    from training.figures import MARK, MEASURED, new_figure

    fig = new_figure(10.0, 4.2)
    axes = fig.subplots(1, 2, sharey=True)
    for ax, (what, cal) in zip(axes, (("class probability (reported class)", report.structure),
                                      ("answer_probability", report.answer))):
        rel = cal.reliability
        ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--", label="calibrated")
        centres = [(rel.edges[k] + rel.edges[k + 1]) / 2 for k in range(len(rel.count))]
        observed = [np.nan if o is None else o for o in rel.observed]
        ax.bar(centres, observed, width=1.0 / len(rel.count), color="0.85", edgecolor=MEASURED, lw=0.6,
               label="observed per bin")
        used = [k for k in range(len(rel.count)) if rel.count[k]]
        ax.plot([rel.mean_p[k] for k in used], [rel.observed[k] for k in used], "o-", color=MARK, ms=4,
                label="mean predicted vs observed")
        for k in used:
            ax.annotate(str(rel.count[k]), (centres[k], rel.observed[k] or 0.0), textcoords="offset points",
                        xytext=(0, 3), ha="center", fontsize=7)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.08)
        ax.set_xlabel("predicted probability [-]")
        ax.set_title(f"{what}: ECE {_fmt(rel.ece, 3)}, n {rel.n}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("observed frequency right [-]")
    axes[0].legend(fontsize=7, loc="upper left")
    return fig


def confidence_files(out: Path, stem: str, plots: bool) -> list[Path]:
    """The files :func:`write_confidence` writes into ``out`` (a caller refuses existing ones before any work)."""
    return [out / f"{stem}.md", out / f"{stem}.json"] + ([out / _figure_name(stem)] if plots else [])


def _figure_name(stem: str) -> str:
    return "fig_reliability" + stem.removeprefix("confidence") + ".png"


def write_confidence(report: ConfidenceReport, out: Path, stem: str, command: str,
                     descriptions: Mapping[str, str] | None = None, title: str = "Confidence of the answers",
                     plots: bool = True) -> list[Path]:
    """Write ``<stem>.md``, ``<stem>.json`` and (with ``plots``, where matplotlib imports) the
    reliability diagram into ``out``, replacing what is there (the caller refused existing files);
    the files written."""
    from som_torch import atomic_write
    from training._json import dumps
    from training.figures import plots_available, save_png
    from training.figures import PLOT_HINT

    out.mkdir(parents=True, exist_ok=True)
    figure, note = None, ""
    written = []
    if plots and plots_available():
        figure = _figure_name(stem)
        written.append(save_png(reliability_figure(report), out / figure, overwrite=True))
    elif plots:
        note = f"reliability diagram skipped: {PLOT_HINT}"
    md, js = out / f"{stem}.md", out / f"{stem}.json"
    text = confidence_markdown(report, command, descriptions, title, figure, note)
    atomic_write(md, lambda f: f.write(text), text=True)
    body = dumps({"command": command, "descriptions": dict(descriptions or {}), **report.to_dict(),
                  "figure": figure}, indent=1) + "\n"
    atomic_write(js, lambda f: f.write(body), text=True)
    return [md, js, *written]
