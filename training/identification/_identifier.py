"""Identification of a record with the shipped maps (SPEC sections 4 and 9).

An app needs three lines::

    from training.identification._identifier import Identifier
    ident = Identifier.load()                   # shipped maps, checked against the manifest
    result = ident.identify_file("run.csv")     # or ident.identify(record) / identify_records([...])

The result is a JSON-able dict: ``structure`` (a class of ``sim.STRUCTURE_CLASSES``),
``parameters`` (SI units, ``backlash`` = total width ``2s`` [rad]; ``None`` where not identified),
``quality`` (figures that say how far to trust it) and ``warnings``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

import som_torch as st
from sim import Record, read_record
from sim.params import STRUCTURE_CLASSES, DriveConfig, TwoMassParams, structure_class
from training.identification._analysis import FEATURE_NAMES, Analysis, analyze
from training.identification._maps import MAP_SPECS, TrainedMap, load_map, recall_targets
from training.identification._refine import RefineConfig, RefineProblem, Refined, refine, torque_reference

#: Where the shipped maps lie (override with ``$TWOMASS_CHECKPOINTS`` or ``Identifier.load(folder)``).
DEFAULT_CHECKPOINTS = Path(os.environ.get("TWOMASS_CHECKPOINTS", Path(__file__).resolve().parents[2] / "checkpoints"))

PARAMETER_NAMES: tuple[str, ...] = ("J_sigma", "V_J", "J_M", "J_L", "f_e", "C_F", "d", "backlash", "M_FC", "mu_F")
_BACKLASH_CLASSES = ("elastic_backlash", "stiff_backlash")


class Identifier:
    """Trained maps, loaded once; identifies records (one at a time or many in one batch).

    ``refine``: the model-based refinement of the maps' answer (:mod:`training.identification._refine`); ``None``
    gives the maps' answer alone (the paper's method)."""

    def __init__(self, maps: dict[str, TrainedMap], refine: RefineConfig | None = RefineConfig()) -> None:
        missing = [n for n in MAP_SPECS if n not in maps]
        if missing:
            raise ValueError(f"Identifier: maps missing: {missing}; expected {list(MAP_SPECS)}")
        if refine is not None and not isinstance(refine, RefineConfig):
            raise TypeError(f"refine: expected a RefineConfig or None, received {type(refine).__name__}")
        self.maps = maps
        self.refine = refine
        self.M_N = float(maps["backlash"].metadata["dataset"]["drive"]["M_N"])

    @classmethod
    def load(cls, folder: str | os.PathLike[str] | None = None, *,
             refine: RefineConfig | None = RefineConfig()) -> "Identifier":
        """Load every map of ``folder`` (default: the shipped ``checkpoints/``) after checking
        the manifest's SHA-256 of each file."""
        folder = Path(folder) if folder is not None else DEFAULT_CHECKPOINTS
        st.verify_manifest(folder)
        return cls({name: load_map(folder / f"{name}.pt") for name in MAP_SPECS}, refine)

    def identify(self, record: Record) -> dict[str, Any]:
        """Identify one record; raises ValueError (one line) when it cannot be analysed."""
        return self.identify_analyses([analyze(record)])[0]

    def identify_records(self, records: Sequence[Record]) -> list[dict[str, Any]]:
        """One result per record, in order; a record that cannot be analysed gets ``{"error": ...}``."""
        analyses: list[Analysis | str] = []
        for r in records:
            try:
                analyses.append(analyze(r))
            except ValueError as err:
                analyses.append(_one_line(err))
        good = [a for a in analyses if isinstance(a, Analysis)]
        results = iter(self.identify_analyses(good))
        return [next(results) if isinstance(a, Analysis) else {"error": a} for a in analyses]

    def identify_file(self, path: str | os.PathLike[str]) -> dict[str, Any]:
        """Read and identify one record file; errors become ``{"error": ...}``."""
        return self.identify_files([path])[0]

    def identify_files(self, paths: Iterable[str | os.PathLike[str]]) -> list[dict[str, Any]]:
        """``{"record": path, ...result}`` per path, in the order given (errors per record)."""
        paths = [str(p) for p in paths]
        records: list[Record | str] = []
        for p in paths:
            try:
                records.append(read_record(p))
            except (ValueError, OSError) as err:
                records.append(_one_line(err))
        good = [r for r in records if isinstance(r, Record)]
        results = iter(self.identify_records(good))
        out = []
        for p, r in zip(paths, records):
            res = next(results) if isinstance(r, Record) else {"error": r}
            out.append({"record": p, **res})
        return out

    def identify_analyses(self, analyses: Sequence[Analysis]) -> list[dict[str, Any]]:
        """Recall all maps for a batch of analysed records (one tensor computation per map)."""
        if not analyses:
            return []
        F = np.stack([a.features for a in analyses])  # M x F
        recalled = {}
        for name, m in self.maps.items():
            cols = [FEATURE_NAMES.index(f) for f in m.spec.features]
            recalled[name] = recall_targets(m, F[:, cols], int(m.metadata["train_config"]["interpolate"]))
        results = [self._assemble(a, {n: {k: float(v[i]) for k, v in r.items()} for n, r in recalled.items()})
                   for i, a in enumerate(analyses)]
        if self.refine is not None:
            # stiff answers are refined too where the oscillation shows above the quantization
            # (near the w_e T_Ei = 1 threshold the maps' f_e decides the class)
            todo = [i for i, (a, res) in enumerate(zip(analyses, results))
                    if res["structure"] != "stiff" or a.osc_quanta >= 1.0]
            problems = [self._problem(analyses[i], results[i]) for i in todo]
            for i, refined in zip(todo, refine(problems, self.refine)):
                self._apply_refined(analyses[i], results[i], refined)
        return results

    def _assemble(self, a: Analysis, r: dict[str, dict[str, float]]) -> dict[str, Any]:
        warnings = list(a.warnings)
        fit = a.fit
        f_fit, V_J_fit = a.feature("log10_f_fit"), a.feature("log10_V_J_fit")
        # the maps store corrections to the eq.-1 fit (training.identification._maps.TARGETS)
        f_e = 10.0 ** (f_fit + r["f_e"]["dlog10_f_e"])
        V_J = 10.0 ** (V_J_fit + r["V_J"]["dlog10_V_J"])
        d = min(max(r["f_e"]["d"], 0.0), 0.9)
        J_M = fit.J_sigma / (1.0 + V_J)
        J_L = fit.J_sigma - J_M
        w_0 = 2 * math.pi * f_e / math.sqrt(1.0 - d * d)
        C_F = w_0 * w_0 * J_M * J_L / fit.J_sigma
        structure, probs = self._structure(a, r, f_e, V_J, w_0)
        M_N = self.M_N
        p: dict[str, float | None] = dict.fromkeys(PARAMETER_NAMES)
        p.update(J_sigma=fit.J_sigma, M_FC=max(fit.M_FC, 0.0), mu_F=max(fit.mu_F, 0.0), backlash=0.0)
        if structure != "stiff":
            p.update(f_e=f_e, V_J=V_J, d=d, J_M=J_M, J_L=J_L, C_F=C_F)
        if structure in _BACKLASH_CLASSES:  # s_N = s C_F / M_N, backlash = 2 s
            p["backlash"] = 2.0 * 10.0 ** r["backlash"]["log10_s_N"] * M_N / C_F
        # how far each recall lies from the training data: distance over the training 99 % quantile
        unseen = {}
        for name, m in self.maps.items():
            q99 = m.metadata["distance_quantiles"]["0.99"]
            unseen[name] = r[name]["distance"] / q99 if q99 > 0 else float("inf")
        used = ["structure"] + (["f_e", "V_J"] if structure != "stiff" else []) + \
               (["backlash"] if structure in _BACKLASH_CLASSES else [])
        for name in used:
            if unseen[name] > 1.0:
                warnings.append(f"record unlike the training data of the {name} map "
                                f"(distance {unseen[name]:.2f} x its 99 % quantile)")
        quality = {
            "structure_probabilities": probs,
            "map_distance_ratio": unseen,
            "osc_quanta": a.osc_quanta,
            "oscillation_fit_r2": a.feature("r2_fit"),
            "one_mass_rel_residual": fit.rel_residual,
            "outside_training": any(unseen[n] > 1.0 for n in used),
            "section_flags": a.section_flags,
            "maps_estimate": {"f_e": f_e, "V_J": V_J, "d": d, "s_N": 10.0 ** r["structure"]["log10_s_N"]},
        }
        if a.osc_quanta < 1.0 and structure != "stiff":
            warnings.append(f"oscillation only {a.osc_quanta:.2f} speed quanta rms: elastic parameters uncertain")
        return {"structure": structure, "parameters": p, "quality": quality, "warnings": warnings}

    def _problem(self, a: Analysis, res: dict[str, Any]) -> RefineProblem:
        """The refinement of one maps' answer: the record's replayed test signal, STEP 2's
        one-mass values, and the maps' ``f_e``, ``V_J``, ``d``, ``s_N`` as the start."""
        b = a.sections.bounds
        start, level = torque_reference(b, a.M_star)
        p = res["quality"]["maps_estimate"]
        segments = np.concatenate([b, [[b[5, 1], len(a.fit.speed)]]])  # the six sections and the tail
        s_N = max(p["s_N"], 1e-3)
        return RefineProblem(speed=a.fit.speed, start=start, level=level, segments=segments, J_sigma=a.fit.J_sigma,
                             M_FC=max(a.fit.M_FC, 0.0), mu_F=max(a.fit.mu_F, 0.0), T_s=a.T_s, T_Ei=a.T_Ei,
                             encoder_counts=_encoder_counts(a), M_N=self.M_N, free_one_mass=bool(a.fit.warnings),
                             theta=np.array([math.log10(p["f_e"]), math.log10(p["V_J"]), p["d"], math.log10(s_N)]))

    def _apply_refined(self, a: Analysis, res: dict[str, Any], m: Refined) -> None:
        """Replace the maps' elastic parameters and backlash width by the refined ones; the
        structure follows SPEC's class rules on the refined values (the maps' class and estimate
        stay in ``quality``). A ``stiff`` result keeps the one-mass answer."""
        J_sigma = a.fit.J_sigma if m.J_sigma is None else m.J_sigma
        model = TwoMassParams.from_dicts(dict(J_sigma=J_sigma, V_J=m.V_J, f_e=m.f_e, d=m.d, backlash=m.backlash,
                                              M_FC=0.0, mu_F=0.0))
        drive = DriveConfig(M_N=self.M_N, T_Ei=a.T_Ei, T_s=a.T_s, encoder_counts=_encoder_counts(a))
        structure = STRUCTURE_CLASSES[int(structure_class(model, drive, a.M_star).reshape(-1)[0])]
        p = res["parameters"]
        if m.J_sigma is not None:  # STEP 2 flagged its fit; the whole-record fit replaced it
            p.update(J_sigma=m.J_sigma, M_FC=m.M_FC)
            res["warnings"].append("J_sigma and M_FC from the two-mass fit of the whole record "
                                   "(the one-mass fit of STEP 2 was not trusted)")
        p.update(f_e=m.f_e, V_J=m.V_J, d=m.d, J_M=float(model.J_M.reshape(-1)[0]), J_L=float(model.J_L.reshape(-1)[0]),
                 C_F=float(model.C_F.reshape(-1)[0]),
                 backlash=m.backlash)  # measured even where the class calls it negligible (elastic)
        if structure == "stiff":
            p.update(f_e=None, V_J=None, d=None, J_M=None, J_L=None, C_F=None, backlash=0.0)
        res["quality"].update(maps_structure=res["structure"], refine_residual=m.residual,
                              refine_start_residual=m.start_residual, refined_s_N=m.s_N)
        res["structure"] = structure
        if m.residual > 0.7 and structure != "stiff":
            res["warnings"].append(f"the refined model reproduces only part of the measured oscillation "
                                   f"(residual {m.residual:.2f} of its rms)")

    def _structure(self, a: Analysis, r: dict[str, dict[str, float]], f_e: float, V_J: float,
                   w_0: float) -> tuple[str, dict[str, float]]:
        """SPEC's stiff rule on the identified values (``w_e T_Ei >= 1`` or ``r_osc < 1``, and the
        map's ``s_N < 0.1``); otherwise the structure map's most likely of the other classes."""
        probs = {c: r["structure"][f"p_{c}"] for c in STRUCTURE_CLASSES}
        s_N = 10.0 ** r["structure"]["log10_s_N"]
        r_osc = V_J * a.M_star / (a.fit.J_sigma * w_0 * a.q_w)
        if s_N < 0.1 and (2 * math.pi * f_e * a.T_Ei >= 1.0 or r_osc < 1.0):
            return "stiff", probs
        others = [c for c in STRUCTURE_CLASSES if c != "stiff"]
        return max(others, key=probs.get), probs


def _encoder_counts(a: Analysis) -> int:
    """The record's encoder counts per revolution, from its speed quantum ``q_w = 2 pi / (counts T_s)``."""
    return int(round(2.0 * math.pi / (a.q_w * a.T_s)))


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__
