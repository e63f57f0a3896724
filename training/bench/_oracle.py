"""The bandwidth oracle of ``twomass bench commission``: the largest speed-loop crossover the TRUE
linear plant allows with the law's own structure, and the true figures of a delivered law.

The plant is the exact sampled linear model of the true mechanic on the drive
(:func:`training.commissioning.linear_plant`: current loop, computation delay, zero-order hold,
speed by difference, the drive's extra delay; no backlash, no Coulomb friction). The law is SPEC
8.1's (:class:`training.commissioning.PISpeedLaw`): PI ``C(z) = Kp (1 + (T_s/Ti) z/(z-1))`` on the
error, up to two notches ``N(z)`` (:class:`NotchSpec`'s Tustin biquads) after it, the speed
low-pass ``F(z) = (1-a) z/(z-a)``, ``a = exp(-T_s/T_f)``, on the feedback. With ``G`` the torque
reference -> measured motor speed and ``G_L`` torque reference -> load speed:

- open loop ``L = C N F G``; ``w_c`` is its first gain crossover (the lowest frequency where
  ``|L|`` falls through 1);
- phase margin: the smallest distance of ``L``'s phase from -180 deg at ANY gain crossover; gain
  margin: the smallest ``|20 log10 |L||`` where the phase crosses -180 deg (mod 360) above ``w_c``;
- load peak: ``max |T_rL|``, ``T_rL = C N G_L / (1 + L)`` (reference -> load speed);
- stable: every eigenvalue of the closed loop inside the unit circle.

Everything here is evaluated apart from the chain's design code: the responses by direct
evaluation of each block on a dense grid (log-spaced over the Nyquist range, denser around the
resonance and the anti-resonance), crossings interpolated linearly in log magnitude/phase over log
frequency, and the closed-loop poles from a state-space built here by series connection of the
blocks (not :func:`training.commissioning._loop.closed_loop_matrices`).

The search (:func:`oracle`): a target crossover ``w_t`` scanned on a log grid from
``scan_high`` of the Nyquist frequency downwards; at each target every structure of
:class:`OracleSearch` (``Ti w_t``, ``T_f`` in samples, no notch / one notch at, below or above the
resonance or the anti-resonance / the pair, several depths and widths) gets ``Kp`` from
``|L(w_t)| = 1``; a candidate is feasible when PM >= 45 deg, GM >= 6 dB, load peak <= 6 dB and the
closed loop is stable; its crossover is its own first crossover (which a notch or the
anti-resonance dip may put below ``w_t``). The scan stops once the targets fall below the best
crossover found; then a local scan between the best target and the next higher one, and bisection
above the best of those (``local_points``, ``refine_steps``). Last, Nelder-Mead from the best of
the grid over ``Kp``, ``Ti`` and the notches' centres, depths and widths (``T_f`` kept), each
constraint a wall and ``Ti w_c`` at most the largest of ``ti_products`` (``polish_evaluations``). The reference is the best feasible crossover found.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from training._settings import AT_LEAST_ONE, POSITIVE, Interval, Values, check_settings
from training.commissioning import LinearPlant, Mechanics, NotchSpec

__all__ = ["OracleSearch", "LoopFigures", "OracleDesign", "PlantResponse", "notches_of", "loop_responses",
           "true_figures", "oracle"]


@dataclass(frozen=True)
class OracleSearch:
    """The oracle's constraints and its search grid."""

    min_phase_margin: float = 45.0
    """Phase margin [deg] every reference loop keeps (SPEC 8.2)."""
    min_gain_margin_dB: float = 6.0
    """Gain margin [dB] every reference loop keeps (SPEC 8.2)."""
    max_load_peak: float = 2.0
    """Largest reference-to-load-speed gain (2 = 6 dB): the load must not ring (SPEC 8.2)."""
    scan_high: float = 0.3
    """The scan starts at this share of the Nyquist frequency (above any crossover the delays allow)."""
    scan_low: float = 0.01
    """... and ends at this crossover [rad/s] (nothing feasible above it: the reference is 0)."""
    scan_per_decade: int = 8
    """Targets per decade of the scan (a step of 33 %) ..."""
    local_points: int = 7
    """... then targets between the best one and the next higher one (3.6 % apart) ..."""
    refine_steps: int = 4
    """... then bisection steps above the best of those (to 0.2 %)."""
    ti_products: tuple[float, ...] = (1.5, 2.0, 3.0, 4.0, 6.0, 10.0, 16.0)
    """``Ti w_t`` tried: from an aggressive integral action to almost P; the largest bounds ``Ti w_c``
    everywhere (a PI whose integral action still acts; a larger one gains a few per cent)."""
    filter_samples: tuple[float, ...] = (0.0, 1.0, 2.0)
    """Speed low-pass ``T_f`` tried [samples ``T_s``] (0: none)."""
    max_notches: int = 2
    """Notches the law may hold (SPEC 8.1: up to two; 0 or 1 to see what each is worth)."""
    notch_centres: tuple[float, ...] = (0.85, 1.0, 1.15)
    """Single-notch centres relative to the resonance and to the anti-resonance (and their geometric mean)."""
    notch_depths: tuple[float, ...] = (0.03, 0.1, 0.3)
    """Notch depths ``D_z/D_p`` tried (gain at the centre)."""
    notch_widths: tuple[float, ...] = (0.2, 0.5)
    """Notch widths ``D_p`` tried."""
    pair_shapes: tuple[tuple[float, float], ...] = ((0.1, 0.5), (0.3, 0.5), (0.1, 1.0), (0.3, 0.2))
    """(depth, width) of each notch of the pair at the anti-resonance and at the resonance."""
    polish_evaluations: int = 300
    """Nelder-Mead evaluations from the best grid design over ``Kp``, ``Ti`` and the notches (0: none)."""
    notch_top: float = 0.95
    """Notch centres above this share of the Nyquist frequency are not tried (the biquad needs it below)."""
    grid_points: int = 1500
    """Log-spaced frequencies from ``grid_low`` of the Nyquist frequency to just below it ..."""
    grid_low: float = 1e-6
    """... (from this share of it) ..."""
    resonance_points: int = 301
    """... plus this many within +- ``resonance_span`` (log) around the resonance and the anti-resonance
    (0.17 % apart: a damping of 0.005 is 1 % wide)."""
    resonance_span: float = 0.25
    """See ``resonance_points``."""

    def __post_init__(self) -> None:
        positive = Values(POSITIVE, empty=False)
        check_settings(self, {
            "min_phase_margin": Interval(0.0, 90.0), "min_gain_margin_dB": Interval(0.0),
            "max_load_peak": POSITIVE, "scan_high": Interval(0.0, 1.0, open_low=True, open_high=True),
            "scan_low": POSITIVE, "scan_per_decade": AT_LEAST_ONE, "local_points": Interval(0, integer=True),
            "refine_steps": Interval(0, integer=True),
            "ti_products": positive, "max_notches": Interval(0, 2, integer=True), "filter_samples": Values(Interval(0.0), empty=False), "notch_centres": positive,
            "notch_depths": Values(Interval(0.0, 1.0, open_low=True), empty=False), "notch_widths": positive,
            "pair_shapes": _PAIR_SHAPES,
            "polish_evaluations": Interval(0, integer=True), "notch_top": Interval(0.0, 1.0, open_low=True, open_high=True), "grid_points": Interval(10, integer=True),
            "grid_low": Interval(0.0, 1.0, open_low=True, open_high=True), "resonance_points": Interval(3, integer=True),
            "resonance_span": POSITIVE})


