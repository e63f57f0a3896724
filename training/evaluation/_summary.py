"""Aggregation of the study's per-system rows (SPEC 7): recognition rates ``E_30``/``E_50`` per grid
cell, per backlash, per true class and overall; per-parameter error statistics; the structure
confusion matrix; the acceptance checks (the study's targets). All figures come from :mod:`._metrics`.

Conventions: a missing estimate is a miss. The SOM gives no ``f_e``/``V_J`` for the ``stiff``
class (``None``), a record it cannot analyse gets ``error``; IV4 results with ``valid=False``
count as missing. Relative errors are signed in the statistics and absolute in ``E_x``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from sim import PARAM_NAMES, STRUCTURE_CLASSES
from training.evaluation import _metrics as metrics
from training.evaluation._metrics import finite_or_none as _num
from training.evaluation._sets import METHOD_PARAMS, METHODS, EvalSet

#: Recognition tolerances reported [%].
TOLERANCES: tuple[int, ...] = (30, 50)
#: Parameters with absolute error statistics (true value may be 0): ``M_FC`` [Nm], ``mu_F`` [Nm s/rad].
ABSOLUTE_PARAMS: tuple[str, ...] = ("M_FC", "mu_F")
#: Parameters with relative error statistics (``backlash`` only over systems with backlash).
RELATIVE_PARAMS: tuple[str, ...] = tuple(p for p in PARAM_NAMES if p not in ABSOLUTE_PARAMS)
#: Predicted-class labels of the confusion matrix: the four classes plus a failed analysis.
PREDICTED_LABELS: tuple[str, ...] = STRUCTURE_CLASSES + ("failed",)


def _column(rows: Sequence[Mapping[str, Any]], part: str, key: str) -> np.ndarray:
    """``rows[i][part][key]`` as float ``N`` (``None`` -> NaN)."""
    return np.array([np.nan if r[part].get(key) is None else float(r[part][key]) for r in rows], dtype=float)


def estimates(rows: Sequence[Mapping[str, Any]], method: str, key: str) -> np.ndarray:
    """Estimates of ``key`` by ``method`` (``N``); NaN where missing, for IV4 also where ``valid`` is False."""
    est = _column(rows, method, key)
    if method == "iv4":
        valid = np.array([bool(r["iv4"].get("valid")) for r in rows], dtype=bool)
        est[~valid] = np.nan
    return est


def relative_errors(rows: Sequence[Mapping[str, Any]], method: str,
                    params: Sequence[str] = metrics.RECOGNITION_PARAMS) -> dict[str, np.ndarray]:
    """Absolute relative errors ``|estimate - truth|/|truth|`` per parameter (``N``, NaN = missing;
    ``metrics.relative_error``)."""
    out = {}
    for p in params:
        truth = _column(rows, "truth", p)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[p] = metrics.relative_error(estimates(rows, method, p), truth)
    return out


def recognition(rows: Sequence[Mapping[str, Any]], method: str, x_percent: float) -> float:
    """``E_x`` [%] of ``method`` over ``rows`` (``metrics.recognition_rate`` of the absolute relative
    errors; NaN for no rows)."""
    if not rows:
        return float("nan")
    return metrics.recognition_rate(relative_errors(rows, method), x_percent)


def _rates(rows: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, dict[str, float | None]]:
    return {m: {f"E_{x}": _num(recognition(rows, m, x)) for x in TOLERANCES} for m in methods}


def parameter_stats(rows: Sequence[Mapping[str, Any]], method: str) -> dict[str, dict[str, Any]]:
    """Per parameter: ``kind`` (relative/absolute), ``n`` (systems with an estimate), ``n_missing``,
    ``mean``, ``std`` (signed error), ``median_abs``, and for relative errors ``within_30``/``within_50``
    (% of the systems in scope within that error, missing counted outside); parameters ``method``
    does not estimate are omitted.
    ``backlash`` is scored only over systems with backlash whose estimate is a backlash class."""
    out: dict[str, dict[str, Any]] = {}
    for p in RELATIVE_PARAMS + ABSOLUTE_PARAMS:
        if p not in METHOD_PARAMS[method]:
            continue
        truth = _column(rows, "truth", p)
        est = estimates(rows, method, p)
        if p in RELATIVE_PARAMS:
            scope = truth > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                err = (est - truth) / truth
        else:
            scope = np.ones_like(truth, dtype=bool)
            err = est - truth
        if p == "backlash":
            err = np.where(est > 0, err, np.nan)  # 0 = "no backlash class": counted as missing
        e = err[scope]
        ok = e[np.isfinite(e)]
        out[p] = {"kind": "relative" if p in RELATIVE_PARAMS else "absolute", "n": int(ok.size),
                  "n_missing": int(e.size - ok.size), "mean": _num(ok.mean()) if ok.size else None,
                  "std": _num(ok.std()) if ok.size else None,
                  "median_abs": _num(np.median(np.abs(ok))) if ok.size else None}
        if p in RELATIVE_PARAMS:  # share of the systems in scope within x % (missing = outside) [%]
            for x in TOLERANCES:
                out[p][f"within_{x}"] = _num(100.0 * np.mean(np.nan_to_num(np.abs(e), nan=np.inf) <= x / 100.0)) \
                    if e.size else None
    return out


def structure_confusion(rows: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """SOM structure confusion (``4 x 5``): rows = true class of :data:`STRUCTURE_CLASSES`,
    columns = predicted class or ``failed`` (:data:`PREDICTED_LABELS`)."""
    truth = np.array([STRUCTURE_CLASSES.index(r["truth"]["structure"]) for r in rows], dtype=int)
    pred = np.array([PREDICTED_LABELS.index(r["som"]["structure"] or "failed") for r in rows], dtype=int)
    return metrics.confusion_matrix(truth, pred, len(PREDICTED_LABELS))[: len(STRUCTURE_CLASSES)]


def _failures(rows: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m in ("som", "maps"):
        if m in methods:
            errs = [r[m]["error"] for r in rows if r[m].get("error")]
            out[m] = {"n_error": len(errs), "examples": sorted(set(errs))[:3],
                      "n_stiff_no_f_e": sum(1 for r in rows if r[m]["structure"] == "stiff")}
    if "iv4" in methods:
        bad = [r["iv4"]["reason"] for r in rows if not r["iv4"].get("valid")]
        out["iv4"] = {"n_invalid": len(bad), "examples": sorted(set(bad))[:3]}
    return out


def summarize_set(rows: Sequence[Mapping[str, Any]], methods: Sequence[str],
                  eval_set: EvalSet | None = None) -> dict[str, Any]:
    """All tables of one set (JSON-able). Cells and per-backlash means when ``eval_set`` is a grid."""
    methods = [m for m in METHODS if m in methods]
    r_osc = _column(rows, "truth", "r_osc")
    per_class = [_class_rates([r for r in rows if r["truth"]["structure"] == c], c, methods) for c in STRUCTURE_CLASSES]
    out: dict[str, Any] = {"n": len(rows), "r_osc_below_1": int(np.sum(r_osc < 1.0)),
                           "overall": _rates(rows, methods), "per_class": per_class,
                           "parameters": {m: parameter_stats(rows, m) for m in methods},
                           "failures": _failures(rows, methods)}
    if "som" in methods:
        out["confusion"] = {"true": list(STRUCTURE_CLASSES), "predicted": list(PREDICTED_LABELS),
                            "matrix": structure_confusion(rows).tolist()}
    if eval_set is not None and eval_set.kind == "grid":
        out["cells"] = [_cell(rows, methods, f_e, bl) for f_e, bl in eval_set.cells()]
        out["backlash_means"] = [{"backlash_deg": bl, **_rates([r for r in rows if r["cell_backlash_deg"] == bl], methods)}
                                 for bl in eval_set.backlash_deg]
    return out


def _class_rates(sub: Sequence[Mapping[str, Any]], structure: str, methods: Sequence[str]) -> dict[str, Any]:
    """The recognition rates over ``sub``, the systems of the true class ``structure``."""
    return {"class": structure, "n": len(sub), **_rates(sub, methods)}


def _cell(rows: Sequence[Mapping[str, Any]], methods: Sequence[str], f_e: float, bl: float) -> dict[str, Any]:
    """The figures of the grid cell ``f_e`` [Hz], ``bl`` [degree]: its systems' ``s_N``, ``r_osc``,
    true classes and each method's recognition rates."""
    sub = [r for r in rows if r["cell_f_e"] == f_e and r["cell_backlash_deg"] == bl]
    s_N = _column(sub, "truth", "s_N")
    classes = {c: sum(1 for r in sub if r["truth"]["structure"] == c) for c in STRUCTURE_CLASSES}
    return {"f_e": f_e, "backlash_deg": bl, "n": len(sub),
            "s_N_median": _num(np.median(s_N)) if sub else None,
            "s_N_above_1": _num(np.mean(s_N > 1.0)) if sub else None,
            "r_osc_below_1": int(np.sum(_column(sub, "truth", "r_osc") < 1.0)),
            "classes": classes, **_rates(sub, methods)}


