"""The free one-mass stage: ``J_sigma``, ``M_FC`` and ``mu_F`` searched with the two-mass model
where STEP 2's one-mass fit cannot be trusted (:class:`FreeSettings`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

import sim
from training._settings import (AT_LEAST_ONE, COUNT, NON_NEGATIVE, NON_NEGATIVE_OR_INF, POSITIVE, REAL, Values,
                                check_settings)
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._one_mass import SECTION_PERIODS
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import DIVERGED, simulate
from training.identification._refine._search import SearchSettings, cem_one, own_rng
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage


@dataclass(frozen=True)
class FreeSettings:
    """Where STEP 2 flagged its fit (very soft mechanics whose test sections are shorter than an
    oscillation period) or the shortest section holds fewer than ``periods`` periods of the chosen
    model (a test whose time scale ``J_sigma w_max / M*`` is a fraction of the period ends before
    the load follows, and STEP 2's fit, unflagged, reads about the motor's inertia: 0.15-0.2 x
    ``J_sigma`` on the servo of the drive matrix), ``J_sigma``, ``M_FC`` and ``mu_F`` join the search
    (:data:`FREE_COORDINATES`), scored by the plain error over the whole record. Their bounds follow
    the record's own scales: ``J_sigma`` within ``J_sigma_decades`` of STEP 2's, ``M_FC`` up to
    ``M*``, ``mu_F`` up to ``M* / w_max``. Each model is scored at its best ``J_sigma``, exactly
    (:func:`scaled_fit`), so ``J_sigma`` needs no grid (a grid over it left the search in a broad
    valley beside the needle in ``f_e``). Grids over ``f_e`` (``f_e_octaves`` around the centre in
    ``f_e_per_octave`` steps an octave: such a mechanic is softer than it looks, and the
    whole-record error is needle-sharp in ``f_e``), ``V_J`` and the friction around the chosen
    model and the maps' answer, then ``rounds`` rounds: one search with ``V_J`` x ``V_J_factors``
    of the centre's, one (a random stream of its own) with ``envelope_V_J`` values over the drive
    envelope's range, for a STEP 2 that read the motor alone (a load 3-5 x the motor lies beyond
    the first). The free model replaces the chosen one only below ``win`` x the chosen one's plain
    squared error with STEP 2's own one-mass values, uncapped (against the capped friction, a 2 Hz
    model 3 x worse than the chosen 37 Hz one would win on a commissioning plant with motor
    friction; the wins measured were 10-60 x lower, a narrow one a wrong mode)."""

    periods: float = SECTION_PERIODS  # runs where a section holds fewer periods of the chosen model (STEP 2's rule)
    rounds: int = 5  # cross-entropy rounds of each search
    # first spread of log10 J_sigma, M_FC / M*, mu_F w_max / M* (in units of their scales)
    spread: tuple[float, float, float] = (0.1, 0.01, 0.01)
    win: float = 0.25  # replaces the chosen model only below this ratio of its error
    J_sigma_decades: float = 2.0  # J_sigma bounded within this many decades of STEP 2's
    # the grids start from STEP 2's friction capped at this x its bounds (a short test's is 10-50 x off) ...
    friction_cap: float = 0.1
    friction_start: tuple[float, float] = (0.025, 0.01)  # ... or from M_FC, mu_F at this x their bounds
    f_e_octaves: tuple[int, int] = (-4, 1)  # the grids' f_e from 2^low to 2^high x the centre's ...
    f_e_per_octave: int = 4  # ... in this many steps an octave
    V_J_factors: tuple[float, ...] = (0.5, 1.0, 2.0)  # the first search's V_J x the centre's
    envelope_V_J: int = 5  # the second search's V_J values over the drive envelope's range
    stream: int = 3  # the second search's random stream

    def __post_init__(self) -> None:
        check_settings(self, {
            "periods": NON_NEGATIVE_OR_INF, "rounds": COUNT, "spread": Values(NON_NEGATIVE, 3, "log10 J_sigma, M_FC, mu_F"),
            "win": NON_NEGATIVE_OR_INF, "J_sigma_decades": NON_NEGATIVE_OR_INF, "friction_cap": NON_NEGATIVE_OR_INF,
            "friction_start": Values(NON_NEGATIVE, 2, "M_FC, mu_F"), "f_e_octaves": Values(REAL, 2, "lowest and highest octave"),
            "f_e_per_octave": AT_LEAST_ONE, "V_J_factors": Values(POSITIVE), "envelope_V_J": AT_LEAST_ONE, "stream": COUNT})


@dataclass(frozen=True)
class FreeFit:
    """The free stage's answer: ``theta``, the chosen model (4) where it lost, else the winner over
    :data:`FREE_COORDINATES` (7); ``n_sims`` the models it simulated."""

    theta: np.ndarray
    n_sims: int


def frees(p: RefineProblem, theta: np.ndarray, settings: FreeSettings) -> bool:
    """Whether the free stage runs on ``p`` whose chosen model is ``theta``: STEP 2 flagged its
    fit, or the shortest test section holds fewer than ``settings.periods`` periods of the model's
    oscillation (STEP 2's one-mass fit then sees the motor's inertia)."""
    sections = np.diff(p.start[1:])  # the six sections' lengths [samples]
    return p.free_one_mass or bool(sections.size and sections.min() * p.T_s * 10.0 ** theta[0] < settings.periods)


def free_one_mass(p: RefineProblem, best: np.ndarray, settings: FreeSettings, search: SearchSettings, seed: int,
                  rng: np.random.Generator, drive: sim.DriveConfig) -> FreeFit:
    """The free stage of ``p`` from its chosen model ``best`` (4), its first search drawing from
    ``rng``, its second from its own stream of ``seed``."""
    low, high, scale = free_bounds(p, settings)
    plain = functools.partial(scaled_fit, p, drive, low, high)
    friction = np.clip([p.M_FC, p.mu_F], 0.0, high[5:])  # STEP 2's
    chosen = np.concatenate([best, [math.log10(p.J_sigma)], friction])  # what the free model must beat
    # the grids start from STEP 2's friction capped (a short test's can be 10-50 x off)
    one_mass = np.array([math.log10(p.J_sigma), *np.minimum(friction, settings.friction_cap * high[5:])])
    start = np.concatenate([best, one_mass])
    # grids over f_e, V_J (the centre's x V_J_factors; the envelope's range) and friction; J_sigma: scaled_fit
    M_FC_start, mu_F_start = settings.friction_start
    pairs = np.array([one_mass[1:], [M_FC_start * high[5], mu_F_start * high[6]]])  # friction: STEP 2's; the start's
    lowest, highest = settings.f_e_octaves
    n = settings.f_e_per_octave
    f_f = np.log10(2.0) * np.arange(lowest * n, highest * n + 1) / n  # f_e x 2^lowest .. 2^highest
    around, held = [chosen[None], start[None]], []
    for center in (start, np.concatenate([np.clip(p.theta, LOW, HIGH), one_mass])):  # chosen model, maps' answer
        for out, V_J in ((around, center[1] + np.log10(settings.V_J_factors)),
                         (held, np.log10(np.geomspace(*SPEC_ENVELOPE["V_J"], settings.envelope_V_J)))):
            f, v, pick = (a.reshape(-1) for a in np.meshgrid(center[0] + f_f, V_J, [0, 1], indexing="ij"))
            grid = np.repeat(center[None], f.size, axis=0)  # G x 7
            grid[:, 0], grid[:, 1], grid[:, 5:] = f, v, pairs[pick]
            out.append(grid)
    spread = np.concatenate([search.spread, np.asarray(settings.spread) * scale])
    found = []  # each grid with its own search: one best model does not cover both kinds of start
    for grid, stream in ((around, rng), (held, own_rng(seed, settings.stream))):
        cost, theta = plain(np.clip(np.concatenate(grid), low, high))
        scored = cem_one(theta, cost, settings.rounds, spread, search, stream, plain, low, high)
        found.append((scored.theta, scored.cost))
    theta, cost = (np.concatenate(v) for v in zip(*found))
    k = int(np.argmin(cost))
    to_beat = float((simulate(p, chosen[None], drive) ** 2).sum())  # the chosen model with STEP 2's values
    return FreeFit(theta[k] if cost[k] < settings.win * to_beat else best, len(cost) + 1)


def scaled_fit(p: RefineProblem, drive: sim.DriveConfig, low: np.ndarray, high: np.ndarray,
               theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain squared speed error ``C`` of each free model ``theta`` ``C x 7`` at its best
    scale, and the models so scaled. The scale is exact: ``J_sigma / k`` and ``mu_F / k`` with
    ``f_e``, ``V_J``, ``d``, ``s_N`` and ``M_FC`` unchanged turn the replayed motor speed into ``k``
    times itself (the gap ``2s = 2 s_N M_N / C_F`` and all speeds and angles scale by ``k``), so one
    replay per model gives the least-squares ``k`` (kept within the bounds ``low``/``high``)."""
    E = simulate(p, theta, drive)  # N x C
    y = E + p.speed[:, None]  # the models' speeds
    yy = (y * y).sum(0)
    k = np.where(yy > 0, (y * p.speed[:, None]).sum(0) / np.where(yy > 0, yy, 1.0), 1.0)
    k_low = np.maximum(10.0 ** (theta[:, 4] - high[4]), theta[:, 6] / high[6])
    k_high = 10.0 ** (theta[:, 4] - low[4])
    k = np.where(np.abs(E).max(0) < DIVERGED, np.clip(k, k_low, k_high), 1.0)  # a diverged model stays
    scaled = theta.copy()
    scaled[:, 4] -= np.log10(k)
    scaled[:, 6] /= k
    return ((k * y - p.speed[:, None]) ** 2).sum(0), scaled


