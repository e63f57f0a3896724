"""The exploring stages' score: short windows after each torque step (:class:`ScoreWindows`),
each candidate's speed over them replayed from a quasi-static start (:func:`window_speeds`), the
error after its best gain (:func:`score_shape`), many records' candidates side by side
(:func:`score_windows`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

import sim
from sim.replay import replay_speed
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import (DIVERGED, BatchSettings, finite, model_values, pack_indices,
                                                     problem_substeps, replay_drive, sim_params, trend_basis)
from training.identification._refine._space import HIGH, LOW


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
                   windows[:, 0].copy(), level_at(p, windows[:, 0]), np.asarray(lead, dtype=np.int64))


def score_shape(theta: np.ndarray, X: np.ndarray, w: ScoreWindows,
                gain_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The exploration score of the candidates ``theta`` ``C x 4`` whose model speeds over the
    windows ``w`` are ``X`` ``C x J x L`` (:func:`window_speeds`): the detrended error after the
    best gain ``g`` on each candidate's detrended speed, ``||y||^2 - <y, x>^2 / ||x||^2`` (``y``
    measured, ``x`` model), and ``theta`` with ``V_J`` scaled by ``g`` (eq. 1: the oscillation is
    about proportional to ``V_J``; ``g`` kept within ``gain_range``)."""
    X = X.transpose(1, 0, 2)  # J x C x L
    X_r = X - (X @ w.Q) @ w.Q.transpose(0, 2, 1)  # each window detrended (0 past its end)
    xy, xx, yy = np.einsum("jcl,jl->c", X_r, w.y_r), np.einsum("jcl,jcl->c", X_r, X_r), w.yy
    some = xx > 0
    gain = np.where(some, xy / np.maximum(xx, 1e-300), 0.0)
    cost = np.maximum(yy - np.where(some, xy * xy / np.maximum(xx, 1e-300), 0.0), 0.0)
    cost = np.where(gain > 0, cost, yy)  # an inverted oscillation is no match
    scaled = theta.copy()
    scaled[:, 1] += np.log10(np.clip(gain, *gain_range))
    return cost, np.clip(scaled, LOW, HIGH)


def first_samples(segments: np.ndarray, length: int) -> np.ndarray:
    """The first ``length`` samples of each segment ``(L, 2)``."""
    seg = np.asarray(segments, dtype=np.int64)
    return np.stack([seg[:, 0], np.minimum(seg[:, 1], seg[:, 0] + length)], axis=1)


def level_at(p: RefineProblem, k: np.ndarray) -> np.ndarray:
    """The torque reference [Nm] over each sample ``k`` (int array, any shape)."""
    return p.level[np.searchsorted(p.start, k, side="right") - 1]


