"""The polish: Levenberg-Marquardt steps on the whole record from the chosen model
(:class:`RefineConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from training.identification._refine._config import HIGH, LOW, NO_GAP, RefineConfig
from training.identification._refine._free import free_bounds, one_mass_values
from training.identification._refine._problem import RefineProblem, Refined
from training.identification._refine._replay import (detrend_basis, detrended, detrended_energy, packed_errors,
                                                     quantization_energy, relative_rms)


def _scored(p: RefineProblem, f_e: float, config: RefineConfig) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """The samples the polish scores (every ``k``-th of each segment: see :class:`RefineConfig`)
    and their detrending basis, segments end to end."""
    k = max(1, int(1.0 / (f_e * p.T_s * config.polish_samples_per_period)))
    rows = [np.arange(a, b, k) for a, b in np.asarray(p.segments, dtype=np.int64).tolist() if b > a]
    ends = np.cumsum([0] + [len(r) for r in rows])
    return np.concatenate(rows), detrend_basis(np.stack([ends[:-1], ends[1:]], axis=1))


def _errors(problems: list[RefineProblem], asked: dict[int, np.ndarray],
            scored: dict[int, tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]]) -> dict[int, np.ndarray]:
    """The detrended errors ``M_i x C_i`` over the samples ``scored[i]`` of the candidates
    ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``."""
    return {i: detrended(E, scored[i][1])
            for i, E in packed_errors(problems, asked, {i: rows for i, (rows, _) in scored.items()})}


@dataclass
class _Lane:
    """One problem's polish: its model ``theta`` over :data:`COORDINATES` (4) or
    :data:`FREE_COORDINATES` (7), the coordinates it moves (``free``), their bounds and difference
    steps ``h``, the ``s_N`` of the model it started from (``start_s_N``: the coordinate stops at
    the search's floor), and whether an iteration has moved it."""

    theta: np.ndarray
    free: list[int]
    low: np.ndarray
    high: np.ndarray
    h: np.ndarray
    start_s_N: float
    moved: bool = False


def polish(problems: list[RefineProblem], chosen: list[Refined], measured: list[float],
           config: RefineConfig) -> list[Refined]:
    """Each ``chosen[i]`` polished on the whole record (see :class:`RefineConfig`; ``measured[i]``
    the measured speed's own detrended energy), the searches side by side: one replay per
    iteration and step kind for the problems on one drive and substep count; ``residual`` and
    ``n_sims`` updated."""
    if not config.polish_iterations:
        return list(chosen)
    lanes, scored = {}, {}
    for i, (p, r) in enumerate(zip(problems, chosen)):
        t = [math.log10(r.f_e), math.log10(r.V_J), r.d, math.log10(max(r.s_N, 10.0 ** LOW[3]))]
        rows, basis = _scored(p, r.f_e, config)
        if r.J_sigma is None:  # STEP 2's one-mass part: the detrended error
            low, high, h = LOW, HIGH, np.asarray(config.polish_steps, dtype=np.float64)
        else:  # the free stage's: its three coordinates too, on the plain error (nothing to detrend)
            low, high, scale = free_bounds(p)
            t += [math.log10(r.J_sigma), float(r.M_FC), float(r.mu_F)]
            h = np.concatenate([config.polish_steps, np.asarray(config.polish_free_steps) * scale])
            basis = [(a, b, Q[:, :0]) for a, b, Q in basis]
        lanes[i], scored[i] = _Lane(np.array(t), _moving(t), low, high, h, r.s_N), (rows, basis)
    n_sims = dict.fromkeys(lanes, 0)
    first = {i: lane.theta.copy() for i, lane in lanes.items()}  # the chosen models
    # the chosen models' errors, what the polished ones must beat (the gap-seeded lanes' here, the others' in _descend)
    start = _gap_seeded(problems, lanes, scored, config, n_sims)
    cost = _descend(problems, lanes, scored, config, n_sims, start)
    # a poor fit, well above the speed's quantization noise: once more from a lighter damping, and
    # once from the maps' answer
    retry = [i for i, lane in lanes.items()
             if cost[i] > config.polish_retry_above * quantization_energy(problems[i], len(scored[i][0]))
             and cost[i] > config.polish_retry_residual ** 2 * _measured(problems[i], scored[i])]
    lighter = {i: replace(lanes[i], theta=lanes[i].theta.copy(), moved=False) for i in retry}
    for lane in lighter.values():
        lane.theta[2] = max(lane.theta[2] * config.polish_retry_damping, float(lane.low[2]))
    maps = {i: _maps_lane(problems[i], lanes[i]) for i in retry}
    # (not where the chosen model is the maps' answer: its descent would repeat the first)
    maps = {i: lane for i, lane in maps.items() if not np.allclose(lane.theta, first[i], rtol=0.0, atol=1e-12)}
    _gap_seeded(problems, maps, scored, config, n_sims)
    for again in (lighter, maps):
        for i, c in _descend(problems, again, scored, config, n_sims, start).items():
            if c < cost[i]:
                lanes[i], cost[i] = replace(again[i], moved=True), c
    won = sorted(i for i, lane in lanes.items() if lane.moved and cost[i] < config.polish_win * start[i])
    out = [replace(r, n_sims=r.n_sims + n_sims.get(i, 0)) for i, r in enumerate(chosen)]
    for i, E in packed_errors(problems, {i: lanes[i].theta[None] for i in won}):  # the winners' whole-record error
        t, total = lanes[i].theta, float(detrended_energy(E, detrend_basis(problems[i].segments))[0])
        # a model without a gap: its own s_N, or its start's where that lay below the search's floor
        s_N = float(10.0 ** t[3]) if t[3] > NO_GAP else min(float(10.0 ** t[3]), lanes[i].start_s_N)
        one_mass = {} if len(t) == 4 else one_mass_values(t)
        out[i] = replace(out[i], **problems[i].answer(t, s_N), **one_mass, residual=relative_rms(total, measured[i]),
                         n_sims=out[i].n_sims + 1)
    return out


def _maps_lane(p: RefineProblem, lane: _Lane) -> _Lane:
    """A lane like ``lane`` from the maps' answer ``p.theta`` (with ``lane``'s one-mass part, if it
    moves one); ``s_N`` moves only where the maps' answer has a gap."""
    t = np.concatenate([np.clip(p.theta, LOW, HIGH), lane.theta[4:]])
    return replace(lane, theta=t, free=_moving(t), start_s_N=float(10.0 ** t[3]), moved=False)


def _moving(theta: np.ndarray | list[float]) -> list[int]:
    """The coordinates a lane at ``theta`` moves: all, but ``s_N`` only where the model has a gap."""
    return [k for k in range(len(theta)) if k != 3 or theta[3] > NO_GAP]


def _gap_seeded(problems: list[RefineProblem], lanes: dict[int, _Lane],
                scored: dict[int, tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]], config: RefineConfig,
                n_sims: dict[int, int]) -> dict[int, float]:
    """Each lane whose model has no gap moved to the best of its models with the gaps of
    ``config.polish_gap_seeds`` where one beats it, with ``s_N`` free then (``theta``, ``free`` and
    ``moved`` updated in place); returns those lanes' errors at their models as they were."""
    seeds = np.log10(np.asarray(config.polish_gap_seeds, dtype=np.float64))
    asked = {i: np.vstack([lane.theta] + [np.concatenate([lane.theta[:3], [g], lane.theta[4:]]) for g in seeds])
             for i, lane in lanes.items() if lane.theta[3] <= NO_GAP and seeds.size}
    before = {}
    for i, R in _errors(problems, asked, scored).items():
        n_sims[i] += R.shape[1]
        c = (R * R).sum(0)
        before[i] = float(c[0])
        k = int(np.argmin(c))
        if k > 0:
            lanes[i].theta, lanes[i].free, lanes[i].moved = asked[i][k], _moving(asked[i][k]), True
    return before


