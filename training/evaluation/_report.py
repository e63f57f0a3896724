"""Evaluation report: markdown + JSON (always), per-system CSV, PNG figures (when matplotlib imports).

Input is the JSON-able summary of :func:`training.evaluation.run_study` (or ``summarize``) plus the per-system
rows of :func:`training.evaluation.run_set`. Files written into the output folder:

- ``report.md``: the tables (paper Fig. 10 as ``E_30``/``E_50`` grids, SOM / IV4 side by side),
- ``report.json``: the summary, the run's config and timing,
- ``systems.csv``: one line per system (truth, SOM and IV4 estimates),
- ``fig9_<set>.png``: relative ``f_e`` error of each system, systems sorted by ``s_N`` (paper Fig. 9),
- ``fig10_recognition.png``: ``E_50`` (left) and ``E_30`` (right) over ``f_e`` per backlash (paper Fig. 10).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from som_torch import atomic_write
from training._json import dumps
from training.evaluation._sets import METHOD_PARAMS, TRUTH_KEYS
from training.evaluation._summary import TOLERANCES, relative_errors

METHOD_TITLES = {"som": "SOM", "maps": "maps only", "iv4": "IV4"}
_LINE = {"som": "-", "maps": ":", "iv4": "--"}  # line style per method in Fig. 10
NO_MATPLOTLIB = "figures skipped: matplotlib is not installed (pip install 'twomass-som[plot]')"


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text), text=True)


def _pct(x: float | None) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.0f}"


def _sig(x: float | None, digits: int = 3) -> str:
    return "–" if x is None else f"{x:.{digits}g}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """The lines of a markdown table: ``header``, its rule, one line per row of cells."""
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _side_by_side(rates: Mapping[str, Mapping[str, float | None]], key: str, methods: Sequence[str]) -> str:
    return " / ".join(_pct(rates[m][key]) for m in methods)


def grid_tables(grid: Mapping[str, Any], methods: Sequence[str]) -> list[str]:
    """Markdown lines: one ``f_e`` x backlash table per tolerance, cells ``SOM / IV4`` in %."""
    cells = grid["cells"]
    f_es = sorted({c["f_e"] for c in cells})
    bls = sorted({c["backlash_deg"] for c in cells})
    by = {(c["f_e"], c["backlash_deg"]): c for c in cells}
    means = {b["backlash_deg"]: b for b in grid["backlash_means"]}
    label = " / ".join(METHOD_TITLES[m] for m in methods)
    lines: list[str] = []
    for x in TOLERANCES:
        key = f"E_{x}"
        lines += [f"**E_{x} [%] ({label})**, {cells[0]['n']} systems per cell", ""]
        body = [[f"{f:g}"] + [_side_by_side(by[(f, b)], key, methods) for b in bls] for f in f_es]
        body.append(["**mean**"] + [_side_by_side(means[b], key, methods) for b in bls])
        lines += markdown_table(["f_e [Hz]"] + [f"backlash {b:g}°" for b in bls], body) + [""]
    lines += ["**Cell context**: median `s_N`, share of systems with `s_N > 1`, systems with `r_osc < 1` "
              "(oscillation below one speed quantum), true classes (stiff/elastic/elastic_backlash/stiff_backlash)", ""]
    body = []
    for f in f_es:
        row = [f"{f:g}"]
        for b in bls:
            c = by[(f, b)]
            cl = "/".join(str(v) for v in c["classes"].values())
            row.append(f"{_sig(c['s_N_median'], 2)}; {_pct(100 * c['s_N_above_1'])} %; {c['r_osc_below_1']}; {cl}")
        body.append(row)
    lines += markdown_table(["f_e [Hz]"] + [f"backlash {b:g}°" for b in bls], body) + [""]
    return lines


def set_tables(name: str, s: Mapping[str, Any], methods: Sequence[str]) -> list[str]:
    """Markdown lines for one set: overall and per-class ``E_x``, parameter errors, confusion, failures."""
    lines = [f"### {name}: {s['n']} systems ({s['r_osc_below_1']} with `r_osc < 1`)", ""]
    lines += _rate_table(s, methods) + [""]
    lines += ["Parameter errors: signed relative error (absolute for `M_FC` [Nm], `mu_F` [Nm s/rad]) over the "
              "systems with an estimate; missing = not identified (stiff class, failed or invalid); "
              "within x %: share of all systems in scope (missing = outside)", ""]
    body = [_parameter_row(m, p, st) for m in methods for p, st in s["parameters"][m].items()]
    lines += markdown_table(["method", "parameter", "n", "missing", "mean", "std", "median abs"]
                            + [f"within {x} % [%]" for x in TOLERANCES], body) + [""]
    if "confusion" in s:
        lines += _confusion_lines(s["confusion"])
    lines += [f"- {n}" for n in _failure_notes(s["failures"])] + [""]
    return lines


def _rate_table(s: Mapping[str, Any], methods: Sequence[str]) -> list[str]:
    """``E_x`` of each method over all systems and per true class."""
    titles = [METHOD_TITLES[m] for m in methods]
    header = ["systems", "n"] + [f"{t} E_{x}" for x in TOLERANCES for t in titles]
    body = [["all", str(s["n"])] + [_pct(s["overall"][m][f"E_{x}"]) for x in TOLERANCES for m in methods]]
    for c in s["per_class"]:
        body.append([f"true {c['class']}", str(c["n"])] + [_pct(c[m][f"E_{x}"]) for x in TOLERANCES for m in methods])
    return markdown_table(header, body)


def _parameter_row(method: str, parameter: str, stats: Mapping[str, Any]) -> list[str]:
    """One line of the parameter-error table: relative errors in %, absolute ones as numbers."""
    relative = stats["kind"] == "relative"

    def size(v: float | None) -> str:  # a spread or size of errors
        return "–" if v is None else (f"{100 * v:.1f} %" if relative else _sig(v))

    mean = stats["mean"]
    mean_text = ("–" if mean is None else f"{100 * mean:+.1f} %") if relative else _sig(mean)
    within = [_pct(stats.get(f"within_{x}")) for x in TOLERANCES]
    return ([METHOD_TITLES[method], f"`{parameter}`", str(stats["n"]), str(stats["n_missing"]), mean_text,
             size(stats["std"]), size(stats["median_abs"])] + within)


def _confusion_lines(conf: Mapping[str, Any]) -> list[str]:
    """The SOM's structure confusion matrix and its accuracy."""
    lines = ["SOM structure confusion (rows: true class, columns: identified class)", ""]
    body = [[f"**{t}**"] + [str(v) for v in row] for t, row in zip(conf["true"], conf["matrix"])]
    lines += markdown_table(["true \\ identified"] + conf["predicted"], body)
    total = sum(sum(r) for r in conf["matrix"])
    diag = sum(conf["matrix"][i][i] for i in range(len(conf["true"])))
    return lines + ["", f"Structure accuracy: {diag} of {total} ({100 * diag / max(total, 1):.0f} %).", ""]


