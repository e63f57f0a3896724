"""Linear loop analysis: the exact sampled linear model of a mechanic on a drive, the margins of a
PI design on it and on a set of models (the guarantee of rule R7), the closed-loop figures.

The linear model follows SPEC 1 without backlash and Coulomb friction: current loop
``1/(1+s T_Ei)`` (or a second-order lag with the same sum time constant, and extra samples of
dead time, for the guarantee's pessimistic models), two-mass mechanic with ``C_F, D_F`` (:func:`sim.two_mass_derived`), viscous
load friction ``mu_F``; the sampled loop has the real timing of the drive: ``M_ref`` computed at
sample ``k`` acts from ``k+1`` (zero-order hold) and the measured speed is the angle difference
over the last sample. Units SI.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg
import torch

import sim
from training._settings import POSITIVE_OR_INF, Interval, check_settings

from ._frf import MeasuredResponse
from ._law import NotchSpec, as_notches

#: The law's notch argument: None, one :class:`NotchSpec`, or a tuple of up to two in series.
Notches = NotchSpec | tuple[NotchSpec, ...] | None

__all__ = [
    "Mechanics", "mechanics_from", "drive_value", "LinearPlant", "linear_plant", "loop_figures",
    "closed_loop_matrices", "constant_input_response", "frequency_grid", "Margins", "loop_margins", "margins",
    "margin_arrays", "load_peak_dB", "reference_to_load", "load_transfer", "controller_parts", "ModelSet", "model_set", "bode",
    "LoopAnalysis", "ANALYSIS", "Notches",
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


#: What :func:`mechanics_from` accepts of each parameter: (names, the test, what is expected); None passes.
_MECHANICS_RANGES: tuple[tuple[tuple[str, ...], Callable[[float], bool], str], ...] = (
    (("V_J", "f_e"), lambda v: v > 0, "a positive value"),
    (("d",), lambda v: 0 <= v < 1, "0 <= d < 1"),
    (("backlash", "M_FC", "mu_F"), lambda v: v >= 0, "a value >= 0"),
)


def _raw_params(params: Mapping[str, Any] | Any) -> dict[str, float | None]:
    """The seven parameters of a dict or a one-system TwoMassParams as numbers (None: missing)."""
    if isinstance(params, Mapping):
        raw = {k: params.get(k) for k in sim.PARAM_NAMES}
    else:
        raw = {k: getattr(params, k, None) for k in sim.PARAM_NAMES}
    return {k: _num(v, k) for k, v in raw.items()}


def _check_mechanics(vals: Mapping[str, float | None]) -> None:
    """ValueError naming the first parameter out of its range (``J_sigma`` required and positive)."""
    if vals["J_sigma"] is None or vals["J_sigma"] <= 0:
        raise ValueError(f"J_sigma: expected a positive inertia in kg m^2, received {vals['J_sigma']}")
    for names, inside, expected in _MECHANICS_RANGES:
        for k in names:
            if vals[k] is not None and not inside(vals[k]):
                raise ValueError(f"{k}: expected {expected}, received {vals[k]}")


def mechanics_from(params: Mapping[str, Any] | Any) -> Mechanics:
    """Read ``J_sigma, V_J, f_e, d, backlash, M_FC, mu_F`` from a dict or a one-system TwoMassParams.

    Missing optional entries (``None``) mean: not identified (``f_e``/``V_J`` -> one-mass model,
    friction and backlash -> 0). Raises ValueError for a missing/non-positive ``J_sigma``.
    """
    if isinstance(params, Mechanics):
        return params
    vals = _raw_params(params)
    _check_mechanics(vals)
    two_mass = vals["f_e"] is not None and vals["V_J"] is not None
    return Mechanics(
        J_sigma=vals["J_sigma"],
        V_J=vals["V_J"] if two_mass else None,
        f_e=vals["f_e"] if two_mass else None,
        **{k: vals[k] or 0.0 for k in ("d", "backlash", "M_FC", "mu_F")},
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
    """Exact sampled linear model from the applied torque reference to the measured speed (no
    backlash, no Coulomb friction).

    ``x[k+1] = Ad x[k] + Bd u[k]``; ``dphi_M[k] = Cd x[k] + Dd u[k]`` is the motor angle gained over
    sample ``k``; ``w_meas[k] = dphi_M[k-1] / T_s``; ``w_L[k] = Lw x[k]`` the load speed (the motor
    speed for one-mass); ``u[k]`` (held over sample ``k``) = ``M_ref`` computed at ``k-1``.
    ``resonances`` [rad/s]: ``w_0`` and ``w_A`` (two-mass), for the frequency grids.
    """

    Ad: np.ndarray
    Bd: np.ndarray
    Cd: np.ndarray
    Dd: float
    Lw: np.ndarray
    T_s: float
    resonances: tuple[float, ...] = ()

    def _state_response(self, z: np.ndarray) -> np.ndarray:
        """``(z I - Ad)^-1 Bd`` at complex ``z`` (array ``F``): the state per unit applied torque, ``(F, n)``."""
        n = self.Ad.shape[0]
        zI = z[:, None, None] * np.eye(n)[None] - self.Ad[None]
        return np.linalg.solve(zI, np.broadcast_to(self.Bd, (len(z), n))[..., None])[..., 0]

    def speed_response(self, z: np.ndarray) -> np.ndarray:
        """Frequency response ``M_ref -> w_meas`` at complex ``z`` (array ``F``), incl. both delays."""
        return self.responses(z)[0]

    def load_response(self, z: np.ndarray) -> np.ndarray:
        """Frequency response ``M_ref -> w_L`` (the load speed, :attr:`Lw`) at complex ``z``, incl.
        the computation delay (``M_ref`` of sample ``k`` acts from ``k+1``)."""
        return self.responses(z)[1]

    def responses(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(speed_response(z), load_response(z))`` from one solve."""
        X = self._state_response(z)
        return (X @ self.Cd + self.Dd) / (z * z * self.T_s), (X @ self.Lw) / z


