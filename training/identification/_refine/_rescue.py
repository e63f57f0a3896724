"""The rescue: a survey of the whole range where the exploration's best explains little of the
windows' energy (:class:`RescueSettings`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training._settings import AT_LEAST_ONE, COUNT, NON_NEGATIVE, NON_NEGATIVE_OR_INF, POSITIVE, Values, check_settings
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import quantization_energy
from training.identification._refine._search import (Score, Scored, SearchSettings, cem, log10_s_N_grid, own_rng,
                                                     product_grid, scored)
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage
from training.identification._refine._windows import ScoreWindows


@dataclass(frozen=True)
class RescueSettings:
    """Where the exploration's best leaves more than ``above`` of the windows' measured energy
    unexplained while that energy is ``signal`` x or more the speed's quantization noise (``q_w^2 /
    6`` per sample: there is a response to explain), the maps' answer is taken to be far off
    (measured on the large axis: a stiff shaft with a wide gap answered ``elastic`` at 13 Hz, the
    truth at 232 Hz; on the noisy drive a shaft with a gap answered at 75 Hz leaving 0.70 of the
    windows' energy, the truth leaving 0.02: a far-off answer can still explain half the energy).
    A grid over the whole range, ``grid_f_e`` eigenfrequencies from the drive envelope's lowest to
    the Nyquist frequency times ``grid_V_J`` times ``grid_s_N``, then ``rounds`` rounds, with a
    random stream of its own. Where it beats the exploration by ``switch_win``, its elites join
    the finalists beside the exploration's (the whole-record choice decides: a model that is wrong
    in the windows' way can still lose there), and the climb and the rattle go on from its best."""

    above: float = 0.5  # runs where the exploration's best leaves this share of the windows' energy ...
    signal: float = 3.0  # ... and that energy is at least this x the speed's quantization noise
    grid_f_e: int = 16  # eigenfrequencies of its grid, the drive envelope's lowest to Nyquist
    grid_V_J: tuple[float, ...] = (0.25, 0.6, 1.5, 3.5)  # V_J of its grid
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # s_N of its grid (0: the start's)
    rounds: int = 6  # cross-entropy rounds after the grid
    switch_win: float = 0.9  # replaces the exploration only below this ratio of its best window error
    stream: int = 1  # its random stream: where it loses, the later searches draw as without it

    def __post_init__(self) -> None:
        check_settings(self, {
            "above": NON_NEGATIVE_OR_INF, "signal": NON_NEGATIVE_OR_INF, "grid_f_e": AT_LEAST_ONE, "grid_V_J": Values(POSITIVE),
            "grid_s_N": Values(NON_NEGATIVE), "rounds": COUNT, "switch_win": NON_NEGATIVE_OR_INF, "stream": COUNT})


def rescues(p: RefineProblem, windows: ScoreWindows, cost: float, settings: RescueSettings) -> bool:
    """Whether the exploration of ``p``, whose best model left ``cost`` of the energy over its
    ``windows``, is followed by the rescue's survey."""
    noise = quantization_energy(p, int(windows.inside.sum()))
    return cost > settings.above * windows.yy and windows.yy >= settings.signal * noise


def survey(problems: list[RefineProblem], theta0: dict[int, np.ndarray], settings: RescueSettings,
           search: SearchSettings, seed: int, score: Score) -> dict[int, Scored]:
    """The rescue's window search of each record ``i`` over the whole range, ``d`` and the start's
    ``s_N`` from ``theta0[i]`` (4), drawing from its own stream of ``seed``; every scored model."""
    grids = {}
    for i, start in theta0.items():
        f_e = np.geomspace(SPEC_ENVELOPE["f_e"][0], min(10.0 ** HIGH[0], 0.5 / problems[i].T_s), settings.grid_f_e)
        grid = product_grid(f_e, settings.grid_V_J, float(start[2]), log10_s_N_grid(start, settings.grid_s_N))
        grids[i] = np.clip(grid, LOW, HIGH)
    rngs = {i: own_rng(seed, settings.stream) for i in theta0}
    return cem(scored(grids, score), settings.rounds, np.asarray(search.spread, dtype=np.float64), search, rngs, score)


STAGE = Stage("rescue", "the exploration's best leaves over `above` of the windows' energy, well above the noise",
              RescueSettings, survey)
