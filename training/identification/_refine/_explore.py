"""The exploring stage: cross-entropy searches scored on short windows after each torque step,
with the rescue, the climb and the rattle (:class:`RefineConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

import sim
from sim.replay import replay_speed
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._refine._config import HIGH, LOW, RefineConfig
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import (finite, model_values, pack_indices, problem_substeps,
                                                     quantization_energy, replay_drive, sim_params, trend_basis)
from training.identification._refine._search import Search, TaggedSearch, cem, own_rng, product_grid, tagged


@dataclass(frozen=True)
class ScoreWindows:
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
    def of(cls, p: RefineProblem, windows: np.ndarray, lead: np.ndarray) -> "ScoreWindows":
        first, lengths = windows[:, 0].tolist(), (windows[:, 1] - windows[:, 0]).tolist()
        J, L = len(first), max(lengths)
        y, Q = np.zeros((J, L)), np.zeros((J, L, 3))
        for j, (a, n) in enumerate(zip(first, lengths)):
            y[j, :n] = p.speed[a:a + n]
            if n > 0:
                Q[j, :n, : min(3, n)] = trend_basis(n)
        y_r = y - (Q @ (y[:, None, :] @ Q).transpose(0, 2, 1))[:, :, 0]  # J x L
        return cls(y, Q, y_r, float((y_r * y_r).sum()), (np.arange(L) < np.array(lengths)[:, None]).astype(np.float64),
                   windows[:, 0].copy(), _level_at(p, windows[:, 0]), np.asarray(lead, dtype=np.int64))


def score_shape(theta: np.ndarray, X: np.ndarray, w: ScoreWindows) -> tuple[np.ndarray, np.ndarray]:
    """The exploration score of the candidates ``theta`` ``C x 4`` whose model speeds over the
    windows ``w`` are ``X`` ``C x J x L`` (:func:`window_speeds`): the detrended error after the
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
    return cost, np.clip(scaled, LOW, HIGH)


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


def window_speeds(items: list[tuple[RefineProblem, np.ndarray, ScoreWindows, bool]], drive: sim.DriveConfig,
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
        m = model_values(p, theta)
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
                np.take_along_axis(_replay_windows({k: v[a:a + step] for k, v in lanes.items()}, drive, substeps,
                                                   length),
                                   lanes["lead"][a:a + step, None] + np.arange(L_w), 1) for a in range(0, n, step)])
        X = X.reshape(C, J, L_w)  # C*J -> C x J x L
        speeds.append((X if np.isfinite(X.sum()) else w.y + finite(X - w.y)) * w.inside)
    return speeds


def _replay_windows(lanes: dict[str, np.ndarray], drive: sim.DriveConfig, substeps: int, length: int) -> np.ndarray:
    """Motor speed ``lanes x length`` [rad/s] of :func:`window_speeds`' lanes: each from its start
    state, at 0 over its first ``lead`` samples (a zero-torque section) and at ``M_new`` after."""
    state = {"w_M": lanes["w_M"], "w_L": lanes["w_M"], "dphi": lanes["dphi"], "M_M": lanes["M_M"]}
    start = np.stack([np.zeros_like(lanes["lead"]), lanes["lead"]], 1)  # lanes x 2
    level = np.stack([np.where(lanes["lead"] > 0, 0.0, lanes["M_new"]), lanes["M_new"]], 1)
    return replay_speed(sim_params(lanes), drive, torch.from_numpy(start), torch.from_numpy(level), length,
                        quantize=False, state=state, substeps=substeps).numpy()  # lanes x length (a view)


def explore_windows(p: RefineProblem, config: RefineConfig) -> ScoreWindows:
    """The exploring stage's windows of ``p``: ``window_periods`` at the start's ``f_e`` (at
    least 8 samples, at most ``window_max`` or ``window_samples``, whichever is longer) after each
    torque step, each after a zero-torque section with that section's length as its lead."""
    period = 1.0 / (10.0 ** np.clip(p.theta[0], LOW[0], HIGH[0]) * p.T_s)  # samples per period at the start's f_e
    seg = np.asarray(p.segments, dtype=np.int64)
    a = seg[:, 0]
    after_zero = (np.arange(len(a)) > 0) & (_level_at(p, a - 1) == 0.0) & (_level_at(p, a) != 0.0)
    lead = np.where(after_zero, a - np.concatenate([[0], a[:-1]]), 0)  # the zero section's length
    longest = max(config.window_max / p.T_s, config.window_samples)  # [samples]
    return ScoreWindows.of(p, _windows(seg, max(8, int(round(min(config.window_periods * period, longest))))), lead)