def acceptance_checks(grid: Mapping[str, Any], methods: Sequence[str]) -> list[dict[str, Any]]:
    """The study's targets on the grid summary: SOM ``E_30 >= 95 %`` in every cell with backlash
    <= 0.2 degree and ``f_e`` <= 80 Hz; SOM ``E_30`` above IV4's in every cell where most
    systems have ``s_N > 1``. Each check: ``name``, ``passed`` (``None``: not applicable), ``detail``."""
    cells = grid.get("cells", [])
    checks = []
    if "som" in methods:
        scope = [c for c in cells if c["backlash_deg"] <= 0.2 and c["f_e"] <= 80.0]
        fail = [c for c in scope if (c["som"]["E_30"] or 0.0) < 95.0]
        checks.append(_cell_check("SOM E_30 >= 95 % where backlash <= 0.2 degree and f_e <= 80 Hz", scope, fail,
                                  lambda c: f"{c['som']['E_30']:.0f} %"))
    if "som" in methods and "iv4" in methods:
        scope = [c for c in cells if (c["s_N_above_1"] or 0.0) > 0.5]
        fail = [c for c in scope if not ((c["som"]["E_30"] or 0.0) > (c["iv4"]["E_30"] or 0.0))]
        checks.append(_cell_check("SOM E_30 > IV4 E_30 where most systems have s_N > 1", scope, fail,
                                  lambda c: f"SOM {c['som']['E_30']:.0f} vs IV4 {c['iv4']['E_30']:.0f} %"))
    return checks


