"""The whole-record error of candidate models: the record's torque reference replayed through
each (:func:`sim.replay.replay_speed`, many records and models per call), less the measured speed,
with each section's quadratic trend removed."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

import sim
from sim.replay import replay_speed
from training._settings import AT_LEAST_ONE, POSITIVE_OR_INF, SHARE, check_settings
from training.identification._refine._problem import RefineProblem

#: The speed error [rad/s] a diverged model's samples read (NaN, +-inf), and the bound above which
#: a model counts as diverged.
DIVERGED = 1e6


@dataclass(frozen=True)
class Accuracy:
    """How finely the refinement's replays integrate: RK4 substeps per sample such that
    ``w_0 dt <= w_0_dt`` for the stiffest model of a call (frequency error < 0.1 %), and ``dt <=
    T_Ei/2`` (:func:`sim.rk4_substeps`). One setting for every stage: models compared in one
    stage and the next must be replayed alike."""

    w_0_dt: float = 0.5  # the stiffest model's w_0 times the substep at most
    minimum: int = 1  # substeps per sample at least

    def __post_init__(self) -> None:
        check_settings(self, {"w_0_dt": POSITIVE_OR_INF, "minimum": AT_LEAST_ONE})


#: The refinement's replay accuracy (:class:`Accuracy`).
ACCURACY = Accuracy()


@dataclass(frozen=True)
class BatchSettings:
    """How many models and samples one replay call takes: what the wall time and the memory
    depend on, never an answer (records run packed only with records on the same drive and
    substep count, and a result does not depend on its pack)."""

    window_models: int = 4096  # exploring windows: simulated windows per replay call at most
    record_models: int = 256  # whole records (choose, polish): models per replay call at most
    length_ratio: float = 0.6  # records packed only within this ratio of the pack's longest (the others idle)
    # window lanes x samples per replay of led windows at most (float32: 64 MB; a zero-torque section
    # that ran to its 10 s timeout at 62.5 us is 160 000 samples long) ...
    led_samples: int = 16 * 2**20
    led_lanes: int = 64  # ... but at least this many lanes per replay

    def __post_init__(self) -> None:
        check_settings(self, {"window_models": AT_LEAST_ONE, "record_models": AT_LEAST_ONE, "length_ratio": SHARE,
                              "led_samples": AT_LEAST_ONE, "led_lanes": AT_LEAST_ONE})


def detrend_basis(segments: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """Per segment ``(a, b, Q)``: orthonormal ``L x 3`` basis of the quadratic trends on it."""
    return [(a, b, trend_basis(b - a)) for a, b in np.asarray(segments, dtype=np.int64).tolist() if b > a]


@functools.lru_cache(maxsize=4096)
def trend_basis(L: int) -> np.ndarray:
    """Orthonormal ``L x min(3, L)`` basis of the polynomials of degree < 3 on ``L`` samples (read-only)."""
    tau = np.linspace(-1.0, 1.0, L)
    V = np.stack([np.ones(L), tau, tau * tau], axis=1)[:, : min(3, L)]  # L x 3
    Q = np.linalg.qr(V)[0]
    Q.flags.writeable = False  # shared by every caller through the cache
    return Q


def detrended_energy(E: np.ndarray, basis: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
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


def finite(E: np.ndarray) -> np.ndarray:
    """``E`` with a diverged model's errors (NaN, +-inf) read as +-1e6 rad/s (a finite sum: none)."""
    return E if np.isfinite(E.sum()) else np.nan_to_num(E, nan=DIVERGED, posinf=DIVERGED, neginf=-DIVERGED)


def model_values(p: RefineProblem, theta: np.ndarray) -> dict[str, np.ndarray]:
    """The :data:`sim.ALL_PARAM_NAMES` values ``C`` of the candidates ``theta`` ``C x 4`` or ``C x 7``
    (backlash ``2s = 2 s_N M_N / C_F``; the problem's ``M_L0``, ``M_FCM`` and ``mu_FM``)."""
    C = theta.shape[0]
    return {"J_sigma": p.J_sigma_of(theta), "V_J": 10.0 ** theta[:, 1], "f_e": 10.0 ** theta[:, 0], "d": theta[:, 2],
            "backlash": sim.gap_width(10.0 ** theta[:, 3], p.M_N, p.C_F(theta)),
            "M_FC": theta[:, 5] if theta.shape[1] > 4 else np.full(C, max(p.M_FC, 0.0)),
            "mu_F": theta[:, 6] if theta.shape[1] > 4 else np.full(C, max(p.mu_F, 0.0)),
            "M_L0": np.full(C, p.M_L0), "M_FCM": np.full(C, max(p.M_FCM, 0.0)), "mu_FM": np.full(C, max(p.mu_FM, 0.0))}


def sim_params(values: dict[str, np.ndarray]) -> sim.TwoMassParams:
    """:func:`model_values` (or several concatenated) as the simulator's parameters."""
    return sim.TwoMassParams(**{n: torch.from_numpy(np.ascontiguousarray(values[n], dtype=np.float64))
                                for n in sim.ALL_PARAM_NAMES})


