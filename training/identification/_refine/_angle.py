"""The backlash the speed hides, found in the motor's angle.

On a coarse encoder a gap whose crossing moves the motor by an encoder count or two is lost in the
speed: the speed is a difference of counts, its quantization noise (``q_w / sqrt(6)`` per sample)
fills every sample, and the crossing is a pulse of a sample or two. The angle, the running sum of
the speed, keeps it: after each torque reversal the motor runs ahead of the one-mass motion by
``2s V_J / (1 + V_J)`` for the whole section, hundreds of samples, while the angle's quantization
error stays below one count. Measured on the 2^13-count 1 ms drive of the matrix (seed 7): the
gaps the speed refinement answered ``stiff`` with a lead of 1.6-3.2 counts score 0.65-0.85 x the
angle error of the best model without a gap. The speed also loses a gap on a slowly sampled
drive's stiff shaft, crossed in a sample or two even where it is tens of counts wide: on a 0.2 Nm
drive at 844 us the speed refinement dropped the maps' gap of 14 counts of lead for a model
without one, while the angle error picks the gap model at 0.82 x.

:func:`hidden_gap` lets models with and without a gap compete on the angle error, each side
with its own search, and returns the gap model where it wins clearly. The angle error is the
running sum of the speed error less its projection on the running sums of the refinement's
per-section quadratic trends (:func:`angle_basis`: the speed's detrending, integrated), so the
small one-mass errors of STEP 2 are absorbed as in the speed, while an offset that a gap leaves
for a whole section is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim import S_N_ELASTIC
from training._settings import (AT_LEAST_ONE, COUNT, NON_NEGATIVE_OR_INF, POSITIVE, POSITIVE_OR_INF, Values,
                                check_settings)
from training.identification._envelope import SPEC_ENVELOPE
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import replay_drive, simulate, trend_basis
from training.identification._refine._search import SearchSettings, cem_one, product_grid
from training.identification._refine._space import HIGH, LOW
from training.identification._refine._stage import Stage

__all__ = ["AngleSettings", "HiddenGap", "angle_basis", "angle_energy", "hidden_gap"]


@dataclass(frozen=True)
class AngleSettings:
    """Models with and without a gap compete on the whole record's angle error: a grid of
    ``grid_f_e`` eigenfrequencies from the drive envelope's lowest to ``grid_top`` x the current
    loop's bandwidth times ``grid_V_J`` times ``grid_s_N`` at damping ``grid_d``, then ``rounds``
    cross-entropy rounds on each side of the class threshold; the gap model wins below ``win``."""

    grid_f_e: int = 12  # eigenfrequencies of the grid, log spaced
    grid_top: float = 4.0  # the grid's highest f_e: this x the current loop's bandwidth
    grid_V_J: tuple[float, ...] = (0.2, 0.45, 1.0, 2.2, 5.0)  # V_J of the grid (the drive envelope's range)
    grid_s_N: tuple[float, ...] = (1e-3, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  # s_N of the grid
    grid_d: float = 0.05  # the grid's damping
    rounds: int = 4  # cross-entropy rounds on each side of the class threshold
    side_margin: float = 1e-9  # the side without a gap ends this far below the threshold [decades of s_N]
    win: float = 0.85  # the gap model wins below this ratio of the best model's angle error without a gap ...
    s_N_clear: float = 1.5  # ... with s_N at least this x the class threshold (models at it stand in for damping)
    # the angle scored on about this many samples at most, every stride-th (a gap's offset lasts a
    # section; a record of 180 000 samples cost 7.8 s of cumulative sums and projections, its replays 1.7 s)
    samples: int = 4000

    def __post_init__(self) -> None:
        check_settings(self, {
            "grid_f_e": AT_LEAST_ONE, "grid_top": POSITIVE_OR_INF, "grid_V_J": Values(POSITIVE), "grid_s_N": Values(POSITIVE),
            "grid_d": NON_NEGATIVE_OR_INF, "rounds": COUNT, "side_margin": NON_NEGATIVE_OR_INF, "win": NON_NEGATIVE_OR_INF,
            "s_N_clear": NON_NEGATIVE_OR_INF, "samples": AT_LEAST_ONE})


@dataclass(frozen=True)
class HiddenGap:
    """The gap model found in the angle: ``f_e`` [Hz], ``V_J``, ``d``, ``s_N``, ``backlash`` = ``2s``
    [rad]; ``angle_ratio``, its angle error over that of the best model without a gap.
    ``J_sigma``: None (STEP 2's stand); ``M_FC``, ``M_FCM`` and ``mu_F``, ``mu_FM``: the load's and
    the motor's Coulomb and viscous friction of the problem where it split them (else None: STEP 2's
    stand); ``M_L0``: None (the analysis's stands)."""

    f_e: float
    V_J: float
    d: float
    s_N: float
    backlash: float
    angle_ratio: float
    J_sigma: None = None
    M_FC: float | None = None
    mu_F: float | None = None
    M_FCM: float | None = None
    M_L0: None = None
    mu_FM: float | None = None


def angle_basis(segments: np.ndarray, N: int, stride: int = 1) -> np.ndarray:
    """Orthonormal ``M x K`` basis of a constant and the running sums of each segment's quadratic
    trend (``segments`` ``(L, 2)`` half-open sample ranges; each sum held after its segment ends)
    at the samples ``stride - 1, 2 stride - 1, ...`` of ``N`` (``M = N // stride``)."""
    columns = [np.ones(N)]
    for a, b in np.asarray(segments, dtype=np.int64).tolist():
        if b <= a:
            continue
        Q = trend_basis(b - a)  # (b - a) x 3
        for j in range(Q.shape[1]):
            c = np.zeros(N)
            c[a:b] = np.cumsum(Q[:, j])
            c[b:] = c[b - 1]
            columns.append(c)
    at = np.arange(stride - 1, N // stride * stride, stride)  # M
    return np.linalg.qr(np.stack(columns, axis=1)[at])[0]  # M x K


def angle_energy(E: np.ndarray, T_s: float, Q: np.ndarray, stride: int) -> np.ndarray:
    """Squared angle error of each column of the speed error ``E`` (``N x C``), at every
    ``stride``-th sample, less its projection on ``Q`` (:func:`angle_basis`) -> ``C`` [rad^2]."""
    M = Q.shape[0]
    blocks = E[: M * stride].reshape(M, stride, -1).sum(axis=1)  # M x C: the speed error summed per stride
    phi = np.cumsum(blocks, axis=0) * T_s  # M x C: the angle error at the stride's last samples
    r = phi - Q @ (Q.T @ phi)
    return (r * r).sum(axis=0)


def hidden_gap(p: RefineProblem, settings: AngleSettings, search: SearchSettings, seed: int) -> HiddenGap | None:
    """The gap model of ``p`` where it explains the angle clearly better than every model without
    a gap (see :class:`AngleSettings`), else None; the searches draw from ``seed``."""
    stride = max(1, len(p.speed) // settings.samples)
    drive, Q = replay_drive(p), angle_basis(p.segments, len(p.speed), stride)

    def score(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # a chunk at a time: the grid is ordered by f_e, so a chunk's substeps suit its models,
        # and the errors of a long record stay small
        chunks = range(0, len(theta), search.candidates)
        return np.concatenate([angle_energy(simulate(p, theta[k:k + search.candidates], drive), p.T_s, Q, stride)
                               for k in chunks]), theta

    bandwidth = 1.0 / (2.0 * math.pi * p.T_Ei)
    f_e = np.geomspace(SPEC_ENVELOPE["f_e"][0], min(settings.grid_top * bandwidth, 10.0 ** HIGH[0]), settings.grid_f_e)
    grid = product_grid(f_e, settings.grid_V_J, settings.grid_d,
                        [math.log10(s) for s in settings.grid_s_N])  # G x 4, ordered by f_e
    cost, _ = score(grid)
    threshold = math.log10(S_N_ELASTIC)
    best: list[tuple[np.ndarray, float]] = []
    rng = np.random.default_rng(seed)
    for gap, low_s, high_s in ((False, LOW[3], threshold - settings.side_margin), (True, threshold, HIGH[3])):
        side = (grid[:, 3] >= threshold) == gap
        low, high = LOW.copy(), HIGH.copy()
        low[3], high[3] = low_s, high_s
        scored = cem_one(grid[side], cost[side], settings.rounds, np.asarray(search.spread), search, rng, score, low,
                         high)
        k = int(np.argmin(scored.cost))
        best.append((scored.theta[k], float(scored.cost[k])))
    (_, no_gap), (theta, with_gap) = best
    ratio = with_gap / no_gap if no_gap > 0 else math.inf
    s_N = float(10.0 ** theta[3])
    if ratio >= settings.win or s_N < settings.s_N_clear * S_N_ELASTIC:
        return None
    split = p.friction_split()
    return HiddenGap(**p.answer(theta, s_N), angle_ratio=ratio, **split)


STAGE = Stage("angle", "the identifier's call: a stiff answer whose speed could hide a gap, or a dropped maps' gap",
              AngleSettings, hidden_gap)
