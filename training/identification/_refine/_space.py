"""The refinement's search space: its coordinates and their bounds."""

from __future__ import annotations

import math

import numpy as np

#: Search coordinates and their bounds: log10 f_e [Hz], log10 V_J, d, log10 s_N (normalized
#: backlash; measured better than searching the width itself: 86 vs 66 % of the widths within 30 %).
COORDINATES: tuple[str, ...] = ("log10_f_e", "log10_V_J", "d", "log10_s_N")
LOW = np.array([0.0, math.log10(0.05), 0.001, -3.0])
HIGH = np.array([math.log10(3000.0), math.log10(20.0), 0.5, 2.0])
#: Where STEP 2's one-mass part is not trusted, three more: log10 J_sigma [kg m^2], M_FC [Nm] and
#: mu_F [Nm s/rad], bounded by the record's own scales (:func:`._free.free_bounds`).
FREE_COORDINATES: tuple[str, ...] = COORDINATES + ("log10_J_sigma", "M_FC", "mu_F")
NO_GAP = math.log10(2e-3)  # log10 s_N at or below which a model has no gap (the search's floor is 1e-3)
