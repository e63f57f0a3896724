"""Model-based refinement of the maps' answer: an output-error fit by batched re-simulation.

The maps give the structure and a first estimate of ``f_e``, ``V_J``, ``d`` and the normalized
backlash ``s_N``. The refinement polishes them on the record itself: candidate two-mass models
(``J_sigma``, ``M_FC``, ``mu_F`` from STEP 2, unless the free stage runs) are simulated open loop
under the record's own torque reference (:func:`sim.replay.replay_speed`, many candidates in one
batch) and scored by how well they reproduce the measured motor speed. Before scoring, a quadratic
trend per section is removed from the speed error: it absorbs the small one-mass errors of STEP 2
(a friction or inertia error tilts a section's speed), so the score measures what the maps are
about: the oscillation after each torque step and the motor's excursions while it crosses the
backlash. The maps' answer stays a candidate: the refined model never reproduces the record worse
than the maps' own answer.

The stages, in order (:data:`PIPELINE`; each a module with its settings, :data:`STAGES`):

- ``explore``: cross-entropy search around the maps' answer, scored on short windows after each
  torque step (:mod:`._explore`);
- ``rescue``: a survey of the whole range where the exploration explains little (:mod:`._rescue`);
- ``climb``: a second exploration up the ridge of stiff shafts with a gap (:mod:`._climb`);
- ``rattle``: the windows after a zero-torque section replayed from its start (:mod:`._rattle`);
- ``choose``: the finalists compete on the whole record (:mod:`._choose`);
- ``split``: STEP 2's Coulomb friction shared between the motor and the load over the finalists;
  where a share goes to the motor, the finalists compete again with it, the free stage, the polish
  and the retry run on both, and the split model wins only by evidence (:mod:`._split`);
- ``free``: ``J_sigma``, ``M_FC``, ``mu_F`` searched too where STEP 2's fit is not trusted (:mod:`._free`);
- ``polish``: Levenberg-Marquardt steps on the whole record (:mod:`._polish`);
- ``retry``: a poor polished fit polished again from a lighter damping and from the maps' answer
  (:mod:`._retry`);
- ``restart``: a fit that leaves far more than the noise refined once more from the start with the
  friction shared between the motor and the load, Coulomb and viscous (:mod:`._restart`);
- ``angle_fit``: an answer with a gap refitted, with the friction's split, on the motor's angle
  (:mod:`._angle_fit`);
- ``angle``: the backlash the speed hides, found in the motor's angle; the identifier runs it on
  the records that call for it (:mod:`._angle`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from training.identification._refine import (_angle, _angle_fit, _choose, _climb, _explore, _free, _polish, _rattle,
                                             _rescue, _restart, _retry, _split)
from training.identification._refine._angle import HiddenGap, hidden_gap
from training.identification._refine._angle_fit import angle_fit
from training.identification._refine._choose import Choice, choose
from training.identification._refine._climb import climb, climbs
from training.identification._refine._config import RefineConfig
from training.identification._refine._explore import explore, explore_windows, starts
from training.identification._refine._free import free_one_mass, frees, one_mass_values
from training.identification._refine._polish import polish as polish_lanes
from training.identification._refine._polish import polished
from training.identification._refine._problem import RefineProblem, Refined
from training.identification._refine._rattle import rattle, rattles
from training.identification._refine._replay import detrended_cost, quantization_energy, relative_rms, replay_drive
from training.identification._refine._rescue import rescues, survey
from training.identification._refine._restart import restart
from training.identification._refine._retry import retry
from training.identification._refine._search import Scored
from training.identification._refine._split import motor_share, splits
from training.identification._refine._stage import Stage
from training.identification._refine._windows import ScoreWindows, score_windows

#: The stages by name, each with its settings class, entry point and when it runs.
STAGES: dict[str, Stage] = {module.STAGE.name: module.STAGE for module in
                            (_explore, _rescue, _climb, _rattle, _choose, _split, _free, _polish, _retry, _restart,
                             _angle_fit, _angle)}
#: The order the stages run in (``angle`` by the identifier, after the others).
PIPELINE: tuple[str, ...] = ("explore", "rescue", "climb", "rattle", "choose", "split", "free", "polish", "retry",
                              "restart", "angle_fit", "angle")


@dataclass(frozen=True)
class Explored:
    """The window stages' answer for one record: the ``finalists`` ``F x 4`` (row 0 the maps'
    answer) and the number of models they simulated (``n_sims``)."""

    finalists: np.ndarray
    n_sims: int


@dataclass(frozen=True)
class _Leading:
    """One record through the window stages so far: the search whose models lead (``winner``), the
    elites of a search it replaced that still compete (``set_aside``) and the models simulated."""

    winner: Scored
    set_aside: tuple[np.ndarray, ...]
    n_sims: int

    def challenged(self, challenger: Scored, switch_win: float, keep: int) -> _Leading:
        """After a ``challenger`` search: it leads where its best is below ``switch_win`` x the
        leader's, the leader's ``keep`` best set aside then (0: none)."""
        n_sims = self.n_sims + len(challenger.cost)
        if not challenger.cost.min() < switch_win * self.winner.cost.min():
            return replace(self, n_sims=n_sims)
        kept = (self.winner.elites(keep),) if keep else ()
        return _Leading(challenger, self.set_aside + kept, n_sims)


def _window_stages(problems: list[RefineProblem], windows: list[ScoreWindows], config: RefineConfig,
                   rngs: list[np.random.Generator]) -> list[Explored]:
    """The window stages (explore, rescue, climb, rattle; ``windows``: :func:`._explore.explore_windows`)
    of every problem, each stage's searches side by side; the finalists of each: the maps' answer;
    the best of the search that led (the exploration, the rescue or the climb), and the
    exploration's too where the rescue led; the rattle's best where it ran."""
    plain, led = (functools.partial(score_windows, problems, windows, tag, config.explore.gain_range, config.batch)
                  for tag in (False, True))
    begins = {i: starts(p, config.explore) for i, p in enumerate(problems)}  # S x 4 each, the maps' answer first
    theta0 = {i: b[0] for i, b in begins.items()}
    explored = explore(begins, config.explore, config.search, dict(enumerate(rngs)), plain)
    state = {i: _Leading(found, (), len(found.cost)) for i, found in explored.items()}
    asked = {i: theta0[i] for i, lead in state.items()
             if rescues(problems[i], windows[i], float(lead.winner.cost.min()), config.rescue)}
    for i, found in survey(problems, asked, config.rescue, config.search, config.seed, plain).items():
        state[i] = state[i].challenged(found, config.rescue.switch_win, config.choose.finalists)
    asked = {i: lead.winner.best for i, lead in state.items()
             if climbs(problems[i], theta0[i], lead.winner.best, config.climb)}
    for i, found in climb(problems, asked, config.climb, config.search, config.seed, plain).items():
        state[i] = state[i].challenged(found, config.climb.switch_win, 0)
    elites = {i: lead.winner.elites(config.choose.finalists) for i, lead in state.items()}
    asked = {i: lead.winner.best for i, lead in state.items() if rattles(lead.winner.best, windows[i], config.rattle)}
    rattled = rattle(asked, elites, config.rattle, config.search, {i: rngs[i] for i in asked}, led)
    return [_explored(theta0[i], lead, elites[i], rattled.get(i), config) for i, lead in sorted(state.items())]


def _explored(theta0: np.ndarray, lead: _Leading, elites: np.ndarray, rattled: Scored | None,
              config: RefineConfig) -> Explored:
    """One record's :class:`Explored` finalists: the maps' answer ``theta0``, the set-aside elites,
    the leading search's ``elites`` and the best of the rattle where it ran."""
    if rattled is None:
        return Explored(np.concatenate([theta0[None], *lead.set_aside, elites]), lead.n_sims)
    return Explored(np.concatenate([theta0[None], *lead.set_aside, elites, rattled.elites(config.rattle.finalists)]),
                    lead.n_sims + len(rattled.cost))


