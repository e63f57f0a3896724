"""The measured frequency response of the plant on the drive (SPEC 8.2): what the closed-loop
frequency-response experiment hands to the design."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MeasuredResponse"]


@dataclass(frozen=True)
class MeasuredResponse:
    """The plant's response from the torque reference to the measured motor speed, measured on the
    drive, in the convention of ``LinearPlant.speed_response`` (``M_ref`` computed at sample ``k``
    and applied from ``k+1``, the speed measured as the angle gained over the last sample: both
    sample delays included), so that ``C(z) F(z) G`` is the loop the law closes.

    ``w`` [rad/s] (``F``, increasing, up to Nyquist), ``G`` (``F``, complex, [rad/s / Nm]),
    ``coherence`` (``F``, in [0, 1]: how much of the measured speed the injected torque explains),
    ``T_s`` [s].
    """

    w: np.ndarray
    G: np.ndarray
    coherence: np.ndarray
    T_s: float