def _cell_check(name: str, scope: Sequence[Mapping[str, Any]], fail: Sequence[Mapping[str, Any]],
                figure: Callable[[Mapping[str, Any]], str]) -> dict[str, Any]:
    """A check over the grid cells ``scope`` that passes where ``fail`` is empty (``None``: no cell in
    scope); its detail names each failing cell and its ``figure``."""
    detail = f"{len(scope) - len(fail)} of {len(scope)} cells pass"
    if fail:
        detail += "; failing: " + ", ".join(f"{c['f_e']:g} Hz/{c['backlash_deg']:g} deg ({figure(c)})" for c in fail)
    return {"name": name, "passed": (not fail) if scope else None, "detail": detail}


def identification_checks(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The identification's targets on a random population set (SOM identifier, SPEC default population):
    structure accuracy >= 95 % over systems at least 20 % away from every class threshold;
    over ``elastic`` and ``elastic_backlash``: ``E_30 >= 95 %`` and ``E_50 >= 99 %``; ``J_sigma``
    within 5 % for >= 95 %; backlash width within 30 % for >= 90 % of systems with ``s_N >= 0.3``;
    Coulomb friction within 0.05 Nm for >= 90 %. Each check: ``name``, ``passed``, ``detail``."""
    if not rows:
        return []
    truth = {k: _column(rows, "truth", k) for k in ("w_e_T_Ei", "s_N", "r_osc", "backlash", "M_FC")}
    far = metrics.threshold_margin({k: truth[k] for k in ("w_e_T_Ei", "s_N", "r_osc")}) >= 0.2
    correct = np.array([r["som"]["structure"] == r["truth"]["structure"] for r in rows])
    elastic = np.array([r["truth"]["structure"] in ("elastic", "elastic_backlash") for r in rows])
    err = relative_errors(rows, "som")
    e30 = float(100 * metrics.recognized({k: v[elastic] for k, v in err.items()}, 30).mean()) if elastic.any() else float("nan")
    e50 = float(100 * metrics.recognized({k: v[elastic] for k, v in err.items()}, 50).mean()) if elastic.any() else float("nan")
    j5 = float(100 * np.mean(np.nan_to_num(err["J_sigma"], nan=np.inf) <= 0.05))
    wide = truth["s_N"] >= 0.3
    bl_err = metrics.relative_error(estimates(rows, "som", "backlash")[wide], truth["backlash"][wide])
    bl30 = float(100 * np.mean(np.nan_to_num(bl_err, nan=np.inf) <= 0.3)) if wide.any() else float("nan")
    fc = float(100 * np.mean(np.nan_to_num(np.abs(estimates(rows, "som", "M_FC") - truth["M_FC"]), nan=np.inf) <= 0.05))
    acc = float(100 * correct[far].mean()) if far.any() else float("nan")
    figures = [
        (f"structure accuracy >= 95 % (systems >= 20 % from every threshold, n={int(far.sum())})", acc, 95.0),
        (f"E_30 >= 95 % over elastic + elastic_backlash (n={int(elastic.sum())})", e30, 95.0),
        (f"E_50 >= 99 % over elastic + elastic_backlash (n={int(elastic.sum())})", e50, 99.0),
        (f"J_sigma within 5 % for >= 95 % (n={len(rows)})", j5, 95.0),
        (f"backlash within 30 % for >= 90 % of s_N >= 0.3 (n={int(wide.sum())})", bl30, 90.0),
        (f"M_FC within 0.05 Nm for >= 90 % (n={len(rows)})", fc, 90.0),
    ]
    return [{"name": name, "passed": bool(value >= target), "detail": f"measured {value:.1f} %"}
            for name, value, target in figures]


def summarize(rows_by_set: Mapping[str, Sequence[Mapping[str, Any]]], sets: Mapping[str, EvalSet],
              methods: Sequence[str]) -> dict[str, Any]:
    """Summaries of all sets plus the acceptance checks (on the set named ``grid``, if any)."""
    out: dict[str, Any] = {"methods": [m for m in METHODS if m in methods], "sets": {}}
    for name, rows in rows_by_set.items():
        out["sets"][name] = summarize_set(rows, methods, sets.get(name))
    out["checks"] = acceptance_checks(out["sets"]["grid"], methods) if "grid" in out["sets"] else []
    if "som" in methods and "population" in rows_by_set:
        out["checks"] += identification_checks(rows_by_set["population"])
    return out
