"""The polish: Levenberg-Marquardt steps on the whole record from the chosen model
(:class:`PolishSettings`), its lanes (:class:`Lane`) shared with the retry (:mod:`._retry`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from training._settings import COUNT, NON_NEGATIVE_OR_INF, POSITIVE, POSITIVE_OR_INF, Interval, Values, check_settings
from training.identification._refine._free import FreeSettings, free_bounds, one_mass_values
from training.identification._refine._problem import RefineProblem, Refined
from training.identification._refine._replay import (BatchSettings, detrend_basis, detrended, detrended_energy,
                                                     packed_errors, relative_rms)
from training.identification._refine._space import HIGH, LOW, NO_GAP
from training.identification._refine._stage import Stage

#: The samples a lane scores and their detrending basis, segments end to end (:func:`_scored`).
Scoring = tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]


@dataclass(frozen=True)
class PolishSettings:
    """Around the chosen model the whole-record error is nearly linear in :data:`COORDINATES`, and
    a model a few % off in ``f_e``, ``V_J`` or ``d`` still scores 10-1000 x worse than the truth
    over a record of many periods. Up to ``iterations`` Levenberg-Marquardt steps: a
    forward-difference Jacobian (``steps`` per coordinate), the damped steps ``(J^T J + lambda
    diag(J^T J)) delta = -J^T r`` for each ``lambda`` of ``damping``, the best kept where it lowers
    the error; a problem stops when an iteration gains less than ``tolerance`` (lightly damped
    records whose answers the windows left 30-40 % off in ``V_J`` and ``d`` came back only with
    ``lambda`` up to 10, a full step overshooting in the needle-sharp ``f_e``, and some only after
    10-20 iterations). The polished model replaces the chosen one only below ``win`` x its error
    (measured on the reference drive: the polish's wins were 2-80 x lower, its losses, models that
    were wrong in another way, 1.0-1.7 x). The error is scored on every ``k``-th sample only,
    ``samples_per_period`` per period at the chosen ``f_e`` (the replay still runs over every
    sample). ``s_N`` moves only where the chosen model has a gap, or where one of ``gap_seeds``
    scores better than the chosen model without it: the polish then starts from the best of them
    (a gap of ``s_N`` 0.02 on a lightly damped shaft is a needle in ``s_N`` that the searches miss).
    A free stage's model moves over all seven :data:`FREE_COORDINATES` (``free_steps``, relative
    to the coordinates' scales) on the plain error, as its stage scored it (measured on the fast
    spindle: without the polish, free models came out with ``V_J`` 10-45 % off)."""

    iterations: int = 20  # Levenberg-Marquardt iterations at most (0: no polish)
    tolerance: float = 0.01  # a problem stops once an iteration gains less than this share
    steps: tuple[float, float, float, float] = (1e-3, 5e-3, 2e-3, 2e-2)  # difference steps over COORDINATES
    damping: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0)  # the lambdas tried per iteration
    win: float = 0.5  # replaces the chosen model only below this error ratio
    samples_per_period: float = 16.0  # the error scored on this many samples per period
    free_steps: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)  # the free stage's three, in their scales
    gap_seeds: tuple[float, ...] = (0.003, 0.005, 0.01, 0.02, 0.04)  # s_N tried on a model without a gap
    diagonal_floor: float = 1e-12  # the damping's diagonal at least this x its largest (a coordinate the error misses)

    def __post_init__(self) -> None:
        check_settings(self, {
            "iterations": COUNT, "tolerance": NON_NEGATIVE_OR_INF, "steps": Values(POSITIVE, 4, "log10 f_e, log10 V_J, d, log10 s_N"),
            "damping": Values(POSITIVE), "win": NON_NEGATIVE_OR_INF, "samples_per_period": POSITIVE_OR_INF,
            "free_steps": Values(POSITIVE, 3, "log10 J_sigma, M_FC, mu_F"),
            "gap_seeds": Values(Interval(10.0 ** NO_GAP, open_low=True)), "diagonal_floor": NON_NEGATIVE_OR_INF})


def _scored(p: RefineProblem, f_e: float, settings: PolishSettings) -> Scoring:
    """The samples the polish scores (every ``k``-th of each segment, ``samples_per_period`` per
    period at ``f_e``) and their detrending basis, segments end to end."""
    k = max(1, int(1.0 / (f_e * p.T_s * settings.samples_per_period)))
    rows = [np.arange(a, b, k) for a, b in np.asarray(p.segments, dtype=np.int64).tolist() if b > a]
    ends = np.cumsum([0] + [len(r) for r in rows])
    return np.concatenate(rows), detrend_basis(np.stack([ends[:-1], ends[1:]], axis=1))


def _errors(problems: list[RefineProblem], asked: dict[int, np.ndarray], scored: dict[int, Scoring],
            batch: BatchSettings) -> dict[int, np.ndarray]:
    """The detrended errors ``M_i x C_i`` over the samples ``scored[i]`` of the candidates
    ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``."""
    return {i: detrended(E, scored[i][1])
            for i, E in packed_errors(problems, asked, batch, {i: rows for i, (rows, _) in scored.items()})}


@dataclass(frozen=True)
class Lane:
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


@dataclass(frozen=True)
class Polishing:
    """The polish of a batch: each problem's :class:`Lane` and its scored samples, the models
    simulated per problem (``n_sims``), the chosen models (``first``), their errors (``start``:
    what a polished model must beat) and each lane's error at its model (``cost``)."""

    lanes: dict[int, Lane]
    scored: dict[int, Scoring]
    n_sims: dict[int, int]
    first: dict[int, np.ndarray]
    start: dict[int, float]
    cost: dict[int, float]


