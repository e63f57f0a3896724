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

import functools
import itertools
import math
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

import sim
from sim.replay import replay_speed
from training.identification._envelope import SPEC_ENVELOPE

__all__ = ["RefineConfig", "RefineProblem", "Refined", "torque_reference", "refine"]

#: Search coordinates and their bounds: log10 f_e [Hz], log10 V_J, d, log10 s_N (normalized
#: backlash; measured better than searching the width itself: 86 vs 66 % of the widths within 30 %).
COORDINATES: tuple[str, ...] = ("log10_f_e", "log10_V_J", "d", "log10_s_N")
_LOW = np.array([0.0, math.log10(0.05), 0.001, -3.0])
_HIGH = np.array([math.log10(3000.0), math.log10(20.0), 0.5, 2.0])
#: Where STEP 2's one-mass part is not trusted, three more: log10 J_sigma [kg m^2], M_FC [Nm] and
#: mu_F [Nm s/rad], bounded by the record's own scales (:func:`_free_bounds`).
FREE_COORDINATES: tuple[str, ...] = COORDINATES + ("log10_J_sigma", "M_FC", "mu_F")
_FREE_J_SIGMA = 2.0  # the free J_sigma within this many decades of STEP 2's
_NO_GAP = math.log10(2e-3)  # log10 s_N at or below which a model has no gap (the search's floor is 1e-3)