def window_speeds(items: list[tuple[RefineProblem, np.ndarray, ScoreWindows, bool]], drive: sim.DriveConfig,
                  substeps: int, batch: BatchSettings) -> list[np.ndarray]:
    """Motor speed ``C x J x L`` [rad/s] of each candidate ``theta`` ``C x 4`` of each item
    ``(problem, theta, windows, led)`` over its windows (0 past each window's end; a diverged
    model's reads :data:`DIVERGED` rad/s off the measured), all items on one drive (the items' results do not
    depend on each other), each window simulated on its own from a quasi-static state: the torque
    before it settled, both masses at the measured speed, the shaft twisted by the torque that
    accelerates the load (``J_L a`` plus the load friction, ``a`` the rigid acceleration) over
    ``C_F``, plus ``s`` on the loaded side. With ``led``, a window after a zero-torque section
    starts at that section's start instead (:mod:`._rattle`); those windows run in replays of
    their own per item, at most ``batch.led_samples`` lane-samples each. An oscillation
    still ringing from before a window is not in its start state (the exploring score tolerates
    it; the polish simulates the whole record)."""
    names = sim.ALL_PARAM_NAMES + ("w_M", "dphi", "M_M", "M_new", "M_lead", "lead")
    flat: dict[str, list[np.ndarray]] = {n: [] for n in names}
    led: list[tuple[np.ndarray, dict[str, np.ndarray]] | None] = []  # per item: its plain lanes' mask, its led lanes
    for p, theta, w, with_lead in items:
        C, J = theta.shape[0], w.y.shape[0]
        lead = np.broadcast_to(w.lead if with_lead else np.zeros(J, dtype=np.int64), (C, J))
        first = w.at - lead  # C x J: the first simulated sample
        w_M = p.speed[first]
        M_prev = np.where(first > 0, level_at(p, first - 1), p.level[0])  # C x J (before the record: the hold)
        m = model_values(p, theta)
        dv = sim.two_mass_derived(m["J_sigma"], m["V_J"], m["f_e"], m["d"])
        sgn = np.sign(w_M)
        load = m["M_FC"][:, None] * sgn + max(p.mu_F, 0.0) * w_M + p.M_L0  # C x J: the load's friction and torque
        motor = m["M_FCM"][:, None] * sgn  # the motor's friction
        M_S = dv.J_L[:, None] * (M_prev - motor - load) / m["J_sigma"][:, None] + load  # C x J: rigid motion
        lane = {**{n: np.repeat(v, J) for n, v in m.items()},  # C*J, window index fastest
                "w_M": w_M.reshape(-1), "dphi": (M_S / dv.C_F[:, None] + (m["backlash"] / 2.0)[:, None]
                                                 * np.sign(M_S)).reshape(-1),
                "M_M": M_prev.reshape(-1), "M_new": np.tile(w.M_new, C), "M_lead": level_at(p, first).reshape(-1),
                "lead": lead.reshape(-1)}
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
            step = max(batch.led_lanes, batch.led_samples // length)  # lanes per replay
            X[~plain] = np.concatenate([
                np.take_along_axis(_replay_windows({k: v[a:a + step] for k, v in lanes.items()}, drive, substeps,
                                                   length),
                                   lanes["lead"][a:a + step, None] + np.arange(L_w), 1) for a in range(0, n, step)])
        X = X.reshape(C, J, L_w)  # C*J -> C x J x L
        speeds.append((X if np.isfinite(X.sum()) else w.y + finite(X - w.y)) * w.inside)
    return speeds


def _replay_windows(lanes: dict[str, np.ndarray], drive: sim.DriveConfig, substeps: int, length: int) -> np.ndarray:
    """Motor speed ``lanes x length`` [rad/s] of :func:`window_speeds`' lanes: each from its start
    state, at ``M_lead`` over its first ``lead`` samples (a zero-torque section, around a held
    axis's hold) and at ``M_new`` after."""
    state = {"w_M": lanes["w_M"], "w_L": lanes["w_M"], "dphi": lanes["dphi"], "M_M": lanes["M_M"]}
    start = np.stack([np.zeros_like(lanes["lead"]), lanes["lead"]], 1)  # lanes x 2
    level = np.stack([np.where(lanes["lead"] > 0, lanes["M_lead"], lanes["M_new"]), lanes["M_new"]], 1)
    return replay_speed(sim_params(lanes), drive, torch.from_numpy(start), torch.from_numpy(level), length,
                        quantize=False, state=state, substeps=substeps).numpy()  # lanes x length (a view)


def score_windows(problems: list[RefineProblem], windows: list[ScoreWindows], led: bool,
                  gain_range: tuple[float, float], batch: BatchSettings,
                  asked: dict[int, np.ndarray]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The window score (:func:`score_shape`) of the candidates ``asked[i]`` ``C_i x 4`` of each
    problem ``i`` over its ``windows[i]`` (``led``: see :func:`window_speeds`), with the candidates
    as scored: the records on one drive, substep count and similar window length go to the
    simulator in one call (:func:`pack_indices`), so that the per-call costs are paid once per
    batch, not once per record (a result does not depend on its pack)."""
    todo = sorted(asked)
    substeps = [problem_substeps(problems[i], asked[i]) for i in todo]
    sizes = [len(asked[i]) * windows[i].y.shape[0] for i in todo]
    packs = pack_indices([problems[i] for i in todo], sizes, substeps, [windows[i].y.shape[1] for i in todo],
                         max_models=batch.window_models, min_length_ratio=batch.length_ratio)
    out = {}
    for pack in packs:
        ids = [todo[k] for k in pack]
        X = window_speeds([(problems[i], asked[i], windows[i], led) for i in ids], replay_drive(problems[ids[0]]),
                          substeps[pack[0]], batch)
        for i, x in zip(ids, X):
            out[i] = score_shape(asked[i], x, windows[i], gain_range)
    return out