def _current_loop(T_Ei: float, damping: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The current loop ``M_ref -> M_M`` as ``(A, B, c)``: first order ``1/(1 + s T_Ei)`` (damping None)
    or second order ``1/(1 + 2 D s/w + s^2/w^2)`` with the same sum time constant ``2 D / w = T_Ei``."""
    if damping is None:
        return np.array([[-1 / T_Ei]]), np.array([1 / T_Ei]), np.array([1.0, 0.0])[:1]
    if not damping > 0:
        raise ValueError(f"current_loop_damping: expected > 0 or None, received {damping}")
    w = 2.0 * damping / T_Ei
    return np.array([[0.0, 1.0], [-w * w, -2 * damping * w]]), np.array([0.0, w * w]), np.array([1.0, 0.0])


def linear_plant(mech: Mechanics | Mapping[str, Any], drive: Any, *, current_loop_damping: float | None = None,
                 extra_delay: int = 0) -> LinearPlant:
    """Discretize (zero-order hold, ``T_s``) the SPEC-1 linear plant of ``mech`` on ``drive``.

    ``current_loop_damping``: None = the SPEC's first-order current loop, else a second-order lag
    of that damping (same sum time constant ``T_Ei``); ``extra_delay``: samples of dead time
    between the torque reference and the current loop (beyond the computation delay of one)."""
    m = mechanics_from(mech)
    T_s, T_Ei = drive_value(drive, "T_s"), drive_value(drive, "T_Ei")
    if isinstance(extra_delay, bool) or not isinstance(extra_delay, int) or extra_delay < 0:
        raise ValueError(f"extra_delay: expected an int >= 0, received {extra_delay!r}")
    Ac, Bc, cc = _current_loop(T_Ei, current_loop_damping)
    q = Ac.shape[0]
    if m.two_mass:
        dv = m.derived
        J_M, J_L, C, D, mu = dv.J_M, dv.J_L, dv.C_F, dv.D_F, m.mu_F
        Am = np.array([[-D / J_M, D / J_M, -C / J_M], [D / J_L, -(D + mu) / J_L, C / J_L], [1.0, -1.0, 0.0]])
        bm = np.array([1 / J_M, 0.0, 0.0])
        c_w, c_L = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
        res = (dv.w_0, m.w_A)
    else:
        Am, bm = np.array([[-m.mu_F / m.J_sigma]]), np.array([1 / m.J_sigma])
        c_w = c_L = np.array([1.0])
        res = ()
    k = Am.shape[0]
    n = q + k
    A = np.zeros((n, n))
    A[:q, :q], A[q:, q:], A[q:, :q] = Ac, Am, np.outer(bm, cc)
    B = np.concatenate([Bc, np.zeros(k)])
    cw, cL = np.concatenate([np.zeros(q), c_w]), np.concatenate([np.zeros(q), c_L])
    # augmented [x; phi_M; u], the input held constant: one matrix exponential gives all
    big = np.zeros((n + 2, n + 2))
    big[:n, :n], big[n, :n], big[:n, n + 1] = A, cw, B
    Phi = scipy.linalg.expm(big * T_s)
    Ad, Bd, Cd, Dd = Phi[:n, :n], Phi[:n, n + 1], Phi[n, :n], float(Phi[n, n + 1])
    if extra_delay:
        d = extra_delay  # a delay line q_1..q_d in front of the plant: q_1 <- u, x <- Bd q_d
        Ad2 = np.zeros((n + d, n + d))
        Ad2[:n, :n], Ad2[:n, n + d - 1] = Ad, Bd
        for i in range(1, d):
            Ad2[n + i, n + i - 1] = 1.0
        Bd = np.zeros(n + d)
        Bd[n] = 1.0
        Cd = np.concatenate([Cd, np.zeros(d - 1), [Dd]])
        Ad, Dd, cL = Ad2, 0.0, np.concatenate([cL, np.zeros(d)])
    return LinearPlant(Ad=Ad, Bd=Bd, Cd=Cd, Dd=Dd, Lw=cL, T_s=T_s, resonances=res)


def controller_parts(T_s: float, z: np.ndarray, *, Ti: Any = None, T_f: Any = None,
                     notch: Notches = None) -> dict[str, np.ndarray]:
    """The law's parts as frequency responses at complex ``z`` (each broadcast against ``z``; ``Ti``
    and ``T_f`` may be arrays with a trailing axis of length 1): ``"pi"`` the PI at ``Kp = 1``
    (``1 + T_s/Ti z/(z-1)``), ``"lowpass"`` the speed low-pass ``F`` (1 where ``T_f = 0``),
    ``"notch"`` the notches in series (1 without). Only the parts asked for are computed."""
    out: dict[str, np.ndarray] = {}
    if Ti is not None:
        out["pi"] = 1.0 + T_s / np.asarray(Ti, dtype=np.float64) * z / (z - 1.0)
    if T_f is not None:
        T_f = np.asarray(T_f, dtype=np.float64)
        a_f = np.where(T_f > 0, np.exp(-T_s / np.maximum(T_f, 1e-300)), 0.0)
        out["lowpass"] = (1 - a_f) * z / (z - a_f)
    N = np.ones_like(z)
    zi = 1.0 / z
    for one in as_notches(notch):
        b, a = one.coefficients(T_s)
        N = N * (b[0] + b[1] * zi + b[2] * zi * zi) / (1.0 + a[1] * zi + a[2] * zi * zi)
    out["notch"] = N
    return out


def _controller_response(Kp: float, Ti: float, T_f: float, notch: Notches, T_s: float, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C(z) N(z), F(z)): PI + notches on the error path, low-pass on the feedback path."""
    parts = controller_parts(T_s, z, Ti=Ti, T_f=T_f, notch=notch)
    return Kp * parts["pi"] * parts["notch"], parts["lowpass"]