@dataclass(frozen=True)
class RefineConfig:
    """The search, in three stages.

    Explore: score only the first ``window_periods`` periods (at the start's ``f_e``; at most
    ``window_max`` seconds or ``window_samples`` samples, whichever is longer: the cost is per
    sample, and on a slowly sampled drive 0.1 s held less than one period of a 10 Hz mechanic, too
    little to tell a small gap) after each torque step, with each candidate's best gain projected
    out: a model whose frequency is a few % off does not lose its match to the phase error that
    builds up over a long section, nor a model with the right shape but a wrong ``V_J`` to its
    amplitude (the gain rescales its ``V_J``). A grid of ``grid_f_e`` eigenfrequencies over
    ``+-grid_span`` decades around the start times the normalized backlash values ``grid_s_N``
    (0: the start's own), then
    ``rounds`` rounds of a cross-entropy search: ``candidates`` models around the best so far,
    the ``elites`` best setting the next round's spread (``spread``: the first round's standard
    deviation per coordinate of :data:`COORDINATES`). Each window is simulated on its own from a
    quasi-static state, so exploring costs a few periods per torque step, not the whole record.

    Choose: the maps' answer and the ``elites`` best of the exploration compete on the plain
    detrended error over the whole record, simulated exactly (more rounds there were measured
    not to help). The C kernel runs blocks of 32 models on the CPU's cores: 64 candidates take
    the wall time of 32 on two.

    Climb (stiff shafts with a gap): a softer shaft with a narrower gap reproduces a gap crossing
    nearly as well as the true model, and the maps read the ``f_e`` of a shaft the current loop
    hardly excites low; the exploring error then falls along a narrow ridge of ``f_e`` and width up
    to the truth, often 2-6 x the maps' ``f_e`` (measured on the large axis: the widths came out
    0.5-0.7 x), farther than one exploration reaches. Where the start's ``f_e`` reaches
    ``climb_above`` x the current loop's bandwidth ``1/(2 pi T_Ei)``, the exploration's best model
    has a gap (``s_N >=`` :data:`sim.S_N_ELASTIC`) and lies ``climb_after`` decades or more above
    the start, a second exploration runs from ``climb`` decades above that model at the same
    backlash width: a grid of ``climb_grid_f_e`` eigenfrequencies over ``+-climb_span`` decades (the
    ridge from the first's best up to 10 x its ``f_e``), then ``far_rounds`` rounds. Where its
    exploring error is below ``switch_win`` x the first's (a clear win only: a narrow one added
    false gaps on stiff shafts of a coarse drive), it replaces the first exploration: its elites
    become the finalists, and the rattle starts from its best; where it loses, the answer is the one
    without it (it draws from a random stream of its own). (Its best models joining the first's
    elites as finalists was not enough: the whole-record error of a lightly damped shaft rattling
    in its gap is needle-sharp, +-5 % in ``f_e`` scores like no fit at all, and the near-true
    models of the climb lost the choice to the first's soft, narrow ones; large axis, held-out
    seeds 9, 11, 13, with the rescue: backlash within 30 % 85.1, 87.5, 88.1 -> 89.4, 96.4, 93.2 %.)

    Rescue (answers that explain nothing): where the exploration's best leaves more than
    ``rescue_above`` of the windows' measured energy unexplained while that energy is
    ``rescue_signal`` x or more the speed's quantization noise (``q_w^2 / 6`` per sample: there is
    a response to explain), the maps' answer is taken to be far off (measured on the large axis: a
    stiff shaft with a wide gap answered ``elastic`` at 13 Hz, the truth at 232 Hz). A grid over
    the whole range, ``rescue_grid_f_e`` eigenfrequencies from SPEC 3.1's lowest to the Nyquist
    frequency times ``rescue_V_J`` times ``grid_s_N``, then ``far_rounds`` rounds, with a random
    stream of its own (where it loses, the answer is the one without it). Where it beats the
    exploration by ``switch_win``, its elites join the finalists beside the exploration's (the
    whole-record choice decides: a model that is wrong in the windows' way can still lose there),
    and the climb and the rattle go on from its best.

    Rattle (gaps): after the torque drops to zero the masses rattle in the gap, and where the next
    torque step finds them decides how far the motor runs free before it takes the load. The
    quasi-static start puts the motor against the load there, and an exploration scored that way
    reads the gap narrower than it is (measured on the large axis: 0.6-0.7 x, with the truth
    scoring worse than the answer on exactly the two windows after the zero-torque sections).
    Where the exploration's best has a gap (``s_N >= rattle_s_N``) and the record a zero-torque
    section before a torque step, the search goes on with those windows simulated from their
    zero-torque section's start (whose state is quasi-static: the section before it held one
    torque): the exploration's elites and its best with ``s_N`` moved by ``rattle_shift`` decades,
    then ``rattle_rounds`` rounds; its ``rattle_finalists`` best join the finalists. This costs a
    replay of the two zero-torque sections per model for those records only (`twomass identify`
    of 1000 reference records: 8-11 % longer).

    Polish (whole record, local): around the chosen model the whole-record error is nearly linear
    in :data:`COORDINATES`, and a model a few % off in ``f_e``, ``V_J`` or ``d`` still scores 10-1000
    x worse than the truth over a record of many periods (measured on every elastic reference
    system outside ``E_10``). Up to ``polish_iterations`` Levenberg-Marquardt steps: a forward-
    difference Jacobian (``polish_steps`` per coordinate), the damped steps ``(J^T J + lambda
    diag(J^T J)) delta = -J^T r`` for each ``lambda`` of ``polish_damping``, the best kept where it
    lowers the error; a problem stops when an iteration gains less than ``polish_tolerance``
    (measured: lightly damped records of many periods whose answers the windows left 30-40 % off
    in ``V_J`` and ``d``, with the truth 100-1000 x better on the whole record, came back only with
    ``lambda`` up to 10, a full step overshooting in the needle-sharp ``f_e``, and some only after
    10-20 iterations; most records stop after a few). The
    polished model replaces the chosen one only where its error is below ``polish_win`` times the
    chosen one's (measured on the reference drive: the polish's wins were 2-80 x lower, its losses,
    models that were wrong in another way, 1.0-1.7 x). The error is scored on every ``k``-th sample
    only, ``polish_samples_per_period`` per period at the chosen ``f_e`` (a slow mechanic's record
    holds hundreds per period; the replay still runs over every sample). ``s_N`` moves only where
    the chosen model has a gap, or where one of ``polish_gap_seeds`` scores better than the chosen
    model without it: the polish then starts from the best of them (a gap of ``s_N`` 0.02 on a
    lightly damped shaft is a needle in ``s_N`` that the searches miss; measured on the large axis,
    they answered without it and bent ``V_J`` 30 % instead, once unwarned). A free stage's model
    moves over all seven :data:`FREE_COORDINATES` (``polish_free_steps``, relative to the
    coordinates' scales, see below) on the plain error, as its stage scored it (measured on the
    fast spindle: without the polish, free models came out with ``V_J`` 10-45 % off where the
    chosen model's was within 3 %).

    Free one-mass part (problems with ``free_one_mass``: STEP 2 flagged its fit, as for very soft
    mechanics whose test sections are shorter than an oscillation period; and wherever the
    shortest section holds fewer than ``free_periods`` periods of the chosen model: a test whose
    time scale ``J_sigma w_max / M*`` is a fraction of the period ends before the load follows,
    and STEP 2's fit, unflagged, reads about the motor's inertia, 0.15-0.2 x ``J_sigma`` on the
    servo of the drive matrix): ``J_sigma``, ``M_FC`` and ``mu_F`` join the search
    (:data:`FREE_COORDINATES`), scored by the plain error over the whole record (an exact
    replay from rest; nothing to detrend once the one-mass part is fitted). Their bounds and
    steps follow the record's own scales: ``J_sigma`` within 2 decades of STEP 2's, ``M_FC``
    up to ``M*``, ``mu_F`` up to ``M* / w_max`` (``w_max``: the record's top speed). Each model is
    scored at its best ``J_sigma``, exactly: ``J_sigma / k`` and ``mu_F / k`` make the replayed speed
    ``k`` times itself (:func:`_scaled_fit`), so ``J_sigma`` needs no grid. Grids over ``f_e`` (x 1/16
    .. 2 in steps of 2^0.25: such a mechanic is softer than it looks, and the whole-record error is
    needle-sharp in ``f_e``, a few % wide), ``V_J`` and the friction (STEP 2's, capped at a tenth of
    its bound; or 2.5 % of ``M*`` and 1 % of ``M* / w_max``) around the chosen model and around the
    maps' answer, then ``free_rounds`` rounds (``free_spread``: the first spread of the three new
    coordinates, in units of their scales 1, ``M*``, ``M* / w_max``): one search with ``V_J`` x 0.5,
    1, 2 of the centre's, one (a random stream of its own) with 5 ``V_J`` over SPEC 3.1's range, for
    a STEP 2 that read the motor alone (a load 3-5 x the motor lies beyond the first). Measured on
    the envelope's tests shorter than one period (seeds 5 and 6, 199 records), against the previous
    grids over ``J_sigma`` (x 1/4 .. 4), ``f_e`` (in steps of 2) and ``V_J`` without the scale: the
    scale alone took ``J_sigma`` within 5 % from 65 to 71 % and ``E_30`` from 74 to 81 %, with the
    finer ``f_e`` grid and the polish's damped steps to 75 and 85 %. The free
    model replaces the chosen one only when its plain squared error is below ``free_win`` times the
    chosen one's with STEP 2's own one-mass values, uncapped (against the capped friction, a 2 Hz
    model 3 x worse than the chosen 37 Hz one had won on a commissioning plant with motor friction).

    Angle (:mod:`training.identification._angle`, run by the identifier where the answer is
    ``stiff`` on a record whose resolution could hide a backlash): models with and without a gap
    compete on the whole record's angle error, ``angle_rounds`` cross-entropy rounds on each side."""

    grid_f_e: int = 11  # explore: eigenfrequencies of the first grid
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # explore: s_N of the first grid (0: the start's)
    grid_span: float = 0.25  # explore: the grid's half width [decades of f_e]
    window_periods: float = 4.0  # explore: periods scored after each torque step
    window_max: float = 0.1  # explore: at most this long [s] ...
    window_samples: int = 400  # ... or this many samples, whichever is longer (0.1 s at 250 us)
    rounds: int = 3  # explore: cross-entropy rounds
    candidates: int = 64  # models per round
    elites: int = 12  # best models that set the next spread (and the finalists)
    spread: tuple[float, float, float, float] = (0.05, 0.12, 0.03, 0.3)  # first spread over COORDINATES
    climb: float = 0.5  # climb: the second exploration's centre above the first's best [decades of f_e]
    climb_span: float = 0.5  # climb: its grid's half width [decades] ...
    climb_grid_f_e: int = 21  # ... over this many eigenfrequencies
    climb_after: float = 0.0  # climb: only where the first's best lies this far above the start [decades]
    climb_above: float = 0.4  # climb: only where the start's f_e reaches this x the current loop's bandwidth
    rescue_above: float = 0.8  # rescue: only where the first's best leaves this share of the windows' energy ...
    rescue_signal: float = 3.0  # ... and that energy is at least this x the speed's quantization noise
    rescue_grid_f_e: int = 16  # rescue: eigenfrequencies of its grid, SPEC 3.1's lowest to Nyquist
    rescue_V_J: tuple[float, ...] = (0.25, 0.6, 1.5, 3.5)  # rescue: V_J of its grid
    far_rounds: int = 6  # climb, rescue: cross-entropy rounds
    switch_win: float = 0.9  # climb, rescue: replace the first exploration below this error ratio
    rattle_s_N: float = 0.1  # rattle: only where the exploration's best has s_N >= this
    rattle_shift: tuple[float, ...] = (-0.2, -0.1, 0.1, 0.2)  # rattle: its best's s_N moved [decades]
    rattle_rounds: int = 2  # rattle: cross-entropy rounds
    rattle_finalists: int = 4  # rattle: its best models that join the finalists
    polish_iterations: int = 20  # polish: Gauss-Newton iterations at most (0: no polish)
    polish_tolerance: float = 0.01  # polish: a problem stops once an iteration gains less than this share
    polish_steps: tuple[float, float, float, float] = (1e-3, 5e-3, 2e-3, 2e-2)  # polish: difference steps
    polish_damping: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0)  # polish: the lambdas tried per iteration
    polish_win: float = 0.5  # polish: replaces the chosen model only below this error ratio
    polish_samples_per_period: float = 16.0  # polish: the error scored on this many samples per period
    polish_free_steps: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)  # polish: the free stage's three, in scales
    polish_gap_seeds: tuple[float, ...] = (0.003, 0.005, 0.01, 0.02, 0.04)  # polish: s_N tried on a model without a gap
    free_rounds: int = 5  # free one-mass part: cross-entropy rounds
    # free one-mass part: first spread of log10 J_sigma, M_FC / M*, mu_F w_max / M*
    free_spread: tuple[float, float, float] = (0.1, 0.01, 0.01)
    free_win: float = 0.25  # free one-mass part: error ratio it must beat
    free_periods: float = 2.0  # free one-mass part: also where a section holds fewer periods of the chosen model
    angle_rounds: int = 4  # angle: cross-entropy rounds on each side of the class threshold
    seed: int = 0  # every search starts from this seed


@dataclass
class RefineProblem:
    """One record to refine: measured ``speed`` ``N`` [rad/s]; torque reference segments
    (``start`` int ``K``, ``level`` ``K`` [Nm]); scored ``segments`` ``(L, 2)`` half-open sample
    ranges; STEP 2's ``J_sigma``, ``M_FC``, ``mu_F``; the drive (``T_s``, ``T_Ei``,
    ``encoder_counts``, ``M_N`` for ``s_N``); the start ``theta`` over :data:`COORDINATES`
    (``s_N`` of 1e-3 or less stands for no backlash)."""

    speed: np.ndarray
    start: np.ndarray
    level: np.ndarray
    segments: np.ndarray
    J_sigma: float
    M_FC: float
    mu_F: float
    T_s: float
    T_Ei: float
    encoder_counts: int
    M_N: float
    theta: np.ndarray
    free_one_mass: bool = False

    def J_sigma_of(self, theta: np.ndarray) -> np.ndarray:
        """``J_sigma`` [kg m^2] of ``theta`` ``*batch x 4`` (STEP 2's) or ``x 7`` (its own)."""
        return 10.0 ** theta[..., 4] if theta.shape[-1] > 4 else np.full(theta.shape[:-1], self.J_sigma)

    def C_F(self, theta: np.ndarray) -> np.ndarray:
        """Shaft stiffness [Nm/rad] of ``theta`` ``*batch x 4`` (or ``x 7``)."""
        return sim.two_mass_derived(self.J_sigma_of(theta), 10.0 ** theta[..., 1], 10.0 ** theta[..., 0],
                                    theta[..., 2]).C_F


