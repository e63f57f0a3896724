"""The climb: a second exploration higher up the ridge of stiff shafts with a gap
(:class:`ClimbSettings`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import sim
from training._settings import (AT_LEAST_ONE, COUNT, NON_NEGATIVE, NON_NEGATIVE_OR_INF, REAL_OR_INF, Values,
                                check_settings)
from training.identification._refine._explore import grid_search
from training.identification._refine._problem import RefineProblem
from training.identification._refine._search import Score, Scored, SearchSettings, own_rng
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage


@dataclass(frozen=True)
class ClimbSettings:
    """A softer shaft with a narrower gap reproduces a gap crossing nearly as well as the true
    model, and the maps read the ``f_e`` of a shaft the current loop hardly excites low; the
    exploring error then falls along a narrow ridge of ``f_e`` and width up to the truth, often
    2-6 x the maps' ``f_e`` (measured on the large axis: the widths came out 0.5-0.7 x), farther
    than one exploration reaches. Where the start's ``f_e`` reaches ``above`` x the current
    loop's bandwidth ``1/(2 pi T_Ei)``, the best model has a gap (``s_N >= min_s_N``) and lies
    ``after`` decades or more above the start, a second exploration runs from ``offset`` decades
    above that model at the same backlash width: ``grid_f_e`` eigenfrequencies over ``+-span``
    decades, then ``rounds`` rounds, with a random stream of its own. Where its exploring error is
    below ``switch_win`` x the first's (a clear win only: a narrow one added false gaps on stiff
    shafts of a coarse drive), it replaces the first exploration: its elites become the finalists
    (the whole-record error of a lightly damped shaft rattling in its gap is needle-sharp: the
    climb's near-true models would lose the choice to the first's soft, narrow ones)."""

    offset: float = 0.5  # its centre above the exploration's best [decades of f_e]
    span: float = 0.5  # its grid's half width [decades] ...
    grid_f_e: int = 21  # ... over this many eigenfrequencies
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # s_N of its grid (0: its centre's)
    after: float = 0.0  # runs only where the exploration's best lies this far above the start [decades] ...
    above: float = 0.4  # ... the start's f_e reaches this x the current loop's bandwidth ...
    min_s_N: float = sim.S_N_ELASTIC  # ... and the best model has a gap (s_N at least this: the class threshold)
    rounds: int = 6  # cross-entropy rounds after the grid
    switch_win: float = 0.9  # replaces the exploration only below this ratio of its best window error
    stream: int = 2  # its random stream: where it loses, the later searches draw as without it

    def __post_init__(self) -> None:
        check_settings(self, {
            "offset": REAL_OR_INF, "span": NON_NEGATIVE_OR_INF, "grid_f_e": AT_LEAST_ONE, "grid_s_N": Values(NON_NEGATIVE),
            "after": REAL_OR_INF, "above": NON_NEGATIVE_OR_INF, "min_s_N": NON_NEGATIVE_OR_INF, "rounds": COUNT,
            "switch_win": NON_NEGATIVE_OR_INF, "stream": COUNT})


def climbs(p: RefineProblem, theta0: np.ndarray, best: np.ndarray, settings: ClimbSettings) -> bool:
    """Whether the exploration of ``p`` from ``theta0`` climbs on from its ``best`` model."""
    bandwidth = 1.0 / (2.0 * math.pi * p.T_Ei)
    return bool(10.0 ** best[3] >= settings.min_s_N and best[0] - theta0[0] >= settings.after
                and 10.0 ** theta0[0] >= settings.above * bandwidth)


def climb(problems: list[RefineProblem], best: dict[int, np.ndarray], settings: ClimbSettings,
          search: SearchSettings, seed: int, score: Score) -> dict[int, Scored]:
    """The climb's window search of each record ``i`` from ``offset`` decades above its ``best[i]``
    (4) at its gap's width, drawing from its own stream of ``seed``; every scored model."""
    up = {}
    for i, model in best.items():
        centre = model.copy()
        centre[0] += settings.offset
        # the same width 2s = 2 s_N M_N / C_F
        centre[3] += math.log10(float(problems[i].C_F(centre) / problems[i].C_F(model)))
        up[i] = np.clip(centre, LOW, HIGH)
    rngs = {i: own_rng(seed, settings.stream) for i in best}
    return grid_search(up, settings.grid_f_e, settings.span, settings.grid_s_N, settings.rounds, search, rngs, score)


STAGE = Stage("climb", "a gap found above the start on a shaft stiff for the current loop", ClimbSettings, climb)
