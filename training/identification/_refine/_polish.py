"""The polish: Levenberg-Marquardt steps on the whole record from the chosen model
(:class:`RefineConfig`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from training.identification._refine._config import HIGH, LOW, NO_GAP, RefineConfig
from training.identification._refine._free import free_bounds, one_mass_values
from training.identification._refine._problem import RefineProblem, Refined
from training.identification._refine._replay import (detrend_basis, detrended, detrended_energy, packed_errors,
                                                     relative_rms)


def _scored(p: RefineProblem, f_e: float, config: RefineConfig) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """The samples the polish scores (every ``k``-th of each segment: see :class:`RefineConfig`)
    and their detrending basis, segments end to end."""
    k = max(1, int(1.0 / (f_e * p.T_s * config.polish_samples_per_period)))
    rows = [np.arange(a, b, k) for a, b in np.asarray(p.segments, dtype=np.int64).tolist() if b > a]
    ends = np.cumsum([0] + [len(r) for r in rows])
    return np.concatenate(rows), detrend_basis(np.stack([ends[:-1], ends[1:]], axis=1))


def _errors(problems: list[RefineProblem], asked: dict[int, np.ndarray],
            scored: dict[int, tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]]) -> dict[int, np.ndarray]:
    """The detrended errors ``M_i x C_i`` over the samples ``scored[i]`` of the candidates
    ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``."""
    return {i: detrended(E, scored[i][1])
            for i, E in packed_errors(problems, asked, {i: rows for i, (rows, _) in scored.items()})}


def polish(problems: list[RefineProblem], chosen: list[Refined], measured: list[float],
           config: RefineConfig) -> list[Refined]:
    """Each ``chosen[i]`` polished on the whole record (see :class:`RefineConfig`; ``measured[i]``
    the measured speed's own detrended energy), the searches side by side: one replay per
    iteration and step kind for the problems on one drive and substep count; ``residual`` and
    ``n_sims`` updated."""
    theta, free, scored, low, high, h = {}, {}, {}, {}, {}, {}
    for i, (p, r) in enumerate(zip(problems, chosen)):
        t = [math.log10(r.f_e), math.log10(r.V_J), r.d, math.log10(max(r.s_N, 10.0 ** LOW[3]))]
        rows, basis = _scored(p, r.f_e, config)
        if r.J_sigma is None:  # STEP 2's one-mass part: the detrended error
            low[i], high[i], h[i] = LOW, HIGH, np.asarray(config.polish_steps, dtype=np.float64)
        else:  # the free stage's: its three coordinates too, on the plain error (nothing to detrend)
            low[i], high[i], scale = free_bounds(p)
            t += [math.log10(r.J_sigma), float(r.M_FC), float(r.mu_F)]
            h[i] = np.concatenate([config.polish_steps, np.asarray(config.polish_free_steps) * scale])
            basis = [(a, b, Q[:, :0]) for a, b, Q in basis]
        theta[i], scored[i] = np.array(t), (rows, basis)
        free[i] = [k for k in range(len(t)) if k != 3 or t[3] > NO_GAP]
    n_sims = dict.fromkeys(theta, 0)
    cost: dict[int, float] = {}
    start: dict[int, float] = {}
    active, moved = set(theta), set()
    # a model without a gap: the best of a few small gaps starts the polish, with s_N free, where it beats it
    seeds = np.log10(np.asarray(config.polish_gap_seeds, dtype=np.float64))
    asked = {i: np.vstack([t] + [np.concatenate([t[:3], [g], t[4:]]) for g in seeds])
             for i, t in theta.items() if t[3] <= NO_GAP and seeds.size and config.polish_iterations}
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
    for i, E in packed_errors(problems, {i: theta[i][None] for i in won}):  # the winners' whole-record error
        t, total = theta[i], float(detrended_energy(E, detrend_basis(problems[i].segments))[0])
        s_N = float(10.0 ** t[3]) if t[3] > NO_GAP else chosen[i].s_N
        one_mass = {} if len(t) == 4 else one_mass_values(t)
        out[i] = replace(out[i], **problems[i].answer(t, s_N), **one_mass, residual=relative_rms(total, measured[i]),
                         n_sims=out[i].n_sims + 1)
    return out
