"""Linear loop analysis: the exact sampled linear model of a mechanic on a drive and the
closed-loop figures of a PI design on it (margins, bandwidth, poles, step and load responses).

The linear model follows SPEC 1 without backlash and Coulomb friction: current loop
``1/(1+s T_Ei)``, two-mass mechanic with ``C_F, D_F`` (:func:`sim.two_mass_derived`), viscous
load friction ``mu_F``; the sampled loop has the real timing of the drive: ``M_ref`` computed at
sample ``k`` acts from ``k+1`` (zero-order hold) and the measured speed is the angle difference
over the last sample. Units SI.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import torch

import sim

from ._law import NotchSpec

__all__ = [
    "Mechanics", "mechanics_from", "drive_value", "LinearPlant", "linear_plant", "loop_figures",
    "closed_loop_matrices", "constant_input_response",
]


@dataclass(frozen=True)
class Mechanics:
    """Scalar mechanical parameters of one plant (SI). ``f_e=None`` means one-mass (stiff).

    ``J_sigma`` [kg m^2], ``V_J`` [-], ``f_e`` [Hz], ``d`` [-], ``backlash`` = ``2s`` [rad],
    ``M_FC`` [Nm], ``mu_F`` [Nm s/rad]; the derived values in :attr:`derived`.
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
    def derived(self) -> sim.TwoMassDerived:
        """``J_M, J_L, w_e, w_0, C_F, D_F`` (:func:`sim.two_mass_derived`); a one-mass mechanic
        has ``J_M = J_sigma``, ``J_L = 0``, ``w_e = w_0 = C_F = inf``, ``D_F = 0``."""
        if not self.two_mass:
            return sim.TwoMassDerived(self.J_sigma, 0.0, math.inf, math.inf, math.inf, 0.0)
        return sim.two_mass_derived(self.J_sigma, self.V_J, self.f_e, self.d)

    @property
    def w_A(self) -> float:
        """Anti-resonance ``w_0 / sqrt(1+V_J)`` [rad/s] (``inf`` for one-mass)."""
        return self.derived.w_0 / math.sqrt(1.0 + self.V_J) if self.two_mass else math.inf


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
    if isinstance(params, Mechanics):
        return params
    if isinstance(params, Mapping):
        raw = {k: params.get(k) for k in sim.PARAM_NAMES}
    else:
        raw = {k: getattr(params, k, None) for k in sim.PARAM_NAMES}
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


def drive_value(drive: Any, name: str) -> float:
    try:
        value = float(getattr(drive, name))
    except AttributeError as err:
        raise TypeError(f"drive: expected a DriveConfig with {name!r}, received {type(drive).__name__}") from err
    if not value > 0:
        raise ValueError(f"drive.{name}: expected > 0, received {value}")
    return value


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
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    if m.two_mass:
        dv = m.derived
        J_M, J_L, C, D, mu = dv.J_M, dv.J_L, dv.C_F, dv.D_F, m.mu_F
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


def closed_loop_matrices(plant: LinearPlant, Kp: float, Ti: float, T_f: float, notch: NotchSpec | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def constant_input_response(A: np.ndarray, b: np.ndarray, c: np.ndarray, n: int) -> np.ndarray:
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
    A, b_r, b_d, c = closed_loop_matrices(plant, Kp, Ti, T_f, notch)
    rho = float(np.abs(np.linalg.eigvals(A)).max())
    w_c_for_time = w_c if math.isfinite(w_c) and w_c > 0 else 1.0 / T_s
    n = int(min(max(40.0 / (w_c_for_time * T_s), 200), 100000))
    t = np.arange(n) * T_s
    y = constant_input_response(A, b_r, c, n)
    figs = _step_figures(t, y, 1.0)
    yl = constant_input_response(A, b_d, c, n)
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