@dataclass
class Refined:
    """The refined model: ``f_e`` [Hz], ``V_J``, ``d``, ``s_N``, ``backlash`` = ``2s`` [rad];
    ``residual`` and ``start_residual``: the detrended speed error of the refined model and of
    the maps' answer over the measured oscillation (both detrended the same way; about the
    quantization noise over the oscillation for a perfect model), ``dof`` the samples they are
    taken over less the trends removed; ``n_sims`` simulated models; ``J_sigma``, ``M_FC``,
    ``mu_F``: refined one-mass values where the free stage won (else None: STEP 2's stand)."""

    f_e: float
    V_J: float
    d: float
    s_N: float
    backlash: float
    residual: float
    start_residual: float
    dof: int
    n_sims: int
    J_sigma: float | None = None
    M_FC: float | None = None
    mu_F: float | None = None

    @property
    def evidence(self) -> float:
        """How much better the refined model explains the record than the maps' answer: the drop of
        the squared error in units of the refined model's own error per degree of freedom (an F
        statistic of the added model; 0 where it is no better, inf where it fits exactly)."""
        gain = self.start_residual ** 2 - self.residual ** 2
        if gain <= 0.0:
            return 0.0
        return math.inf if self.residual == 0.0 else gain * self.dof / self.residual ** 2


def torque_reference(bounds: np.ndarray, M_star: float) -> tuple[np.ndarray, np.ndarray]:
    """The switching test's torque reference (SPEC 2) from its six section ``bounds`` ``(6, 2)``:
    0 before section I, :data:`sim.SECTION_LEVELS` ``x M*`` over the sections, 0 in the tail.
    Returns ``start`` (int ``8``) and ``level`` (``8`` [Nm]) for :func:`sim.replay.replay_speed`."""
    bounds = np.asarray(bounds, dtype=np.int64)
    if bounds.shape != (6, 2):
        raise ValueError(f"bounds: expected shape (6, 2), received {bounds.shape}")
    start = np.concatenate([[0], bounds[:, 0], [bounds[5, 1]]])
    level = M_star * np.array([0.0, *sim.SECTION_LEVELS, 0.0])
    return start, level