def free_bounds(p: RefineProblem, settings: FreeSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The free stage's bounds over :data:`FREE_COORDINATES` (``J_sigma`` within
    ``settings.J_sigma_decades`` of STEP 2's, ``M_FC`` from 0 to the test's ``M*``, ``mu_F`` from 0
    to ``M* / w_max``) and the scales of its three coordinates (1, ``M*``, ``M* / w_max``)."""
    M_star = p.M_star
    w_max = max(float(np.abs(p.speed).max()), 1e-9)  # (a record at rest)
    J = math.log10(p.J_sigma)
    scale = np.array([1.0, M_star, M_star / w_max])
    decades = settings.J_sigma_decades
    return (np.concatenate([LOW, [J - decades, 0.0, 0.0]]),
            np.concatenate([HIGH, [J + decades, M_star, M_star / w_max]]), scale)


def one_mass_values(theta: np.ndarray) -> dict[str, float]:
    """The :class:`Refined` one-mass values of the free stage's model ``theta`` (7)."""
    return {"J_sigma": float(10.0 ** theta[4]), "M_FC": float(theta[5]), "mu_F": float(theta[6])}


STAGE = Stage("free", "STEP 2 flagged its fit, or a test section holds fewer than `periods` of the chosen model",
              FreeSettings, free_one_mass)