def _chosen(p: RefineProblem, choice: Choice, explored: int, config: RefineConfig,
            rng: np.random.Generator) -> Refined:
    """The refined model of ``p`` from its ``choice`` (``explored`` models before it), after the
    free stage where it runs."""
    n_sims = explored + len(choice.cost)
    best, best_cost = choice.best, float(choice.cost.min())
    if frees(p, best, config.free):
        fit = free_one_mass(p, best, config.free, config.search, config.seed, rng, replay_drive(p))
        best, n_sims = fit.theta, n_sims + fit.n_sims
        best_cost = float(detrended_cost(p, best[None], choice.basis, replay_drive(p))[0])
    split = p.friction_split()
    return Refined(**p.answer(best, float(10.0 ** best[3])), M_L0=p.M_L0,
                   residual=relative_rms(best_cost, choice.measured),
                   start_residual=relative_rms(float(choice.cost[0]), choice.measured),
                   dof=sum(b - a - Q.shape[1] for a, b, Q in choice.basis), n_sims=n_sims,
                   **{**split, **(one_mass_values(best) if len(best) > 4 else {})})


def _trusted_load(p: RefineProblem, choice: Choice, config: RefineConfig) -> RefineProblem:
    """``p`` with the hold as its load torque (0 where the axis was not held) where the free stage
    will search its one-mass part: STEP 2's constant torque is then its model error, not a load
    (measured: a 5 Hz shaft of the fast spindle read 0.8 Nm of 5 on an axis without any, ``J_sigma``
    41 % off with it, 3 % without; soft shafts on the 200 W servo, held, 0.1-0.5 Nm of 0.64 over
    their hold, ``J_sigma`` 13-300 % off)."""
    if not frees(p, choice.best, config.free):
        return p
    return replace(p, M_L0=float(p.level[0]))