def _measured(p: RefineProblem, scored: tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]) -> float:
    """The measured speed's own energy over the polish's samples (detrended as its errors are)."""
    rows, basis = scored
    return float((detrended(p.speed[rows, None], basis) ** 2).sum())


def _with_steps(lane: _Lane) -> np.ndarray:
    """The lane's model and the model stepped by ``h`` in each of its free coordinates, clipped: ``(1 + F) x D``."""
    stepped = lane.theta + lane.h[lane.free, None] * np.eye(len(lane.theta))[lane.free]  # F x D
    return np.clip(np.vstack([lane.theta, stepped]), lane.low, lane.high)


def _descend(problems: list[RefineProblem], lanes: dict[int, _Lane],
             scored: dict[int, tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]], config: RefineConfig,
             n_sims: dict[int, int], start: dict[int, float]) -> dict[int, float]:
    """Up to ``config.polish_iterations`` Levenberg-Marquardt iterations of each lane (``theta`` and
    ``moved`` updated in place; a lane stops once an iteration gains less than ``polish_tolerance``),
    the lanes side by side; returns each lane's error at its final model (``start`` gets the error
    of a lane's first model where it has none, ``n_sims`` the models simulated)."""
    cost: dict[int, float] = {}
    active = set(lanes)
    for _ in range(config.polish_iterations):
        if not active:
            break
        # the error r and its forward-difference Jacobian J (M x F) at each model, one replay for all
        asked = {i: _with_steps(lanes[i]) for i in active}
        trials = {}
        for i, R in _errors(problems, asked, scored).items():
            lane = lanes[i]
            n_sims[i] += R.shape[1]
            r = R[:, 0]
            cost[i] = float(r @ r)
            start.setdefault(i, cost[i])
            step = asked[i][1:, lane.free].diagonal() - lane.theta[lane.free]  # the steps as clipped
            J = (R[:, 1:] - r[:, None]) / np.where(step != 0, step, 1.0)  # M x F
            A, g = J.T @ J, J.T @ r
            D = np.diag(np.maximum(np.diag(A), 1e-12 * max(float(np.diag(A).max()), 1e-300)))
            moves = np.repeat(lane.theta[None], len(config.polish_damping), axis=0)  # L x D
            for row, lam in zip(moves, config.polish_damping):
                row[lane.free] += np.linalg.solve(A + lam * D, -g)
            trials[i] = np.clip(moves, lane.low, lane.high)
        for i, R in _errors(problems, trials, scored).items():
            n_sims[i] += R.shape[1]
            c = (R * R).sum(0)
            k = int(np.argmin(c))
            ratio = float(c[k]) / cost[i] if cost[i] > 0 else 1.0
            if ratio < 1.0:
                lanes[i].theta, cost[i], lanes[i].moved = trials[i][k], float(c[k]), True
            if ratio > 1.0 - config.polish_tolerance:  # no better, or hardly: done
                active.discard(i)
    return cost