@dataclass(frozen=True)
class _PairShapes:
    """A tuple of (depth in (0, 1], width > 0) pairs."""

    def holds(self, value: Any) -> bool:
        return isinstance(value, tuple) and all(Values(POSITIVE, 2).holds(v) and v[0] <= 1 for v in value)

    def text(self) -> str:
        return "a tuple of (depth in (0, 1], width > 0) pairs"


_PAIR_SHAPES = _PairShapes()

#: The oracle's settings.
SEARCH = OracleSearch()


def notches_of(notch: Any) -> tuple[NotchSpec, ...]:
    """A law's ``notch`` field as a tuple of :class:`NotchSpec` (None, one, or a sequence of up to two)."""
    if notch is None:
        return ()
    if isinstance(notch, NotchSpec):
        return (notch,)
    if isinstance(notch, Sequence) and all(isinstance(n, NotchSpec) or n is None for n in notch):
        return tuple(n for n in notch if n is not None)
    raise TypeError(f"notch: expected None, a NotchSpec or a sequence of them, received {type(notch).__name__}")


@dataclass(frozen=True)
class LoopFigures:
    """A law on the true linear plant: ``w_c`` [rad/s] (first gain crossover; nan: none),
    ``phase_margin`` [deg], ``gain_margin_dB``, ``load_peak_dB`` (reference -> load speed), ``stable``."""

    w_c: float
    phase_margin: float
    gain_margin_dB: float
    load_peak_dB: float
    stable: bool

    def meets(self, search: OracleSearch = SEARCH) -> bool:
        """The oracle's constraints."""
        return (self.stable and self.phase_margin >= search.min_phase_margin
                and self.gain_margin_dB >= search.min_gain_margin_dB
                and self.load_peak_dB <= 20 * math.log10(search.max_load_peak) + 1e-9)