def _failure_notes(failures: Mapping[str, Any]) -> list[str]:
    """One note per method on its failed, stiff or invalid results."""
    notes = []
    if "som" in failures:
        som = failures["som"]
        notes.append(f"SOM: {som['n_error']} records failed the analysis"
                     + (f" (e.g. {som['examples'][0]})" if som["examples"] else "")
                     + f"; {som['n_stiff_no_f_e']} identified as stiff (no `f_e`, `V_J`: misses)")
    if "iv4" in failures:
        iv4 = failures["iv4"]
        notes.append(f"IV4: {iv4['n_invalid']} invalid results (misses)"
                     + (f", e.g. {iv4['examples'][0]}" if iv4["examples"] else ""))
    return notes


def timing_lines(timing: Mapping[str, Any], workers: int | None) -> list[str]:
    """Markdown lines: this run's wall time over the study (from :func:`run_study`), and how long the (possibly cached) results took to compute."""
    sets = timing["sets"]
    lines = [f"Wall time of this run's study (the command's start-up not counted): {timing['total_s']:.0f} s ("
             + ", ".join(f"{k} {v['s']:.0f} s" for k, v in sets.items()) + f"), {workers} workers."]
    done = []
    for name, v in sets.items():
        seen = set()
        for m, info in v["methods"].items():
            key = (info.get("compute_s"), tuple(info.get("methods_together", [m])))
            if key in seen:
                continue
            seen.add(key)
            if info.get("compute_s") is None:
                done.append(f"{name} {m}: from a cache without timing")
                continue
            load = info.get("loadavg") or [None, None]
            load_txt = "" if None in load else f", 1-min load average {load[0]:.1f} -> {load[1]:.1f} on {os.cpu_count()} cores"
            done.append(f"{name} ({'+'.join(key[1])}, {v['n']} systems): {info['compute_s']:.0f} s"
                        f"{' (cached)' if info.get('cached') else ''} with {info.get('workers')} workers{load_txt}"
                        f"{', ' + info['date'] if info.get('date') else ''}")
    lines += ["", "Simulation + identification time: " + "; ".join(done) + ".", ""]
    return lines


