"""The speed-controller law of SPEC 8.1: a discrete PI speed controller with an optional speed
low-pass and an optional notch on the torque reference.

:class:`PISpeedLaw` keeps the law contract (``params``, ``reset()``, ``step(w_meas, w_ref) ->
M_ref``, computed at sample k, applied from k+1): a drive runs it sample by sample, or loads its
``params`` into its own controller. Gains may be numpy arrays ``B`` (then ``step`` takes and returns
arrays ``B``): the linear model runs many candidates side by side with the same code. Units SI:
torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s].
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["NotchSpec", "PISpeedLaw", "HoldLaw", "as_notches", "MAX_NOTCHES"]

#: The most notches the law applies in series (SPEC 8.1: up to two).
MAX_NOTCHES: int = 2


@dataclass(frozen=True)
class NotchSpec:
    """Notch ``(s^2 + 2 D_z w_n s + w_n^2)/(s^2 + 2 D_p w_n s + w_n^2)`` on the torque reference.

    ``f_n`` [Hz] centre, ``D_z`` (depth: gain at ``f_n`` = ``D_z/D_p``) and ``D_p`` (width).
    Discretized by Tustin with pre-warping at ``f_n``.
    """

    f_n: float
    D_z: float = 0.05
    D_p: float = 0.5

    def coefficients(self, T_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Biquad ``(b0, b1, b2), (1, a1, a2)`` in powers of ``z^-1``."""
        w_n = 2.0 * math.pi * self.f_n
        if not 0 < w_n * T_s < math.pi:
            raise ValueError(f"notch f_n={self.f_n} Hz: expected below the Nyquist frequency {0.5 / T_s} Hz")
        c = w_n / math.tan(w_n * T_s / 2.0)  # pre-warped Tustin constant
        def poly(D: float) -> np.ndarray:
            return np.array([c * c + 2 * D * w_n * c + w_n**2, 2 * (w_n**2 - c * c), c * c - 2 * D * w_n * c + w_n**2])
        b, a = poly(self.D_z), poly(self.D_p)
        return b / a[0], a / a[0]


def as_notches(notch: Any) -> tuple[NotchSpec, ...]:
    """The law's notches in series from ``notch``: None (none), one :class:`NotchSpec`, or a tuple
    or list of at most :data:`MAX_NOTCHES` of them; else a one-line error naming ``notch``."""
    if notch is None:
        return ()
    if isinstance(notch, NotchSpec):
        return (notch,)
    if isinstance(notch, (tuple, list)) and all(isinstance(n, NotchSpec) for n in notch):
        if len(notch) > MAX_NOTCHES:
            raise ValueError(f"notch: expected at most {MAX_NOTCHES} notches, received {len(notch)}")
        return tuple(notch)
    raise TypeError(f"notch: expected None, a NotchSpec or a tuple of up to {MAX_NOTCHES}, received {type(notch).__name__}")


def _array(value: Any, name: str) -> np.ndarray:
    """``value`` (a number, numpy array or CPU torch tensor) as a float64 array; else ``TypeError`` naming it."""
    if value is None:  # np.asarray(None, float) would be NaN
        raise TypeError(f"{name}: expected a number or an array of numbers, received None")
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name}: expected a number or an array of numbers, received {type(value).__name__} "
                        f"({str(err).splitlines()[0] if str(err) else 'not convertible'})") from None


