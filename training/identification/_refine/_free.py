"""The free one-mass stage: ``J_sigma``, ``M_FC`` and ``mu_F`` searched with the two-mass model
where STEP 2's one-mass fit cannot be trusted (:class:`RefineConfig`)."""

from __future__ import annotations

import functools
import math

import numpy as np

import sim
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._refine._config import HIGH, LOW, RefineConfig
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import simulate
from training.identification._refine._search import cem, own_rng, run

_FREE_J_SIGMA = 2.0  # the free J_sigma within this many decades of STEP 2's


def short_sections(p: RefineProblem, theta: np.ndarray, config: RefineConfig) -> bool:
    """Whether the shortest test section of ``p`` holds fewer than ``config.free_periods`` periods
    of the model ``theta``'s oscillation (STEP 2's one-mass fit then sees the motor's inertia)."""
    sections = np.diff(p.start[1:])  # the six sections' lengths [samples]
    return bool(sections.size and sections.min() * p.T_s * 10.0 ** theta[0] < config.free_periods)


def free_one_mass(p: RefineProblem, best: np.ndarray, config: RefineConfig, rng: np.random.Generator,
                  drive: sim.DriveConfig) -> tuple[np.ndarray, int]:
    """The free stage (see :class:`RefineConfig`): ``best`` (4) or the winner over
    :data:`FREE_COORDINATES` (7), and the number of simulated models."""
    low, high, scale = free_bounds(p)
    plain = functools.partial(scaled_fit, p, drive, low, high)
    friction = np.clip([p.M_FC, p.mu_F], 0.0, high[5:])  # STEP 2's
    chosen = np.concatenate([best, [math.log10(p.J_sigma)], friction])  # what the free model must beat
    # the grids start from STEP 2's friction capped at a tenth of its bounds (a short test's can be 10-50 x off)
    one_mass = np.array([math.log10(p.J_sigma), *np.minimum(friction, 0.1 * high[5:])])
    start = np.concatenate([best, one_mass])
    # grids over f_e, V_J (the centre's x 0.5, 1, 2; SPEC 3.1's range) and friction; J_sigma: scaled_fit
    pairs = np.array([one_mass[1:], [0.025 * high[5], 0.01 * high[6]]])  # friction: STEP 2's; 2.5 %, 1 %
    f_f = np.log10(2.0) * np.arange(-16, 5) / 4.0  # f_e x 1/16 .. 2 in steps of 2^0.25
    around, held = [chosen[None], start[None]], []
    for center in (start, np.concatenate([np.clip(p.theta, LOW, HIGH), one_mass])):  # chosen model, maps' answer
        for out, V_J in ((around, center[1] + np.log10([0.5, 1.0, 2.0])),
                         (held, np.log10(np.geomspace(*SPEC_ENVELOPE["V_J"], 5)))):
            f, v, pick = (a.reshape(-1) for a in np.meshgrid(center[0] + f_f, V_J, [0, 1], indexing="ij"))
            grid = np.repeat(center[None], f.size, axis=0)  # G x 7
            grid[:, 0], grid[:, 1], grid[:, 5:] = f, v, pairs[pick]
            out.append(grid)
    spread = np.concatenate([config.spread, np.asarray(config.free_spread) * scale])
    found = []  # each grid with its own search: one best model does not cover both kinds of start
    for grid, stream in ((around, rng), (held, own_rng(config, 3))):
        cost, theta = plain(np.clip(np.concatenate(grid), low, high))
        found.append(run(cem(theta, cost, config.free_rounds, spread, config, stream, low, high), plain))
    theta, cost = (np.concatenate(v) for v in zip(*found))
    k = int(np.argmin(cost))
    # a clear win only (measured: 10-60 x lower on soft mechanics; a narrow one was a wrong mode)
    to_beat = float((simulate(p, chosen[None], drive) ** 2).sum())  # the chosen model with STEP 2's values
    return (theta[k] if cost[k] < config.free_win * to_beat else best), len(cost) + 1


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
    k = np.where(np.abs(E).max(0) < 1e6, np.clip(k, k_low, k_high), 1.0)  # a diverged model stays
    scaled = theta.copy()
    scaled[:, 4] -= np.log10(k)
    scaled[:, 6] /= k
    return ((k * y - p.speed[:, None]) ** 2).sum(0), scaled


def free_bounds(p: RefineProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The free stage's bounds over :data:`FREE_COORDINATES` (``J_sigma`` within
    :data:`_FREE_J_SIGMA` decades of STEP 2's, ``M_FC`` from 0 to the test's ``M*``, ``mu_F`` from 0
    to ``M* / w_max``) and the scales of its three coordinates (1, ``M*``, ``M* / w_max``)."""
    M_star, w_max = float(np.abs(p.level).max()), max(float(np.abs(p.speed).max()), 1e-9)  # (a record at rest)
    J = math.log10(p.J_sigma)
    scale = np.array([1.0, M_star, M_star / w_max])
    return (np.concatenate([LOW, [J - _FREE_J_SIGMA, 0.0, 0.0]]),
            np.concatenate([HIGH, [J + _FREE_J_SIGMA, M_star, M_star / w_max]]), scale)


def one_mass_values(theta: np.ndarray) -> dict[str, float]:
    """The :class:`Refined` one-mass values of the free stage's model ``theta`` (7)."""
    return {"J_sigma": float(10.0 ** theta[4]), "M_FC": float(theta[5]), "mu_F": float(theta[6])}