def simulate(p: RefineProblem, theta: np.ndarray, drive: sim.DriveConfig) -> np.ndarray:
    """Speed error ``N x C`` [rad/s] (model minus measurement; time-major, as the kernel writes it)
    of each candidate ``theta`` ``C x 4``."""
    return simulate_packed([(p, theta)], drive)[0]


def simulate_packed(items: list[tuple[RefineProblem, np.ndarray]], drive: sim.DriveConfig,
                    rows: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """:func:`simulate` for several records on one drive in one replay call (the kernel's blocks
    of 32 models fill up and run on all cores): one ``N_i x C_i`` error per item (``rows``: only
    these samples of each item's record, ``R_i x C_i``)."""
    values = [model_values(p, th) for p, th in items]
    flat = {n: np.concatenate([v[n] for v in values]) for n in sim.ALL_PARAM_NAMES}
    N = max(len(p.speed) for p, _ in items)
    K = max(len(p.start) for p, _ in items)
    start = np.concatenate([np.broadcast_to(np.pad(p.start, (0, K - len(p.start)), constant_values=2**30),
                                            (len(th), K)) for p, th in items])  # n x K
    level = np.concatenate([np.broadcast_to(np.pad(p.level, (0, K - len(p.level)), mode="edge"),
                                            (len(th), K)) for p, th in items])
    w = replay_speed(sim_params(flat), drive, torch.from_numpy(start), torch.from_numpy(level), N, quantize=False,
                     substeps=_substeps(flat, drive.T_s, drive.T_Ei)).numpy().T  # N x n
    out, i = [], 0
    for k, (p, th) in enumerate(items):
        at = slice(0, len(p.speed)) if rows is None else rows[k]
        out.append(finite(w[at, i:i + len(th)] - p.speed[at, None]))
        i += len(th)
    return out


def problem_substeps(p: RefineProblem, theta: np.ndarray) -> int:
    """:func:`_substeps` of the candidates ``theta`` of ``p`` on its drive."""
    return _substeps(model_values(p, theta), p.T_s, p.T_Ei)


def _substeps(values: dict[str, np.ndarray], T_s: float, T_Ei: float) -> int:
    """RK4 substeps per sample for the models of :func:`model_values` (:data:`ACCURACY`)."""
    w_0 = sim.two_mass_derived(values["J_sigma"], values["V_J"], values["f_e"], values["d"]).w_0
    return sim.rk4_substeps(float(w_0.max()), T_s, T_Ei, w_0_dt=ACCURACY.w_0_dt, minimum=ACCURACY.minimum)


def replay_drive(p: RefineProblem) -> sim.DriveConfig:
    """The drive the candidates of ``p`` run on (no torque limit: the levels are what was applied)."""
    return sim.DriveConfig(M_max=1e9, T_Ei=p.T_Ei, T_s=p.T_s, encoder_counts=p.encoder_counts)


def detrended_cost(p: RefineProblem, theta: np.ndarray, basis: list, drive: sim.DriveConfig) -> np.ndarray:
    """Detrended squared speed error of each candidate ``theta`` ``C x 4`` -> ``C``."""
    return detrended_energy(simulate(p, theta, drive), basis)


def packed_errors(problems: list[RefineProblem], asked: dict[int, np.ndarray], batch: BatchSettings,
                  rows: dict[int, np.ndarray] | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """``(i, E)``: the speed error ``N_i x C_i`` (or over the samples ``rows[i]`` only) of the
    candidates ``asked[i]`` ``C_i x 4`` (or ``x 7``) of each problem ``i``, a pack at a time
    (:func:`pack_indices`: one drive and substep count per replay call; a result does not depend on its
    pack)."""
    todo = sorted(asked)
    substeps = [problem_substeps(problems[i], asked[i]) for i in todo]
    for pack in pack_indices([problems[i] for i in todo], [len(asked[i]) for i in todo], substeps, None,
                             max_models=batch.record_models, min_length_ratio=batch.length_ratio):
        ids = [todo[k] for k in pack]
        yield from zip(ids, simulate_packed([(problems[i], asked[i]) for i in ids], replay_drive(problems[ids[0]]),
                                            None if rows is None else [rows[i] for i in ids]))


def quantization_energy(p: RefineProblem, samples: int) -> float:
    """The squared error [rad^2/s^2] the encoder speed's quantization leaves over ``samples`` samples
    even for the true model: ``q_w^2 / 6`` per sample (two independent quantizations of the angle)."""
    return samples * sim.speed_quantum(p.encoder_counts, p.T_s) ** 2 / 6.0


def relative_rms(cost: float, measured: float) -> float:
    """A detrended error's rms over that of the detrended measured speed (``measured``: its energy)."""
    return math.sqrt(cost / measured) if measured > 0 else math.sqrt(cost)


def pack_indices(problems: list[RefineProblem], sizes: list[int], substeps: list[int], lengths: list[int] | None,
                 max_models: int, min_length_ratio: float) -> list[list[int]]:
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


def detrended(E: np.ndarray, basis: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """The errors ``E`` (``N x C``) with each segment's quadratic trend removed, segments end to
    end: ``M x C`` (their squared sum is the refinement's detrended energy)."""
    return np.concatenate([_detrend(E[a:b], Q) for a, b, Q in basis], axis=0)
