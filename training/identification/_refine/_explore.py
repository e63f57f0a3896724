"""The exploring stage: a grid around the maps' answer (and around the maps' other ``f_e`` read-out
where it lies apart), then cross-entropy rounds, each model scored on short windows after each
torque step (:mod:`._windows`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from training._settings import (AT_LEAST_ONE, COUNT, NON_NEGATIVE, NON_NEGATIVE_OR_INF, POSITIVE, POSITIVE_OR_INF,
                                Values, check_settings)
from training.identification._refine._problem import RefineProblem
from training.identification._refine._search import Score, Scored, SearchSettings, cem, log10_s_N_grid, scored
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage
from training.identification._refine._windows import ScoreWindows, first_samples, level_at


@dataclass(frozen=True)
class ExploreSettings:
    """The exploration scores only the first ``window_periods`` periods (at the start's ``f_e``;
    at most ``window_max`` seconds or ``window_samples`` samples, whichever is longer: the cost is
    per sample, and on a slowly sampled drive 0.1 s held less than one period of a 10 Hz
    mechanic, too little to tell a small gap) after each torque step, with each candidate's best
    gain projected out: a model whose frequency is a few % off does not lose its match to the
    phase error that builds up over a long section, nor a model with the right shape but a wrong
    ``V_J`` to its amplitude (the gain rescales its ``V_J``). Each window is simulated on its own
    from a quasi-static state, so exploring costs a few periods per torque step, not the whole
    record. The search: a grid of ``grid_f_e`` eigenfrequencies over ``+-grid_span`` decades
    around the start times the normalized backlash values ``grid_s_N``, then ``rounds`` rounds.
    Where the maps' other read-out of ``f_e`` (:attr:`RefineProblem.f_e_other`) lies more than
    ``other_apart`` decades from the start's, the grid is laid around both (the windows at the
    lower ``f_e``)."""

    grid_f_e: int = 11  # eigenfrequencies of the first grid
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # s_N of the first grid (0: the start's)
    grid_span: float = 0.25  # the grid's half width [decades of f_e]
    rounds: int = 3  # cross-entropy rounds after the grid
    window_periods: float = 4.0  # periods scored after each torque step
    window_max: float = 0.1  # at most this long [s] ...
    window_samples: int = 400  # ... or this many samples, whichever is longer (0.1 s at 250 us)
    window_min: int = 8  # but at least this many samples (a quadratic trend and some shape)
    gain_range: tuple[float, float] = (0.25, 4.0)  # each candidate's best gain kept within this (its V_J x it)
    other_apart: float = 0.1  # a second grid around the maps' other f_e beyond this [decades]; inf: never

    def __post_init__(self) -> None:
        check_settings(self, {
            "grid_f_e": AT_LEAST_ONE, "grid_s_N": Values(NON_NEGATIVE), "grid_span": NON_NEGATIVE_OR_INF, "rounds": COUNT,
            "window_periods": POSITIVE_OR_INF, "window_max": NON_NEGATIVE_OR_INF, "window_samples": COUNT,
            "window_min": AT_LEAST_ONE, "gain_range": Values(POSITIVE, 2, "lowest and highest gain"),
            "other_apart": NON_NEGATIVE_OR_INF})


def starts(p: RefineProblem, settings: ExploreSettings) -> np.ndarray:
    """The exploration's starts ``S x 4``: ``p.theta`` (clipped to the search space) first, and it
    with the maps' other ``f_e`` where that lies more than ``other_apart`` decades away."""
    theta = np.clip(np.asarray(p.theta, dtype=np.float64), LOW, HIGH)
    if p.f_e_other is None or not abs(math.log10(p.f_e_other) - theta[0]) > settings.other_apart:
        return theta[None]
    other = theta.copy()
    other[0] = math.log10(p.f_e_other)
    return np.clip(np.stack([theta, other]), LOW, HIGH)  # 2 x 4


def explore_windows(p: RefineProblem, settings: ExploreSettings) -> ScoreWindows:
    """The exploring windows of ``p``: ``window_periods`` at the lowest start's ``f_e`` (at least
    ``window_min`` samples, at most ``window_max`` or ``window_samples``, whichever is longer)
    after each torque step, each after a zero-torque section with that section's length as its lead."""
    period = 1.0 / (10.0 ** starts(p, settings)[:, 0].min() * p.T_s)  # samples per period at the lowest start f_e
    seg = np.asarray(p.segments, dtype=np.int64)
    a = seg[:, 0]
    after_zero = (np.arange(len(a)) > 0) & (level_at(p, a - 1) == 0.0) & (level_at(p, a) != 0.0)
    lead = np.where(after_zero, a - np.concatenate([[0], a[:-1]]), 0)  # the zero section's length
    longest = max(settings.window_max / p.T_s, settings.window_samples)  # [samples]
    length = max(settings.window_min, int(round(min(settings.window_periods * period, longest))))
    return ScoreWindows.of(p, first_samples(seg, length), lead)


def grid_search(theta0: dict[int, np.ndarray], grid_f_e: int, span: float, grid_s_N: Sequence[float], rounds: int,
                search: SearchSettings, rngs: dict[int, np.random.Generator], score: Score) -> dict[int, Scored]:
    """A window search of each record ``i`` from ``theta0[i]`` (4, or ``S x 4`` starts): around each
    start ``grid_f_e`` eigenfrequencies over ``+-span`` decades times the backlash values ``grid_s_N``
    (0: the start's), then ``rounds`` rounds drawn from ``rngs[i]``; every scored model."""
    grids = {}
    for i, theta in theta0.items():
        parts = []
        for start in np.atleast_2d(theta):
            grid = np.repeat(start[None], grid_f_e * len(grid_s_N), axis=0)  # G x 4
            grid[:, 0] += np.repeat(np.linspace(-span, span, grid_f_e), len(grid_s_N))
            grid[:, 3] = np.tile(log10_s_N_grid(start, grid_s_N), grid_f_e)
            parts.append(grid)
        grids[i] = np.clip(np.concatenate(parts), LOW, HIGH)  # (S*G) x 4
    return cem(scored(grids, score), rounds, np.asarray(search.spread, dtype=np.float64), search, rngs, score)


def explore(theta0: dict[int, np.ndarray], settings: ExploreSettings, search: SearchSettings,
            rngs: dict[int, np.random.Generator], score: Score) -> dict[int, Scored]:
    """The exploration of each record ``i`` from its :func:`starts` ``theta0[i]`` (``S x 4``),
    scored on its windows by ``score``; every scored model."""
    return grid_search(theta0, settings.grid_f_e, settings.grid_span, settings.grid_s_N, settings.rounds, search,
                       rngs, score)


STAGE = Stage("explore", "always: every refined record", ExploreSettings, explore)
