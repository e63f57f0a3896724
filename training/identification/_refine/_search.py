"""The cross-entropy search shared by the stages (:func:`cem`, :class:`SearchSettings`), written
as a generator that yields candidates and is sent their costs, so that many records' searches
share one simulator call per step."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from training.identification._refine._checks import at_least, not_below_field, sized
from training.identification._refine._space import HIGH, LOW

#: A search: yields candidates ``C x D``, is sent ``(cost C, candidates as scored)`` for each, returns its result.
Search = Generator[np.ndarray, tuple[np.ndarray, np.ndarray], Any]
#: The exploration's search: its candidates come with whether their windows take the lead (:func:`window_speeds`).
TaggedSearch = Generator[tuple[np.ndarray, bool], tuple[np.ndarray, np.ndarray], Any]


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
        at_least(self, 2, "elites")
        not_below_field(self, "candidates", "elites")
        sized(self, "spread", 4, "log10 f_e, log10 V_J, d, log10 s_N")
        at_least(self, 0.0, "elite_weight", "memory", "floor")


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


def cem(theta: np.ndarray, cost: np.ndarray, rounds: int, spread: np.ndarray, search: SearchSettings,
        rng: np.random.Generator, low: np.ndarray = LOW, high: np.ndarray = HIGH) -> Search:
    """``rounds`` of the cross-entropy search from the best of ``theta``/``cost`` (all kept), as a
    :data:`Search` that returns the :class:`Scored` models, the scored candidates appended."""
    mean, std = theta[int(np.argmin(cost))], spread
    for _ in range(rounds):
        cand = np.clip(mean + std * rng.standard_normal((search.candidates, theta.shape[1])), low, high)
        c, cand = yield cand
        theta, cost = np.concatenate([theta, cand]), np.concatenate([cost, c])
        elite = theta[np.argsort(cost)[: search.elites]]
        mean = elite[0]  # the best so far; the elites' spread sets the next step
        std = np.maximum(search.elite_weight * elite.std(axis=0) + search.memory * std, search.floor * spread)
    return Scored(theta, cost)


def run(search: Search, score: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Any:
    """The result of ``search`` with each of its candidates scored by ``score``."""
    try:
        candidates = next(search)
        while True:
            candidates = search.send(score(candidates))
    except StopIteration as done:
        return done.value


def own_rng(seed: int, stream: int) -> np.random.Generator:
    """The random stream ``stream`` of an optional stage, apart from the exploration's (``seed``):
    where the stage loses, the searches after it draw what they would have drawn without it."""
    return np.random.default_rng([seed, stream])


def tagged(search: Search, led: bool) -> TaggedSearch:
    """``search`` with each of its candidates tagged ``led`` (the exploring stage's searches)."""
    try:
        candidates = next(search)
        while True:
            candidates = search.send((yield candidates, led))
    except StopIteration as done:
        return done.value


def product_grid(f_e: Sequence[float], V_J: Sequence[float], d: float, log10_s_N: Sequence[float]) -> np.ndarray:
    """Every combination of the eigenfrequencies ``f_e`` [Hz], inertia ratios ``V_J`` and
    ``log10_s_N`` at damping ``d``, as models over :data:`COORDINATES` ``G x 4`` (``f_e`` slowest)."""
    return np.array([[math.log10(f), math.log10(v), d, s] for f, v, s in itertools.product(f_e, V_J, log10_s_N)])


def log10_s_N_grid(theta0: np.ndarray, grid_s_N: Sequence[float]) -> list[float]:
    """log10 ``s_N`` of a stage's grid ``grid_s_N``, its 0 standing for the start's (``theta0``)."""
    return [math.log10(v) if v > 0 else float(theta0[3]) for v in grid_s_N]
