"""Model-based refinement of the maps' answer: an output-error fit by batched re-simulation.

The maps give the structure and a first estimate of ``f_e``, ``V_J``, ``d`` and the normalized
backlash ``s_N``. This module polishes them on the record itself: candidate two-mass models
(``J_sigma``, ``M_FC``, ``mu_F`` from STEP 2, unless STEP 2 flags its own fit: see
:class:`RefineConfig`) are simulated open loop under the record's own
torque reference (:func:`sim.replay.replay_speed`, many candidates in one batch) and scored by
how well they reproduce the measured motor speed. Before scoring, a quadratic trend per section
is removed from the speed error: it absorbs the small one-mass errors of STEP 2 (a friction or
inertia error tilts a section's speed), so the score measures what the maps are about: the
oscillation after each torque step and the motor's excursions while it crosses the backlash.

The search is a cross-entropy method (sample around the best models so far, keep the elites,
shrink), started from the maps' answer, which stays a candidate: the refined model never
reproduces the record worse than the maps' own answer.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

import sim
from sim.replay import replay_speed

__all__ = ["RefineConfig", "RefineProblem", "Refined", "torque_reference", "refine"]

#: Search coordinates and their bounds: log10 f_e [Hz], log10 V_J, d, log10 s_N (normalized
#: backlash; measured better than searching the width itself: 86 vs 66 % of the widths within 30 %).
COORDINATES: tuple[str, ...] = ("log10_f_e", "log10_V_J", "d", "log10_s_N")
_LOW = np.array([0.0, math.log10(0.05), 0.001, -3.0])
_HIGH = np.array([math.log10(3000.0), math.log10(20.0), 0.5, 2.0])
#: With a one-mass fit that STEP 2 flags, two more: log10 J_sigma [kg m^2] and M_FC [Nm].
FREE_COORDINATES: tuple[str, ...] = COORDINATES + ("log10_J_sigma", "M_FC")
_LOW_FREE = np.concatenate([_LOW, [-4.0, 0.0]])
_HIGH_FREE = np.concatenate([_HIGH, [1.0, 5.0]])


@dataclass(frozen=True)
class RefineConfig:
    """The search, in three stages.

    Explore: score only the first ``window_periods`` periods (at the start's ``f_e``; at most
    ``window_max`` seconds) after each torque step, with each candidate's best gain projected
    out: a model whose frequency is a few % off does not lose its match to the phase error that
    builds up over a long section, nor a model with the right shape but a wrong ``V_J`` to its
    amplitude (the gain rescales its ``V_J``). A grid of ``grid_f_e`` eigenfrequencies over
    ``+-grid_span`` decades around the start times the normalized backlash values ``grid_s_N``
    (0: the start's own), then
    ``rounds`` rounds of a cross-entropy search: ``candidates`` models around the best so far,
    the ``elites`` best setting the next round's spread (``spread``: the first round's standard
    deviation per coordinate of :data:`COORDINATES`). Each window is simulated on its own from a
    quasi-static state, so exploring costs a few periods per torque step, not the whole record.

    Choose: the maps' answer and the ``elites`` best of the exploration compete on the plain
    detrended error over the whole record, simulated exactly (more rounds there were measured
    not to help). The C kernel runs blocks of 32 models on the CPU's cores: 64 candidates take
    the wall time of 32 on two.

    Free one-mass part (problems with ``free_one_mass``: STEP 2 flagged its fit, as for very soft
    mechanics whose test sections are shorter than an oscillation period): ``J_sigma`` and
    ``M_FC`` join the search (:data:`FREE_COORDINATES`), scored by the plain error over the
    whole record (an exact replay from rest; nothing to detrend once the one-mass part is
    fitted): a grid over ``J_sigma`` (x 1/4 .. 4), ``f_e`` (x 1/16 .. 2: such a mechanic is
    softer than it looks), ``V_J`` and ``M_FC`` around the chosen model and around the maps'
    answer, then ``free_rounds`` rounds (``free_spread``: the first spread of the two new
    coordinates). The free model replaces the chosen one only when its plain squared error is
    below ``free_win`` times the chosen one's (with STEP 2's ``J_sigma`` and ``M_FC``)."""

    grid_f_e: int = 11  # explore: eigenfrequencies of the first grid
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # explore: s_N of the first grid (0: the start's)
    grid_span: float = 0.25  # explore: the grid's half width [decades of f_e]
    window_periods: float = 4.0  # explore: periods scored after each torque step
    window_max: float = 0.1  # explore: at most this long [s]
    rounds: int = 3  # explore: cross-entropy rounds
    candidates: int = 64  # models per round
    elites: int = 12  # best models that set the next spread (and the finalists)
    spread: tuple[float, float, float, float] = (0.05, 0.12, 0.03, 0.3)  # first spread over COORDINATES
    free_rounds: int = 5  # free one-mass part: cross-entropy rounds
    free_spread: tuple[float, float] = (0.1, 0.1)  # free one-mass part: first spread of log10 J_sigma, M_FC
    free_win: float = 0.25  # free one-mass part: error ratio it must beat
    seed: int = 0  # every search starts from this seed


@dataclass
class RefineProblem:
    """One record to refine: measured ``speed`` ``N`` [rad/s]; torque reference segments
    (``start`` int ``K``, ``level`` ``K`` [Nm]); scored ``segments`` ``(L, 2)`` half-open sample
    ranges; STEP 2's ``J_sigma``, ``M_FC``, ``mu_F``; the drive (``T_s``, ``T_Ei``,
    ``encoder_counts``, ``M_N`` for ``s_N``); the start ``theta`` over :data:`COORDINATES`
    (``s_N`` of 1e-3 or less stands for no backlash)."""

    speed: np.ndarray
    start: np.ndarray
    level: np.ndarray
    segments: np.ndarray
    J_sigma: float
    M_FC: float
    mu_F: float
    T_s: float
    T_Ei: float
    encoder_counts: int
    M_N: float
    theta: np.ndarray
    free_one_mass: bool = False

    def J_sigma_of(self, theta: np.ndarray) -> np.ndarray:
        """``J_sigma`` [kg m^2] of ``theta`` ``*batch x 4`` (STEP 2's) or ``x 6`` (its own)."""
        return 10.0 ** theta[..., 4] if theta.shape[-1] == 6 else np.full(theta.shape[:-1], self.J_sigma)

    def C_F(self, theta: np.ndarray) -> np.ndarray:
        """Shaft stiffness [Nm/rad] of ``theta`` ``*batch x 4`` (or ``x 6``)."""
        return sim.two_mass_derived(self.J_sigma_of(theta), 10.0 ** theta[..., 1], 10.0 ** theta[..., 0],
                                    theta[..., 2]).C_F


@dataclass
class Refined:
    """The refined model: ``f_e`` [Hz], ``V_J``, ``d``, ``s_N``, ``backlash`` = ``2s`` [rad];
    ``residual`` and ``start_residual``: the detrended speed error of the refined model and of
    the maps' answer over the measured oscillation (both detrended the same way; about the
    quantization noise over the oscillation for a perfect model); ``n_sims`` simulated models;
    ``J_sigma``, ``M_FC``: refined one-mass values where the free stage won (else None: STEP 2's
    stand)."""

    f_e: float
    V_J: float
    d: float
    s_N: float
    backlash: float
    residual: float
    start_residual: float
    n_sims: int
    J_sigma: float | None = None
    M_FC: float | None = None


def torque_reference(bounds: np.ndarray, M_star: float) -> tuple[np.ndarray, np.ndarray]:
    """The switching test's torque reference (SPEC 2) from its six section ``bounds`` ``(6, 2)``:
    0 before section I, :data:`sim.SECTION_LEVELS` ``x M*`` over the sections, 0 in the tail.
    Returns ``start`` (int ``8``) and ``level`` (``8`` [Nm]) for :func:`sim.replay.replay_speed`."""
    bounds = np.asarray(bounds, dtype=np.int64)
    if bounds.shape != (6, 2):
        raise ValueError(f"bounds: expected shape (6, 2), received {bounds.shape}")
    start = np.concatenate([[0], bounds[:, 0], [bounds[5, 1]]])
    level = M_star * np.array([0.0, *sim.SECTION_LEVELS, 0.0])
    return start, level


def _detrend_basis(segments: np.ndarray) -> list[tuple[int, int, torch.Tensor]]:
    """Per segment ``(a, b, Q)``: orthonormal ``L x 3`` basis of the quadratic trends on it."""
    return [(a, b, _trend_basis(b - a)) for a, b in np.asarray(segments, dtype=np.int64).tolist() if b > a]


@functools.lru_cache(maxsize=4096)
def _trend_basis(L: int) -> torch.Tensor:
    """Orthonormal ``L x min(3, L)`` basis of the polynomials of degree < 3 on ``L`` samples."""
    tau = np.linspace(-1.0, 1.0, L)
    V = np.stack([np.ones(L), tau, tau * tau], axis=1)[:, : min(3, L)]  # L x 3
    return torch.as_tensor(np.linalg.qr(V)[0], dtype=torch.float64)


def _detrended_energy(E: torch.Tensor, basis: list[tuple[int, int, torch.Tensor]]) -> torch.Tensor:
    """``sum ||e - Q Q^T e||^2`` over the segments for each row of ``E`` (``C x N``) -> ``C``."""
    total = torch.zeros(E.shape[0], dtype=torch.float64)
    for a, b, Q in basis:
        e = E[:, a:b]  # C x L
        total += (e * e).sum(-1) - ((e @ Q) ** 2).sum(-1)
    return total.clamp(min=0.0)


def _models(p: RefineProblem, theta: np.ndarray) -> sim.TwoMassParams:
    """Candidate models ``C`` from ``theta`` ``C x 4`` or ``C x 6`` (backlash ``2s = 2 s_N M_N / C_F``)."""
    f_e, V_J, d = 10.0 ** theta[:, 0], 10.0 ** theta[:, 1], theta[:, 2]
    backlash = 2.0 * 10.0 ** theta[:, 3] * p.M_N / p.C_F(theta)
    C = theta.shape[0]
    M_FC = theta[:, 5] if theta.shape[1] == 6 else np.full(C, max(p.M_FC, 0.0))
    t = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
    return sim.TwoMassParams(J_sigma=t(p.J_sigma_of(theta)), V_J=t(V_J), f_e=t(f_e), d=t(d), backlash=t(backlash),
                             M_FC=t(M_FC), mu_F=torch.full((C,), max(p.mu_F, 0.0), dtype=torch.float64))


def _simulate(p: RefineProblem, theta: np.ndarray, drive: sim.DriveConfig) -> torch.Tensor:
    """Speed error ``C x N`` [rad/s] (model minus measurement) of each candidate ``theta`` ``C x 4``."""
    return _simulate_packed([(p, theta)], drive)[0]


def _simulate_packed(items: list[tuple[RefineProblem, np.ndarray]], drive: sim.DriveConfig) -> list[torch.Tensor]:
    """:func:`_simulate` for several records on one drive in one replay call (the kernel's blocks
    of 32 models fill up and run on all cores): one ``C_i x N_i`` error per item."""
    models = [_models(p, th) for p, th in items]
    flat = sim.TwoMassParams(**{k: torch.cat([getattr(m, k) for m in models])
                                for k in sim.PARAM_NAMES})
    N = max(len(p.speed) for p, _ in items)
    K = max(len(p.start) for p, _ in items)
    start = np.concatenate([np.broadcast_to(np.pad(p.start, (0, K - len(p.start)), constant_values=2**30),
                                            (len(th), K)) for p, th in items])  # n x K
    level = np.concatenate([np.broadcast_to(np.pad(p.level, (0, K - len(p.level)), mode="edge"),
                                            (len(th), K)) for p, th in items])
    S = _substeps(flat, drive.T_s)
    w = replay_speed(flat, drive, torch.as_tensor(start), torch.as_tensor(level), N, quantize=False, substeps=S)
    out, i = [], 0
    for p, th in items:
        E = w[i:i + len(th), : len(p.speed)].to(torch.float64) - torch.as_tensor(p.speed, dtype=torch.float64)
        out.append(torch.nan_to_num(E, nan=1e6, posinf=1e6, neginf=-1e6))
        i += len(th)
    return out


def _substeps(models: sim.TwoMassParams, T_s: float) -> int:
    """RK4 substeps per sample: ``w_0 dt <= 0.5`` for the stiffest model (frequency error < 0.1 %)."""
    return max(1, math.ceil(float(models.w_0.max()) * T_s / 0.5))


def _drive(p: RefineProblem) -> sim.DriveConfig:
    """The drive the candidates of ``p`` run on (no torque limit: the levels are what was applied)."""
    return sim.DriveConfig(M_max=1e9, T_Ei=p.T_Ei, T_s=p.T_s, encoder_counts=p.encoder_counts)


def _score(p: RefineProblem, theta: np.ndarray, basis: list, drive: sim.DriveConfig) -> np.ndarray:
    """Detrended squared speed error of each candidate ``theta`` ``C x 4`` -> ``C``."""
    return _detrended_energy(_simulate(p, theta, drive), basis).numpy()


@dataclass(frozen=True)
class _ScoreWindows:
    """What the exploration score needs of a record's ``windows`` ``(J, 2)``, computed once: the
    measured speed ``y`` over them laid end to end (``sum L_j``), the block-diagonal orthonormal
    basis ``B`` ``(sum L_j, 3J)`` of each window's quadratic trend, and ``y`` detrended (``y_r``)."""

    windows: np.ndarray
    y: torch.Tensor
    B: torch.Tensor
    y_r: torch.Tensor

    @classmethod
    def of(cls, p: RefineProblem, windows: np.ndarray) -> "_ScoreWindows":
        y = torch.cat([torch.as_tensor(p.speed[a:b], dtype=torch.float64) for a, b in windows.tolist()])
        B = torch.block_diag(*[_trend_basis(b - a) for a, b in windows.tolist() if b > a])  # sum L_j x 3J
        return cls(windows, y, B, y - B @ (B.T @ y))


def _score_shape(p: RefineProblem, theta: np.ndarray, w: _ScoreWindows,
                 drive: sim.DriveConfig) -> tuple[np.ndarray, np.ndarray]:
    """The exploration score over the windows ``w``: the detrended error after the best gain ``g``
    on each candidate's detrended speed, ``||y||^2 - <y, x>^2 / ||x||^2`` (``y`` measured, ``x``
    model), and ``theta`` with ``V_J`` scaled by ``g`` (eq. 1: the oscillation is about
    proportional to ``V_J``)."""
    X = _simulate_windows(p, theta, w.windows, drive) + w.y  # C x sum(L_j): the model speeds
    X_r = X - (X @ w.B) @ w.B.T  # C x sum(L_j), each window detrended
    xy, xx, yy = X_r @ w.y_r, (X_r * X_r).sum(-1), w.y_r @ w.y_r
    gain = torch.where(xx > 0, xy / xx.clamp(min=1e-300), torch.zeros_like(xx))
    cost = (yy - torch.where(xx > 0, xy * xy / xx.clamp(min=1e-300), torch.zeros_like(xx))).clamp(min=0.0)
    cost = torch.where(gain > 0, cost, yy.expand_as(cost))  # an inverted oscillation is no match
    scaled = theta.copy()
    scaled[:, 1] += np.log10(np.clip(gain.numpy(), 0.25, 4.0))
    return cost.numpy(), np.clip(scaled, _LOW, _HIGH)


def _windows(segments: np.ndarray, length: int) -> np.ndarray:
    """The first ``length`` samples of each segment ``(L, 2)``."""
    seg = np.asarray(segments, dtype=np.int64)
    return np.stack([seg[:, 0], np.minimum(seg[:, 1], seg[:, 0] + length)], axis=1)


def _level_at(p: RefineProblem, k: int) -> float:
    """The torque reference [Nm] over sample ``k``."""
    return float(p.level[np.searchsorted(p.start, k, side="right") - 1])


def _simulate_windows(p: RefineProblem, theta: np.ndarray, windows: np.ndarray,
                      drive: sim.DriveConfig) -> torch.Tensor:
    """Speed error ``C x sum(L_j)`` of each candidate over the ``windows`` ``(J, 2)`` (concatenated),
    each simulated on its own from a quasi-static state: the torque before the window settled,
    both masses at the measured speed, the shaft twisted by the torque that accelerates the load
    (``J_L a`` plus the load friction, ``a`` the rigid acceleration) over ``C_F``, plus ``s`` on the
    loaded side. An oscillation still ringing from before the window is not in that state (the
    exploring score tolerates it; the polish simulates the whole record)."""
    C, J = theta.shape[0], len(windows)
    models = _models(p, theta)
    lengths = (windows[:, 1] - windows[:, 0]).tolist()
    L = max(lengths)
    w = torch.as_tensor(p.speed[windows[:, 0]], dtype=torch.float64)  # J: speed at each window start
    M_prev = torch.tensor([_level_at(p, a - 1) if a > 0 else 0.0 for a in windows[:, 0].tolist()], dtype=torch.float64)
    M_new = torch.tensor([_level_at(p, a) for a in windows[:, 0].tolist()], dtype=torch.float64)
    friction = models.M_FC[:, None] * torch.sign(w) + max(p.mu_F, 0.0) * w  # C x J
    M_S = models.J_L[:, None] * (M_prev - friction) / models.J_sigma[:, None] + friction  # C x J: rigid motion
    s = (models.backlash / 2.0)[:, None]
    dphi = M_S / models.C_F[:, None] + s * torch.sign(M_S)
    rep = lambda v: v.repeat_interleave(J)  # noqa: E731  C -> C*J, window index fastest
    flat = sim.TwoMassParams(**{n: rep(getattr(models, n)) for n in sim.PARAM_NAMES})
    state = {"w_M": w.repeat(C), "w_L": w.repeat(C), "dphi": dphi.reshape(-1), "M_M": M_prev.repeat(C)}
    start = torch.zeros(C * J, 1, dtype=torch.int32)
    level = M_new.repeat(C)[:, None]
    out = replay_speed(flat, drive, start, level, L, quantize=False, state=state,
                       substeps=_substeps(models, p.T_s)).reshape(C, J, L)
    E = torch.cat([out[:, j, :n].to(torch.float64) - torch.as_tensor(p.speed[a:a + n], dtype=torch.float64)
                   for j, (a, n) in enumerate(zip(windows[:, 0].tolist(), lengths))], dim=1)  # C x sum(L_j)
    return torch.nan_to_num(E, nan=1e6, posinf=1e6, neginf=-1e6)


def _cem(theta: np.ndarray, cost: np.ndarray, score: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
         rounds: int, spread: np.ndarray, config: RefineConfig, rng: np.random.Generator,
         low: np.ndarray = _LOW, high: np.ndarray = _HIGH) -> tuple[np.ndarray, np.ndarray]:
    """``rounds`` of the cross-entropy search from the best of ``theta``/``cost`` (all kept);
    ``score(candidates) -> (cost, candidates as scored)``."""
    mean, std = theta[int(np.argmin(cost))], spread
    for _ in range(rounds):
        cand = np.clip(mean + std * rng.standard_normal((config.candidates, theta.shape[1])), low, high)
        c, cand = score(cand)
        theta, cost = np.concatenate([theta, cand]), np.concatenate([cost, c])
        elite = theta[np.argsort(cost)[: config.elites]]
        mean = elite[0]  # the best so far; the elites' spread sets the next step
        std = np.maximum(0.7 * elite.std(axis=0) + 0.15 * std, 0.02 * spread)
    return theta, cost


def refine(problems: list[RefineProblem], config: RefineConfig | None = None) -> list[Refined]:
    """Refine each problem's ``theta`` (see module docstring); one :class:`Refined` per problem,
    each the same whatever the other problems (every search starts from ``config.seed``; the
    whole-record choice of records on the same drive and of similar length runs packed in one
    replay)."""
    config = config or RefineConfig()
    if config.elites < 2 or config.candidates < config.elites or config.rounds < 0 or config.window_periods <= 0:
        raise ValueError(f"RefineConfig: expected rounds >= 0, window_periods > 0 and candidates >= elites >= 2, "
                         f"received {config}")
    rngs = [np.random.default_rng(config.seed) for _ in problems]
    finalists = [_explore(p, config, rng) for p, rng in zip(problems, rngs)]
    costs: list[np.ndarray] = [np.empty(0)] * len(problems)
    substeps = [_substeps(_models(p, f), p.T_s) for p, f in zip(problems, finalists)]
    bases = [_detrend_basis(p.segments) for p in problems]  # the whole record's sections and tail
    for pack in _packs(problems, [len(f) for f in finalists], substeps):
        errors = _simulate_packed([(problems[i], finalists[i]) for i in pack], _drive(problems[pack[0]]))
        for i, E in zip(pack, errors):
            costs[i] = _detrended_energy(E, bases[i]).numpy()
    return [_finish(p, th, c, b, config, rng) for p, th, c, b, rng in zip(problems, finalists, costs, bases, rngs)]


def _packs(problems: list[RefineProblem], sizes: list[int], substeps: list[int], max_models: int = 256,
           min_length_ratio: float = 0.6) -> list[list[int]]:
    """Indices of ``problems`` in packs of one drive and one substep count (so that a result does
    not depend on its pack), lengths within ``min_length_ratio`` of the pack's longest (the
    shorter ones idle while it runs) and at most ``max_models`` models."""
    key = lambda i: (problems[i].T_s, problems[i].T_Ei, problems[i].encoder_counts, substeps[i])  # noqa: E731
    order = sorted(range(len(problems)), key=lambda i: (key(i), -len(problems[i].speed)))
    packs: list[list[int]] = []
    for i in order:
        last = packs[-1] if packs else None
        fits = (last and key(last[0]) == key(i)
                and len(problems[i].speed) >= min_length_ratio * len(problems[last[0]].speed)
                and sum(sizes[j] for j in last) + sizes[i] <= max_models)
        if fits:
            last.append(i)
        else:
            packs.append([i])
    return packs


def _explore(p: RefineProblem, config: RefineConfig, rng: np.random.Generator) -> np.ndarray:
    """The exploring stage; returns the finalists ``F x 4``: the maps' answer, then the elites."""
    drive = _drive(p)
    spread = np.asarray(config.spread, dtype=np.float64)
    theta0 = np.clip(np.asarray(p.theta, dtype=np.float64), _LOW, _HIGH)
    period = 1.0 / (10.0 ** theta0[0] * p.T_s)  # samples per period at the start's f_e
    short = _windows(p.segments, max(8, int(round(min(config.window_periods * period, config.window_max / p.T_s)))))
    windows = _ScoreWindows.of(p, short)
    explore = lambda th: _score_shape(p, th, windows, drive)  # noqa: E731
    grid = np.repeat(theta0[None], config.grid_f_e * len(config.grid_s_N), axis=0)  # G x 4
    grid[:, 0] += np.repeat(np.linspace(-config.grid_span, config.grid_span, config.grid_f_e), len(config.grid_s_N))
    grid[:, 3] = np.tile([math.log10(v) if v > 0 else theta0[3] for v in config.grid_s_N], config.grid_f_e)
    cost, theta = explore(np.clip(grid, _LOW, _HIGH))
    theta, cost = _cem(theta, cost, explore, config.rounds, spread, config, rng)
    return np.concatenate([theta0[None], theta[np.argsort(cost)[: config.elites]]])


def _finish(p: RefineProblem, theta: np.ndarray, cost: np.ndarray, full: list, config: RefineConfig,
            rng: np.random.Generator) -> Refined:
    """The best finalist (``theta`` with its whole-record ``cost`` over the detrending basis
    ``full``; row 0 the maps' answer), after the free stage where the problem asks for it."""
    n_sims = config.grid_f_e * len(config.grid_s_N) + config.rounds * config.candidates + len(cost)
    best, best_cost = theta[int(np.argmin(cost))], float(cost.min())
    if p.free_one_mass:
        best, n_free = _free_one_mass(p, best, config, rng, _drive(p))
        n_sims += n_free
        best_cost = float(_score(p, best[None], full, _drive(p))[0])
    measured = _detrended_energy(torch.as_tensor(p.speed, dtype=torch.float64)[None], full)[0].item()
    norm = math.sqrt(measured) if measured > 0 else 1.0
    s_N = float(10.0 ** best[3])
    free = len(best) == 6
    return Refined(f_e=float(10.0 ** best[0]), V_J=float(10.0 ** best[1]), d=float(best[2]),
                   s_N=s_N, backlash=2.0 * s_N * p.M_N / float(p.C_F(best)),
                   residual=math.sqrt(best_cost) / norm, start_residual=math.sqrt(float(cost[0])) / norm,
                   n_sims=n_sims, J_sigma=float(10.0 ** best[4]) if free else None,
                   M_FC=float(best[5]) if free else None)


def _free_one_mass(p: RefineProblem, best: np.ndarray, config: RefineConfig, rng: np.random.Generator,
                   drive: sim.DriveConfig) -> tuple[np.ndarray, int]:
    """The free stage (see :class:`RefineConfig`): ``best`` (4) or the winner over
    :data:`FREE_COORDINATES` (6), and the number of simulated models."""
    plain = lambda th: ((_simulate(p, th, drive) ** 2).sum(-1).numpy(), th)  # noqa: E731
    one_mass = [math.log10(p.J_sigma), min(max(p.M_FC, 0.0), 1.0)]
    start = np.concatenate([best, one_mass])
    J_f, f_f, V_f, M_v = np.meshgrid(np.log10([1 / 4, 1 / 2, 1.0, 2.0, 4.0]),
                                     np.log10([1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0]),
                                     np.log10([0.5, 1.0, 2.0]), [one_mass[1], 0.25], indexing="ij")
    grids = []
    for center in (start, np.concatenate([np.clip(p.theta, _LOW, _HIGH), one_mass])):  # chosen model, maps' answer
        grid = np.repeat(center[None], J_f.size, axis=0)  # G x 6
        grid[:, 4] += J_f.reshape(-1)
        grid[:, 0] += f_f.reshape(-1)
        grid[:, 1] += V_f.reshape(-1)
        grid[:, 5] = M_v.reshape(-1)
        grids.append(grid)
    theta = np.clip(np.concatenate([start[None], *grids]), _LOW_FREE, _HIGH_FREE)
    cost, theta = plain(theta)
    spread = np.concatenate([config.spread, config.free_spread])
    theta, cost = _cem(theta, cost, plain, config.free_rounds, spread, config, rng, _LOW_FREE, _HIGH_FREE)
    k = int(np.argmin(cost))
    # a clear win only (measured: 10-60 x lower on soft mechanics; a narrow one was a wrong mode)
    return (theta[k] if cost[k] < config.free_win * cost[0] else best), len(cost)
