"""The study of SPEC 7 on a matrix of drives across SPEC 3.1's envelope (``twomass evaluate
--drives``): per drive, a population whose test time scale, friction and
torque fit that drive, simulated on it, identified with the maps, scored. The same on drives
drawn at random over the envelope (``--envelope-drives``, :func:`envelope_rows`): drives no
matrix chose.

Figures per drive: structure accuracy over systems at least 20 % from every class threshold,
``E_30`` and ``E_10`` over ``elastic`` + ``elastic_backlash``, ``J_sigma`` within 5 %, backlash
width within 30 % for ``s_N >= 0.3``, and the **silent-wrong rate**: the share of systems whose
answer is wrong (class wrong, or an elastic answer outside ``E_30``, or ``J_sigma`` off by 30 %)
with no warning at all. Beside ``E_30``, the same over the oscillations the encoder's speed shows
(``r_osc >= 1``, SPEC 1's visibility); beside the structure and the backlash figures, the same
over the gaps the record can show: those whose motor lead (:func:`training.identification.motor_lead`, the
backlash resolution's angle path) reaches :data:`~training.identification.BACKLASH_VISIBLE_COUNTS`
encoder counts (for the structure: every system but those whose backlash counts in the class rule,
``s_N >= 0.1``, and stays below that lead).

On SPEC 1.1's real axes (``--real-axis EFFECT``, :data:`REAL_AXIS_EFFECTS`: the load torque alone,
the motor friction alone, or both) the figures gain, over every system (a failed analysis counts as
off; an answer's ``None`` as 0): ``M_L0`` within 5 % of the test torque ``M*``, ``M_FC`` and ``M_FCM``
each within 1 % of ``M*``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from sim import (R_OSC_VISIBLE, S_N_ELASTIC, DriveConfig, EnvelopeRanges, PopulationRanges, RealAxisRanges,
                 TestSignalConfig,
                 TwoMassParams, inertia_of_time_scale, iter_records, sample_envelope, sample_population, time_scale)
from training.evaluation._answers import row_values, score_rows
from training.evaluation._confidence import warned_shares
from training.evaluation._metrics import relative_error, threshold_margin
from training.evaluation._report import markdown_table
from training.identification import BACKLASH_VISIBLE_COUNTS, motor_lead

@dataclass(frozen=True)
class DriveCase:
    """One drive of the matrix: the drive, its test signal and the test's time-scale range
    ``J_sigma w_max / M*`` [s] (the population's inertias follow from it)."""

    name: str
    description: str
    drive: DriveConfig
    signal: TestSignalConfig
    time_scale: tuple[float, float] = (0.1, 2.0)

    def ranges(self) -> PopulationRanges:
        """The default population's mechanics with inertias for :attr:`time_scale` and friction
        scaled to the test's torque (``M_FC`` up to 5 % of ``M*``, ``mu_F w_max`` up to 5 %)."""
        M, w = self.signal.M_star, self.signal.w_max
        return PopulationRanges(J_sigma=(inertia_of_time_scale(self.time_scale[0], M, w),
                                         inertia_of_time_scale(self.time_scale[1], M, w)),
                                M_FC=(0.0, 0.05 * M), mu_F=(0.0, 0.05 * M / w))

    def population(self, n: int, seed: int, real_axis: RealAxisRanges | bool = False) -> TwoMassParams:
        """``n`` systems of :meth:`ranges` (seed ``seed``); ``real_axis``: with SPEC 1.1's parts
        (``True``: :class:`sim.RealAxisRanges`' defaults, SPEC 1.1's population; ranges: those, e.g. an
        effect of :data:`REAL_AXIS_EFFECTS`), their shares of this drive's test torque and speed (the
        ranges are shares on the reference test). The same seed draws the same systems and parts
        whatever the ranges' shares (a part a range leaves out is 0 where it would be drawn)."""
        if real_axis is False:
            return sample_population(n, seed, self.ranges())
        if real_axis is True:
            real_axis = RealAxisRanges()
        if not isinstance(real_axis, RealAxisRanges):
            raise TypeError(f"real_axis: expected RealAxisRanges or a bool, received {type(real_axis).__name__}")
        r, reference = real_axis, TestSignalConfig()
        k = self.signal.M_star / reference.M_star  # the torques' scale
        k_w = k * reference.w_max / self.signal.w_max  # the viscous friction's, M*/w_max
        scaled = replace(r, M_L0=(r.M_L0[0] * k, r.M_L0[1] * k), M_FCM=(r.M_FCM[0] * k, r.M_FCM[1] * k),
                         mu_FM=(r.mu_FM[0] * k_w, r.mu_FM[1] * k_w))
        return sample_population(n, seed, self.ranges(), real_axis=scaled)


#: SPEC 1.1's real-axis parts one at a time and together (``twomass evaluate --real-axis EFFECT``):
#: ``both`` SPEC 1.1's population (``M_L0`` on half of the systems, ``M_FCM`` on half, ``mu_FM`` on
#: all); ``load`` the constant load torque alone (``M_L0`` on half, no motor friction); ``motor`` the
#: motor friction alone (``M_FCM`` on half, ``mu_FM`` on all, no ``M_L0``). Shares of the reference
#: test's ``M*`` and ``w_max`` (:meth:`DriveCase.population` scales them to the drive).
REAL_AXIS_EFFECTS: dict[str, RealAxisRanges] = {
    "both": RealAxisRanges(),
    "load": replace(RealAxisRanges(), M_FCM_share=0.0, mu_FM=(0.0, 0.0)),
    "motor": replace(RealAxisRanges(), M_L0_share=0.0),
}


def real_axis_effect(name: str) -> RealAxisRanges:
    """The ranges of the effect ``name`` of :data:`REAL_AXIS_EFFECTS`; another name: ``ValueError``."""
    if name not in REAL_AXIS_EFFECTS:
        raise ValueError(f"expected an effect of {', '.join(REAL_AXIS_EFFECTS)}, received {name!r}")
    return REAL_AXIS_EFFECTS[name]


def _case(name: str, description: str, M_N: float, w_max: float, time_scale: tuple[float, float] = (0.1, 2.0),
          noise: float = 0.001, **drive: Any) -> DriveCase:
    """A drive tested at ``M* = M_N`` with current noise ``noise`` x ``M*`` (std)."""
    K_M = drive.pop("K_M", 1.0)
    d = DriveConfig(M_N=M_N, M_max=drive.pop("M_max", 2.0 * M_N), K_M=K_M, current_noise_std=noise * M_N / K_M,
                    **drive)
    return DriveCase(name, description, d, TestSignalConfig(M_star=M_N, w_max=w_max), time_scale)


#: The matrix of drives: the reference drive and five others, each inside SPEC 3.1's envelope.
DRIVES: dict[str, DriveCase] = {c.name: c for c in (
    _case("reference", "the reference drive", 10.0, 100.0),
    _case("servo_200w", "200 W servo, 125 us, 2^17 counts", 0.64, 300.0, (0.05, 1.0), M_max=1.9, K_M=0.4,
          T_s=125e-6, T_Ei=2e-4, encoder_counts=2**17, noise=0.005),
    _case("low_res_1ms", "low-resolution drive, 1 ms, 2^13 counts", 10.0, 100.0, T_s=1e-3, T_Ei=1e-3,
          encoder_counts=2**13),
    _case("noisy", "reference drive with current noise 5 % of M*", 10.0, 100.0, noise=0.05),
    _case("large_axis", "large industrial axis, 500 us, 2^16 counts", 200.0, 150.0, M_max=600.0, K_M=2.0,
          T_s=5e-4, T_Ei=1.5e-3, encoder_counts=2**16),
    _case("fast_spindle", "fast spindle, 62.5 us, 2^22 counts", 5.0, 600.0, (0.05, 1.0), M_max=12.0,
          T_s=62.5e-6, T_Ei=1e-4, encoder_counts=2**22),
)}


def drive_rows(case: DriveCase, n: int, seed: int, identifier: Any,
               progress: Callable[[int], object] | None = None,
               real_axis: RealAxisRanges | bool = False) -> list[dict[str, Any]]:
    """Simulate ``n`` systems of ``case`` (``real_axis`` as :meth:`DriveCase.population`) and identify
    them; one row per system: ``truth`` (true parameters, ``s_N``, ``r_osc``, ``w_e_T_Ei``, class,
    the test torque ``M_star`` [Nm]) and ``som`` (``structure``, the parameters, ``n_warnings``,
    ``error`` and :func:`confidence_columns`)."""
    return _rows(case.population(n, seed, real_axis), case.drive, case.signal, seed, identifier, progress)


def envelope_rows(drives: int, per_drive: int, seed: int, identifier: Any,
                  progress: Callable[[int], object] | None = None) -> Iterator[tuple[str, str, list[dict[str, Any]]]]:
    """The drives of :func:`envelope_cases`, simulated and identified a drive at a time: (name, the
    drive in words, its rows as :func:`drive_rows`)."""
    for name, drive, signal, params, noise_seed in envelope_cases(drives, per_drive, seed):
        yield name, _describe(drive, signal, params), _rows(params, drive, signal, noise_seed, identifier, progress)


def envelope_cases(drives: int, per_drive: int, seed: int) -> Iterator[
        tuple[str, DriveConfig, TestSignalConfig, TwoMassParams, int]]:
    """``drives`` drives and test runs drawn at random over SPEC 3.1's envelope, ``per_drive`` systems
    each (:func:`sim.sample_envelope`: the maps' training distribution, with no cell on the reference
    drive): (name, drive, test, systems, noise seed)."""
    sample = sample_envelope(drives * per_drive, seed, EnvelopeRanges(cell=per_drive, reference_share=0.0))
    for k, (drive, signal) in enumerate(sample.cases):
        params = sample.params[torch.nonzero(sample.cell == k).flatten()]  # per_drive systems
        yield f"envelope_{k}", drive, signal, params, seed * 1000 + k


def _describe(drive: DriveConfig, signal: TestSignalConfig, params: TwoMassParams) -> str:
    """A drive and its test in words: sample time, encoder, current loop, torques, speed, noise,
    and the test time scales ``J_sigma w_max / M*`` of ``params``."""
    ts = time_scale(params.J_sigma, signal.M_star, signal.w_max)
    return (f"T_s {drive.T_s * 1e6:.4g} us, 2^{math.log2(drive.encoder_counts):.0f} counts, T_Ei "
            f"{drive.T_Ei * 1e3:.3g} ms, M_N {drive.M_N:.3g} Nm, M* {signal.M_star:.3g} Nm, w_max {signal.w_max:.3g} "
            f"rad/s, noise {100 * drive.current_noise(signal.M_star):.2g} % of M*, time scale "
            f"{float(ts.min()):.3g}..{float(ts.max()):.3g} s")


def _rows(params: TwoMassParams, drive: DriveConfig, signal: TestSignalConfig, seed: int, identifier: Any,
          progress: Callable[[int], object] | None) -> list[dict[str, Any]]:
    records = list(iter_records(params, drive, signal, seed=seed, progress=progress))
    rows = []
    for rec, out in zip(records, identifier.identify_records(records)):
        truth = dict(rec.info.truth)
        truth["w_e_T_Ei"] = truth["w_e"] * drive.T_Ei
        truth["gap_counts"] = motor_lead(truth["backlash"], truth["V_J"]) / drive.q_phi
        truth["M_star"] = signal.M_star  # the scale of the real-axis torques' figures
        som: dict[str, Any] = {"structure": None, "n_warnings": 0, "error": None}
        if out.ok:
            som.update(out.parameters.to_dict(), structure=out.structure, n_warnings=len(out.warnings),
                       **confidence_columns(out))
        else:
            som["error"] = out.error
        rows.append({"truth": truth, "som": som})
    return rows


def confidence_columns(result: Any) -> dict[str, Any]:
    """What the confidence study reads of one answer (JSON-able): ``intervals`` (parameter ->
    ``[low, high]``, or ``None`` without a calibration), ``probabilities`` (class -> probability),
    ``answer_probability`` (``None`` without a calibration), ``warning_codes`` and ``note_codes``."""
    return {"intervals": None if result.intervals is None else result.intervals.to_dict(),
            "probabilities": dict(result.quality.structure_probabilities),
            "answer_probability": result.quality.answer_probability,
            "warning_codes": [w.code for w in result.warnings], "note_codes": [w.code for w in result.notes]}


#: The real-axis figures of :func:`drive_figures`: name -> (parameter, tolerance as a share of the
#: test torque ``M*``).
REAL_AXIS_FIGURES: dict[str, tuple[str, float]] = {"M_L0_5": ("M_L0", 0.05), "M_FC_1": ("M_FC", 0.01),
                                                   "M_FCM_1": ("M_FCM", 0.01)}


def real_axis_figures(rows: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """Of :data:`REAL_AXIS_FIGURES`, each the share [%] of ``rows`` whose estimate lies within its
    tolerance times the row's ``truth["M_star"]`` [Nm] of the truth (an answer's ``None``: not
    identified, counts as 0; a failed analysis counts as off); ``None`` without rows. A row without
    ``M_star``: ``ValueError``."""
    if not rows:
        return {name: None for name in REAL_AXIS_FIGURES}
    M_star = row_values(rows, "truth", "M_star")
    if np.isnan(M_star).any():
        raise ValueError("real-axis figures: expected every row's truth to hold the test torque M_star [Nm]")
    answered = np.array([r["som"]["error"] is None for r in rows], dtype=bool)
    out: dict[str, float | None] = {}
    for name, (key, share) in REAL_AXIS_FIGURES.items():
        off = np.abs(np.nan_to_num(row_values(rows, "som", key), nan=0.0) - row_values(rows, "truth", key))
        out[name] = float(100.0 * (answered & (off <= share * M_star)).mean())  # a NaN truth: off
    return out


def drive_figures(rows: Sequence[dict[str, Any]], real_axis: bool = False) -> dict[str, Any]:
    """The figures of one drive (module docstring), in percent, with the counts they rest on;
    ``real_axis``: with :func:`real_axis_figures` (rows of a real-axis population)."""
    truth = {k: row_values(rows, "truth", k) for k in ("w_e_T_Ei", "s_N", "r_osc", "backlash")}
    far = threshold_margin({k: truth[k] for k in ("w_e_T_Ei", "s_N", "r_osc")}) >= 0.2
    score = score_rows(rows)
    correct, elastic = score.class_right, score.elastic
    elastic_visible = elastic & (truth["r_osc"] >= R_OSC_VISIBLE)  # an oscillation the encoder's speed shows
    e30, e10 = score.recognized(30), score.recognized(10)
    j_err = np.nan_to_num(score.errors["J_sigma"], nan=np.inf)
    wide = truth["s_N"] >= 0.3
    shows = row_values(rows, "truth", "gap_counts") >= BACKLASH_VISIBLE_COUNTS
    visible = wide & shows
    far_visible = far & (shows | (truth["s_N"] < S_N_ELASTIC))
    bl = np.zeros(len(rows), dtype=bool)
    bl[wide] = np.nan_to_num(relative_error(row_values(rows, "som", "backlash")[wide], truth["backlash"][wide]),
                             nan=np.inf) <= 0.3
    silent = score.wrong & ~score.warned & ~score.failed
    pct = lambda mask, over: float(100.0 * mask[over].mean()) if over.any() else None  # noqa: E731
    every = np.ones(len(rows), dtype=bool)
    shares = warned_shares(rows)
    return {"n": len(rows), "failed": int(score.failed.sum()),
            "structure": pct(correct, far), "n_structure": int(far.sum()),
            "structure_visible": pct(correct, far_visible), "n_structure_visible": int(far_visible.sum()),
            "E_30": pct(e30, elastic), "E_10": pct(e10, elastic), "n_elastic": int(elastic.sum()),
            "E_30_visible": pct(e30, elastic_visible), "n_elastic_visible": int(elastic_visible.sum()),
            "J_sigma_5": pct(j_err <= 0.05, every), "backlash_30": pct(bl, wide), "n_backlash": int(wide.sum()),
            "backlash_30_visible": pct(bl, visible), "n_backlash_visible": int(visible.sum()),
            "silent_wrong": pct(silent, every), "warned": pct(score.warned, every),
            "right_warned": shares.right_warned, "n_right": shares.n_right,
            "wrong_unwarned": shares.wrong_unwarned, "n_wrong": shares.n_wrong,
            **(real_axis_figures(rows) if real_axis else {})}


def drives_markdown(figures: dict[str, dict[str, Any]], command: str, descriptions: dict[str, str] | None = None,
                    title: str = "Identification on a matrix of drives") -> str:
    """The per-drive table (``figures``: drive name -> :func:`drive_figures`; ``descriptions``: drive
    name -> the drive in words, default those of :data:`DRIVES`)."""
    fmt = lambda v: "n/a" if v is None else f"{v:.1f}"  # noqa: E731
    descriptions = {name: case.description for name, case in DRIVES.items()} if descriptions is None else descriptions
    header = ["drive", "n", "failed", "structure (n)", "of them visible (n)", "E_30", "E_10 (n elastic)",
              "E_30 visible (n)", "J_sigma 5 %",
              "backlash 30 % (n)", "of them visible (n)", "silent wrong", "warned", "right warned (n)",
              "wrong unwarned (n)"]
    rows = [[f"{name}: {descriptions.get(name, '')}", str(f["n"]), str(f["failed"]),
             f"{fmt(f['structure'])} ({f['n_structure']})", f"{fmt(f['structure_visible'])} ({f['n_structure_visible']})",
             fmt(f["E_30"]), f"{fmt(f['E_10'])} ({f['n_elastic']})",
             f"{fmt(f['E_30_visible'])} ({f['n_elastic_visible']})", fmt(f["J_sigma_5"]),
             f"{fmt(f['backlash_30'])} ({f['n_backlash']})", f"{fmt(f['backlash_30_visible'])} ({f['n_backlash_visible']})",
             fmt(f["silent_wrong"]), fmt(f["warned"]), f"{fmt(f['right_warned'])} ({f['n_right']})",
             f"{fmt(f['wrong_unwarned'])} ({f['n_wrong']})"] for name, f in figures.items()]
    real_axis = bool(figures) and all(k in f for f in figures.values() for k in REAL_AXIS_FIGURES)
    if real_axis:  # the real-axis torques' columns
        header += ["M_L0 5 % of M*", "M_FC 1 % of M*", "M_FCM 1 % of M*"]
        rows = [row + [fmt(f[k]) for k in REAL_AXIS_FIGURES] for row, f in zip(rows, figures.values())]
    lines = [f"# {title}", "", f"Made by `{command}`.", "", *markdown_table(header, rows)]
    lines += ["", "Figures in %. Structure over systems >= 20 % from every class threshold; E_x over elastic + "
              f"elastic_backlash, E_30 visible over those whose r_osc reaches {R_OSC_VISIBLE:g} (the oscillation "
              "shows in the encoder's speed); backlash over s_N >= 0.3; visible: of those the gaps whose motor lead "
              f"2s V_J / (1 + V_J) reaches {BACKLASH_VISIBLE_COUNTS:g} encoder counts (for the structure: all but the "
              f"systems with s_N >= {S_N_ELASTIC:g} whose lead stays below that); silent wrong: class wrong, or an "
              "elastic answer outside E_30, or J_sigma off by 30 %, with no warning (a failed analysis is not silent); "
              "right warned: of the answers that are not wrong, those with a warning (SPEC 4.1: at most 10 %); wrong "
              "unwarned: of the wrong answers (failed analyses left out), those with none (at most 1 %)."
              + (" M_L0, M_FC, M_FCM: of all systems those whose estimate lies within 5 %, 1 %, 1 % of the "
                 "test torque M* of the truth (an answer without it counts as 0, a failed analysis as off)."
                 if real_axis else ""), ""]
    return "\n".join(lines)