def _lane(p: RefineProblem, chosen: Refined, settings: PolishSettings, free: FreeSettings) -> tuple[Lane, Scoring]:
    """The lane of ``p`` from its ``chosen`` model and the samples it scores."""
    t = [math.log10(chosen.f_e), math.log10(chosen.V_J), chosen.d, math.log10(max(chosen.s_N, 10.0 ** LOW[3]))]
    rows, basis = _scored(p, chosen.f_e, settings)
    if chosen.J_sigma is None:  # STEP 2's one-mass part: the detrended error
        low, high, h = LOW, HIGH, np.asarray(settings.steps, dtype=np.float64)
    else:  # the free stage's: its three coordinates too, on the plain error (nothing to detrend)
        low, high, scale = free_bounds(p, free)
        t += [math.log10(chosen.J_sigma), float(chosen.M_FC), float(chosen.mu_F)]
        h = np.concatenate([settings.steps, np.asarray(settings.free_steps) * scale])
        basis = [(a, b, Q[:, :0]) for a, b, Q in basis]
    return Lane(np.array(t), moving(t), low, high, h, chosen.s_N), (rows, basis)


def polish(problems: list[RefineProblem], chosen: list[Refined], settings: PolishSettings, free: FreeSettings,
           batch: BatchSettings) -> Polishing:
    """Each ``chosen[i]`` polished on the whole record, the searches side by side: one replay per
    iteration and step kind for the problems on one drive and substep count."""
    lanes, scored = {}, {}
    for i, (p, r) in enumerate(zip(problems, chosen)):
        lanes[i], scored[i] = _lane(p, r, settings, free)
    first = {i: lane.theta.copy() for i, lane in lanes.items()}  # the chosen models
    seeded = gap_seeded(problems, lanes, scored, settings, batch)
    descent = descend(problems, seeded.lanes, scored, settings, batch)
    # the chosen models' errors, what the polished ones must beat (the gap-seeded lanes' before their seeds)
    start = {**descent.first, **seeded.before}
    n_sims = {i: seeded.n_sims.get(i, 0) + descent.n_sims[i] for i in lanes}
    return Polishing(lanes=descent.lanes, scored=scored, n_sims=n_sims, first=first, start=start, cost=descent.cost)


def polished(problems: list[RefineProblem], chosen: list[Refined], measured: list[float], polishing: Polishing,
             settings: PolishSettings, batch: BatchSettings) -> list[Refined]:
    """The answers after the polish (``measured[i]``: the measured speed's own detrended energy):
    a lane's model where it moved and won (below ``settings.win`` x its start), with its
    whole-record ``residual``; ``n_sims`` updated."""
    lanes, cost, start = polishing.lanes, polishing.cost, polishing.start
    won = sorted(i for i, lane in lanes.items() if lane.moved and cost[i] < settings.win * start[i])
    out = [replace(r, n_sims=r.n_sims + polishing.n_sims.get(i, 0)) for i, r in enumerate(chosen)]
    for i, E in packed_errors(problems, {i: lanes[i].theta[None] for i in won}, batch):  # the winners' whole record
        t, total = lanes[i].theta, float(detrended_energy(E, detrend_basis(problems[i].segments))[0])
        # a model without a gap: its own s_N, or its start's where that lay below the search's floor
        s_N = float(10.0 ** t[3]) if t[3] > NO_GAP else min(float(10.0 ** t[3]), lanes[i].start_s_N)
        one_mass = {} if len(t) == 4 else one_mass_values(t)
        out[i] = replace(out[i], **problems[i].answer(t, s_N), **one_mass, residual=relative_rms(total, measured[i]),
                         n_sims=out[i].n_sims + 1)
    return out


def maps_lane(p: RefineProblem, lane: Lane) -> Lane:
    """A lane like ``lane`` from the maps' answer ``p.theta`` (with ``lane``'s one-mass part, if it
    moves one); ``s_N`` moves only where the maps' answer has a gap."""
    t = np.concatenate([np.clip(p.theta, LOW, HIGH), lane.theta[4:]])
    return replace(lane, theta=t, free=moving(t), start_s_N=float(10.0 ** t[3]), moved=False)


def moving(theta: np.ndarray | list[float]) -> list[int]:
    """The coordinates a lane at ``theta`` moves: all, but ``s_N`` only where the model has a gap."""
    return [k for k in range(len(theta)) if k != 3 or theta[3] > NO_GAP]


