"""Input checks shared by the signal-processing modules (one-line errors naming the input)."""

from __future__ import annotations

from typing import Any

import numpy as np


def as_signal(name: str, x: Any) -> np.ndarray:
    """``x`` as a float64 1-D array of finite values; ValueError/TypeError naming ``name`` otherwise."""
    if isinstance(x, (str, bytes)):
        raise TypeError(f"{name}: expected a 1-D array of numbers, received {type(x).__name__}")
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array (N,), received shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, received {int(np.sum(~np.isfinite(arr)))} NaN/inf")
    return arr
