"""From one record to everything the maps need: sections, one-mass fit (STEP 2), named features.

:func:`analyze` is the single place where a record becomes numbers, so that training data and
identification can never disagree on the feature definition (``FEATURE_VERSION``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from training.identification._features import EXTRA_NAMES, FEATURE_SETS, eigenfrequency_features, extra_features, structure_features
from training.identification._one_mass import OneMassFit, fit_one_mass
from training.identification._oscillation import fit_oscillation
from training.identification._plausibility import check_record
from training.identification._sections import SectionSplit, detect_sections

#: Version of the whole feature vector below; stored in checkpoints and checked at recall.
FEATURE_VERSION = "twomass-features-v2"

#: Names of the feature vector's components, in order.
FEATURE_NAMES: tuple[str, ...] = (
    FEATURE_SETS["paper-eig-v1"].components + FEATURE_SETS["paper-struct-v1"].components + EXTRA_NAMES
    + ("log10_osc_quanta", "log10_f_fit", "log10_V_J_fit", "d_fit", "r2_fit")
)

#: Default encoder resolution when a record's metadata does not give one (SPEC reference drive).
_DEFAULT_ENCODER_COUNTS = 2**20
_DEFAULT_T_Ei = 5e-4


@dataclass
class Analysis:
    """One record, analysed.

    ``features``: ``(F,)`` float64 in the order of :data:`FEATURE_NAMES`.
    ``fit``: the STEP 2 one-mass fit (``J_sigma``, ``M_FC``, ``mu_F``, ``M_0``, ``w_osc``).
    ``M_star``: the test's torque amplitude [Nm] (metadata, else estimated from the record).
    ``osc_quanta``: rms of ``w_osc`` over the speed quantum ``q_w`` [rad/s] (how visible the oscillation is).
    ``T_Ei``: current-loop time constant [s] (metadata, else the reference drive's).
    """

    sections: SectionSplit
    fit: OneMassFit
    features: np.ndarray
    M_star: float
    T_s: float
    osc_quanta: float
    q_w: float
    T_Ei: float
    warnings: list[str] = field(default_factory=list)
    section_flags: list[str] = field(default_factory=list)

    def feature(self, name: str) -> float:
        return float(self.features[FEATURE_NAMES.index(name)])


def _torque(record: Any) -> np.ndarray:
    if getattr(record, "torque", None) is not None:
        return np.asarray(record.torque, dtype=np.float64)
    K_M = record.meta.get("K_M")
    if K_M is None:
        raise ValueError(f"{record.name}: K_M missing in the metadata, needed to turn current into torque")
    return np.asarray(record.current, dtype=np.float64) * float(K_M)


def analyze(record: Any) -> Analysis:
    """Sections, one-mass fit and features of one record (``sim.Record`` or alike).

    Raises:
        ValueError: one line, when the record has no recognisable test run.
    """
    check_record(record)  # units and metadata against the signals (training/plausibility.py)
    T_s = float(record.meta["T_s"])
    torque = _torque(record)
    split = detect_sections(record)
    fit = fit_one_mass(torque, record.speed, T_s, sections=split.bounds)
    w_osc = fit.w_osc
    eig = eigenfrequency_features(w_osc, T_s, split.bounds)
    struct = structure_features(w_osc, T_s, split.bounds)
    steps = np.diff(np.r_[0.0, split.levels])  # torque step at each section start [Nm]
    extra = extra_features(w_osc, T_s, split.bounds, J_sigma=fit.J_sigma, torque_steps=steps,
                           speed_span=float(np.ptp(record.speed)), structure=struct)
    counts = int(record.meta.get("encoder_counts") or _DEFAULT_ENCODER_COUNTS)
    q_w = 2.0 * math.pi / (counts * T_s)
    sel = np.concatenate([w_osc[a:b] for a, b in split.bounds.tolist()])
    osc_quanta = float(np.sqrt(np.mean(sel * sel))) / q_w if sel.size else 0.0
    f_peak = 10.0 ** extra[EXTRA_NAMES.index("log10_f_peak")] if extra[EXTRA_NAMES.index("log10_f_peak")] else 0.0
    osc = fit_oscillation(torque, w_osc, split.bounds, T_s, f_peak)
    V_J_fit = osc.gain * fit.J_sigma  # eq. 1: gain = V_J / J_sigma
    features = np.concatenate([eig, struct, extra, [
        math.log10(max(osc_quanta, 1e-3)),
        math.log10(osc.f_0) if osc.f_0 > 0 else 0.0,
        math.log10(V_J_fit) if V_J_fit > 1e-3 else -3.0,
        osc.d, osc.r2]])
    return Analysis(sections=split, fit=fit, features=features, M_star=float(split.M_star), T_s=T_s,
                    osc_quanta=osc_quanta, q_w=q_w,
                    T_Ei=float(record.meta.get("T_Ei") or _DEFAULT_T_Ei), warnings=list(fit.warnings), section_flags=list(split.flags))