@dataclass(frozen=True)
class OracleDesign:
    """The reference loop: ``w_c`` [rad/s] (0: nothing feasible), the law (``Kp``, ``Ti``, ``T_f``,
    ``notches``) and its :class:`LoopFigures`; ``evaluated``: candidates tried."""

    w_c: float
    Kp: float
    Ti: float
    T_f: float
    notches: tuple[NotchSpec, ...]
    figures: LoopFigures | None
    evaluated: int


@dataclass(frozen=True)
class PlantResponse:
    """The true plant on the grid ``w`` [rad/s]: ``G`` (torque reference -> measured motor speed) and
    ``G_L`` (torque reference -> load speed)."""

    w: np.ndarray
    G: np.ndarray
    G_L: np.ndarray


def _grid(plant: LinearPlant, search: OracleSearch) -> np.ndarray:
    w_ny = math.pi / plant.T_s
    parts = [np.logspace(math.log10(w_ny * search.grid_low), math.log10(w_ny * 0.9995), search.grid_points)]
    for w_r in plant.resonances:
        if 0 < w_r < w_ny:
            parts.append(w_r * np.exp(np.linspace(-search.resonance_span, search.resonance_span, search.resonance_points)))
    w = np.unique(np.concatenate(parts))
    return w[w < w_ny]


def loop_responses(plant: LinearPlant, w: np.ndarray) -> PlantResponse:
    """``G`` and ``G_L`` of ``plant`` at ``w``: ``u`` (applied) = ``M_ref`` delayed one sample;
    ``w_meas[k] = (Cd x[k-1] + Dd u[k-1]) / T_s``; ``w_L[k] = Lw x[k]``."""
    z = np.exp(1j * np.asarray(w, dtype=float) * plant.T_s)
    n = plant.Ad.shape[0]
    X = np.linalg.solve(z[:, None, None] * np.eye(n) - plant.Ad, np.broadcast_to(plant.Bd, (len(z), n))[..., None])[..., 0]
    G = (X @ plant.Cd + plant.Dd) / (z * z * plant.T_s)
    return PlantResponse(np.asarray(w, dtype=float), G, (X @ plant.Lw) / z)


def _pi_shape(z: np.ndarray, Ti: Any, T_s: float) -> np.ndarray:
    """``C / Kp = 1 + (T_s/Ti) z/(z-1)``."""
    return 1.0 + T_s / Ti * z / (z - 1.0)