def render_markdown(summary: Mapping[str, Any], *, command: str = "", figures: Sequence[str] = (),
                    figure_note: str = "") -> str:
    """The whole report as markdown (figures linked by file name, relative to the report)."""
    methods = summary["methods"]
    lines = ["# twomass evaluate: SOM identification vs IV4", ""]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    t = summary.get("timing")
    if t:
        lines += timing_lines(t, summary.get("workers"))
    lines += ["`E_x` = share of systems whose `f_e`, `V_J` and `J_sigma` are all within x % relative error "
              "(paper section 4). A missing estimate is a miss: the SOM's `stiff` class has no `f_e`/`V_J`, "
              "IV4 results with `valid=False` count as misses.", ""]
    if summary.get("checks"):
        lines += ["## Acceptance checks", ""]
        for c in summary["checks"]:
            mark = {True: "PASS", False: "FAIL", None: "n/a"}[c["passed"]]
            lines.append(f"- **{mark}** {c['name']}: {c['detail']}")
        lines.append("")
    if "grid" in summary["sets"] and "cells" in summary["sets"]["grid"]:
        lines += ["## Paper grid (Fig. 10)", ""] + grid_tables(summary["sets"]["grid"], methods)
    lines += ["## Per set", ""]
    for name, s in summary["sets"].items():
        lines += set_tables(name, s, methods)
    lines += ["## Figures", ""]
    if figure_note:
        lines += [figure_note, ""]
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    return "\n".join(lines).rstrip() + "\n"


def _csv_rows(rows: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> tuple[list[str], list[list[Any]]]:
    header = ["set", "index", "cell_f_e", "cell_backlash_deg"] + [f"true_{k}" for k in TRUTH_KEYS]
    extra = {"som": ["structure", "error"], "maps": ["structure", "error"], "iv4": ["valid", "reason"]}
    for m in methods:
        header += [f"{m}_{k}" for k in METHOD_PARAMS[m] + tuple(extra[m])]
    out = []
    for r in rows:
        line = [r["set"], r["index"], r["cell_f_e"], r["cell_backlash_deg"]] + [r["truth"][k] for k in TRUTH_KEYS]
        for m in methods:
            line += [r[m].get(k) for k in METHOD_PARAMS[m] + tuple(extra[m])]
        out.append(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in line])
    return header, out


def _csv_text(header: Sequence[str], lines: Sequence[Sequence[Any]]) -> str:
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(lines)
    return buf.getvalue()


_STYLE = {"som": dict(color="tab:blue", marker="o"), "maps": dict(color="tab:green", marker="."),
          "iv4": dict(color="tab:red", marker="x")}  # colour and marker per method
_CEILING = 10.0  # where Fig. 9 draws a miss (1000 %)


