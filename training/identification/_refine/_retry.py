"""The retry: a poor polished fit polished once more from a lighter damping and once from the
maps' answer (:class:`RetrySettings`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from training._settings import NON_NEGATIVE_OR_INF, SHARE, check_settings
from training.identification._refine._polish import (Lane, Polishing, PolishSettings, descend, gap_seeded, maps_lane,
                                                     measured_energy)
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import BatchSettings, quantization_energy
from training.identification._refine._stage import Stage


@dataclass(frozen=True)
class RetrySettings:
    """Where the polished model still leaves more than ``residual`` of the measured speed
    (relative rms over the scored samples) and more than ``above`` x the speed's quantization
    noise, the polish runs once more from it with its ``d`` times ``damping``, and once from the
    maps' answer (with the gap seeds where it has no gap), and the lowest error stands. Too much
    damping is where the lightly damped shafts' valleys hold it (measured: a noisy drive's ``d``
    0.012 at 20 Hz stopped at ``d`` 0.028 and ``V_J`` 41 % high, unwarned, the truth scoring 300 x
    better; from half the damping it reaches the truth; about 10 % of the reference drive's records
    are retried, and retrying every fit above 4 x the noise took twice as long for the same
    answers). The maps' answer, where it was near, is the other way out (measured: a fast
    spindle's 88 Hz shaft answered with ``V_J`` 33 % low, unwarned; the maps had ``V_J`` 7 % low
    and no gap, and from there, with the gap seeds, the polish reaches the truth)."""

    residual: float = 0.3  # runs where the relative error stays above this ...
    above: float = 30.0  # ... and above this x the speed's quantization noise
    damping: float = 0.5  # once from the polished model with its d times this
    same_model: float = 1e-12  # not from the maps' answer where the chosen model is it (within this)

    def __post_init__(self) -> None:
        check_settings(self, {"residual": NON_NEGATIVE_OR_INF, "above": NON_NEGATIVE_OR_INF, "damping": SHARE,
                              "same_model": NON_NEGATIVE_OR_INF})


def retried(p: RefineProblem, polishing: Polishing, i: int, settings: RetrySettings) -> bool:
    """Whether the polish of problem ``i`` (``p``) is a poor fit, well above the speed's quantization noise."""
    cost, scored = polishing.cost[i], polishing.scored[i]
    return bool(cost > settings.above * quantization_energy(p, len(scored[0]))
                and cost > settings.residual ** 2 * measured_energy(p, scored))


def _lighter(lane: Lane, settings: RetrySettings) -> Lane:
    """``lane`` from its model with its ``d`` times ``settings.damping`` (within its bounds)."""
    theta = lane.theta.copy()
    theta[2] = max(theta[2] * settings.damping, float(lane.low[2]))
    return replace(lane, theta=theta, moved=False)


def retry(problems: list[RefineProblem], polishing: Polishing, settings: RetrySettings, polish: PolishSettings,
          batch: BatchSettings) -> Polishing:
    """``polishing`` with each poor fit polished again: its lane and cost replaced where a retry
    lowers its error, the models simulated added."""
    lanes, cost, n_sims = dict(polishing.lanes), dict(polishing.cost), dict(polishing.n_sims)
    again = [i for i in lanes if retried(problems[i], polishing, i, settings)]
    lighter = {i: _lighter(lanes[i], settings) for i in again}
    maps = {i: maps_lane(problems[i], lanes[i]) for i in again}
    # (not where the chosen model is the maps' answer: its descent would repeat the first)
    maps = {i: lane for i, lane in maps.items()
            if not np.allclose(lane.theta, polishing.first[i], rtol=0.0, atol=settings.same_model)}
    seeded = gap_seeded(problems, maps, polishing.scored, polish, batch)
    for i, n in seeded.n_sims.items():
        n_sims[i] += n
    for tried in (lighter, seeded.lanes):
        descent = descend(problems, tried, polishing.scored, polish, batch)
        for i, n in descent.n_sims.items():
            n_sims[i] += n
        for i, c in descent.cost.items():
            if c < cost[i]:
                lanes[i], cost[i] = replace(descent.lanes[i], moved=True), c
    return replace(polishing, lanes=lanes, cost=cost, n_sims=n_sims)


STAGE = Stage("retry", "a polished fit above `residual` of the measured speed and `above` x its noise",
              RetrySettings, retry)