def _notch_response(notches: tuple[NotchSpec, ...], z: np.ndarray, T_s: float) -> np.ndarray:
    out = np.ones_like(z)
    for notch in notches:
        b, a = notch.coefficients(T_s)
        zi = 1.0 / z
        out = out * (b[0] + b[1] * zi + b[2] * zi * zi) / (a[0] + a[1] * zi + a[2] * zi * zi)
    return out


def _filter_response(T_f: float, z: np.ndarray, T_s: float) -> np.ndarray:
    if T_f <= 0:
        return np.ones_like(z)
    a = math.exp(-T_s / T_f)
    return (1 - a) * z / (z - a)


def _series(first: tuple, second: tuple) -> tuple:
    """State space of ``second(first(u))`` (discrete, SISO: ``A, B, C, D`` as arrays, ``D`` a float)."""
    A1, B1, C1, D1 = first
    A2, B2, C2, D2 = second
    n1, n2 = A1.shape[0], A2.shape[0]
    A = np.zeros((n1 + n2, n1 + n2))
    A[:n1, :n1], A[n1:, n1:], A[n1:, :n1] = A1, A2, np.outer(B2, C1)
    return A, np.concatenate([B1, B2 * D1]), np.concatenate([D2 * C1, C2]), D2 * D1


def _biquad(b: np.ndarray, a: np.ndarray) -> tuple:
    """``(b0 + b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2)`` as a state space (controllable form)."""
    b0 = b[0]
    A = np.array([[-a[1], -a[2]], [1.0, 0.0]])
    return A, np.array([1.0, 0.0]), np.array([b[1] - b0 * a[1], b[2] - b0 * a[2]]), float(b0)


def closed_loop_poles(plant: LinearPlant, Kp: float, Ti: float, T_f: float, notches: tuple[NotchSpec, ...]) -> np.ndarray:
    """Eigenvalues of the closed loop ``e = -F G N C e``, built block by block (PI, notches, the plant
    with its input and measurement delays, the low-pass)."""
    T_s = plant.T_s
    ki = Kp * T_s / Ti
    # PI: I[k] = I[k-1] + ki e[k], u = Kp e + I  ->  state I[k-1]: x+ = x + ki e, u = x + (Kp + ki) e
    law = (np.array([[1.0]]), np.array([ki]), np.array([1.0]), Kp + ki)
    for notch in notches:
        law = _series(law, _biquad(*notch.coefficients(T_s)))
    n = plant.Ad.shape[0]  # plant: states [x, u_applied, dphi_prev], input M_ref, output dphi_prev / T_s
    A = np.zeros((n + 2, n + 2))
    A[:n, :n], A[:n, n], A[n + 1, :n], A[n + 1, n] = plant.Ad, plant.Bd, plant.Cd, plant.Dd
    B = np.zeros(n + 2)
    B[n] = 1.0
    C = np.zeros(n + 2)
    C[n + 1] = 1.0 / T_s
    loop = _series(law, (A, B, C, 0.0))
    if T_f > 0:
        a = math.exp(-T_s / T_f)  # w_f[k] = a w_f[k-1] + (1-a) w[k]: state w_f[k-1]
        loop = _series(loop, (np.array([[a]]), np.array([1 - a]), np.array([a]), 1 - a))
    A_L, B_L, C_L, D_L = loop
    if D_L != 0:
        raise ValueError("closed_loop_poles: the loop must hold a delay (D = 0)")
    return np.linalg.eigvals(A_L - np.outer(B_L, C_L))