def _explore(p: RefineProblem, windows: ScoreWindows, config: RefineConfig,
             rng: np.random.Generator) -> TaggedSearch:
    """The exploring stage of ``p`` (``windows``: :func:`explore_windows`) as a
    :data:`TaggedSearch` scored by :func:`score_shape`; returns the finalists ``F x 4`` (the
    maps' answer; the elites of the search that won, the exploration, the rescue or the climb, and
    the exploration's too where the rescue won; the rattle's best where it ran: see
    :class:`RefineConfig`) and the number of models explored."""
    theta0 = np.clip(np.asarray(p.theta, dtype=np.float64), LOW, HIGH)
    theta, cost = yield from tagged(_search(theta0, config, rng), False)
    explored = len(cost)
    finalists = [theta0[None]]
    if _rescues(p, windows, float(cost.min()), config):
        theta_g, cost_g = yield from tagged(_survey(p, theta0, config, own_rng(config, 1)), False)
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
        theta_up, cost_up = yield from tagged(_search(np.clip(up, LOW, HIGH), far, own_rng(config, 2)), False)
        explored += len(cost_up)
        if cost_up.min() < config.switch_win * cost.min():
            theta, cost = theta_up, cost_up
            best = theta[int(np.argmin(cost))]
    elites = theta[np.argsort(cost)[: config.elites]]
    finalists.append(elites)
    if 10.0 ** best[3] >= config.rattle_s_N and windows.lead.any():
        again = np.concatenate([elites, np.repeat(best[None], len(config.rattle_shift), axis=0)])
        again[-len(config.rattle_shift):, 3] += config.rattle_shift
        cost_r, theta_r = yield np.clip(again, LOW, HIGH), True
        theta_r, cost_r = yield from tagged(cem(theta_r, cost_r, config.rattle_rounds,
                                                np.asarray(config.spread, dtype=np.float64), config, rng), True)
        explored += len(cost_r)
        finalists.append(theta_r[np.argsort(cost_r)[: config.rattle_finalists]])
    return np.concatenate(finalists), explored


def _search(theta0: np.ndarray, config: RefineConfig, rng: np.random.Generator) -> Search:
    """One exploration from ``theta0`` (4): the grid around it, then the cross-entropy rounds;
    returns every scored model and its cost."""
    grid = np.repeat(theta0[None], config.grid_f_e * len(config.grid_s_N), axis=0)  # G x 4
    grid[:, 0] += np.repeat(np.linspace(-config.grid_span, config.grid_span, config.grid_f_e), len(config.grid_s_N))
    grid[:, 3] = np.tile(_grid_s_N(theta0, config), config.grid_f_e)
    cost, theta = yield np.clip(grid, LOW, HIGH)
    return (yield from cem(theta, cost, config.rounds, np.asarray(config.spread, dtype=np.float64), config, rng))


def _grid_s_N(theta0: np.ndarray, config: RefineConfig) -> list[float]:
    """log10 ``s_N`` of the grids: ``config.grid_s_N``, its 0 standing for the start's (``theta0``)."""
    return [math.log10(v) if v > 0 else float(theta0[3]) for v in config.grid_s_N]


def _rescues(p: RefineProblem, windows: ScoreWindows, cost: float, config: RefineConfig) -> bool:
    """Whether the exploration of ``p``, whose best model left ``cost`` of the energy over its
    ``windows``, is followed by the rescue's survey (see :class:`RefineConfig`)."""
    noise = quantization_energy(p, int(windows.inside.sum()))
    return cost > config.rescue_above * windows.yy and windows.yy >= config.rescue_signal * noise


def _survey(p: RefineProblem, theta0: np.ndarray, config: RefineConfig, rng: np.random.Generator) -> Search:
    """The rescue's search over the whole range (see :class:`RefineConfig`), ``d`` and the
    start's ``s_N`` from ``theta0`` (4); returns every scored model and its cost."""
    f_e = np.geomspace(SPEC_ENVELOPE["f_e"][0], min(10.0 ** HIGH[0], 0.5 / p.T_s), config.rescue_grid_f_e)
    cost, theta = yield np.clip(product_grid(f_e, config.rescue_V_J, float(theta0[2]), _grid_s_N(theta0, config)),
                                LOW, HIGH)
    return (yield from cem(theta, cost, config.far_rounds, np.asarray(config.spread, dtype=np.float64), config, rng))


def _climbs(p: RefineProblem, theta0: np.ndarray, best: np.ndarray, config: RefineConfig) -> bool:
    """Whether the exploration of ``p`` from ``theta0`` climbs on from its ``best`` model (see
    :class:`RefineConfig`)."""
    bandwidth = 1.0 / (2.0 * math.pi * p.T_Ei)
    return bool(10.0 ** best[3] >= sim.S_N_ELASTIC and best[0] - theta0[0] >= config.climb_after
                and 10.0 ** theta0[0] >= config.climb_above * bandwidth)


def explore_all(problems: list[RefineProblem], config: RefineConfig,
                rngs: list[np.random.Generator]) -> list[tuple[np.ndarray, int]]:
    """The finalists of each problem and the number of models explored (:func:`_explore`), the
    searches run side by side: each step's candidates of every problem on one drive, substep count
    and similar window length go to the simulator in one call (:func:`pack_indices`), so that the
    per-call costs are paid once per batch, not once per record."""
    windows = [explore_windows(p, config) for p in problems]
    searches = [_explore(p, w, config, rng) for p, w, rng in zip(problems, windows, rngs)]
    asked = {i: next(s) for i, s in enumerate(searches)}
    explored: list[tuple[np.ndarray, int]] = [(np.empty(0), 0)] * len(problems)
    while asked:
        todo = sorted(asked)
        substeps = [problem_substeps(problems[i], asked[i][0]) for i in todo]
        sizes = [len(asked[i][0]) * windows[i].y.shape[0] for i in todo]
        packs = pack_indices([problems[i] for i in todo], sizes, substeps, [windows[i].y.shape[1] for i in todo],
                             max_models=4096)
        for pack in packs:
            ids = [todo[k] for k in pack]
            X = window_speeds([(problems[i], asked[i][0], windows[i], asked[i][1]) for i in ids],
                              replay_drive(problems[ids[0]]), substeps[pack[0]])
            for i, x in zip(ids, X):
                try:
                    asked[i] = searches[i].send(score_shape(asked[i][0], x, windows[i]))
                except StopIteration as done:
                    explored[i] = done.value
                    del asked[i]
    return explored