def _detrend_basis(segments: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """Per segment ``(a, b, Q)``: orthonormal ``L x 3`` basis of the quadratic trends on it."""
    return [(a, b, _trend_basis(b - a)) for a, b in np.asarray(segments, dtype=np.int64).tolist() if b > a]


@functools.lru_cache(maxsize=4096)
def _trend_basis(L: int) -> np.ndarray:
    """Orthonormal ``L x min(3, L)`` basis of the polynomials of degree < 3 on ``L`` samples (read-only)."""
    tau = np.linspace(-1.0, 1.0, L)
    V = np.stack([np.ones(L), tau, tau * tau], axis=1)[:, : min(3, L)]  # L x 3
    Q = np.linalg.qr(V)[0]
    Q.flags.writeable = False  # shared by every caller through the cache
    return Q


def _detrended_energy(E: np.ndarray, basis: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """``sum ||e - Q Q^T e||^2`` over the segments for each column of ``E`` (``N x C``) -> ``C``,
    summed over the detrended errors themselves (``||e||^2 - ||Q^T e||^2`` loses the digits of a
    small residual under a large trend: the measured speed's own, 6e-7 of its root measured)."""
    total = np.zeros(E.shape[1])
    for a, b, Q in basis:
        r = _detrend(E[a:b], Q)  # L x C
        total += (r * r).sum(0)
    return total


def _detrend(e: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``e`` (``L x C``) less its projection on the orthonormal trend basis ``Q`` (``L x 3``)."""
    return e - Q @ (Q.T @ e)


def _finite(E: np.ndarray) -> np.ndarray:
    """``E`` with a diverged model's errors (NaN, +-inf) read as +-1e6 rad/s (a finite sum: none)."""
    return E if np.isfinite(E.sum()) else np.nan_to_num(E, nan=1e6, posinf=1e6, neginf=-1e6)


def _model_values(p: RefineProblem, theta: np.ndarray) -> dict[str, np.ndarray]:
    """The :data:`sim.PARAM_NAMES` values ``C`` of the candidates ``theta`` ``C x 4`` or ``C x 7``
    (backlash ``2s = 2 s_N M_N / C_F``)."""
    C = theta.shape[0]
    return {"J_sigma": p.J_sigma_of(theta), "V_J": 10.0 ** theta[:, 1], "f_e": 10.0 ** theta[:, 0], "d": theta[:, 2],
            "backlash": 2.0 * 10.0 ** theta[:, 3] * p.M_N / p.C_F(theta),
            "M_FC": theta[:, 5] if theta.shape[1] > 4 else np.full(C, max(p.M_FC, 0.0)),
            "mu_F": theta[:, 6] if theta.shape[1] > 4 else np.full(C, max(p.mu_F, 0.0))}


def _params(values: dict[str, np.ndarray]) -> sim.TwoMassParams:
    """:func:`_model_values` (or several concatenated) as the simulator's parameters."""
    return sim.TwoMassParams(**{n: torch.from_numpy(np.ascontiguousarray(values[n], dtype=np.float64))
                                for n in sim.PARAM_NAMES})


def _simulate(p: RefineProblem, theta: np.ndarray, drive: sim.DriveConfig) -> np.ndarray:
    """Speed error ``N x C`` [rad/s] (model minus measurement; time-major, as the kernel writes it)
    of each candidate ``theta`` ``C x 4``."""
    return _simulate_packed([(p, theta)], drive)[0]


def _simulate_packed(items: list[tuple[RefineProblem, np.ndarray]], drive: sim.DriveConfig,
                     rows: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """:func:`_simulate` for several records on one drive in one replay call (the kernel's blocks
    of 32 models fill up and run on all cores): one ``N_i x C_i`` error per item (``rows``: only
    these samples of each item's record, ``R_i x C_i``)."""
    values = [_model_values(p, th) for p, th in items]
    flat = {n: np.concatenate([v[n] for v in values]) for n in sim.PARAM_NAMES}
    N = max(len(p.speed) for p, _ in items)
    K = max(len(p.start) for p, _ in items)
    start = np.concatenate([np.broadcast_to(np.pad(p.start, (0, K - len(p.start)), constant_values=2**30),
                                            (len(th), K)) for p, th in items])  # n x K
    level = np.concatenate([np.broadcast_to(np.pad(p.level, (0, K - len(p.level)), mode="edge"),
                                            (len(th), K)) for p, th in items])
    w = replay_speed(_params(flat), drive, torch.from_numpy(start), torch.from_numpy(level), N, quantize=False,
                     substeps=_substeps(flat, drive.T_s, drive.T_Ei)).numpy().T  # N x n
    out, i = [], 0
    for k, (p, th) in enumerate(items):
        at = slice(0, len(p.speed)) if rows is None else rows[k]
        out.append(_finite(w[at, i:i + len(th)] - p.speed[at, None]))
        i += len(th)
    return out


def _problem_substeps(p: RefineProblem, theta: np.ndarray) -> int:
    """:func:`_substeps` of the candidates ``theta`` of ``p`` on its drive."""
    return _substeps(_model_values(p, theta), p.T_s, p.T_Ei)


def _substeps(values: dict[str, np.ndarray], T_s: float, T_Ei: float) -> int:
    """RK4 substeps per sample: ``w_0 dt <= 0.5`` for the stiffest model of
    :func:`_model_values` (frequency error < 0.1 %), ``dt <= T_Ei/2`` (:func:`sim.rk4_substeps`)."""
    w_0 = sim.two_mass_derived(values["J_sigma"], values["V_J"], values["f_e"], values["d"]).w_0
    return sim.rk4_substeps(float(w_0.max()), T_s, T_Ei, w_0_dt=0.5, minimum=1)


def _drive(p: RefineProblem) -> sim.DriveConfig:
    """The drive the candidates of ``p`` run on (no torque limit: the levels are what was applied)."""
    return sim.DriveConfig(M_max=1e9, T_Ei=p.T_Ei, T_s=p.T_s, encoder_counts=p.encoder_counts)


def _score(p: RefineProblem, theta: np.ndarray, basis: list, drive: sim.DriveConfig) -> np.ndarray:
    """Detrended squared speed error of each candidate ``theta`` ``C x 4`` -> ``C``."""
    return _detrended_energy(_simulate(p, theta, drive), basis)


@dataclass(frozen=True)
class _ScoreWindows:
    """What the exploration score needs of a record's ``J`` windows (the first samples after each
    torque step), computed once, each window padded with zeros to the longest (``L``): the
    measured speed ``y`` ``J x L``, the orthonormal bases ``Q`` ``J x L x 3`` of each window's
    quadratic trend, ``y`` detrended (``y_r``, with ``yy = ||y_r||^2``), ``inside`` (1 over each
    window's own samples, else 0), its first sample ``at`` and the torque reference over it
    (``M_new``), and ``lead``: the length of the zero-torque section before a window that follows
    one (else 0); ``J`` each."""

    y: np.ndarray
    Q: np.ndarray
    y_r: np.ndarray
    yy: float
    inside: np.ndarray
    at: np.ndarray
    M_new: np.ndarray
    lead: np.ndarray

    @classmethod
    def of(cls, p: RefineProblem, windows: np.ndarray, lead: np.ndarray) -> "_ScoreWindows":
        first, lengths = windows[:, 0].tolist(), (windows[:, 1] - windows[:, 0]).tolist()
        J, L = len(first), max(lengths)
        y, Q = np.zeros((J, L)), np.zeros((J, L, 3))
        for j, (a, n) in enumerate(zip(first, lengths)):
            y[j, :n] = p.speed[a:a + n]
            if n > 0:
                Q[j, :n, : min(3, n)] = _trend_basis(n)
        y_r = y - (Q @ (y[:, None, :] @ Q).transpose(0, 2, 1))[:, :, 0]  # J x L
        return cls(y, Q, y_r, float((y_r * y_r).sum()), (np.arange(L) < np.array(lengths)[:, None]).astype(np.float64),
                   windows[:, 0].copy(), _level_at(p, windows[:, 0]), np.asarray(lead, dtype=np.int64))


def _score_shape(theta: np.ndarray, X: np.ndarray, w: _ScoreWindows) -> tuple[np.ndarray, np.ndarray]:
    """The exploration score of the candidates ``theta`` ``C x 4`` whose model speeds over the
    windows ``w`` are ``X`` ``C x J x L`` (:func:`_window_speeds`): the detrended error after the
    best gain ``g`` on each candidate's detrended speed, ``||y||^2 - <y, x>^2 / ||x||^2`` (``y``
    measured, ``x`` model), and ``theta`` with ``V_J`` scaled by ``g`` (eq. 1: the oscillation is
    about proportional to ``V_J``)."""
    X = X.transpose(1, 0, 2)  # J x C x L
    X_r = X - (X @ w.Q) @ w.Q.transpose(0, 2, 1)  # each window detrended (0 past its end)
    xy, xx, yy = np.einsum("jcl,jl->c", X_r, w.y_r), np.einsum("jcl,jcl->c", X_r, X_r), w.yy
    some = xx > 0
    gain = np.where(some, xy / np.maximum(xx, 1e-300), 0.0)
    cost = np.maximum(yy - np.where(some, xy * xy / np.maximum(xx, 1e-300), 0.0), 0.0)
    cost = np.where(gain > 0, cost, yy)  # an inverted oscillation is no match
    scaled = theta.copy()
    scaled[:, 1] += np.log10(np.clip(gain, 0.25, 4.0))
    return cost, np.clip(scaled, _LOW, _HIGH)


def _windows(segments: np.ndarray, length: int) -> np.ndarray:
    """The first ``length`` samples of each segment ``(L, 2)``."""
    seg = np.asarray(segments, dtype=np.int64)
    return np.stack([seg[:, 0], np.minimum(seg[:, 1], seg[:, 0] + length)], axis=1)


def _level_at(p: RefineProblem, k: np.ndarray) -> np.ndarray:
    """The torque reference [Nm] over each sample ``k`` (int array, any shape)."""
    return p.level[np.searchsorted(p.start, k, side="right") - 1]


#: Lanes x samples of one replay of led windows at most (float32: 64 MB; a zero-torque section
#: that ran to its 10 s timeout at 62.5 us is 160 000 samples long).
_LED_SAMPLES = 16 * 2**20


def _window_speeds(items: list[tuple[RefineProblem, np.ndarray, _ScoreWindows, bool]], drive: sim.DriveConfig,
                   substeps: int) -> list[np.ndarray]:
    """Motor speed ``C x J x L`` [rad/s] of each candidate ``theta`` ``C x 4`` of each item
    ``(problem, theta, windows, led)`` over its windows (0 past each window's end; a diverged
    model's reads 1e6 rad/s off the measured), all items on one drive (the items' results do not
    depend on each other), each window simulated on its own from a quasi-static state: the torque
    before it settled, both masses at the measured speed, the shaft twisted by the torque that
    accelerates the load (``J_L a`` plus the load friction, ``a`` the rigid acceleration) over
    ``C_F``, plus ``s`` on the loaded side. With ``led``, a window after a zero-torque section
    starts at that section's start instead (:class:`RefineConfig`, rattle); those windows run in
    replays of their own per item, at most :data:`_LED_SAMPLES` lane-samples each. An oscillation
    still ringing from before a window is not in its start state (the exploring score tolerates
    it; the polish simulates the whole record)."""
    names = sim.PARAM_NAMES + ("w_M", "dphi", "M_M", "M_new", "lead")
    flat: dict[str, list[np.ndarray]] = {n: [] for n in names}
    led: list[tuple[np.ndarray, dict[str, np.ndarray]] | None] = []  # per item: its plain lanes' mask, its led lanes
    for p, theta, w, with_lead in items:
        C, J = theta.shape[0], w.y.shape[0]
        lead = np.broadcast_to(w.lead if with_lead else np.zeros(J, dtype=np.int64), (C, J))
        first = w.at - lead  # C x J: the first simulated sample
        w_M = p.speed[first]
        M_prev = np.where(first > 0, _level_at(p, first - 1), 0.0)  # C x J (rest before the record)
        m = _model_values(p, theta)
        dv = sim.two_mass_derived(m["J_sigma"], m["V_J"], m["f_e"], m["d"])
        friction = m["M_FC"][:, None] * np.sign(w_M) + max(p.mu_F, 0.0) * w_M  # C x J
        M_S = dv.J_L[:, None] * (M_prev - friction) / m["J_sigma"][:, None] + friction  # C x J: rigid motion
        lane = {**{n: np.repeat(v, J) for n, v in m.items()},  # C*J, window index fastest
                "w_M": w_M.reshape(-1), "dphi": (M_S / dv.C_F[:, None] + (m["backlash"] / 2.0)[:, None]
                                                 * np.sign(M_S)).reshape(-1),
                "M_M": M_prev.reshape(-1), "M_new": np.tile(w.M_new, C), "lead": lead.reshape(-1)}
        plain = lane["lead"] == 0
        for n in names:
            flat[n].append(lane[n][plain])
        led.append((plain, {n: v[~plain] for n, v in lane.items()}) if not plain.all() else None)
    out = _replay_windows({n: np.concatenate(v) for n, v in flat.items()}, drive, substeps,
                          max(w.y.shape[1] for _, _, w, _ in items))
    speeds, i = [], 0
    for (_, theta, w, _), item_led in zip(items, led):
        C, (J, L_w) = theta.shape[0], w.y.shape
        if item_led is None:
            X = out[i:i + C * J, :L_w].astype(np.float64)
            i += C * J
        else:
            plain, lanes = item_led
            X = np.empty((C * J, L_w))
            X[plain] = out[i:i + int(plain.sum()), :L_w]
            i += int(plain.sum())
            n, length = len(lanes["w_M"]), int(lanes["lead"].max()) + L_w
            step = max(64, _LED_SAMPLES // length)  # lanes per replay
            X[~plain] = np.concatenate([
                np.take_along_axis(_replay_windows({k: v[a:a + step] for k, v in lanes.items()}, drive, substeps, length),
                                   lanes["lead"][a:a + step, None] + np.arange(L_w), 1) for a in range(0, n, step)])
        X = X.reshape(C, J, L_w)  # C*J -> C x J x L
        speeds.append((X if np.isfinite(X.sum()) else w.y + _finite(X - w.y)) * w.inside)
    return speeds


def _replay_windows(lanes: dict[str, np.ndarray], drive: sim.DriveConfig, substeps: int, length: int) -> np.ndarray:
    """Motor speed ``lanes x length`` [rad/s] of :func:`_window_speeds`' lanes: each from its start
    state, at 0 over its first ``lead`` samples (a zero-torque section) and at ``M_new`` after."""
    state = {"w_M": lanes["w_M"], "w_L": lanes["w_M"], "dphi": lanes["dphi"], "M_M": lanes["M_M"]}
    start = np.stack([np.zeros_like(lanes["lead"]), lanes["lead"]], 1)  # lanes x 2
    level = np.stack([np.where(lanes["lead"] > 0, 0.0, lanes["M_new"]), lanes["M_new"]], 1)
    return replay_speed(_params(lanes), drive, torch.from_numpy(start), torch.from_numpy(level), length,
                        quantize=False, state=state, substeps=substeps).numpy()  # lanes x length (a view)


#: A search: yields candidates ``C x D``, is sent ``(cost C, candidates as scored)`` for each, returns its result.
Search = Generator[np.ndarray, tuple[np.ndarray, np.ndarray], Any]
#: The exploration's search: its candidates come with whether their windows take the lead (:func:`_window_speeds`).
TaggedSearch = Generator[tuple[np.ndarray, bool], tuple[np.ndarray, np.ndarray], Any]


def _cem(theta: np.ndarray, cost: np.ndarray, rounds: int, spread: np.ndarray, config: RefineConfig,
         rng: np.random.Generator, low: np.ndarray = _LOW, high: np.ndarray = _HIGH) -> Search:
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


def _run(search: Search, score: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Any:
    """The result of ``search`` with each of its candidates scored by ``score``."""
    try:
        candidates = next(search)
        while True:
            candidates = search.send(score(candidates))
    except StopIteration as done:
        return done.value


def refine(problems: list[RefineProblem], config: RefineConfig | None = None) -> list[Refined]:
    """Refine each problem's ``theta`` (see module docstring); one :class:`Refined` per problem,
    each the same whatever the other problems (every search starts from ``config.seed``; the
    whole-record choice of records on the same drive and of similar length runs packed in one
    replay)."""
    config = config or RefineConfig()
    if (config.elites < 2 or config.candidates < config.elites or config.rounds < 0 or config.window_periods <= 0
            or config.window_samples < 0 or config.polish_iterations < 0 or config.angle_rounds < 0
            or config.far_rounds < 0 or min(config.grid_f_e, config.climb_grid_f_e, config.rescue_grid_f_e) < 1
            or len(config.free_spread) != 3 or len(config.polish_free_steps) != 3 or config.free_rounds < 0
            or any(not g > 10.0 ** _NO_GAP for g in config.polish_gap_seeds)):
        raise ValueError(f"RefineConfig: expected rounds >= 0, far_rounds >= 0, free_rounds >= 0, "
                         f"polish_iterations >= 0, angle_rounds >= 0, grid_f_e >= 1, climb_grid_f_e >= 1, "
                         f"rescue_grid_f_e >= 1, window_periods > 0, window_samples >= 0, candidates >= elites >= 2, "
                         f"three values each in free_spread and polish_free_steps (log10 J_sigma, M_FC, mu_F) "
                         f"and polish_gap_seeds above {10.0 ** _NO_GAP:g}, "
                         f"received {config}")
    rngs = [np.random.default_rng(config.seed) for _ in problems]
    explored = _explore_all(problems, config, rngs)
    finalists = [f for f, _ in explored]
    costs: list[np.ndarray] = [np.empty(0)] * len(problems)
    bases = [_detrend_basis(p.segments) for p in problems]  # the whole record's sections and tail
    for i, E in _packed_errors(problems, dict(enumerate(finalists))):
        costs[i] = _detrended_energy(E, bases[i])
    measured = [float(_detrended_energy(p.speed[:, None], b)[0]) for p, b in zip(problems, bases)]
    chosen = [_finish(p, th, c, b, m, n, config, rng)
              for p, th, c, b, m, (_, n), rng in zip(problems, finalists, costs, bases, measured, explored, rngs)]
    return _polish(problems, chosen, measured, config) if config.polish_iterations else chosen


def _packed_errors(problems: list[RefineProblem], asked: dict[int, np.ndarray],
                   rows: dict[int, np.ndarray] | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """``(i, E)``: the speed error ``N_i x C_i`` (or over the samples ``rows[i]`` only) of the
    candidates ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``, a pack at a time
    (:func:`_packs`: one drive and substep count per replay call; a result does not depend on its
    pack)."""
    todo = sorted(asked)
    substeps = [_problem_substeps(problems[i], asked[i]) for i in todo]
    for pack in _packs([problems[i] for i in todo], [len(asked[i]) for i in todo], substeps):
        ids = [todo[k] for k in pack]
        yield from zip(ids, _simulate_packed([(problems[i], asked[i]) for i in ids], _drive(problems[ids[0]]),
                                             None if rows is None else [rows[i] for i in ids]))


def _relative(cost: float, measured: float) -> float:
    """A detrended error's rms over that of the detrended measured speed (``measured``: its energy)."""
    return math.sqrt(cost / measured) if measured > 0 else math.sqrt(cost)


def _answer(p: RefineProblem, theta: np.ndarray, s_N: float) -> dict[str, float]:
    """The :class:`Refined` model values of ``theta`` (4 or 6) with the normalized backlash ``s_N``."""
    return {"f_e": float(10.0 ** theta[0]), "V_J": float(10.0 ** theta[1]), "d": float(theta[2]), "s_N": s_N,
            "backlash": 2.0 * s_N * p.M_N / float(p.C_F(theta))}


def _packs(problems: list[RefineProblem], sizes: list[int], substeps: list[int], lengths: list[int] | None = None,
           max_models: int = 256, min_length_ratio: float = 0.6) -> list[list[int]]:
    """Indices of ``problems`` in packs of one drive and one substep count (so that a result does
    not depend on its pack), simulated lengths (default: the records') within
    ``min_length_ratio`` of the pack's longest (the shorter ones idle while it runs) and at most
    ``max_models`` simulated models (``sizes``)."""
    lengths = [len(p.speed) for p in problems] if lengths is None else lengths
    key = lambda i: (problems[i].T_s, problems[i].T_Ei, problems[i].encoder_counts, substeps[i])  # noqa: E731
    order = sorted(range(len(problems)), key=lambda i: (key(i), -lengths[i]))
    packs: list[list[int]] = []
    for i in order:
        last = packs[-1] if packs else None
        fits = (last and key(last[0]) == key(i)
                and lengths[i] >= min_length_ratio * lengths[last[0]]
                and sum(sizes[j] for j in last) + sizes[i] <= max_models)
        if fits:
            last.append(i)
        else:
            packs.append([i])
    return packs


def _explore_windows(p: RefineProblem, config: RefineConfig) -> _ScoreWindows:
    """The exploring stage's windows of ``p``: ``window_periods`` at the start's ``f_e`` (at
    least 8 samples, at most ``window_max`` or ``window_samples``, whichever is longer) after each
    torque step, each after a zero-torque section with that section's length as its lead."""
    period = 1.0 / (10.0 ** np.clip(p.theta[0], _LOW[0], _HIGH[0]) * p.T_s)  # samples per period at the start's f_e
    seg = np.asarray(p.segments, dtype=np.int64)
    a = seg[:, 0]
    after_zero = (np.arange(len(a)) > 0) & (_level_at(p, a - 1) == 0.0) & (_level_at(p, a) != 0.0)
    lead = np.where(after_zero, a - np.concatenate([[0], a[:-1]]), 0)  # the zero section's length
    longest = max(config.window_max / p.T_s, config.window_samples)  # [samples]
    return _ScoreWindows.of(p, _windows(seg, max(8, int(round(min(config.window_periods * period, longest))))), lead)


def _explore(p: RefineProblem, windows: _ScoreWindows, config: RefineConfig,
             rng: np.random.Generator) -> TaggedSearch:
    """The exploring stage of ``p`` (``windows``: :func:`_explore_windows`) as a
    :data:`TaggedSearch` scored by :func:`_score_shape`; returns the finalists ``F x 4`` (the
    maps' answer; the elites of the search that won, the exploration, the rescue or the climb, and
    the exploration's too where the rescue won; the rattle's best where it ran: see
    :class:`RefineConfig`) and the number of models explored."""
    theta0 = np.clip(np.asarray(p.theta, dtype=np.float64), _LOW, _HIGH)
    theta, cost = yield from _tagged(_search(theta0, config, rng), False)
    explored = len(cost)
    finalists = [theta0[None]]
    if _rescues(p, windows, float(cost.min()), config):
        theta_g, cost_g = yield from _tagged(_survey(p, theta0, config, _own_rng(config, 1)), False)
        explored += len(cost_g)
        if cost_g.min() < config.switch_win * cost.min():
            finalists.append(theta[np.argsort(cost)[: config.elites]])
            theta, cost = theta_g, cost_g
    best = theta[int(np.argmin(cost))]
    if _climbs(p, theta0, best, config):
        up = best.copy()
        up[0] += config.climb
        up[3] += math.log10(float(p.C_F(up) / p.C_F(best)))  # the same width 2s = 2 s_N M_N / C_F
        far = replace(config, grid_f_e=config.climb_grid_f_e, grid_span=config.climb_span, rounds=config.far_rounds)
        theta_up, cost_up = yield from _tagged(_search(np.clip(up, _LOW, _HIGH), far, _own_rng(config, 2)), False)
        explored += len(cost_up)
        if cost_up.min() < config.switch_win * cost.min():
            theta, cost = theta_up, cost_up
            best = theta[int(np.argmin(cost))]
    elites = theta[np.argsort(cost)[: config.elites]]
    finalists.append(elites)
    if 10.0 ** best[3] >= config.rattle_s_N and windows.lead.any():
        again = np.concatenate([elites, np.repeat(best[None], len(config.rattle_shift), axis=0)])
        again[-len(config.rattle_shift):, 3] += config.rattle_shift
        cost_r, theta_r = yield np.clip(again, _LOW, _HIGH), True
        theta_r, cost_r = yield from _tagged(_cem(theta_r, cost_r, config.rattle_rounds,
                                                  np.asarray(config.spread, dtype=np.float64), config, rng), True)
        explored += len(cost_r)
        finalists.append(theta_r[np.argsort(cost_r)[: config.rattle_finalists]])
    return np.concatenate(finalists), explored


def _own_rng(config: RefineConfig, stage: int) -> np.random.Generator:
    """The random stream of an optional stage (1: rescue, 2: climb, 3: the free stage's second
    search), apart from the exploration's: where the stage loses, the searches after it draw what
    they would have drawn without it."""
    return np.random.default_rng([config.seed, stage])


def _tagged(search: Search, led: bool) -> TaggedSearch:
    """``search`` with each of its candidates tagged ``led`` (:func:`_explore`)."""
    try:
        candidates = next(search)
        while True:
            candidates = search.send((yield candidates, led))
    except StopIteration as done:
        return done.value


def _search(theta0: np.ndarray, config: RefineConfig, rng: np.random.Generator) -> Search:
    """One exploration from ``theta0`` (4): the grid around it, then the cross-entropy rounds;
    returns every scored model and its cost."""
    grid = np.repeat(theta0[None], config.grid_f_e * len(config.grid_s_N), axis=0)  # G x 4
    grid[:, 0] += np.repeat(np.linspace(-config.grid_span, config.grid_span, config.grid_f_e), len(config.grid_s_N))
    grid[:, 3] = np.tile(_grid_s_N(theta0, config), config.grid_f_e)
    cost, theta = yield np.clip(grid, _LOW, _HIGH)
    return (yield from _cem(theta, cost, config.rounds, np.asarray(config.spread, dtype=np.float64), config, rng))


def _product_grid(f_e: Sequence[float], V_J: Sequence[float], d: float, log10_s_N: Sequence[float]) -> np.ndarray:
    """Every combination of the eigenfrequencies ``f_e`` [Hz], inertia ratios ``V_J`` and
    ``log10_s_N`` at damping ``d``, as models over :data:`COORDINATES` ``G x 4`` (``f_e`` slowest)."""
    return np.array([[math.log10(f), math.log10(v), d, s] for f, v, s in itertools.product(f_e, V_J, log10_s_N)])


def _grid_s_N(theta0: np.ndarray, config: RefineConfig) -> list[float]:
    """log10 ``s_N`` of the grids: ``config.grid_s_N``, its 0 standing for the start's (``theta0``)."""
    return [math.log10(v) if v > 0 else float(theta0[3]) for v in config.grid_s_N]


def _rescues(p: RefineProblem, windows: _ScoreWindows, cost: float, config: RefineConfig) -> bool:
    """Whether the exploration of ``p``, whose best model left ``cost`` of the energy over its
    ``windows``, is followed by the rescue's survey (see :class:`RefineConfig`)."""
    noise = float(windows.inside.sum()) * sim.speed_quantum(p.encoder_counts, p.T_s) ** 2 / 6.0
    return cost > config.rescue_above * windows.yy and windows.yy >= config.rescue_signal * noise


def _survey(p: RefineProblem, theta0: np.ndarray, config: RefineConfig, rng: np.random.Generator) -> Search:
    """The rescue's search over the whole range (see :class:`RefineConfig`), ``d`` and the
    start's ``s_N`` from ``theta0`` (4); returns every scored model and its cost."""
    f_e = np.geomspace(SPEC_ENVELOPE["f_e"][0], min(10.0 ** _HIGH[0], 0.5 / p.T_s), config.rescue_grid_f_e)
    cost, theta = yield np.clip(_product_grid(f_e, config.rescue_V_J, float(theta0[2]), _grid_s_N(theta0, config)),
                                _LOW, _HIGH)
    return (yield from _cem(theta, cost, config.far_rounds, np.asarray(config.spread, dtype=np.float64), config, rng))


def _climbs(p: RefineProblem, theta0: np.ndarray, best: np.ndarray, config: RefineConfig) -> bool:
    """Whether the exploration of ``p`` from ``theta0`` climbs on from its ``best`` model (see
    :class:`RefineConfig`)."""
    bandwidth = 1.0 / (2.0 * math.pi * p.T_Ei)
    return bool(10.0 ** best[3] >= sim.S_N_ELASTIC and best[0] - theta0[0] >= config.climb_after
                and 10.0 ** theta0[0] >= config.climb_above * bandwidth)


def _explore_all(problems: list[RefineProblem], config: RefineConfig,
                 rngs: list[np.random.Generator]) -> list[tuple[np.ndarray, int]]:
    """The finalists of each problem and the number of models explored (:func:`_explore`), the
    searches run side by side: each step's candidates of every problem on one drive, substep count
    and similar window length go to the simulator in one call (:func:`_packs`), so that the
    per-call costs are paid once per batch, not once per record."""
    windows = [_explore_windows(p, config) for p in problems]
    searches = [_explore(p, w, config, rng) for p, w, rng in zip(problems, windows, rngs)]
    asked = {i: next(s) for i, s in enumerate(searches)}
    explored: list[tuple[np.ndarray, int]] = [(np.empty(0), 0)] * len(problems)
    while asked:
        todo = sorted(asked)
        substeps = [_problem_substeps(problems[i], asked[i][0]) for i in todo]
        sizes = [len(asked[i][0]) * windows[i].y.shape[0] for i in todo]
        packs = _packs([problems[i] for i in todo], sizes, substeps, [windows[i].y.shape[1] for i in todo],
                       max_models=4096)
        for pack in packs:
            ids = [todo[k] for k in pack]
            X = _window_speeds([(problems[i], asked[i][0], windows[i], asked[i][1]) for i in ids],
                               _drive(problems[ids[0]]), substeps[pack[0]])
            for i, x in zip(ids, X):
                try:
                    asked[i] = searches[i].send(_score_shape(asked[i][0], x, windows[i]))
                except StopIteration as done:
                    explored[i] = done.value
                    del asked[i]
    return explored


def _finish(p: RefineProblem, theta: np.ndarray, cost: np.ndarray, full: list, measured: float, explored: int,
            config: RefineConfig, rng: np.random.Generator) -> Refined:
    """The best finalist (``theta`` with its whole-record ``cost`` over the detrending basis
    ``full``; row 0 the maps' answer; ``measured`` the measured speed's own detrended energy;
    ``explored`` models before), after the free stage where the problem asks for it."""
    n_sims = explored + len(cost)
    best, best_cost = theta[int(np.argmin(cost))], float(cost.min())
    if p.free_one_mass or _short_sections(p, best, config):
        best, n_free = _free_one_mass(p, best, config, rng, _drive(p))
        n_sims += n_free
        best_cost = float(_score(p, best[None], full, _drive(p))[0])
    free = len(best) > 4
    return Refined(**_answer(p, best, float(10.0 ** best[3])), residual=_relative(best_cost, measured),
                   start_residual=_relative(float(cost[0]), measured), dof=sum(b - a - Q.shape[1] for a, b, Q in full),
                   n_sims=n_sims,
                   **(_one_mass(best) if free else {}))


def _short_sections(p: RefineProblem, theta: np.ndarray, config: RefineConfig) -> bool:
    """Whether the shortest test section of ``p`` holds fewer than ``config.free_periods`` periods
    of the model ``theta``'s oscillation (STEP 2's one-mass fit then sees the motor's inertia)."""
    sections = np.diff(p.start[1:])  # the six sections' lengths [samples]
    return bool(sections.size and sections.min() * p.T_s * 10.0 ** theta[0] < config.free_periods)


def _free_one_mass(p: RefineProblem, best: np.ndarray, config: RefineConfig, rng: np.random.Generator,
                   drive: sim.DriveConfig) -> tuple[np.ndarray, int]:
    """The free stage (see :class:`RefineConfig`): ``best`` (4) or the winner over
    :data:`FREE_COORDINATES` (7), and the number of simulated models."""
    low, high, scale = _free_bounds(p)
    plain = functools.partial(_scaled_fit, p, drive, low, high)
    friction = np.clip([p.M_FC, p.mu_F], 0.0, high[5:])  # STEP 2's
    chosen = np.concatenate([best, [math.log10(p.J_sigma)], friction])  # what the free model must beat
    # the grids start from STEP 2's friction capped at a tenth of its bounds (a short test's can be 10-50 x off)
    one_mass = np.array([math.log10(p.J_sigma), *np.minimum(friction, 0.1 * high[5:])])
    start = np.concatenate([best, one_mass])
    # grids over f_e, V_J (the centre's x 0.5, 1, 2; SPEC 3.1's range) and friction; J_sigma: _scaled_fit
    pairs = np.array([one_mass[1:], [0.025 * high[5], 0.01 * high[6]]])  # friction: STEP 2's; 2.5 %, 1 %
    f_f = np.log10(2.0) * np.arange(-16, 5) / 4.0  # f_e x 1/16 .. 2 in steps of 2^0.25
    around, held = [chosen[None], start[None]], []
    for center in (start, np.concatenate([np.clip(p.theta, _LOW, _HIGH), one_mass])):  # chosen model, maps' answer
        for out, V_J in ((around, center[1] + np.log10([0.5, 1.0, 2.0])),
                         (held, np.log10(np.geomspace(*SPEC_ENVELOPE["V_J"], 5)))):
            f, v, pick = (a.reshape(-1) for a in np.meshgrid(center[0] + f_f, V_J, [0, 1], indexing="ij"))
            grid = np.repeat(center[None], f.size, axis=0)  # G x 7
            grid[:, 0], grid[:, 1], grid[:, 5:] = f, v, pairs[pick]
            out.append(grid)
    spread = np.concatenate([config.spread, np.asarray(config.free_spread) * scale])
    found = []  # each grid with its own search: one best model does not cover both kinds of start
    for grid, stream in ((around, rng), (held, _own_rng(config, 3))):
        cost, theta = plain(np.clip(np.concatenate(grid), low, high))
        found.append(_run(_cem(theta, cost, config.free_rounds, spread, config, stream, low, high), plain))
    theta, cost = (np.concatenate(v) for v in zip(*found))
    k = int(np.argmin(cost))
    # a clear win only (measured: 10-60 x lower on soft mechanics; a narrow one was a wrong mode)
    to_beat = float((_simulate(p, chosen[None], drive) ** 2).sum())  # the chosen model with STEP 2's values
    return (theta[k] if cost[k] < config.free_win * to_beat else best), len(cost) + 1


def _scaled_fit(p: RefineProblem, drive: sim.DriveConfig, low: np.ndarray, high: np.ndarray,
                theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain squared speed error ``C`` of each free model ``theta`` ``C x 7`` at its best
    scale, and the models so scaled. The scale is exact: ``J_sigma / k`` and ``mu_F / k`` with
    ``f_e``, ``V_J``, ``d``, ``s_N`` and ``M_FC`` unchanged turn the replayed motor speed into ``k``
    times itself (the gap ``2s = 2 s_N M_N / C_F`` and all speeds and angles scale by ``k``), so one
    replay per model gives the least-squares ``k`` (kept within the bounds ``low``/``high``)."""
    E = _simulate(p, theta, drive)  # N x C
    y = E + p.speed[:, None]  # the models' speeds
    yy = (y * y).sum(0)
    k = np.where(yy > 0, (y * p.speed[:, None]).sum(0) / np.where(yy > 0, yy, 1.0), 1.0)
    k_low = np.maximum(10.0 ** (theta[:, 4] - high[4]), theta[:, 6] / high[6])
    k_high = 10.0 ** (theta[:, 4] - low[4])
    k = np.where(np.abs(E).max(0) < 1e6, np.clip(k, k_low, k_high), 1.0)  # a diverged model stays
    scaled = theta.copy()
    scaled[:, 4] -= np.log10(k)
    scaled[:, 6] /= k
    return ((k * y - p.speed[:, None]) ** 2).sum(0), scaled


def _free_bounds(p: RefineProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The free stage's bounds over :data:`FREE_COORDINATES` (``J_sigma`` within
    :data:`_FREE_J_SIGMA` decades of STEP 2's, ``M_FC`` from 0 to the test's ``M*``, ``mu_F`` from 0
    to ``M* / w_max``) and the scales of its three coordinates (1, ``M*``, ``M* / w_max``)."""
    M_star, w_max = float(np.abs(p.level).max()), max(float(np.abs(p.speed).max()), 1e-9)  # (a record at rest)
    J = math.log10(p.J_sigma)
    scale = np.array([1.0, M_star, M_star / w_max])
    return (np.concatenate([_LOW, [J - _FREE_J_SIGMA, 0.0, 0.0]]),
            np.concatenate([_HIGH, [J + _FREE_J_SIGMA, M_star, M_star / w_max]]), scale)


def _one_mass(theta: np.ndarray) -> dict[str, float]:
    """The :class:`Refined` one-mass values of the free stage's model ``theta`` (7)."""
    return {"J_sigma": float(10.0 ** theta[4]), "M_FC": float(theta[5]), "mu_F": float(theta[6])}


def _detrended(E: np.ndarray, basis: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """The errors ``E`` (``N x C``) with each segment's quadratic trend removed, segments end to
    end: ``M x C`` (their squared sum is the refinement's detrended energy)."""
    return np.concatenate([_detrend(E[a:b], Q) for a, b, Q in basis], axis=0)


def _scored(p: RefineProblem, f_e: float, config: RefineConfig) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """The samples the polish scores (every ``k``-th of each segment: see :class:`RefineConfig`)
    and their detrending basis, segments end to end."""
    k = max(1, int(1.0 / (f_e * p.T_s * config.polish_samples_per_period)))
    rows = [np.arange(a, b, k) for a, b in np.asarray(p.segments, dtype=np.int64).tolist() if b > a]
    ends = np.cumsum([0] + [len(r) for r in rows])
    return np.concatenate(rows), _detrend_basis(np.stack([ends[:-1], ends[1:]], axis=1))


def _errors(problems: list[RefineProblem], asked: dict[int, np.ndarray],
            scored: dict[int, tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]]) -> dict[int, np.ndarray]:
    """The detrended errors ``M_i x C_i`` over the samples ``scored[i]`` of the candidates
    ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``."""
    return {i: _detrended(E, scored[i][1])
            for i, E in _packed_errors(problems, asked, {i: rows for i, (rows, _) in scored.items()})}


def _polish(problems: list[RefineProblem], chosen: list[Refined], measured: list[float],
            config: RefineConfig) -> list[Refined]:
    """Each ``chosen[i]`` polished on the whole record (see :class:`RefineConfig`; ``measured[i]``
    the measured speed's own detrended energy), the searches side by side: one replay per
    iteration and step kind for the problems on one drive and substep count; ``residual`` and
    ``n_sims`` updated."""
    theta, free, scored, low, high, h = {}, {}, {}, {}, {}, {}
    for i, (p, r) in enumerate(zip(problems, chosen)):
        t = [math.log10(r.f_e), math.log10(r.V_J), r.d, math.log10(max(r.s_N, 10.0 ** _LOW[3]))]
        rows, basis = _scored(p, r.f_e, config)
        if r.J_sigma is None:  # STEP 2's one-mass part: the detrended error
            low[i], high[i], h[i] = _LOW, _HIGH, np.asarray(config.polish_steps, dtype=np.float64)
        else:  # the free stage's: its three coordinates too, on the plain error (nothing to detrend)
            low[i], high[i], scale = _free_bounds(p)
            t += [math.log10(r.J_sigma), float(r.M_FC), float(r.mu_F)]
            h[i] = np.concatenate([config.polish_steps, np.asarray(config.polish_free_steps) * scale])
            basis = [(a, b, Q[:, :0]) for a, b, Q in basis]
        theta[i], scored[i] = np.array(t), (rows, basis)
        free[i] = [k for k in range(len(t)) if k != 3 or t[3] > _NO_GAP]
    n_sims = dict.fromkeys(theta, 0)
    cost: dict[int, float] = {}
    start: dict[int, float] = {}
    active, moved = set(theta), set()
    # a model without a gap: the best of a few small gaps starts the polish, with s_N free, where it beats it
    seeds = np.log10(np.asarray(config.polish_gap_seeds, dtype=np.float64))
    asked = {i: np.vstack([t] + [np.concatenate([t[:3], [g], t[4:]]) for g in seeds])
             for i, t in theta.items() if t[3] <= _NO_GAP and seeds.size and config.polish_iterations}
    for i, R in _errors(problems, asked, scored).items():
        n_sims[i] += R.shape[1]
        c = (R * R).sum(0)
        start[i] = float(c[0])  # the chosen model's: what the polished one must beat
        k = int(np.argmin(c))
        if k > 0:
            theta[i], free[i], cost[i] = asked[i][k], list(range(len(theta[i]))), float(c[k])
            moved.add(i)
    for _ in range(config.polish_iterations):
        if not active:
            break
        # the error r and its forward-difference Jacobian J (M x F) at each model, one replay for all
        asked = {i: np.clip(np.vstack([theta[i]] + [theta[i] + h[i][k] * np.eye(len(theta[i]))[k] for k in free[i]]),
                            low[i], high[i]) for i in active}
        trials = {}
        for i, R in _errors(problems, asked, scored).items():
            n_sims[i] += R.shape[1]
            r = R[:, 0]
            cost[i] = float(r @ r)
            start.setdefault(i, cost[i])
            step = asked[i][1:, free[i]].diagonal() - theta[i][free[i]]  # the steps as clipped
            J = (R[:, 1:] - r[:, None]) / np.where(step != 0, step, 1.0)  # M x F
            A, g = J.T @ J, J.T @ r
            D = np.diag(np.maximum(np.diag(A), 1e-12 * max(float(np.diag(A).max()), 1e-300)))
            moves = np.repeat(theta[i][None], len(config.polish_damping), axis=0)  # L x D
            for row, lam in zip(moves, config.polish_damping):
                row[free[i]] += np.linalg.solve(A + lam * D, -g)
            trials[i] = np.clip(moves, low[i], high[i])
        for i, R in _errors(problems, trials, scored).items():
            n_sims[i] += R.shape[1]
            c = (R * R).sum(0)
            k = int(np.argmin(c))
            ratio = float(c[k]) / cost[i] if cost[i] > 0 else 1.0
            if ratio < 1.0:
                theta[i], cost[i] = trials[i][k], float(c[k])
                moved.add(i)
            if ratio > 1.0 - config.polish_tolerance:  # no better, or hardly: done
                active.discard(i)
    won = sorted(i for i in moved if cost[i] < config.polish_win * start[i])
    out = [replace(r, n_sims=r.n_sims + n_sims.get(i, 0)) for i, r in enumerate(chosen)]
    for i, E in _packed_errors(problems, {i: theta[i][None] for i in won}):  # the winners' whole-record error
        t, total = theta[i], float(_detrended_energy(E, _detrend_basis(problems[i].segments))[0])
        s_N = float(10.0 ** t[3]) if t[3] > _NO_GAP else chosen[i].s_N
        one_mass = {} if len(t) == 4 else _one_mass(t)
        out[i] = replace(out[i], **_answer(problems[i], t, s_N), **one_mass, residual=_relative(total, measured[i]),
                         n_sims=out[i].n_sims + 1)
    return out
