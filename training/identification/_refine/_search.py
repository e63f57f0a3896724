"""The cross-entropy search, written as a generator that yields candidates and is sent their
costs, so that many records' searches share one simulator call per step."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Generator, Sequence
from typing import Any

import numpy as np

from training.identification._refine._config import HIGH, LOW, RefineConfig

#: A search: yields candidates ``C x D``, is sent ``(cost C, candidates as scored)`` for each, returns its result.
Search = Generator[np.ndarray, tuple[np.ndarray, np.ndarray], Any]
#: The exploration's search: its candidates come with whether their windows take the lead (:func:`window_speeds`).
TaggedSearch = Generator[tuple[np.ndarray, bool], tuple[np.ndarray, np.ndarray], Any]


def cem(theta: np.ndarray, cost: np.ndarray, rounds: int, spread: np.ndarray, config: RefineConfig,
        rng: np.random.Generator, low: np.ndarray = LOW, high: np.ndarray = HIGH) -> Search:
    """``rounds`` of the cross-entropy search from the best of ``theta``/``cost`` (all kept), as a
    :data:`Search` that returns ``(theta, cost)``, the scored candidates appended."""
    mean, std = theta[int(np.argmin(cost))], spread
    for _ in range(rounds):
        cand = np.clip(mean + std * rng.standard_normal((config.candidates, theta.shape[1])), low, high)
        c, cand = yield cand
        theta, cost = np.concatenate([theta, cand]), np.concatenate([cost, c])
        elite = theta[np.argsort(cost)[: config.elites]]
        mean = elite[0]  # the best so far; the elites' spread sets the next step
        std = np.maximum(0.7 * elite.std(axis=0) + 0.15 * std, 0.02 * spread)
    return theta, cost


def run(search: Search, score: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Any:
    """The result of ``search`` with each of its candidates scored by ``score``."""
    try:
        candidates = next(search)
        while True:
            candidates = search.send(score(candidates))
    except StopIteration as done:
        return done.value


def own_rng(config: RefineConfig, stage: int) -> np.random.Generator:
    """The random stream of an optional stage (1: rescue, 2: climb, 3: the free stage's second
    search), apart from the exploration's: where the stage loses, the searches after it draw what
    they would have drawn without it."""
    return np.random.default_rng([config.seed, stage])


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
