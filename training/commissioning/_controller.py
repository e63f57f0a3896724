"""Speed-controller proposal (knowledge-base rules) and batched discrete speed controllers.

Two parts, one job: turn identified structure + parameters into a speed controller.

* :class:`PISpeedController` — a discrete PI speed controller sampled at ``T_s`` with
  conditional-integration anti-windup, output clamped to ``+-M_max``, an optional first-order
  low-pass on the measured speed and an optional notch on the torque reference. It implements
  the sim controller contract (``reset(batch_shape)``, ``step(k, w_meas) -> M_ref``) and is
  batched: gains are tensors with a leading batch shape, broadcast to the plant's batch.
* :func:`propose_controller` — the documented rules (docs/commissioning.md) that pick the
  concept and its parameters, then check them on the exact discrete linear two-mass model
  (:func:`linear_plant`, :func:`loop_figures`) and lower the gain until the margins hold.

Units SI: torque [Nm], speed [rad/s], ``Kp`` [Nm s/rad], ``Ti``, ``T_f``, ``T_s`` [s].
The linear model follows SPEC 1 without backlash and Coulomb friction: current loop
``1/(1+s T_Ei)``, two-mass mechanic with ``C_F, D_F``, viscous load friction ``mu_F``; the
sampled loop has the real timing of the drive: ``M_ref`` computed at sample ``k`` acts from
``k+1`` (zero-order hold) and the measured speed is the angle difference over the last sample.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg
import torch

__all__ = [
    "Mechanics",
    "NotchSpec",
    "ControllerSpec",
    "ControllerProposal",
    "LinearPlant",
    "PISpeedController",
    "linear_plant",
    "loop_figures",
    "mechanics_from",
    "propose_cautious",
    "propose_controller",
    "STRUCTURES",
]

STRUCTURES = ("stiff", "elastic", "elastic_backlash", "stiff_backlash")


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Mechanics:
    """Scalar mechanical parameters of one plant (SI). ``f_e=None`` means one-mass (stiff).

    ``J_sigma`` [kg m^2], ``V_J`` [-], ``f_e`` [Hz], ``d`` [-], ``backlash`` = ``2s`` [rad],
    ``M_FC`` [Nm], ``mu_F`` [Nm s/rad].
    """

    J_sigma: float
    V_J: float | None = None
    f_e: float | None = None
    d: float = 0.0
    backlash: float = 0.0
    M_FC: float = 0.0
    mu_F: float = 0.0

    @property
    def two_mass(self) -> bool:
        return self.f_e is not None and self.V_J is not None and self.V_J > 0

    @property
    def J_M(self) -> float:
        return self.J_sigma / (1.0 + self.V_J) if self.two_mass else self.J_sigma

    @property
    def J_L(self) -> float:
        return self.J_sigma - self.J_M

    @property
    def w_0(self) -> float:
        """Natural frequency [rad/s] (``w_e / sqrt(1-d^2)``); ``inf`` for one-mass."""
        if not self.two_mass:
            return math.inf
        return 2.0 * math.pi * self.f_e / math.sqrt(max(1.0 - self.d**2, 1e-12))

    @property
    def w_A(self) -> float:
        """Anti-resonance ``w_0 / sqrt(1+V_J)`` [rad/s]."""
        return self.w_0 / math.sqrt(1.0 + self.V_J) if self.two_mass else math.inf

    @property
    def C_F(self) -> float:
        return self.w_0**2 * self.J_M * self.J_L / self.J_sigma if self.two_mass else math.inf

    @property
    def D_F(self) -> float:
        return 2.0 * self.d * self.C_F / self.w_0 if self.two_mass else 0.0


def _num(value: Any, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            raise ValueError(f"parameter {name!r}: expected one value, received shape {tuple(value.shape)}")
        value = value.item()
    try:
        out = float(value)
    except (TypeError, ValueError) as err:
        raise TypeError(f"parameter {name!r}: expected a number, received {type(value).__name__}") from err
    if not math.isfinite(out):
        raise ValueError(f"parameter {name!r}: expected a finite number, received {out}")
    return out


def mechanics_from(params: Mapping[str, Any] | Any) -> Mechanics:
    """Read ``J_sigma, V_J, f_e, d, backlash, M_FC, mu_F`` from a dict or a one-system TwoMassParams.

    Missing optional entries (``None``) mean: not identified (``f_e``/``V_J`` -> one-mass model,
    friction and backlash -> 0). Raises ValueError for a missing/non-positive ``J_sigma``.
    """
    keys = ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F")
    if isinstance(params, Mechanics):
        return params
    if isinstance(params, Mapping):
        raw = {k: params.get(k) for k in keys}
    else:
        raw = {k: getattr(params, k, None) for k in keys}
    vals = {k: _num(v, k) for k, v in raw.items()}
    if vals["J_sigma"] is None or vals["J_sigma"] <= 0:
        raise ValueError(f"J_sigma: expected a positive inertia in kg m^2, received {vals['J_sigma']}")
    for k in ("V_J", "f_e"):
        if vals[k] is not None and vals[k] <= 0:
            raise ValueError(f"{k}: expected a positive value, received {vals[k]}")
    if vals["d"] is not None and not 0 <= vals["d"] < 1:
        raise ValueError(f"d: expected 0 <= d < 1, received {vals['d']}")
    for k in ("backlash", "M_FC", "mu_F"):
        if vals[k] is not None and vals[k] < 0:
            raise ValueError(f"{k}: expected a value >= 0, received {vals[k]}")
    two_mass = vals["f_e"] is not None and vals["V_J"] is not None
    return Mechanics(
        J_sigma=vals["J_sigma"],
        V_J=vals["V_J"] if two_mass else None,
        f_e=vals["f_e"] if two_mass else None,
        d=vals["d"] or 0.0,
        backlash=vals["backlash"] or 0.0,
        M_FC=vals["M_FC"] or 0.0,
        mu_F=vals["mu_F"] or 0.0,
    )


def _drive_value(drive: Any, name: str) -> float:
    try:
        value = float(getattr(drive, name))
    except AttributeError as err:
        raise TypeError(f"drive: expected a DriveConfig with {name!r}, received {type(drive).__name__}") from err
    if not value > 0:
        raise ValueError(f"drive.{name}: expected > 0, received {value}")
    return value


# --------------------------------------------------------------------------- controller law


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


def _as_tensor(value: Any, name: str) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    if not torch.isfinite(t).all():
        raise ValueError(f"{name}: expected finite values, received {value}")
    return t


class PISpeedController:
    """Batched discrete PI speed controller (contract: ``reset(batch_shape)``, ``step(k, w_meas)``).

    Law per sample ``k`` (``e = w_ref[k] - w_f[k]``)::

        w_f[k] = a w_f[k-1] + (1-a) w_meas[k],  a = exp(-T_s/T_f)   (T_f = 0: w_f = w_meas)
        I[k]   = I[k-1] + Kp T_s/Ti e[k]        (not while the output saturates in the sign of e)
        u[k]   = Kp e[k] + I[k];  v = notch(u);  M_ref[k] = clamp(v, -M_max, M_max)

    Args:
        Kp: proportional gain [Nm s/rad], float or tensor ``*gbatch``.
        Ti: integral time [s], same broadcastable shape.
        T_s: sample time [s]. M_max: torque limit [Nm].
        T_f: speed low-pass time constant [s] (0: none), float or tensor ``*gbatch``.
        notch: optional :class:`NotchSpec` (one for the whole batch).
        w_ref: speed reference [rad/s]: a float, a tensor ``N`` (sample ``k`` uses
            ``w_ref[min(k, N-1)]``) or ``*batch x N``.

    ``reset(batch_shape)`` broadcasts the gains to ``batch_shape`` (the plant's batch) and clears
    the states; ``step`` takes ``w_meas`` ``*batch`` [rad/s] and returns ``M_ref`` ``*batch`` [Nm].
    """

    def __init__(
        self,
        Kp: float | torch.Tensor,
        Ti: float | torch.Tensor,
        *,
        T_s: float,
        M_max: float,
        T_f: float | torch.Tensor = 0.0,
        notch: NotchSpec | None = None,
        w_ref: float | torch.Tensor = 0.0,
    ) -> None:
        self.Kp = _as_tensor(Kp, "Kp")
        self.Ti = _as_tensor(Ti, "Ti")
        self.T_f = _as_tensor(T_f, "T_f")
        if (self.Kp <= 0).any() or (self.Ti <= 0).any() or (self.T_f < 0).any():
            raise ValueError("Kp, Ti: expected > 0 and T_f >= 0")
        if not (T_s > 0 and M_max > 0):
            raise ValueError(f"T_s, M_max: expected > 0, received {T_s}, {M_max}")
        self.T_s, self.M_max = float(T_s), float(M_max)
        if notch is not None and not isinstance(notch, NotchSpec):
            raise TypeError(f"notch: expected NotchSpec or None, received {type(notch).__name__}")
        self.notch = notch
        self._nb, self._na = notch.coefficients(self.T_s) if notch is not None else (None, None)
        self.w_ref = _as_tensor(w_ref, "w_ref")
        self.batch_shape: torch.Size | None = None

    @property
    def gain_shape(self) -> torch.Size:
        return torch.broadcast_shapes(self.Kp.shape, self.Ti.shape, self.T_f.shape)

    def reset(self, batch_shape: tuple[int, ...] | torch.Size) -> None:
        shape = torch.Size(batch_shape)
        try:
            torch.broadcast_shapes(self.gain_shape, shape)
        except RuntimeError as err:
            raise ValueError(f"controller gains of shape {tuple(self.gain_shape)} do not broadcast to plant batch {tuple(shape)}") from err
        if torch.broadcast_shapes(self.gain_shape, shape) != shape:
            raise ValueError(f"controller gains of shape {tuple(self.gain_shape)} are larger than plant batch {tuple(shape)}")
        self.batch_shape = shape
        self._kp = self.Kp.expand(shape)
        self._ki = (self.Kp * self.T_s / self.Ti).expand(shape)
        self._a = torch.where(self.T_f > 0, torch.exp(-self.T_s / self.T_f.clamp_min(1e-300)), torch.zeros(())).expand(shape)
        self._1a = 1.0 - self._a
        zero = torch.zeros(shape, dtype=torch.float64)
        self._I, self._wf = zero.clone(), zero.clone()
        self._nx = [zero.clone(), zero.clone()]  # notch input history u[k-1], u[k-2]
        self._ny = [zero.clone(), zero.clone()]  # notch output history
        self._started = False

    def reference(self, k: int) -> torch.Tensor:
        """Speed reference at sample ``k`` [rad/s], broadcastable to the batch."""
        r = self.w_ref
        if r.dim() == 0:
            return r
        return r[..., min(k, r.shape[-1] - 1)]

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        if self.batch_shape is None:
            raise ValueError("call reset(batch_shape) before step()")
        w = torch.as_tensor(w_meas, dtype=torch.float64)
        if w.shape != self.batch_shape:
            raise ValueError(f"w_meas: expected shape {tuple(self.batch_shape)}, received {tuple(w.shape)}")
        if not self._started:
            self._wf = w.clone()
            self._started = True
        self._wf = self._a * self._wf + self._1a * w
        e = self.reference(k) - self._wf
        pe = self._kp * e
        I_try = (self._I + self._ki * e).clamp(-self.M_max, self.M_max)
        u_try = pe + I_try
        windup = (u_try.abs() > self.M_max) & (u_try * e > 0)
        self._I = torch.where(windup, self._I, I_try)
        u = pe + self._I
        if self.notch is not None:
            b, a = self._nb, self._na
            v = b[0] * u + b[1] * self._nx[0] + b[2] * self._nx[1] - a[1] * self._ny[0] - a[2] * self._ny[1]
            self._nx = [u, self._nx[0]]
            self._ny = [v, self._ny[0]]
            u = v
        return u.clamp(-self.M_max, self.M_max)


# --------------------------------------------------------------------------- linear model


@dataclass(frozen=True)
class LinearPlant:
    """Exact sampled linear model from ``M_ref`` to the measured speed (no backlash/Coulomb).

    ``x[k+1] = Ad x[k] + Bd u[k] + Ed M_load[k]``; ``dphi_M[k] = Cd x[k] + Dd u[k] + Fd M_load[k]``
    is the motor angle gained over sample ``k``; ``w_meas[k] = dphi_M[k-1] / T_s``;
    ``u[k]`` (air-gap torque reference held over sample ``k``) = ``M_ref`` computed at ``k-1``.
    States: ``[M_M, w_M, w_L, dphi]`` (two-mass) or ``[M_M, w]`` (one-mass). ``M_load`` acts on
    the load (opposing positive speed).
    """

    Ad: np.ndarray
    Bd: np.ndarray
    Ed: np.ndarray
    Cd: np.ndarray
    Dd: float
    Fd: float
    T_s: float

    def speed_response(self, z: np.ndarray) -> np.ndarray:
        """Frequency response ``M_ref -> w_meas`` at complex ``z`` (array ``F``), incl. both delays."""
        n = self.Ad.shape[0]
        zI = z[:, None, None] * np.eye(n)[None] - self.Ad[None]
        g = np.einsum("i,fi->f", self.Cd, np.linalg.solve(zI, np.broadcast_to(self.Bd, (len(z), n))[..., None])[..., 0])
        return (g + self.Dd) / (z * z * self.T_s)


def linear_plant(mech: Mechanics | Mapping[str, Any], drive: Any) -> LinearPlant:
    """Discretize (zero-order hold, ``T_s``) the SPEC-1 linear plant of ``mech`` on ``drive``."""
    m = mechanics_from(mech)
    T_s, T_Ei = _drive_value(drive, "T_s"), _drive_value(drive, "T_Ei")
    if m.two_mass:
        J_M, J_L, C, D, mu = m.J_M, m.J_L, m.C_F, m.D_F, m.mu_F
        A = np.array([
            [-1 / T_Ei, 0, 0, 0],
            [1 / J_M, -D / J_M, D / J_M, -C / J_M],
            [0, D / J_L, -(D + mu) / J_L, C / J_L],
            [0, 1, -1, 0],
        ])
        B = np.array([1 / T_Ei, 0, 0, 0])
        E = np.array([0, 0, -1 / J_L, 0])
        c_w = np.array([0, 1.0, 0, 0])
    else:
        J, mu = m.J_sigma, m.mu_F
        A = np.array([[-1 / T_Ei, 0], [1 / J, -mu / J]])
        B = np.array([1 / T_Ei, 0])
        E = np.array([0, -1 / J])
        c_w = np.array([0, 1.0])
    n = A.shape[0]
    # augmented [x; phi_M; u; M_load], inputs held constant: one matrix exponential gives all
    big = np.zeros((n + 3, n + 3))
    big[:n, :n] = A
    big[n, :n] = c_w
    big[:n, n + 1] = B
    big[:n, n + 2] = E
    Phi = scipy.linalg.expm(big * T_s)
    return LinearPlant(
        Ad=Phi[:n, :n], Bd=Phi[:n, n + 1], Ed=Phi[:n, n + 2],
        Cd=Phi[n, :n], Dd=float(Phi[n, n + 1]), Fd=float(Phi[n, n + 2]), T_s=T_s,
    )


def _controller_response(Kp: float, Ti: float, T_f: float, notch: NotchSpec | None, T_s: float, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C(z) N(z), F(z)): PI + notch on the error path, low-pass on the feedback path."""
    C = Kp + Kp * T_s / Ti * z / (z - 1.0)
    if notch is not None:
        b, a = notch.coefficients(T_s)
        zi = 1.0 / z
        C = C * (b[0] + b[1] * zi + b[2] * zi * zi) / (1.0 + a[1] * zi + a[2] * zi * zi)
    if T_f > 0:
        a_f = math.exp(-T_s / T_f)
        F = (1 - a_f) * z / (z - a_f)
    else:
        F = np.ones_like(z)
    return C, F


def _closed_loop_matrices(plant: LinearPlant, Kp: float, Ti: float, T_f: float, notch: NotchSpec | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closed loop of the (unclamped) controller law on ``plant`` as ``s[k+1] = A s + b_r r + b_d M_load``.

    State ``s = [x, u_applied, dphi_prev, w_f, I, u1, u2, v1, v2]``; output ``w_meas[k] = c s[k]``.
    Built by applying one linear sample of the law (same order as :class:`PISpeedController`) to
    unit vectors, so model and controller cannot drift apart. Returns ``(A, b_r, b_d, c)``.
    """
    n = plant.Ad.shape[0]
    ki, a_f = Kp * plant.T_s / Ti, (math.exp(-plant.T_s / T_f) if T_f > 0 else 0.0)
    b, a = notch.coefficients(plant.T_s) if notch is not None else (np.array([1.0, 0, 0]), np.array([1.0, 0, 0]))

    def one(s: np.ndarray, r: float, d: float) -> np.ndarray:
        x, u_app, dphi_prev, wf, I, u1, u2, v1, v2 = s[:n], *s[n:]
        w = dphi_prev / plant.T_s
        wf = a_f * wf + (1 - a_f) * w
        e = r - wf
        I = I + ki * e
        u = Kp * e + I
        v = b[0] * u + b[1] * u1 + b[2] * u2 - a[1] * v1 - a[2] * v2
        dphi = plant.Cd @ x + plant.Dd * u_app + plant.Fd * d
        x_new = plant.Ad @ x + plant.Bd * u_app + plant.Ed * d
        return np.concatenate([x_new, [v, dphi, wf, I, u, u1, v, v1]])

    m = n + 8
    A = np.stack([one(col, 0.0, 0.0) for col in np.eye(m)], axis=1)
    zero = np.zeros(m)
    c = np.zeros(m)
    c[n + 1] = 1.0 / plant.T_s
    return A, one(zero, 1.0, 0.0), one(zero, 0.0, 1.0), c


def _constant_input_response(A: np.ndarray, b: np.ndarray, c: np.ndarray, n: int) -> np.ndarray:
    """``y[k] = c s[k]``, ``s[k+1] = A s[k] + b``, ``s[0] = 0`` for ``k < n`` (by repeated squaring)."""
    m = A.shape[0]
    Aa = np.zeros((m + 1, m + 1))
    Aa[:m, :m], Aa[:m, m], Aa[m, m] = A, b, 1.0
    S = np.zeros((m + 1, 1))
    S[m, 0] = 1.0
    P = Aa
    while S.shape[1] < n:
        S = np.concatenate([S, P @ S], axis=1)
        P = P @ P
        if not np.isfinite(P).all():
            P = np.nan_to_num(P, nan=np.inf)
    with np.errstate(invalid="ignore", over="ignore"):
        return c @ S[:m, :n]


def _step_figures(t: np.ndarray, y: np.ndarray, final: float) -> dict[str, float]:
    """Overshoot [%], rise time 10-90 % [s], 2 %-settling time [s] of a step response to ``final``."""
    if not np.isfinite(y).all() or final == 0:
        return {"overshoot_pct": math.inf, "rise_time": math.inf, "settling_time": math.inf}
    yn = y / final
    i10 = np.argmax(yn >= 0.1) if (yn >= 0.1).any() else None
    i90 = np.argmax(yn >= 0.9) if (yn >= 0.9).any() else None
    rise = float(t[i90] - t[i10]) if i10 is not None and i90 is not None else math.inf
    outside = np.nonzero(np.abs(yn - 1.0) > 0.02)[0]
    settle = math.inf if len(outside) and outside[-1] == len(yn) - 1 else (float(t[outside[-1] + 1]) if len(outside) else 0.0)
    return {"overshoot_pct": float(max(0.0, yn.max() - 1.0) * 100.0), "rise_time": rise, "settling_time": settle}


def loop_figures(
    mech: Mechanics | Mapping[str, Any],
    drive: Any,
    Kp: float,
    Ti: float,
    T_f: float = 0.0,
    notch: NotchSpec | None = None,
    *,
    n_freq: int = 1500,
) -> dict[str, float]:
    """Expected closed-loop figures of a PI design on the exact sampled linear model.

    Returns a dict (SI): ``w_c`` [rad/s] (first gain crossover), ``f_c`` [Hz], ``phase_margin``
    [deg] (signed at the first crossover; angular distance to -180 deg at further ones, e.g. a
    resonance peak; the smallest), ``gain_margin_dB`` (smallest over -180 deg crossings),
    ``modulus_margin`` (min ``|1+L|``), ``bandwidth`` [rad/s] (-3 dB of reference -> speed),
    ``stable`` (1/0: all closed-loop poles inside the unit circle), ``spectral_radius``,
    ``decay_time`` [s] (slowest closed-loop mode), and from a linear step response: ``overshoot_pct``, ``rise_time``,
    ``settling_time`` [s], plus ``load_dip`` [rad/s per Nm] (largest speed drop after a 1 Nm load
    step). Delays included: computation (1 sample), zero-order hold, speed-by-difference.
    """
    plant = linear_plant(mech, drive)
    T_s = plant.T_s
    w_ny = math.pi / T_s
    w = np.logspace(math.log10(w_ny * 1e-5), math.log10(w_ny * 0.999), n_freq)
    z = np.exp(1j * w * T_s)
    P = plant.speed_response(z)
    C, F = _controller_response(Kp, Ti, T_f, notch, T_s, z)
    L = C * P * F
    mag = np.abs(L)
    phase = np.unwrap(np.angle(L))
    # a PI loop starts with phase near -180 deg (two integrators): shift the branch accordingly
    phase = phase - 2 * math.pi * np.round((phase[0] + math.pi) / (2 * math.pi))
    down = np.nonzero((mag[:-1] >= 1) & (mag[1:] < 1))[0]
    up = np.nonzero((mag[:-1] < 1) & (mag[1:] >= 1))[0]
    cross = np.concatenate([down, up])
    # main crossover: signed margin 180 + phase; further crossings (resonance peak): angular
    # distance of L to -1 (a phase-stabilized resonance has a large one)
    pms = [abs(((math.degrees(phase[i]) + 180.0 + 180.0) % 360.0) - 180.0) for i in cross]
    if len(down):
        pms.append(((math.degrees(phase[down[0]]) + 180.0 + 180.0) % 360.0) - 180.0)
    w_c = float(w[down[0]]) if len(down) else math.nan
    pc = np.nonzero(np.diff(np.floor((phase + math.pi) / (2 * math.pi))) != 0)[0]
    gms = [-20 * math.log10(max(mag[i], 1e-300)) for i in pc if w[i] > (w_c if math.isfinite(w_c) else 0) * 0.5]
    T_ref = C * P / (1 + L)
    bw_idx = np.nonzero(np.abs(T_ref) < 1 / math.sqrt(2))[0]
    bandwidth = float(w[bw_idx[0]]) if len(bw_idx) else float(w_ny)
    # closed-loop poles, step and load responses over ~ 40/w_c (bounded)
    A, b_r, b_d, c = _closed_loop_matrices(plant, Kp, Ti, T_f, notch)
    rho = float(np.abs(np.linalg.eigvals(A)).max())
    w_c_for_time = w_c if math.isfinite(w_c) and w_c > 0 else 1.0 / T_s
    n = int(min(max(40.0 / (w_c_for_time * T_s), 200), 100000))
    t = np.arange(n) * T_s
    y = _constant_input_response(A, b_r, c, n)
    figs = _step_figures(t, y, 1.0)
    yl = _constant_input_response(A, b_d, c, n)
    stable = bool(rho < 1.0)
    return {
        "w_c": w_c,
        "f_c": w_c / (2 * math.pi),
        "phase_margin": float(min(pms)) if pms else math.nan,
        "gain_margin_dB": float(min(gms)) if gms else math.inf,
        "modulus_margin": float(np.abs(1 + L).min()),
        "bandwidth": bandwidth,
        "stable": float(stable),
        "spectral_radius": rho,
        "decay_time": (-T_s / math.log(rho)) if 0 < rho < 1 else math.inf,
        **figs,
        "load_dip": float(-np.nanmin(yl)) if np.isfinite(yl).all() else math.inf,
    }


# --------------------------------------------------------------------------- proposal rules


@dataclass(frozen=True)
class ControllerSpec:
    """Design requirements and rule constants (see docs/commissioning.md, "Controller rules").

    ``a``: symmetric-optimum ratio (``w_c = 1/(a T_sigma)``, ``Ti = a^2 T_sigma``; 2 = classic
    SO, 37 deg; 3 = 53 deg). ``a_backlash``: the same for backlash structures (lower gain).
    ``anti_resonance_ratio``: ``w_c <= ratio(V_J) * w_A`` as ``(V_J_small, ratio_small,
    ratio_mid, V_J_large, ratio_large)``. ``min_phase_margin`` [deg], ``min_gain_margin_dB``:
    the check on the linear model; the gain is lowered by ``backoff`` until both hold.
    ``speed_filter_samples``: low-pass ``T_f`` in samples (0: none). ``allow_notch``: try a notch
    at the resonance when the elastic bandwidth limit costs more than ``notch_gain_factor``.
    ``cautious_bandwidth`` [rad/s]: the crossover of the fallback F1 (:func:`propose_cautious`),
    below R3's limit for every mechanic of the SPEC population (the lowest anti-resonance there,
    5 Hz with ``V_J = 5``, is 12.8 rad/s; R3 allows 0.3 of it).
    """

    a: float = 3.0
    a_backlash: float = 4.0
    anti_resonance_ratio: tuple[float, float, float, float, float] = (0.5, 1.0, 0.5, 2.0, 0.3)
    min_phase_margin: float = 45.0
    min_gain_margin_dB: float = 6.0
    backoff: float = 0.8
    max_backoff_steps: int = 30
    speed_filter_samples: float = 1.0
    allow_notch: bool = True
    notch_gain_factor: float = 3.0
    cautious_bandwidth: float = 3.0


@dataclass(frozen=True)
class ControllerProposal:
    """A speed-controller concept and its parameters, with the expected figures and the rules used.

    ``concept``: "PI", "PI+lowpass" or "PI+lowpass+notch". ``Kp`` [Nm s/rad], ``Ti`` [s],
    ``T_f`` [s] (speed low-pass, 0 = none), ``notch`` (or None). ``figures``: :func:`loop_figures`.
    """

    concept: str
    Kp: float
    Ti: float
    T_f: float
    notch: NotchSpec | None
    figures: dict[str, float]
    rules: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    structure: str = "stiff"
    mechanics: Mechanics | None = field(default=None, repr=False)

    def build(self, drive: Any, *, w_ref: float | torch.Tensor = 0.0, Kp: Any = None, Ti: Any = None, T_f: Any = None) -> PISpeedController:
        """The controller object on ``drive`` (gains overridable, e.g. by batched tensors)."""
        return PISpeedController(
            self.Kp if Kp is None else Kp,
            self.Ti if Ti is None else Ti,
            T_s=_drive_value(drive, "T_s"),
            M_max=_drive_value(drive, "M_max"),
            T_f=self.T_f if T_f is None else T_f,
            notch=self.notch,
            w_ref=w_ref,
        )

    def with_gains(self, drive: Any, Kp: float, Ti: float, T_f: float, rule: str) -> ControllerProposal:
        """A copy with new gains, new figures and one more rule line."""
        figs = loop_figures(self.mechanics, drive, Kp, Ti, T_f, self.notch)
        return replace(self, Kp=Kp, Ti=Ti, T_f=T_f, figures=figs, rules=self.rules + (rule,))

    def to_dict(self) -> dict[str, Any]:
        return {
            "concept": self.concept, "structure": self.structure, "Kp": self.Kp, "Ti": self.Ti, "T_f": self.T_f,
            "notch": None if self.notch is None else {"f_n": self.notch.f_n, "D_z": self.notch.D_z, "D_p": self.notch.D_p},
            "figures": dict(self.figures), "rules": list(self.rules), "warnings": list(self.warnings),
        }


def _margins_ok(f: dict[str, float], spec: ControllerSpec) -> bool:
    return bool(f["stable"]) and f["phase_margin"] >= spec.min_phase_margin and f["gain_margin_dB"] >= spec.min_gain_margin_dB


def propose_controller(
    structure: str,
    params: Mapping[str, Any] | Any,
    drive: Any,
    spec: ControllerSpec | None = None,
) -> ControllerProposal:
    """Propose a speed controller from the identified structure and parameters (rules R1-R7).

    Args:
        structure: one of :data:`STRUCTURES`.
        params: identified parameters (dict or one-system TwoMassParams), at least ``J_sigma``;
            ``V_J`` and ``f_e`` for the elastic structures.
        drive: DriveConfig (``T_s``, ``T_Ei``, ``M_max``).
        spec: rule constants and margin requirements.

    Returns a :class:`ControllerProposal` whose ``figures`` come from the exact sampled linear
    two-mass model (delays included) and meet ``spec``'s margins where the rules could reach them
    (else a warning says so).
    """
    spec = spec or ControllerSpec()
    if structure not in STRUCTURES:
        raise ValueError(f"structure: expected one of {STRUCTURES}, received {structure!r}")
    mech = mechanics_from(params)
    T_s, T_Ei = _drive_value(drive, "T_s"), _drive_value(drive, "T_Ei")
    _drive_value(drive, "M_max")
    elastic = structure in ("elastic", "elastic_backlash")
    if elastic and not mech.two_mass:
        raise ValueError(f"structure {structure!r} needs V_J and f_e, received V_J={mech.V_J}, f_e={mech.f_e}")
    rules: list[str] = []
    warnings: list[str] = []
    backlash = structure in ("elastic_backlash", "stiff_backlash")

    # R1: small sum time constant of the current loop, filter and sampled speed loop
    T_f = spec.speed_filter_samples * T_s
    T_sigma = T_Ei + 2.0 * T_s + T_f
    rules.append(f"R1 T_sigma = T_Ei + 2 T_s + T_f = {T_sigma:.3g} s (T_f = {T_f:.3g} s speed low-pass)")
    # R2: symmetric optimum on the total inertia
    a = spec.a_backlash if backlash else spec.a
    w_c = 1.0 / (a * T_sigma)
    rules.append(f"R2 symmetric optimum a = {a:g}: w_c = 1/(a T_sigma) = {w_c:.4g} rad/s on J_sigma")
    if backlash:
        rules.append(f"R6 backlash: a = {spec.a_backlash:g} (lower gain) instead of {spec.a:g}")
        warnings.append("backlash: integral action with backlash can cause a limit cycle around standstill; "
                        "keep Ti long and check the closed loop at low speed")
    # R3: elastic bandwidth limit from the anti-resonance, by inertia ratio
    notch = None
    if elastic:
        v_small, r_small, r_mid, v_large, r_large = spec.anti_resonance_ratio
        ratio = r_small if mech.V_J <= v_small else (r_mid if mech.V_J <= v_large else r_large)
        w_lim = ratio * mech.w_A
        rules.append(f"R3 elastic: V_J = {mech.V_J:.3g} -> w_c <= {ratio:g} w_A = {w_lim:.4g} rad/s "
                     f"(w_A = {mech.w_A:.4g}, w_0 = {mech.w_0:.4g} rad/s)")
        if w_c > w_lim:
            # R4: a notch at the resonance when the limit costs much bandwidth and f_0 is resolvable
            f_0 = mech.w_0 / (2 * math.pi)
            if spec.allow_notch and w_c > spec.notch_gain_factor * w_lim and f_0 < 0.4 / T_s:
                notch = NotchSpec(f_n=f_0, D_z=max(mech.d, 0.02), D_p=0.7)
                w_c = min(w_c, 0.8 * mech.w_A)
                rules.append(f"R4 notch at f_0 = {f_0:.4g} Hz (D_z = {notch.D_z:.3g}, D_p = 0.7): w_c = 0.8 w_A = {w_c:.4g} rad/s")
            else:
                w_c = w_lim
    Kp = mech.J_sigma * w_c
    Ti = a / w_c if not elastic else max(a / w_c, a * a * T_sigma)
    rules.append(f"R5 Kp = J_sigma w_c = {Kp:.4g} Nm s/rad, Ti = a / w_c = {Ti:.4g} s")
    concept = "PI" + ("+lowpass" if T_f > 0 else "") + ("+notch" if notch is not None else "")
    prop = ControllerProposal(concept, Kp, Ti, T_f, notch, loop_figures(mech, drive, Kp, Ti, T_f, notch),
                              tuple(rules), tuple(warnings), structure, mech)
    # R4b: a notch that does not help is dropped again
    if notch is not None and not _margins_ok(prop.figures, spec):
        w_c = w_lim
        Kp, Ti = mech.J_sigma * w_c, max(a / w_c, a * a * T_sigma)
        prop = replace(prop, concept=concept.replace("+notch", ""), notch=None,
                       figures=loop_figures(mech, drive, Kp, Ti, T_f, None), Kp=Kp, Ti=Ti,
                       rules=prop.rules + (f"R4b notch did not meet the margins: dropped, w_c = {w_c:.4g} rad/s",))
    # R7: check on the linear model; lower the gain (and slow the integral) until the margins hold
    steps = 0
    while not _margins_ok(prop.figures, spec) and steps < spec.max_backoff_steps:
        steps += 1
        prop = replace(prop, Kp=prop.Kp * spec.backoff, Ti=prop.Ti / spec.backoff)
        prop = replace(prop, figures=loop_figures(mech, drive, prop.Kp, prop.Ti, prop.T_f, prop.notch))
    if steps:
        prop = replace(prop, rules=prop.rules + (f"R7 margins: Kp x {spec.backoff:g}^{steps}, Ti / {spec.backoff:g}^{steps} "
                                                 f"-> PM {prop.figures['phase_margin']:.1f} deg, GM {prop.figures['gain_margin_dB']:.1f} dB",))
    if not _margins_ok(prop.figures, spec):
        prop = replace(prop, warnings=prop.warnings + (
            f"margins not reached on the linear model (PM {prop.figures['phase_margin']:.1f} deg, "
            f"GM {prop.figures['gain_margin_dB']:.1f} dB, stable={bool(prop.figures['stable'])})",))
    return prop


def propose_cautious(J_sigma: float, drive: Any, spec: ControllerSpec | None = None) -> ControllerProposal:
    """Fallback F1 when the identification is refused: a PI on the one-mass ``J_sigma`` of STEP 2
    alone (least squares on the whole record, the most robust figure of a test run) with the
    crossover ``spec.cautious_bandwidth``, far below any plausible anti-resonance, and a long
    integral time (``Ti = a / w_c``). It is meant as the start of a search on the plant itself
    (the mechanic's model is not trusted), not as a tuned controller."""
    spec = spec or ControllerSpec()
    if not (isinstance(J_sigma, (int, float)) and math.isfinite(J_sigma) and J_sigma > 0):
        raise ValueError(f"J_sigma: expected a finite number > 0, received {J_sigma!r}")
    prop = propose_controller("stiff", {"J_sigma": float(J_sigma)}, drive, spec)
    w_c = spec.cautious_bandwidth
    return prop.with_gains(drive, float(J_sigma) * w_c, spec.a / w_c, prop.T_f, rule=(
        f"F1 identification refused: cautious PI on J_sigma alone, w_c = {w_c:g} rad/s (below R3's limit for "
        f"every mechanic of the SPEC population), Kp = {float(J_sigma) * w_c:.4g} Nm s/rad, Ti = a / w_c = "
        f"{spec.a / w_c:.4g} s; to be tuned on the plant"))