def motor_shares(problems: list[RefineProblem], choices: list[Choice], finalists: list[np.ndarray],
                 noise: list[float], config: RefineConfig) -> dict[int, float]:
    """The split stage's scan (:func:`._split.motor_share`) over each problem's ``finalists``
    (``noise[i]``: :func:`noise_energy` of problem ``i``): the problems whose friction it would put
    partly on the motor, with that share."""
    best = {i: np.argsort(c.cost)[:config.split.finalists] for i, c in enumerate(choices)}
    asked = {i: finalists[i][best[i]] for i, p in enumerate(problems) if splits(p, config.split)}
    shares = motor_share(problems, asked, config.split, config.batch, {i: noise[i] for i in asked})
    return {i: s for i, s in shares.items() if s > 0}


def noise_energy(p: RefineProblem, choice: Choice) -> float:
    """The quantization's expected detrended energy over the samples ``choice`` scores."""
    return quantization_energy(p, sum(b - a for a, b, _ in choice.basis))


def polish(problems: list[RefineProblem], chosen: list[Refined], measured: list[float],
           config: RefineConfig) -> list[Refined]:
    """The polish and the retry of each ``chosen[i]`` on the whole record (``measured[i]``: the
    measured speed's own detrended energy); ``residual`` and ``n_sims`` updated."""
    if not config.polish.iterations:
        return list(chosen)
    polishing = polish_lanes(problems, chosen, config.polish, config.free, config.batch)
    polishing = retry(problems, polishing, config.retry, config.polish, config.batch)
    return polished(problems, chosen, measured, polishing, config.polish, config.batch)


def find_hidden_gap(p: RefineProblem, config: RefineConfig) -> HiddenGap | None:
    """The angle stage of ``p`` (:func:`._angle.hidden_gap`) with ``config``'s settings."""
    return hidden_gap(p, config.angle, config.search, config.seed)


def refine(problems: list[RefineProblem], config: RefineConfig | None = None) -> list[Refined]:
    """Refine each problem's ``theta`` through :data:`PIPELINE` (up to the angle); one
    :class:`Refined` per problem, each the same whatever the other problems (every search starts
    from ``config.seed``; records on the same drive and of similar length run packed in one replay).
    A refined model with motor friction (``M_FCM``, ``mu_FM``) was refined on its problem with that
    split (:meth:`RefineProblem.with_motor_share`)."""
    config = config or RefineConfig()
    done, measured, noise = _refine_once(problems, config, split=True)
    done = restart(problems, done, measured, noise, config.restart, config.split, config.seed,
                   lambda again, seed: _refine_once(again, replace(config, seed=seed), split=False)[0])
    return angle_fit(problems, done, measured, config.angle_fit, config.split, config.angle, config.search,
                     config.seed)


def _refine_once(problems: list[RefineProblem], config: RefineConfig,
                 split: bool) -> tuple[list[Refined], list[float], list[float]]:
    """The stages up to the retry (the split stage where ``split``); with each problem's measured
    detrended energy and the quantization's expected energy over the same samples."""
    rngs = [np.random.default_rng(config.seed) for _ in problems]
    windows = [explore_windows(p, config.explore) for p in problems]
    explored = _window_stages(problems, windows, config, rngs)
    finalists = [e.finalists for e in explored]
    choices = choose(problems, finalists, config.batch)
    noise = [noise_energy(p, c) for p, c in zip(problems, choices)]
    shares = motor_shares(problems, choices, finalists, noise, config) if split else {}
    shared = {i: problems[i].with_motor_share(s) for i, s in shares.items()}
    shared_choices = dict(zip(shared, choose(list(shared.values()), [finalists[i] for i in shared], config.batch)))
    lanes = [*zip(problems, choices, explored, rngs),
             *((shared[i], shared_choices[i], explored[i], np.random.default_rng(config.seed)) for i in shared)]
    lanes = [(_trusted_load(p, c, config), c, e, rng) for p, c, e, rng in lanes]
    chosen = [_chosen(p, c, e.n_sims, config, rng) for p, c, e, rng in lanes]
    done = polish([p for p, *_ in lanes], chosen, [c.measured for _, c, *_ in lanes], config)
    out = done[:len(problems)]
    for k, i in enumerate(shared, start=len(problems)):  # the split wins only by evidence (:class:`SplitSettings`)
        gain = (out[i].residual ** 2 - done[k].residual ** 2) * choices[i].measured
        if gain > config.split.evidence * noise[i]:
            out[i] = done[k]
    return out, [c.measured for c in choices], noise