def closed_loop_matrices(plant: LinearPlant, Kp: float, Ti: float, T_f: float,
                         notch: Notches) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closed loop of the (unclamped) law on ``plant`` as ``s[k+1] = A s + b_r r + b_d M_dist``, the
    disturbance added to the torque reference as a drive injects it (SPEC 8.1).

    State ``s = [x, u_applied, dphi_prev, w_f, I, (u1, u2, v1, v2) per notch]`` (one pass-through
    stage without a notch); outputs ``w_meas[k] = c s[k]``, ``w_L[k] = c_L s[k]``. Built by applying
    one linear sample of the law (same order as :class:`PISpeedLaw`) to unit vectors, so model and
    law cannot drift apart. Returns ``(A, b_r, b_d, c, c_L)``.
    """
    n, T_s = plant.Ad.shape[0], plant.T_s
    ki, a_f = Kp * T_s / Ti, (math.exp(-T_s / T_f) if T_f > 0 else 0.0)
    stages = [one.coefficients(T_s) for one in as_notches(notch)] or [(np.array([1.0, 0, 0]), np.array([1.0, 0, 0]))]
    m = n + 4 + 4 * len(stages)

    def one(s: np.ndarray, r: float, d: float) -> np.ndarray:
        """One sample of the loop on the columns of ``s`` (``(m, B)``)."""
        x, (u_app, dphi_prev, wf, I) = s[:n], s[n:n + 4]
        wf = a_f * wf + (1 - a_f) * dphi_prev / T_s
        e = r - wf
        I = I + ki * e
        u = Kp * e + I
        history = []
        for (b, a), (u1, u2, v1, v2) in zip(stages, s[n + 4:].reshape(len(stages), 4, -1)):
            v = b[0] * u + b[1] * u1 + b[2] * u2 - a[1] * v1 - a[2] * v2
            history += [u, u1, v, v1]
            u = v
        dphi = plant.Cd @ x + plant.Dd * u_app
        x_new = plant.Ad @ x + np.outer(plant.Bd, u_app)
        return np.vstack([x_new, u + d, dphi, wf, I, *history])

    A = one(np.eye(m), 0.0, 0.0)
    zero = np.zeros((m, 1))
    c = np.zeros(m)
    c[n + 1] = 1.0 / T_s
    c_L = np.concatenate([plant.Lw, np.zeros(m - n)])
    return A, one(zero, 1.0, 0.0)[:, 0], one(zero, 0.0, 1.0)[:, 0], c, c_L


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


@dataclass(frozen=True)
class LoopAnalysis:
    """The frequency grid of the margins and the Bode plots, and the step response of :func:`loop_figures`."""

    grid_points: int = 600
    """Log-spaced points of the frequency grid ..."""
    grid_low: float = 1e-5
    """... from this share of the Nyquist frequency ..."""
    grid_high: float = 0.999
    """... to this share (just below it)."""
    resonance_span: float = 0.15
    """The grid is dense within +- this (log, relative) around each resonance (a lightly damped one
    is a few per mille wide) ..."""
    resonance_points: int = 151
    """... with this many points (0.2 % steps)."""
    step_crossovers: float = 40.0
    """The step response runs this many ``1/w_c`` ..."""
    step_min: int = 200
    """... at least this many samples ..."""
    step_max: int = 100000
    """... at most this many."""
    settle_band: float = 0.02
    """The step response has settled inside +- this share of its final value."""

    def __post_init__(self) -> None:
        check_settings(self, {  # grid_low first: grid_high's bound
            "grid_low": Interval(0.0, 1.0, open_low=True, open_high=True),
            "grid_high": Interval("grid_low", 1.0, open_low=True, open_high=True),
            "grid_points": Interval(2, integer=True), "resonance_span": POSITIVE_OR_INF,
            "resonance_points": Interval(2, integer=True), "step_crossovers": POSITIVE_OR_INF,
            "step_min": Interval(2, integer=True), "step_max": Interval(2, integer=True), "settle_band": POSITIVE_OR_INF})


#: The grid and the step response the loop analysis uses.
ANALYSIS = LoopAnalysis()


def frequency_grid(T_s: float, resonances: Sequence[float] = (), n: int | None = None) -> np.ndarray:
    """Angular frequencies [rad/s] for margins and Bode plots: ``n`` (default
    ``ANALYSIS.grid_points``) log-spaced points over the Nyquist frequency's share
    ``ANALYSIS.grid_low`` .. ``grid_high``, dense around each of ``resonances`` (:class:`LoopAnalysis`)."""
    w_ny = math.pi / T_s
    n = ANALYSIS.grid_points if n is None else n
    parts = [np.logspace(math.log10(w_ny * ANALYSIS.grid_low), math.log10(w_ny * ANALYSIS.grid_high), n)]
    span = ANALYSIS.resonance_span
    for w_r in resonances:
        if math.isfinite(w_r) and 0 < w_r < w_ny:
            parts.append(w_r * np.exp(np.linspace(-span, span, ANALYSIS.resonance_points)))
    w = np.unique(np.concatenate(parts))
    return w[w < w_ny]


@dataclass(frozen=True)
class Margins:
    """Stability margins of a loop: ``phase_margin`` [deg] (smallest angular distance of ``L`` from
    -1 at any gain crossover), ``gain_margin_dB`` (smallest distance from ``|L| = 1`` at any crossing
    of the negative real axis above the first crossover, up or down), ``w_c`` [rad/s] (first gain
    crossover), ``stable`` (closed-loop poles inside the unit circle), ``model`` (which model)."""

    phase_margin: float
    gain_margin_dB: float
    w_c: float
    stable: bool
    model: str = "nominal"

    def meets(self, min_phase_margin: float, min_gain_margin_dB: float) -> bool:
        return self.stable and self.phase_margin >= min_phase_margin and self.gain_margin_dB >= min_gain_margin_dB


def margin_arrays(L: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase margin [deg], gain margin [dB] and first gain crossover [rad/s] of open-loop frequency
    responses ``L`` (``(..., F)``) on the grid ``w`` (``F``, or broadcast to ``L``), one per leading
    index (:class:`Margins` says what each is); every crossing interpolated linearly in log
    frequency, log magnitude and phase between its two grid points; none: ``inf``, ``inf``, ``nan``."""
    lm = np.log(np.maximum(np.abs(L), 1e-300))
    ph = np.unwrap(np.angle(L), axis=-1)
    lw = np.log(np.broadcast_to(w, L.shape))
    l0, l1, p0, p1, w0, w1 = lm[..., :-1], lm[..., 1:], ph[..., :-1], ph[..., 1:], lw[..., :-1], lw[..., 1:]
    cross = (l0 >= 0) != (l1 >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(cross, -l0 / np.where(cross, l1 - l0, 1.0), 0.0)
        phase = p0 + frac * (p1 - p0)
        off = np.abs(phase - 2 * math.pi * np.round(phase / (2 * math.pi)))  # distance from 0 mod 360 deg
        pm = np.where(cross, 180.0 - np.degrees(off), np.inf).min(axis=-1)
        down = cross & (l0 >= 0)
        first = np.argmax(down, axis=-1)[..., None]
        w_c = np.where(down.any(axis=-1), np.exp(np.take_along_axis(w0 + frac * (w1 - w0), first, axis=-1)[..., 0]), np.nan)
        # crossings of the negative real axis: phase through -180 deg (mod 360), above the first crossover
        k = np.floor((ph + math.pi) / (2 * math.pi))
        k0, k1 = k[..., :-1], k[..., 1:]
        axis = (k0 != k1) & (w0 > np.log(np.where(np.isfinite(w_c), w_c, 0.0))[..., None])
        target = np.maximum(k0, k1) * 2 * math.pi - math.pi
        at = l0 + (target - p0) / np.where(axis, p1 - p0, 1.0) * (l1 - l0)
        gm = np.where(axis, np.abs(20 * at / math.log(10)), np.inf).min(axis=-1)
    return pm, gm, w_c


def loop_margins(L: np.ndarray, w: np.ndarray, stable: bool, model: str = "nominal") -> Margins:
    """:class:`Margins` of an open-loop frequency response ``L`` on the grid ``w`` [rad/s] (:func:`margin_arrays`)."""
    pm, gm, w_c = margin_arrays(L, w)
    return Margins(float(pm), float(gm), float(w_c), bool(stable), model)


def load_transfer(C: np.ndarray, F: np.ndarray, G: np.ndarray, G_L: np.ndarray) -> np.ndarray:
    """``C N G_L / (1 + C N F G)`` from the law's parts ``C`` (PI and notches), ``F`` and the plant's
    ``G``, ``G_L`` (arrays broadcast): the reference-to-load-speed response."""
    return C * G_L / (1.0 + C * F * G)


def reference_to_load(plant: LinearPlant, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None, *,
                      w: np.ndarray | None = None) -> np.ndarray:
    """The closed loop's response from the speed reference to the load speed, ``T_rL = C N G_L /
    (1 + C N F G)`` (``G_L`` :meth:`LinearPlant.load_response`, ``G`` the measured speed's) on the
    grid ``w`` [rad/s] (default :func:`frequency_grid`)."""
    w = frequency_grid(plant.T_s, plant.resonances) if w is None else w
    z = np.exp(1j * w * plant.T_s)
    C, F = _controller_response(Kp, Ti, T_f, notch, plant.T_s, z)
    return load_transfer(C, F, plant.speed_response(z), plant.load_response(z))


def load_peak_dB(plant: LinearPlant, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None) -> float:
    """The peak of :func:`reference_to_load` [dB]: above 0 dB the load overshoots the reference
    (SPEC 8.2: at most 6 dB, the load must not ring)."""
    return float(20 * np.log10(np.abs(reference_to_load(plant, Kp, Ti, T_f, notch)).max()))


def margins(plant: LinearPlant, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None, *,
            w: np.ndarray | None = None, model: str = "nominal", response: np.ndarray | None = None) -> Margins:
    """:class:`Margins` of the PI law on ``plant`` (poles from :func:`closed_loop_matrices`);
    ``response``: the plant's ``speed_response`` on the grid ``w``, where already computed."""
    w = frequency_grid(plant.T_s, plant.resonances) if w is None else w
    z = np.exp(1j * w * plant.T_s)
    C, F = _controller_response(Kp, Ti, T_f, notch, plant.T_s, z)
    A = closed_loop_matrices(plant, Kp, Ti, T_f, notch)[0]
    stable = bool(np.abs(np.linalg.eigvals(A)).max() < 1.0)
    return loop_margins(C * F * (plant.speed_response(z) if response is None else response), w, stable, model)


@dataclass(frozen=True)
class ModelSet:
    """The models a delivered loop must keep its margins on: the identified mechanics and its
    plausible spread, each with the current loop as a second-order lag and extra samples of delay,
    plus the identified model as it is (``plants``, named by ``labels``); and, where the plant's
    frequency response was measured, that response at its trusted frequencies (``measured``: a
    non-parametric model; its margins count, its stability is judged on the parametric models).
    ``load_checked``: per plant, whether its reference-to-load peak counts (default: every one).
    ``transient``: per plant, whether it is a state the plant only passes through (a backlash
    plant's decoupled motor while the gap is open): held to ``transient_margins`` (phase [deg], gain
    [dB]) instead of the guarantee's, and its load peak does not count (default: none is)."""

    plants: tuple[LinearPlant, ...]
    labels: tuple[str, ...]
    measured: MeasuredResponse | None = None
    load_checked: tuple[bool, ...] | None = None
    transient: tuple[bool, ...] | None = None
    transient_margins: tuple[float, float] = (0.0, 0.0)
    _responses: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list, compare=False, repr=False)

    #: The label of the measured response among the models.
    MEASURED = "measured frequency response"

    def responses(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per plant its grid ``w`` [rad/s] (:func:`frequency_grid`), speed and load responses
        (computed once: they do not depend on the law)."""
        if not self._responses:
            for p in self.plants:
                w = frequency_grid(p.T_s, p.resonances)
                self._responses.append((w, *p.responses(np.exp(1j * w * p.T_s))))
        return self._responses

    def each(self, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None) -> list[Margins]:
        """The margins on every model (the plants', then the measured response's)."""
        out = [margins(p, Kp, Ti, T_f, notch, model=lab, w=w, response=G)
               for p, lab, (w, G, _) in zip(self.plants, self.labels, self.responses())]
        if self.measured is not None:
            z = np.exp(1j * self.measured.w * self.measured.T_s)
            C, F = _controller_response(Kp, Ti, T_f, notch, self.measured.T_s, z)
            out.append(loop_margins(C * F * self.measured.G, self.measured.w, True, self.MEASURED))
        return out

    def is_transient(self, i: int) -> bool:
        """Whether plant ``i`` is a transient state (:attr:`transient`)."""
        return bool(self.transient) and i < len(self.plants) and self.transient[i]

    def load_counts(self, i: int) -> bool:
        """Whether plant ``i``'s reference-to-load peak counts (:attr:`load_checked`, never on a transient one)."""
        return (self.load_checked[i] if self.load_checked else True) and not self.is_transient(i)

    def margins(self, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None) -> Margins:
        """The worst margins over the set's lasting models; ``stable`` False where any model is
        unstable or a transient one misses :attr:`transient_margins` (then ``model`` names it, else
        the worst model's label); ``w_c`` the first model's (the identified one)."""
        every = self.each(Kp, Ti, T_f, notch)
        each = [m for i, m in enumerate(every) if not self.is_transient(i)]
        worst_pm = min(each, key=lambda m: m.phase_margin)
        worst_gm = min(each, key=lambda m: m.gain_margin_dB)
        unstable = [m for i, m in enumerate(every)
                    if not (m.meets(*self.transient_margins) if self.is_transient(i) else m.stable)]
        worst = unstable[0] if unstable else (worst_pm if worst_pm.phase_margin - 40 <= worst_gm.gain_margin_dB - 6 else worst_gm)
        return Margins(worst_pm.phase_margin, worst_gm.gain_margin_dB, each[0].w_c, not unstable, worst.model)

    def load_peaks_dB(self, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None) -> np.ndarray:
        """The peak of the reference-to-load response [dB] on every plant whose load counts
        (:func:`reference_to_load`; ``-inf`` on the others)."""
        out = []
        checked = [self.load_counts(i) for i in range(len(self.plants))]
        for p, load, (w, G, G_L) in zip(self.plants, checked, self.responses()):
            C, F = _controller_response(Kp, Ti, T_f, notch, p.T_s, np.exp(1j * w * p.T_s))
            out.append(20 * np.log10(np.abs(load_transfer(C, F, G, G_L)).max()) if load else -np.inf)
        return np.array(out)


def model_set(mechanics: Sequence[Mechanics | Mapping[str, Any]], drive: Any, *, spread: float = 0.3,
              current_loop_damping: float | None = 1 / math.sqrt(2), extra_delay: int = 1) -> ModelSet:
    """:class:`ModelSet` over ``mechanics`` (the identified one first; more for a class's worst
    cases): each as it is, and with the second-order current loop and ``extra_delay``, at ``f_e``,
    ``V_J`` scaled by ``1 - spread``, 1, ``1 + spread`` (two-mass mechanics)."""
    plants, labels = [], []
    for mech in mechanics:
        m = mechanics_from(mech)
        base = f"J_sigma {m.J_sigma:.3g}" if not m.two_mass else f"f_e {m.f_e:.3g} Hz, V_J {m.V_J:.3g}"
        plants.append(linear_plant(m, drive))
        labels.append(base)
        scales = (1 - spread, 1.0, 1 + spread) if m.two_mass and spread > 0 else (1.0,)
        for sf in scales:
            for sv in scales:
                mm = replace(m, f_e=m.f_e * sf, V_J=m.V_J * sv) if m.two_mass else m
                plants.append(linear_plant(mm, drive, current_loop_damping=current_loop_damping, extra_delay=extra_delay))
                labels.append((f"f_e {mm.f_e:.3g} Hz, V_J {mm.V_J:.3g}" if m.two_mass else base)
                              + f", 2nd-order current loop, +{extra_delay} sample delay")
    return ModelSet(tuple(plants), tuple(labels))


def bode(plant: LinearPlant, Kp: float, Ti: float, T_f: float = 0.0, notch: Notches = None) -> dict[str, np.ndarray]:
    """Open-loop Bode data of the law on ``plant``: ``w`` [rad/s], ``mag_dB``, ``phase_deg``."""
    w = frequency_grid(plant.T_s, plant.resonances)
    z = np.exp(1j * w * plant.T_s)
    C, F = _controller_response(Kp, Ti, T_f, notch, plant.T_s, z)
    L = C * F * plant.speed_response(z)
    phase = np.degrees(np.unwrap(np.angle(L)))
    phase -= 360.0 * np.round((phase[0] + 180.0) / 360.0)
    return {"w": w, "mag_dB": 20 * np.log10(np.maximum(np.abs(L), 1e-300)), "phase_deg": phase}


def _step_figures(t: np.ndarray, y: np.ndarray, final: float) -> dict[str, float]:
    """Overshoot [%], rise time 10-90 % [s], settling time [s] (inside ``ANALYSIS.settle_band``) of a
    step response to ``final``."""
    if not np.isfinite(y).all() or final == 0:
        return {"overshoot_pct": math.inf, "rise_time": math.inf, "settling_time": math.inf}
    yn = y / final
    i10 = np.argmax(yn >= 0.1) if (yn >= 0.1).any() else None
    i90 = np.argmax(yn >= 0.9) if (yn >= 0.9).any() else None
    rise = float(t[i90] - t[i10]) if i10 is not None and i90 is not None else math.inf
    outside = np.nonzero(np.abs(yn - 1.0) > ANALYSIS.settle_band)[0]
    settle = math.inf if len(outside) and outside[-1] == len(yn) - 1 else (float(t[outside[-1] + 1]) if len(outside) else 0.0)
    return {"overshoot_pct": float(max(0.0, yn.max() - 1.0) * 100.0), "rise_time": rise, "settling_time": settle}


def loop_figures(
    mech: Mechanics | Mapping[str, Any],
    drive: Any,
    Kp: float,
    Ti: float,
    T_f: float = 0.0,
    notch: Notches = None,
) -> dict[str, float]:
    """Expected closed-loop figures of a PI design on the exact sampled linear model (SPEC 1's
    first-order current loop, no extra delay).

    Returns a dict (SI): ``w_c`` [rad/s] (first gain crossover), ``f_c`` [Hz], ``phase_margin``
    [deg], ``gain_margin_dB`` (:class:`Margins`), ``bandwidth`` [rad/s] (-3 dB of reference ->
    speed), ``stable`` (1/0: all closed-loop poles inside the unit circle), ``spectral_radius``,
    ``decay_time`` [s] (slowest closed-loop mode), and from a linear step response:
    ``overshoot_pct``, ``rise_time``, ``settling_time`` [s], plus ``load_dip`` [rad/s per Nm]
    (largest speed drop after a 1 Nm disturbance step at the torque reference). Delays included:
    computation (1 sample), zero-order hold, speed-by-difference.
    """
    plant = linear_plant(mech, drive)
    T_s = plant.T_s
    w = frequency_grid(T_s, plant.resonances)
    z = np.exp(1j * w * T_s)
    P = plant.speed_response(z)
    C, F = _controller_response(Kp, Ti, T_f, notch, T_s, z)
    A, b_r, b_d, c, _ = closed_loop_matrices(plant, Kp, Ti, T_f, notch)
    rho = float(np.abs(np.linalg.eigvals(A)).max())
    mg = loop_margins(C * P * F, w, rho < 1.0)
    T_ref = C * P / (1 + C * P * F)
    bw_idx = np.nonzero(np.abs(T_ref) < 1 / math.sqrt(2))[0]
    bandwidth = float(w[bw_idx[0]]) if len(bw_idx) else math.pi / T_s
    w_c_for_time = mg.w_c if math.isfinite(mg.w_c) and mg.w_c > 0 else 1.0 / T_s
    n = int(min(max(ANALYSIS.step_crossovers / (w_c_for_time * T_s), ANALYSIS.step_min), ANALYSIS.step_max))
    t = np.arange(n) * T_s
    figs = _step_figures(t, constant_input_response(A, b_r, c, n), 1.0)
    yl = constant_input_response(A, b_d, c, n)
    return {
        "w_c": mg.w_c,
        "f_c": mg.w_c / (2 * math.pi),
        "phase_margin": mg.phase_margin,
        "gain_margin_dB": mg.gain_margin_dB,
        "bandwidth": bandwidth,
        "stable": float(mg.stable),
        "spectral_radius": rho,
        "decay_time": (-T_s / math.log(rho)) if 0 < rho < 1 else math.inf,
        **figs,
        "load_dip": float(np.nanmax(np.abs(yl))) if np.isfinite(yl).all() else math.inf,
    }
