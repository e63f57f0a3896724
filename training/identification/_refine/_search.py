"""The cross-entropy search shared by the stages (:func:`cem`, :class:`SearchSettings`), many
records' searches side by side, so that they share one simulator call per round."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from training._settings import NON_NEGATIVE, NON_NEGATIVE_OR_INF, Interval, Values, check_settings
from training.identification._refine._space import HIGH, LOW

#: Scores a batch of records' candidates: ``{record: C x D}`` -> ``{record: (cost C, candidates as scored)}``.
Score = Callable[[dict[int, np.ndarray]], dict[int, tuple[np.ndarray, np.ndarray]]]


@dataclass(frozen=True)
class SearchSettings:
    """The cross-entropy search every stage runs: ``candidates`` models a round around the best
    so far, the ``elites`` best setting the next round's spread (``spread``: the first round's
    standard deviation per coordinate of :data:`COORDINATES`). The C kernel runs blocks of 32
    models on the CPU's cores: 64 candidates take the wall time of 32 on two."""

    candidates: int = 64  # models per round
    elites: int = 12  # best models that set the next round's spread
    spread: tuple[float, float, float, float] = (0.05, 0.12, 0.03, 0.3)  # first spread over COORDINATES
    elite_weight: float = 0.7  # the next spread: this x the elites' standard deviation ...
    memory: float = 0.15  # ... plus this x the last spread (the search shrinks, but not at once) ...
    floor: float = 0.02  # ... and never below this x the first spread (it keeps moving)

    def __post_init__(self) -> None:
        check_settings(self, {  # elites first: the candidates' bound
            "elites": Interval(2, integer=True), "candidates": Interval("elites", integer=True),
            "spread": Values(NON_NEGATIVE, 4, "log10 f_e, log10 V_J, d, log10 s_N"), "elite_weight": NON_NEGATIVE_OR_INF,
            "memory": NON_NEGATIVE_OR_INF, "floor": NON_NEGATIVE_OR_INF})


@dataclass(frozen=True)
class Scored:
    """Every model a search scored (``theta`` ``C x D``) and its cost (``C``)."""

    theta: np.ndarray
    cost: np.ndarray

    @property
    def best(self) -> np.ndarray:
        """The model of the lowest cost."""
        return self.theta[int(np.argmin(self.cost))]

    def elites(self, count: int) -> np.ndarray:
        """The ``count`` models of the lowest costs, best first."""
        return self.theta[np.argsort(self.cost)[:count]]


def scored(asked: dict[int, np.ndarray], score: Score) -> dict[int, Scored]:
    """The candidates ``asked`` of each record as scored by ``score``."""
    return {i: Scored(theta, cost) for i, (cost, theta) in score(asked).items()}


def cem(start: dict[int, Scored], rounds: int, spread: np.ndarray, search: SearchSettings,
        rngs: dict[int, np.random.Generator], score: Score, low: np.ndarray = LOW,
        high: np.ndarray = HIGH) -> dict[int, Scored]:
    """``rounds`` of the cross-entropy search of each record from the best of its ``start`` (all
    kept), the records side by side (one ``score`` call a round; each record draws from its own
    ``rngs[i]``, so its search is the same whatever the others); returns every scored model."""
    found = dict(start)
    mean = {i: s.best for i, s in found.items()}
    std = dict.fromkeys(found, spread)
    for _ in range(rounds):
        asked = {i: np.clip(mean[i] + std[i] * rngs[i].standard_normal((search.candidates, found[i].theta.shape[1])),
                            low, high) for i in found}
        for i, new in scored(asked, score).items():
            found[i] = Scored(np.concatenate([found[i].theta, new.theta]), np.concatenate([found[i].cost, new.cost]))
            elite = found[i].elites(search.elites)
            mean[i] = elite[0]  # the best so far; the elites' spread sets the next step
            std[i] = np.maximum(search.elite_weight * elite.std(axis=0) + search.memory * std[i], search.floor * spread)
    return found


def cem_one(theta: np.ndarray, cost: np.ndarray, rounds: int, spread: np.ndarray, search: SearchSettings,
            rng: np.random.Generator, score: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
            low: np.ndarray = LOW, high: np.ndarray = HIGH) -> Scored:
    """:func:`cem` of one record scored by ``score`` (``C x D`` -> ``(cost C, candidates as scored)``)."""
    return cem({0: Scored(theta, cost)}, rounds, spread, search, {0: rng},
               lambda asked: {i: score(theta) for i, theta in asked.items()}, low, high)[0]


def own_rng(seed: int, stream: int) -> np.random.Generator:
    """The random stream ``stream`` of an optional stage, apart from the exploration's (``seed``):
    where the stage loses, the searches after it draw what they would have drawn without it."""
    return np.random.default_rng([seed, stream])


def product_grid(f_e: Sequence[float], V_J: Sequence[float], d: float, log10_s_N: Sequence[float]) -> np.ndarray:
    """Every combination of the eigenfrequencies ``f_e`` [Hz], inertia ratios ``V_J`` and
    ``log10_s_N`` at damping ``d``, as models over :data:`COORDINATES` ``G x 4`` (``f_e`` slowest)."""
    return np.array([[math.log10(f), math.log10(v), d, s] for f, v, s in itertools.product(f_e, V_J, log10_s_N)])


def log10_s_N_grid(theta0: np.ndarray, grid_s_N: Sequence[float]) -> list[float]:
    """log10 ``s_N`` of a stage's grid ``grid_s_N``, its 0 standing for the start's (``theta0``)."""
    return [math.log10(v) if v > 0 else float(theta0[3]) for v in grid_s_N]