def _positive(value: Any, name: str) -> float:
    """``value`` as a float if it is a finite real number > 0 (not a bool); else a one-line error naming it."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name}: expected a finite number > 0, received {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a finite number > 0, received {value!r}")
    return float(value)


def _gain(value: Any, name: str, positive: bool) -> np.ndarray:
    """``value`` as a float64 array of finite values > 0 (``positive``) or >= 0; else a one-line error naming it."""
    values = _array(value, name)
    bad = (values <= 0) if positive else (values < 0)
    if not np.isfinite(values).all() or bad.any():
        raise ValueError(f"{name}: expected finite values {'> 0' if positive else '>= 0'}, received {value}")
    return values


class PISpeedLaw:
    """Discrete PI speed controller (SPEC 8.1 law). Per sample (``e = w_ref - w_f``)::

        w_f = a w_f + (1-a) w_meas,  a = exp(-T_s/T_f)   (T_f = 0: w_f = w_meas; first sample: w_f = w_meas)
        I   = I + Kp T_s/Ti e        (not while the output saturates in the sign of e)
        u   = Kp e + I;  v = notch_2(notch_1(u));  M_ref = clamp(v, -M_max, M_max)

    Args:
        Kp [Nm s/rad], Ti [s], T_f [s] (0: no low-pass): floats, or arrays ``B`` (broadcast).
        T_s: sample time [s]. M_max: torque limit [Nm] (finite real numbers > 0). notch: None, a
        :class:`NotchSpec` or a tuple of up to two, applied in series (:attr:`notches`; ``notch``
        is the first or None). ``step`` takes numbers, numpy arrays or CPU torch tensors.
    """

    def __init__(self, Kp: Any, Ti: Any, *, T_s: float, M_max: float, T_f: Any = 0.0,
                 notch: NotchSpec | tuple[NotchSpec, ...] | None = None) -> None:
        self.Kp, self.Ti, self.T_f = _gain(Kp, "Kp", True), _gain(Ti, "Ti", True), _gain(T_f, "T_f", False)
        T_s, M_max = _positive(T_s, "T_s"), _positive(M_max, "M_max")
        self.notches = as_notches(notch)
        self.notch = self.notches[0] if self.notches else None
        self.T_s, self.M_max = T_s, M_max
        self.shape = np.broadcast_shapes(self.Kp.shape, self.Ti.shape, self.T_f.shape)
        self._ki = self.Kp * self.T_s / self.Ti
        self._a = np.where(self.T_f > 0, np.exp(-self.T_s / np.maximum(self.T_f, 1e-300)), 0.0)
        self._biquads = [n.coefficients(self.T_s) for n in self.notches]
        self.reset()

    @property
    def params(self) -> dict[str, Any]:
        """What a drive loads into its own controller (SI units; arrays as lists)."""
        each = [{"f_n": n.f_n, "D_z": n.D_z, "D_p": n.D_p} for n in self.notches]
        return {"type": "PI", "Kp": self.Kp.tolist(), "Ti": self.Ti.tolist(), "T_f": self.T_f.tolist(),
                "T_s": self.T_s, "M_max": self.M_max, "notch": each[0] if each else None, "notches": each}

    def reset(self) -> None:
        zero = np.zeros(self.shape)
        self._I, self._wf = zero.copy(), zero.copy()
        self._hist = [[zero.copy() for _ in range(4)] for _ in self.notches]  # per notch: u1, u2, v1, v2
        self._started = False

    def step(self, w_meas: Any, w_ref: Any) -> Any:
        """``M_ref`` [Nm] for the measured speed ``w_meas`` and the reference ``w_ref`` [rad/s]: numbers,
        numpy arrays or CPU torch tensors (converted to float64 numpy); a float when all is scalar,
        else a numpy array of the broadcast shape."""
        w, w_ref = _array(w_meas, "w_meas"), _array(w_ref, "w_ref")
        if not self._started:
            self._wf = np.broadcast_to(w, np.broadcast_shapes(w.shape, self.shape)).copy()
            self._started = True
        self._wf = self._a * self._wf + (1.0 - self._a) * w
        e = w_ref - self._wf
        pe = self.Kp * e
        I_try = np.clip(self._I + self._ki * e, -self.M_max, self.M_max)
        u_try = pe + I_try
        self._I = np.where((np.abs(u_try) > self.M_max) & (u_try * e > 0), self._I, I_try)
        u = pe + self._I
        for (b, a), hist in zip(self._biquads, self._hist):
            u1, u2, v1, v2 = hist
            v = b[0] * u + b[1] * u1 + b[2] * u2 - a[1] * v1 - a[2] * v2
            hist[:] = [u, u1, v, v1]
            u = v
        out = np.clip(u, -self.M_max, self.M_max)
        return float(out) if out.ndim == 0 else out


class HoldLaw:
    """The speed loop off: a law (SPEC 8.1 contract) whose torque reference is 0 at every sample, so
    that the drive's own holding torque ``M_hold`` (SPEC 1.1: what a drive adds to every law's
    output on a held axis) holds the axis alone. The chain's rest check runs it
    (:func:`training.commissioning._rest.check_rest`); a drive that loads ``params`` reads
    ``{"type": "hold"}``: no speed controller, the holding torque only."""

    def __init__(self) -> None:
        self.params: dict[str, Any] = {"type": "hold"}

    def reset(self) -> None:
        """Nothing to reset: the law has no state."""

    def step(self, w_meas: Any, w_ref: Any) -> float:
        """``M_ref = 0`` [Nm] whatever the speeds (the drive adds its holding torque)."""
        return 0.0
