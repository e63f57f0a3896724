"""Model-based refinement of the maps' answer: an output-error fit by batched re-simulation.

The maps give the structure and a first estimate of ``f_e``, ``V_J``, ``d`` and the normalized
backlash ``s_N``. This module polishes them on the record itself: candidate two-mass models
(``J_sigma``, ``M_FC``, ``mu_F`` from STEP 2, unless STEP 2 flags its own fit or the test's
sections are short for the oscillation found: see :class:`RefineConfig`) are simulated open loop
under the record's own torque reference (:func:`sim.replay.replay_speed`, many candidates in one
batch) and scored by how well they reproduce the measured motor speed. Before scoring, a quadratic
trend per section is removed from the speed error: it absorbs the small one-mass errors of STEP 2
(a friction or inertia error tilts a section's speed), so the score measures what the maps are
about: the oscillation after each torque step and the motor's excursions while it crosses the
backlash.

The search is a cross-entropy method (sample around the best models so far, keep the elites,
shrink), started from the maps' answer, which stays a candidate: the refined model never
reproduces the record worse than the maps' own answer. A Levenberg-Marquardt polish on the whole
record finishes it (:class:`RefineConfig`).
"""


from __future__ import annotations

import numpy as np

from training.identification._refine._config import RefineConfig
from training.identification._refine._explore import explore_all
from training.identification._refine._free import free_one_mass, one_mass_values, short_sections
from training.identification._refine._polish import polish
from training.identification._refine._problem import RefineProblem, Refined
from training.identification._refine._replay import (detrend_basis, detrended_cost, detrended_energy,
                                                     packed_errors, relative_rms, replay_drive)


def refine(problems: list[RefineProblem], config: RefineConfig | None = None) -> list[Refined]:
    """Refine each problem's ``theta`` (see module docstring); one :class:`Refined` per problem,
    each the same whatever the other problems (every search starts from ``config.seed``; the
    whole-record choice of records on the same drive and of similar length runs packed in one
    replay)."""
    config = config or RefineConfig()
    rngs = [np.random.default_rng(config.seed) for _ in problems]
    explored = explore_all(problems, config, rngs)
    finalists = [f for f, _ in explored]
    costs: list[np.ndarray] = [np.empty(0)] * len(problems)
    bases = [detrend_basis(p.segments) for p in problems]  # the whole record's sections and tail
    for i, E in packed_errors(problems, dict(enumerate(finalists))):
        costs[i] = detrended_energy(E, bases[i])
    measured = [float(detrended_energy(p.speed[:, None], b)[0]) for p, b in zip(problems, bases)]
    chosen = [_finish(p, th, c, b, m, n, config, rng)
              for p, th, c, b, m, (_, n), rng in zip(problems, finalists, costs, bases, measured, explored, rngs)]
    return polish(problems, chosen, measured, config)


def _finish(p: RefineProblem, theta: np.ndarray, cost: np.ndarray, full: list, measured: float, explored: int,
            config: RefineConfig, rng: np.random.Generator) -> Refined:
    """The best finalist (``theta`` with its whole-record ``cost`` over the detrending basis
    ``full``; row 0 the maps' answer; ``measured`` the measured speed's own detrended energy;
    ``explored`` models before), after the free stage where the problem asks for it."""
    n_sims = explored + len(cost)
    best, best_cost = theta[int(np.argmin(cost))], float(cost.min())
    if p.free_one_mass or short_sections(p, best, config):
        best, n_free = free_one_mass(p, best, config, rng, replay_drive(p))
        n_sims += n_free
        best_cost = float(detrended_cost(p, best[None], full, replay_drive(p))[0])
    free = len(best) > 4
    return Refined(**p.answer(best, float(10.0 ** best[3])), residual=relative_rms(best_cost, measured),
                   start_residual=relative_rms(float(cost[0]), measured),
                   dof=sum(b - a - Q.shape[1] for a, b, Q in full), n_sims=n_sims,
                   **(one_mass_values(best) if free else {}))
