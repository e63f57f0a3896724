"""From one record to everything the maps need: sections, one-mass fit (STEP 2), named features.

:func:`analyze` is the single place where a record becomes numbers, so that training data and
identification can never disagree on the feature definition (``FEATURE_VERSION``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim import Record
from training.errors import IdentificationError, one_line
from training.identification._drive import REFERENCE_DRIVE, DriveValues, drive_values
from training.identification._features import (EIG_NAMES, EXTRA_NAMES, STRUCT_NAMES, eigenfrequency_features,
                                               extra_features, structure_features)
from training.identification._one_mass import OneMassFit, fit_one_mass
from training.identification._oscillation import fit_oscillation
from training.identification._plausibility import check_record
from training.identification._result import IdentWarning
from training.identification._sections import SectionSplit, detect_sections

#: Version of the whole feature vector below; stored in checkpoints and checked at recall.
FEATURE_VERSION = "twomass-features-v2"

#: Names of the feature vector's components, in order.
FEATURE_NAMES: tuple[str, ...] = (
    EIG_NAMES + STRUCT_NAMES + EXTRA_NAMES + ("log10_osc_quanta", "log10_f_fit", "log10_V_J_fit", "d_fit", "r2_fit")
)

__all__ = ["FEATURE_VERSION", "FEATURE_NAMES", "REFERENCE_DRIVE", "Analysis", "analyze"]


class _FromDrive:
    """A drive value of an :class:`Analysis`: the attribute of the same name of its ``drive``."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(obj.drive, self.name)


@dataclass(frozen=True)
class Analysis:
    """One record, analysed.

    ``features``: ``(F,)`` float64 in the order of :data:`FEATURE_NAMES`.
    ``fit``: the STEP 2 one-mass fit (``J_sigma``, ``M_FC``, ``mu_F``, ``M_0``, ``w_osc``).
    ``drive``: the drive and test values (SPEC 3: from the record, else estimated or defaulted;
    :mod:`training.identification._drive`); ``M_star``, ``T_s``, ``T_Ei``, ``encoder_counts``,
    ``M_N``, ``q_w`` read from it.
    ``osc_quanta``: rms of ``w_osc`` over the speed quantum :attr:`q_w` (how visible the oscillation is).
    ``warnings``: STEP 2's and the drive values' (coded); ``section_flags``: the section detection's notes.
    """

    sections: SectionSplit
    fit: OneMassFit
    features: np.ndarray
    drive: DriveValues
    osc_quanta: float
    warnings: tuple[IdentWarning, ...] = ()
    section_flags: tuple[str, ...] = ()

    M_star, T_s, T_Ei, encoder_counts, M_N, q_w = (_FromDrive() for _ in range(6))  # read from ``drive``

    def feature(self, name: str) -> float:
        return float(self.features[FEATURE_NAMES.index(name)])


def analyze(record: Record) -> Analysis:
    """Sections, one-mass fit and features of one record.

    Raises:
        IdentificationError: one line, when the record cannot be analysed (implausible units,
            no recognisable test run, an uninformative one-mass fit, a missing ``K_M``).
    """
    try:
        return _analyze(record)
    except IdentificationError:
        raise
    except ValueError as err:  # RecordError, plausibility, sections, fit
        raise IdentificationError(one_line(err)) from err


def _analyze(record: Record) -> Analysis:
    check_record(record)  # units and metadata against the signals
    T_s = record.T_s
    torque = record.motor_torque
    split = detect_sections(record)
    fit = fit_one_mass(torque, record.speed, T_s, sections=split.bounds)
    w_osc = fit.w_osc
    eig = eigenfrequency_features(w_osc, T_s, split.bounds)
    struct = structure_features(w_osc, T_s, split.bounds)
    steps = np.diff(np.r_[0.0, split.levels])  # torque step at each section start [Nm]
    extra = extra_features(w_osc, T_s, split.bounds, J_sigma=fit.J_sigma, torque_steps=steps,
                           speed_span=float(np.ptp(record.speed)), structure=struct)
    drive, drive_warnings = drive_values(record, split, torque)
    q_w = drive.q_w
    sel = np.concatenate([w_osc[a:b] for a, b in split.bounds.tolist()])
    osc_quanta = float(np.sqrt(np.mean(sel * sel))) / q_w if sel.size else 0.0
    log10_f_peak = extra[EXTRA_NAMES.index("log10_f_peak")]
    osc = fit_oscillation(torque, w_osc, split.bounds, T_s, 10.0 ** log10_f_peak if log10_f_peak else 0.0)
    V_J_fit = osc.gain * fit.J_sigma  # eq. 1: gain = V_J / J_sigma
    features = np.concatenate([eig, struct, extra, [
        math.log10(max(osc_quanta, 1e-3)),
        math.log10(osc.f_0) if osc.f_0 > 0 else 0.0,
        math.log10(V_J_fit) if V_J_fit > 1e-3 else -3.0,
        osc.d, osc.r2]])
    return Analysis(sections=split, fit=fit, features=features, drive=drive, osc_quanta=osc_quanta,
                    warnings=fit.warnings + tuple(drive_warnings), section_flags=split.flags)