@dataclass(frozen=True)
class Seeded:
    """The gap seeds tried: every lane (those a seed beat moved to it, ``s_N`` free then), the
    errors of the tried lanes at their models as they were (``before``) and the models simulated."""

    lanes: dict[int, Lane]
    before: dict[int, float]
    n_sims: dict[int, int]


def gap_seeded(problems: list[RefineProblem], lanes: dict[int, Lane], scored: dict[int, Scoring],
               settings: PolishSettings, batch: BatchSettings) -> Seeded:
    """Each lane whose model has no gap moved to the best of its models with the gaps of
    ``settings.gap_seeds`` where one beats it."""
    seeds = np.log10(np.asarray(settings.gap_seeds, dtype=np.float64))
    asked = {i: np.vstack([lane.theta] + [np.concatenate([lane.theta[:3], [g], lane.theta[4:]]) for g in seeds])
             for i, lane in lanes.items() if lane.theta[3] <= NO_GAP and seeds.size}
    out, before, n_sims = dict(lanes), {}, {}
    for i, R in _errors(problems, asked, scored, batch).items():
        n_sims[i] = R.shape[1]
        c = (R * R).sum(0)
        before[i] = float(c[0])
        k = int(np.argmin(c))
        if k > 0:
            out[i] = replace(lanes[i], theta=asked[i][k], free=moving(asked[i][k]), moved=True)
    return Seeded(out, before, n_sims)


def measured_energy(p: RefineProblem, scored: Scoring) -> float:
    """The measured speed's own energy over the polish's samples (detrended as its errors are)."""
    rows, basis = scored
    return float((detrended(p.speed[rows, None], basis) ** 2).sum())


def _with_steps(lane: Lane) -> np.ndarray:
    """The lane's model and the model stepped by ``h`` in each of its free coordinates, clipped: ``(1 + F) x D``."""
    stepped = lane.theta + lane.h[lane.free, None] * np.eye(len(lane.theta))[lane.free]  # F x D
    return np.clip(np.vstack([lane.theta, stepped]), lane.low, lane.high)


@dataclass(frozen=True)
class Descent:
    """The Levenberg-Marquardt descent of some lanes: each lane at its final model (``moved`` where
    an iteration moved it), its error there (``cost``) and at its first model (``first``), and the
    models simulated per lane."""

    lanes: dict[int, Lane]
    cost: dict[int, float]
    first: dict[int, float]
    n_sims: dict[int, int]


def _damped_moves(lane: Lane, asked: np.ndarray, R: np.ndarray, settings: PolishSettings) -> np.ndarray:
    """The lane's damped Levenberg-Marquardt steps ``L x D`` (clipped) from its errors ``R`` at its
    model and its stepped models ``asked`` (:func:`_with_steps`), one per ``lambda`` of ``settings.damping``."""
    r = R[:, 0]
    step = asked[1:, lane.free].diagonal() - lane.theta[lane.free]  # the steps as clipped
    J = (R[:, 1:] - r[:, None]) / np.where(step != 0, step, 1.0)  # M x F: the forward-difference Jacobian
    A, g = J.T @ J, J.T @ r
    D = np.diag(np.maximum(np.diag(A), settings.diagonal_floor * max(float(np.diag(A).max()), 1e-300)))
    moves = np.repeat(lane.theta[None], len(settings.damping), axis=0)  # L x D
    for row, lam in zip(moves, settings.damping):
        row[lane.free] += np.linalg.solve(A + lam * D, -g)
    return np.clip(moves, lane.low, lane.high)


def descend(problems: list[RefineProblem], lanes: dict[int, Lane], scored: dict[int, Scoring],
            settings: PolishSettings, batch: BatchSettings) -> Descent:
    """Up to ``settings.iterations`` Levenberg-Marquardt iterations of each lane (a lane stops once
    an iteration gains less than ``tolerance``), the lanes side by side: one replay per iteration
    for the errors at the models and their steps, one for the damped moves."""
    lanes, cost, first, n_sims = dict(lanes), {}, {}, dict.fromkeys(lanes, 0)
    active = set(lanes)
    for _ in range(settings.iterations):
        if not active:
            break
        asked = {i: _with_steps(lanes[i]) for i in active}
        trials = {}
        for i, R in _errors(problems, asked, scored, batch).items():
            n_sims[i] += R.shape[1]
            cost[i] = float(R[:, 0] @ R[:, 0])
            first.setdefault(i, cost[i])
            trials[i] = _damped_moves(lanes[i], asked[i], R, settings)
        for i, R in _errors(problems, trials, scored, batch).items():
            n_sims[i] += R.shape[1]
            c = (R * R).sum(0)
            k = int(np.argmin(c))
            ratio = float(c[k]) / cost[i] if cost[i] > 0 else 1.0
            if ratio < 1.0:
                lanes[i], cost[i] = replace(lanes[i], theta=trials[i][k], moved=True), float(c[k])
            if ratio > 1.0 - settings.tolerance:  # no better, or hardly: done
                active.discard(i)
    return Descent(lanes, cost, first, n_sims)


STAGE = Stage("polish", "always, unless `iterations` is 0: every chosen model", PolishSettings, polish)
