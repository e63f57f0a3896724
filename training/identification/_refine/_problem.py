"""One record to refine (:class:`RefineProblem`), the refined model (:class:`Refined`) and the
switching test's torque reference the models are replayed under."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

import sim


@dataclass
class RefineProblem:
    """One record to refine: measured ``speed`` ``N`` [rad/s]; torque reference segments
    (``start`` int ``K``, ``level`` ``K`` [Nm]); scored ``segments`` ``(L, 2)`` half-open sample
    ranges; STEP 2's ``J_sigma``, ``M_FC``, ``mu_F``; the drive (``T_s``, ``T_Ei``,
    ``encoder_counts``, ``M_N`` for ``s_N``); the start ``theta`` over :data:`COORDINATES`
    (``s_N`` of 1e-3 or less stands for no backlash); SPEC 1.1's parts: the constant load torque
    ``M_L0`` [Nm] (STEP 2's offset; the model starts at rest held by it) and the motor's Coulomb
    and viscous friction ``M_FCM`` [Nm], ``mu_FM`` [Nm s/rad] (``M_FC``, ``mu_F`` are then the
    load's: :meth:`with_motor_share` splits STEP 2's); ``f_e_other`` [Hz]: another read-out of the
    maps' ``f_e`` the exploration also starts from (``None``: only ``theta``'s)."""

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
    M_L0: float = 0.0
    M_FCM: float = 0.0
    f_e_other: float | None = None
    mu_FM: float = 0.0

    @property
    def M_star(self) -> float:
        """The test's torque step ``M*`` [Nm]: the largest level around the one before the test (the hold)."""
        return float(np.abs(self.level - self.level[0]).max())

    @property
    def coulomb(self) -> float:
        """The Coulomb friction of motor and load together [Nm] (STEP 2's ``M_FC``)."""
        return self.M_FC + self.M_FCM

    @property
    def viscous(self) -> float:
        """The viscous friction of motor and load together [Nm s/rad] (STEP 2's ``mu_F``)."""
        return self.mu_F + self.mu_FM

    def with_motor_share(self, share: float, viscous_share: float = 0.0) -> RefineProblem:
        """This problem with the share ``share`` (0..1) of :attr:`coulomb` and ``viscous_share`` of
        :attr:`viscous` on the motor, the rest on the load."""
        return replace(self, M_FC=(1.0 - share) * self.coulomb, M_FCM=share * self.coulomb,
                       mu_F=(1.0 - viscous_share) * self.viscous, mu_FM=viscous_share * self.viscous)

    def friction_split(self) -> dict[str, float]:
        """The load's and the motor's friction where this problem splits it (``M_FC``, ``M_FCM``,
        and ``mu_F``, ``mu_FM`` where the viscous part is split too; empty: all on the load)."""
        split = {"M_FC": self.M_FC, "M_FCM": self.M_FCM} if self.M_FCM > 0 or self.mu_FM > 0 else {}
        return {**split, "mu_F": self.mu_F, "mu_FM": self.mu_FM} if self.mu_FM > 0 else split

    def with_friction_of(self, refined: Refined) -> RefineProblem:
        """This problem with the motor's shares of the Coulomb and viscous friction that ``refined``
        found (itself where it found none)."""
        if not (refined.M_FCM or refined.mu_FM):
            return self
        return self.with_motor_share((refined.M_FCM or 0.0) / self.coulomb if self.coulomb > 0 else 0.0,
                                     (refined.mu_FM or 0.0) / self.viscous if self.viscous > 0 else 0.0)

    def J_sigma_of(self, theta: np.ndarray) -> np.ndarray:
        """``J_sigma`` [kg m^2] of ``theta`` ``*batch x 4`` (STEP 2's) or ``x 7`` (its own)."""
        return 10.0 ** theta[..., 4] if theta.shape[-1] > 4 else np.full(theta.shape[:-1], self.J_sigma)

    def C_F(self, theta: np.ndarray) -> np.ndarray:
        """Shaft stiffness [Nm/rad] of ``theta`` ``*batch x 4`` (or ``x 7``)."""
        return sim.two_mass_derived(self.J_sigma_of(theta), 10.0 ** theta[..., 1], 10.0 ** theta[..., 0],
                                    theta[..., 2]).C_F

    def answer(self, theta: np.ndarray, s_N: float) -> dict[str, float]:
        """The :class:`Refined` model values of ``theta`` (4 or 7) with the normalized backlash ``s_N``."""
        return {"f_e": float(10.0 ** theta[0]), "V_J": float(10.0 ** theta[1]), "d": float(theta[2]), "s_N": s_N,
                "backlash": sim.gap_width(s_N, self.M_N, float(self.C_F(theta)))}


@dataclass
class Refined:
    """The refined model: ``f_e`` [Hz], ``V_J``, ``d``, ``s_N``, ``backlash`` = ``2s`` [rad];
    ``residual`` and ``start_residual``: the detrended speed error of the refined model and of
    the maps' answer over the measured oscillation (both detrended the same way; about the
    quantization noise over the oscillation for a perfect model), ``dof`` the samples they are
    taken over less the trends removed; ``n_sims`` simulated models; ``J_sigma``, ``M_FC``,
    ``mu_F``: refined one-mass values where the free stage won (else None: STEP 2's stand);
    ``M_FC``, ``M_FCM``: the load's and the motor's Coulomb friction where the split stage ran;
    ``M_L0``: the load torque the model carried; ``mu_F``, ``mu_FM``: the load's and the motor's
    viscous friction where the restart split it (:mod:`._restart`)."""

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
    M_FCM: float | None = None
    M_L0: float | None = None
    mu_FM: float | None = None

    @property
    def evidence(self) -> float:
        """How much better the refined model explains the record than the maps' answer: the drop of
        the squared error in units of the refined model's own error per degree of freedom (an F
        statistic of the added model; 0 where it is no better, inf where it fits exactly)."""
        gain = self.start_residual ** 2 - self.residual ** 2
        if gain <= 0.0:
            return 0.0
        return math.inf if self.residual == 0.0 else gain * self.dof / self.residual ** 2


def torque_reference(bounds: np.ndarray, M_star: float, M_hold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The switching test's torque reference (SPEC 2) from its six section ``bounds`` ``(6, 2)``:
    0 before section I, :data:`sim.SECTION_LEVELS` ``x M*`` over the sections, 0 in the tail, each
    around the holding torque ``M_hold`` [Nm] (SPEC 1.1; 0: the plain levels).
    Returns ``start`` (int ``8``) and ``level`` (``8`` [Nm]) for :func:`sim.replay.replay_speed`."""
    bounds = np.asarray(bounds, dtype=np.int64)
    if bounds.shape != (6, 2):
        raise ValueError(f"bounds: expected shape (6, 2), received {bounds.shape}")
    start = np.concatenate([[0], bounds[:, 0], [bounds[5, 1]]])
    level = M_hold + M_star * np.array([0.0, *sim.SECTION_LEVELS, 0.0])
    return start, level
