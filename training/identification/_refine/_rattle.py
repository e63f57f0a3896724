"""The rattle: the exploration goes on with the windows after a zero-torque section replayed from
that section's start (:class:`RattleSettings`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training._settings import COUNT, NON_NEGATIVE_OR_INF, REAL, Values, check_settings
from training.identification._refine._search import Score, Scored, SearchSettings, cem, scored
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage
from training.identification._refine._windows import ScoreWindows


@dataclass(frozen=True)
class RattleSettings:
    """After the torque drops to zero the masses rattle in the gap, and where the next torque step
    finds them decides how far the motor runs free before it takes the load. The quasi-static
    start puts the motor against the load there, and an exploration scored that way reads the gap
    narrower than it is (measured on the large axis: 0.6-0.7 x, with the truth scoring worse than
    the answer on exactly the two windows after the zero-torque sections). Where the
    exploration's best has a gap (``s_N >= min_s_N``) and the record a zero-torque section before
    a torque step, the search goes on with those windows simulated from their zero-torque
    section's start: the exploration's elites and its best with ``s_N`` moved by ``shift``
    decades, then ``rounds`` rounds; its ``finalists`` best join the finalists (`twomass
    identify` of 1000 reference records: 8-11 % longer)."""

    min_s_N: float = 0.1  # runs only where the exploration's best has s_N >= this
    shift: tuple[float, ...] = (-0.2, -0.1, 0.1, 0.2)  # its start: the best's s_N moved [decades]
    rounds: int = 2  # cross-entropy rounds
    finalists: int = 4  # its best models that join the finalists

    def __post_init__(self) -> None:
        check_settings(self, {"min_s_N": NON_NEGATIVE_OR_INF, "shift": Values(REAL), "rounds": COUNT, "finalists": COUNT})


def rattles(best: np.ndarray, windows: ScoreWindows, settings: RattleSettings) -> bool:
    """Whether the exploration whose best model is ``best`` goes on with its led ``windows``."""
    return bool(10.0 ** best[3] >= settings.min_s_N and windows.lead.any())


def rattle(best: dict[int, np.ndarray], elites: dict[int, np.ndarray], settings: RattleSettings,
           search: SearchSettings, rngs: dict[int, np.random.Generator], score: Score) -> dict[int, Scored]:
    """The rattle's window search of each record ``i`` (``score`` replays its led windows from
    their zero-torque section) from the exploration's ``elites[i]`` and its ``best[i]`` with
    ``s_N`` shifted, drawing from ``rngs[i]``; every scored model."""
    again = {}
    for i, model in best.items():
        start = np.concatenate([elites[i], np.repeat(model[None], len(settings.shift), axis=0)])
        start[-len(settings.shift):, 3] += settings.shift
        again[i] = np.clip(start, LOW, HIGH)
    return cem(scored(again, score), settings.rounds, np.asarray(search.spread, dtype=np.float64), search, rngs, score)


STAGE = Stage("rattle", "the exploration's best has a gap and the record a zero-torque section before a step",
              RattleSettings, rattle)