def _plot(summary: Mapping[str, Any], rows_by_set: Mapping[str, Sequence[Mapping[str, Any]]],
          out: Path) -> list[str]:
    """Fig. 9 per set and Fig. 10 for the grid; raises ImportError without matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = summary["methods"]
    files = [_fig9(plt, name, rows, methods, out) for name, rows in rows_by_set.items() if rows]
    grid = summary["sets"].get("grid")
    if grid and "cells" in grid:
        files.append(_fig10(plt, grid, methods, out))
    return files


def _fig9(plt: Any, name: str, rows: Sequence[Mapping[str, Any]], methods: Sequence[str], out: Path) -> str:
    """Fig. 9 of set ``name``: each system's relative ``f_e`` error, systems sorted by ``s_N``."""
    s_N = np.array([r["truth"]["s_N"] for r in rows])
    order = np.argsort(s_N, kind="stable")
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    x = np.arange(len(rows))
    for m in methods:
        e = np.abs(relative_errors(rows, m, ("f_e",))["f_e"])[order]
        miss = ~np.isfinite(e)
        ax.scatter(x[~miss], np.maximum(e[~miss], 1e-5), s=8, label=f"{METHOD_TITLES[m]}", **_STYLE[m])
        if miss.any():
            ax.scatter(x[miss], np.full(miss.sum(), _CEILING), s=14, facecolors="none", edgecolors=_STYLE[m]["color"],
                       marker="^", label=f"{METHOD_TITLES[m]}: no f_e ({miss.sum()})")
    ax.axhline(0.3, color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_ylim(1e-5, _CEILING * 1.5)
    ax.set_ylabel("|relative f_e error|")
    ax.set_title(f"{name}: relative f_e error, systems sorted by s_N (paper Fig. 9); dashed: 30 %")
    ax.legend(loc="upper left", fontsize=8)
    ax2.plot(x, s_N[order], color="k", lw=1)
    ax2.set_yscale("symlog", linthresh=1e-2)
    ax2.axhline(1.0, color="gray", lw=0.8, ls=":")
    ax2.set_ylabel("s_N")
    ax2.set_xlabel("system (sorted by s_N)")
    fig.tight_layout()
    fname = _FIG9.format(name)
    fig.savefig(out / fname, dpi=110)
    plt.close(fig)
    return fname


def _fig10(plt: Any, grid: Mapping[str, Any], methods: Sequence[str], out: Path) -> str:
    """Fig. 10: ``E_50`` (left) and ``E_30`` (right) over ``f_e``, one line per backlash and method."""
    from matplotlib.ticker import NullFormatter

    cells = grid["cells"]
    bls = sorted({c["backlash_deg"] for c in cells})
    means = {b["backlash_deg"]: b for b in grid["backlash_means"]}
    f_es = sorted({c["f_e"] for c in cells})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, x in zip(axes, sorted(TOLERANCES, reverse=True)):
        key = f"E_{x}"
        for i, b in enumerate(bls):
            sub = sorted((c for c in cells if c["backlash_deg"] == b), key=lambda c: c["f_e"])
            f = [c["f_e"] for c in sub]
            for m in methods:
                y = [np.nan if c[m][key] is None else c[m][key] for c in sub]
                ax.plot(f, y, ls=_LINE[m], marker=_STYLE[m]["marker"], color=colors[i],
                        label=f"{METHOD_TITLES[m]} {b:g}° (mean {_pct(means[b][m][key])} %)")
        ax.set_xscale("log")
        ax.set_xticks(f_es)
        ax.set_xticklabels([f"{c:g}" for c in f_es])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(-3, 103)
        ax.set_xlabel("f_e [Hz]")
        ax.set_title(f"recognition rate E_{x} (f_e & V_J & J_sigma within {x} %)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    axes[0].set_ylabel("E_x [%]")
    fig.tight_layout()
    fig.savefig(out / _FIG10, dpi=110)
    plt.close(fig)
    return _FIG10


#: The report's files: its tables, a Fig. 9 per set, Fig. 10 of the grid.
_TABLES, _FIG9, _FIG10 = ("report.md", "report.json", "systems.csv"), "fig9_{}.png", "fig10_recognition.png"


def report_files(out_dir: str | os.PathLike[str], set_names: Sequence[str], *, plots: bool = True) -> list[Path]:
    """Every file :func:`write_report` may write for the sets ``set_names`` (so that a caller can refuse
    existing ones before any work): the tables, and with ``plots`` the figures."""
    names = list(_TABLES)
    if plots:
        names += [_FIG9.format(name) for name in set_names] + ([_FIG10] if "grid" in set_names else [])
    return [Path(out_dir) / n for n in names]


def write_report(summary: Mapping[str, Any], rows_by_set: Mapping[str, Sequence[Mapping[str, Any]]],
                 out_dir: str | os.PathLike[str], *, command: str = "", plots: bool = True) -> dict[str, Any]:
    """Write ``report.md``, ``report.json``, ``systems.csv`` and (if matplotlib imports) the PNGs.

    Returns ``{"files": [paths], "note": str}``; ``note`` is the one-line reason when figures were skipped.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    note = ""
    if plots:
        try:
            figures = _plot(summary, rows_by_set, out)
        except ImportError:
            note = NO_MATPLOTLIB
    md = render_markdown(summary, command=command, figures=figures, figure_note=note)
    header, lines = _csv_rows([r for rows in rows_by_set.values() for r in rows], summary["methods"])
    texts = (md, dumps({**summary, "command": command, "figures": figures}, indent=1) + "\n", _csv_text(header, lines))
    for name, text in zip(_TABLES, texts):
        _write_text(out / name, text)
    files = [out / n for n in (*_TABLES, *figures)]
    return {"files": [str(f) for f in files], "note": note}