def _margins(L: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First gain crossover ``w_c``, phase margin [deg] and gain margin [dB] of each row of ``L`` (K x W)."""
    L = np.atleast_2d(L)
    lm = np.log(np.maximum(np.abs(L), 1e-300))
    ph = np.unwrap(np.angle(L), axis=1)
    lw = np.log(w)
    dl = np.diff(lm, axis=1)
    above = lm >= 0
    cross = above[:, :-1] != above[:, 1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(cross, -lm[:, :-1] / np.where(dl == 0, 1.0, dl), 0.0)
    ph_c = ph[:, :-1] + frac * np.diff(ph, axis=1)
    pm_each = 180.0 - np.abs(np.degrees(np.remainder(ph_c + math.pi, 2 * math.pi) - math.pi))
    pm = np.where(cross, pm_each, np.inf).min(axis=1)
    down = cross & above[:, :-1]
    first = np.argmax(down, axis=1)
    rows = np.arange(L.shape[0])
    w_c = np.where(down.any(axis=1), np.exp(lw[first] + frac[rows, first] * (lw[first + 1] - lw[first])), np.nan)
    turn = np.floor((ph + math.pi) / (2 * math.pi))
    pc = turn[:, :-1] != turn[:, 1:]
    target = np.maximum(turn[:, :-1], turn[:, 1:]) * 2 * math.pi - math.pi
    dph = np.diff(ph, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        f2 = np.where(pc, (target - ph[:, :-1]) / np.where(dph == 0, 1.0, dph), 0.0)
    w_x = np.exp(lw[:-1] + f2 * np.diff(lw))
    gm_each = np.abs(20.0 / math.log(10) * (lm[:, :-1] + f2 * dl))
    gm = np.where(pc & (w_x > np.nan_to_num(w_c, nan=0.0)[:, None]), gm_each, np.inf).min(axis=1)
    return w_c, pm, gm


def _figures(resp: PlantResponse, plant: LinearPlant, Kp: float, Ti: float, T_f: float,
             notches: tuple[NotchSpec, ...]) -> LoopFigures:
    z = np.exp(1j * resp.w * plant.T_s)
    CN = Kp * _pi_shape(z, Ti, plant.T_s) * _notch_response(notches, z, plant.T_s)
    L = CN * _filter_response(T_f, z, plant.T_s) * resp.G
    w_c, pm, gm = _margins(L, resp.w)
    peak = float(np.max(np.abs(CN * resp.G_L / (1.0 + L))))
    stable = bool(np.abs(closed_loop_poles(plant, Kp, Ti, T_f, notches)).max() < 1.0)
    return LoopFigures(float(w_c[0]), float(pm[0]), float(gm[0]), 20 * math.log10(max(peak, 1e-300)), stable)


def true_figures(plant: LinearPlant, Kp: float, Ti: float, T_f: float, notch: Any,
                 search: OracleSearch = SEARCH) -> LoopFigures:
    """:class:`LoopFigures` of the law (``notch``: None, a NotchSpec or up to two) on the true ``plant``."""
    return _figures(loop_responses(plant, _grid(plant, search)), plant, Kp, Ti, T_f, notches_of(notch))


def _notch_sets(mech: Mechanics, T_s: float, search: OracleSearch) -> list[tuple[NotchSpec, ...]]:
    """No notch; one at, below and above the resonance, the anti-resonance and their geometric mean,
    each depth and width; the pair (anti-resonance, resonance) in :attr:`OracleSearch.pair_shapes`."""
    sets: list[tuple[NotchSpec, ...]] = [()]
    if not mech.two_mass or search.max_notches == 0:
        return sets
    top = search.notch_top * math.pi / T_s
    w_0, w_A = mech.derived.w_0, mech.w_A
    centres = sorted({w * f for w in (w_A, math.sqrt(w_A * w_0), w_0) for f in search.notch_centres})
    for w_n, depth, width in itertools.product(centres, search.notch_depths, search.notch_widths):
        if w_n < top:
            sets.append((NotchSpec(w_n / (2 * math.pi), depth * width, width),))
    if w_0 < top and search.max_notches == 2:
        for (d1, p1), (d2, p2) in itertools.product(search.pair_shapes, repeat=2):
            sets.append((NotchSpec(w_A / (2 * math.pi), d1 * p1, p1), NotchSpec(w_0 / (2 * math.pi), d2 * p2, p2)))
    return sets


@dataclass
class _Candidates:
    """The structures at one plant: (notches, T_f) with ``N F`` on the grid; ``Ti w_t`` apart."""

    shapes: list[tuple[tuple[NotchSpec, ...], float]]
    NF: np.ndarray  # shapes x W
    N: np.ndarray   # shapes x W


def _candidates(mech: Mechanics, plant: LinearPlant, z: np.ndarray, search: OracleSearch) -> _Candidates:
    T_s = plant.T_s
    shapes, NF, N = [], [], []
    for notches in _notch_sets(mech, T_s, search):
        n_resp = _notch_response(notches, z, T_s)
        for k in search.filter_samples:
            shapes.append((notches, k * T_s))
            NF.append(n_resp * _filter_response(k * T_s, z, T_s))
            N.append(n_resp)
    return _Candidates(shapes, np.array(NF), np.array(N))


def _at_target(w_t: float, cand: _Candidates, resp: PlantResponse, plant: LinearPlant, search: OracleSearch) -> OracleDesign | None:
    """The feasible candidate with the highest own crossover at target ``w_t``; None: none."""
    T_s = plant.T_s
    z = np.exp(1j * resp.w * T_s)
    z_t = np.exp(1j * np.array([w_t]) * T_s)
    G_t = loop_responses(plant, np.array([w_t])).G[0]
    NF_t = np.array([(_notch_response(n, z_t, T_s) * _filter_response(tf, z_t, T_s))[0] for n, tf in cand.shapes])
    found: list[tuple[float, float, float, int]] = []
    for tau in search.ti_products:
        Ti = tau / w_t
        L_t = _pi_shape(z_t, Ti, T_s)[0] * NF_t * G_t
        # |L(w_t)| = 1 makes w_t a gain crossover: its phase margin there screens the candidates cheaply
        keep = np.nonzero(180.0 - np.abs(np.degrees(np.angle(L_t))) >= search.min_phase_margin)[0]
        if not len(keep):
            continue
        Kp = 1.0 / np.abs(L_t[keep])
        P = _pi_shape(z, Ti, T_s)
        L = Kp[:, None] * P * cand.NF[keep] * resp.G[None]
        w_c, pm, gm = _margins(L, resp.w)
        ok = np.nonzero((pm >= search.min_phase_margin) & (gm >= search.min_gain_margin_dB) & np.isfinite(w_c))[0]
        peak = np.max(np.abs(Kp[ok, None] * P * cand.N[keep[ok]] * resp.G_L[None] / (1.0 + L[ok])), axis=1)
        found += [(float(w_c[j]), float(Kp[j]), Ti, int(keep[j])) for j in ok[peak <= search.max_load_peak]]
    for w_c, Kp, Ti, i in sorted(found, reverse=True):
        notches, T_f = cand.shapes[i]
        if np.abs(closed_loop_poles(plant, Kp, Ti, T_f, notches)).max() < 1.0:
            return OracleDesign(w_c, Kp, Ti, T_f, notches, None, 0)
    return None


def oracle(plant: LinearPlant, mech: Mechanics, search: OracleSearch = SEARCH) -> OracleDesign:
    """The largest feasible first crossover of the law's structure on the true ``plant`` of ``mech``
    (the module docstring says how it is searched); ``w_c`` 0 where nothing is feasible."""
    resp = loop_responses(plant, _grid(plant, search))
    cand = _candidates(mech, plant, np.exp(1j * resp.w * plant.T_s), search)
    per_target = len(cand.shapes) * len(search.ti_products)
    step = 10 ** (1.0 / search.scan_per_decade)
    w_t, evaluated = search.scan_high * math.pi / plant.T_s, 0
    best: OracleDesign | None = None
    best_target = math.nan
    while w_t >= search.scan_low and (best is None or w_t > best.w_c):
        design = _at_target(w_t, cand, resp, plant, search)
        evaluated += per_target
        if design is not None and (best is None or design.w_c > best.w_c):
            best, best_target = design, w_t
        w_t /= step
    if best is None:
        return OracleDesign(0.0, math.nan, math.nan, math.nan, (), None, evaluated)
    local = best_target * step ** np.linspace(0.0, 1.0, search.local_points + 2)[1:-1]
    for w_t in local:  # the feasible set need not be an interval: a local scan first ...
        design = _at_target(float(w_t), cand, resp, plant, search)
        evaluated += per_target
        if design is not None and design.w_c > best.w_c:
            best, best_target = design, float(w_t)
    low, high = best_target, min(t for t in (*local, best_target * step) if t > best_target)
    for _ in range(search.refine_steps):  # ... then bisection above the best target
        mid = math.sqrt(low * high)
        design = _at_target(mid, cand, resp, plant, search)
        evaluated += per_target
        if design is not None and design.w_c > best.w_c:
            best = design
        low, high = (mid, high) if design is not None else (low, mid)
    best, polished = _polish(best, resp, plant, search)
    figures = _figures(resp, plant, best.Kp, best.Ti, best.T_f, best.notches)
    return OracleDesign(figures.w_c, best.Kp, best.Ti, best.T_f, best.notches, figures, evaluated + polished)


def _unpack(x: np.ndarray, T_f: float, count: int) -> tuple[float, float, float, tuple[NotchSpec, ...]]:
    """``x = [log Kp, log Ti, (log f_n, log depth, log D_p) per notch]`` -> the law (depth at most 1)."""
    notches = tuple(NotchSpec(math.exp(x[2 + 3 * i]), math.exp(min(x[3 + 3 * i], 0.0) + x[4 + 3 * i]), math.exp(x[4 + 3 * i]))
                    for i in range(count))
    return math.exp(x[0]), math.exp(x[1]), T_f, notches


def _polish(best: OracleDesign, resp: PlantResponse, plant: LinearPlant, search: OracleSearch) -> tuple[OracleDesign, int]:
    """Nelder-Mead from the best grid design over ``Kp``, ``Ti`` and the notches' centre, depth and
    width (``T_f`` kept): maximize the first crossover, every constraint a wall. Returns the better
    design and the evaluations spent."""
    from scipy.optimize import minimize

    x0 = [math.log(best.Kp), math.log(best.Ti)]
    for n in best.notches:
        x0 += [math.log(n.f_n), math.log(n.D_z / n.D_p), math.log(n.D_p)]
    top = search.notch_top * 0.5 / plant.T_s
    count = len(best.notches)

    def cost(x: np.ndarray) -> float:
        Kp, Ti, T_f, notches = _unpack(x, best.T_f, count)
        if any(n.f_n >= top for n in notches):
            return math.inf
        figs = _figures(resp, plant, Kp, Ti, T_f, notches)
        pi_like = Ti * figs.w_c <= max(search.ti_products)  # a PI whose integral action still acts
        return -math.log(figs.w_c) if figs.meets(search) and math.isfinite(figs.w_c) and pi_like else math.inf

    if search.polish_evaluations == 0 or not math.isfinite(cost(np.array(x0))):
        return best, 0
    result = minimize(cost, np.array(x0), method="Nelder-Mead",
                      options={"maxfev": search.polish_evaluations, "xatol": 1e-3, "fatol": 1e-4,
                               "initial_simplex": np.array(x0) + np.vstack([np.zeros(len(x0)), 0.05 * np.eye(len(x0))])})
    if not math.isfinite(result.fun) or math.exp(-result.fun) <= best.w_c:
        return best, int(result.nfev)
    Kp, Ti, T_f, notches = _unpack(result.x, best.T_f, count)
    return OracleDesign(math.exp(-result.fun), Kp, Ti, T_f, notches, None, 0), int(result.nfev)
