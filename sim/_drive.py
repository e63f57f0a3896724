"""The drive interface of SPEC 8.1 and the simulator behind it (:class:`SimulatedDrive`).

A *drive* runs whole experiments in its own real-time loop at ``T_s`` and hands back the measured
record (SPEC 3), as vendor auto-tuners do with their signal generator and scope:

* ``config``: what the drive knows of itself (``T_s``, ``K_M``, ``T_Ei``, ``encoder_counts``,
  ``M_N``, ``M_max``; a :class:`sim.DriveConfig` has them all);
* ``run_test(M_star, w_max, limits) -> Record``: the switching test of SPEC 2 from rest (record
  with ``torque_ref`` and ``section``);
* ``run_closed_loop(law, scenario, limits) -> Record``: the speed loop with ``law`` over
  ``scenario`` from rest.

A drive stops an experiment (torque reference 0) as soon as the measured speed or the measured
travel (encoder angle from the start) passes a limit of :class:`DriveLimits`, and flags the
record (``meta["aborted"] = True``). A real axis with a constant load torque (SPEC 1.1) is held:
:class:`SimulatedDrive` starts every experiment at rest held by ``M_hold`` (``M_L0``), runs the
test's levels around it, adds it to the law's torque reference in closed loop (the drive's
holding-torque feedforward: as if the law's integrator started at ``M_hold``) and, at a stop,
holds the axis with it instead of reference 0; its records say ``M_hold``. A simulated drive may
offer ``truth()`` (the true parameters)
for evaluation; the commissioning chain never decides on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from sim.params import DriveConfig, TwoMassParams, check_real
from sim.plant import simulate, simulate_test
from sim.records import Record, responses_to_records
from sim._signal import SwitchingController, TestSignalConfig

__all__ = ["DriveLimits", "Scenario", "SpeedLaw", "Drive", "SimulatedDrive", "limit_violation"]


@dataclass(frozen=True)
class DriveLimits:
    """The user's limits for every experiment: ``w_max`` [rad/s] on ``|speed|``, ``travel`` [rad]
    on ``|phi_M|`` from the start position, ``M_max`` [Nm] on ``|M_ref|`` (None: the drive's own;
    the commissioning chain hands a drive :meth:`for_drive`'s concrete cap instead)."""

    w_max: float
    travel: float
    M_max: float | None = None

    def __post_init__(self) -> None:
        for name in ("w_max", "travel", "M_max"):
            v = getattr(self, name)
            if v is None and name == "M_max":
                continue
            try:
                v = check_real(f"DriveLimits.{name}", v)
            except TypeError as err:  # this class has always said ValueError for every bad value
                raise ValueError(str(err)) from None
            if v <= 0:
                raise ValueError(f"DriveLimits.{name}: expected a finite number > 0, received {v!r}")
            object.__setattr__(self, name, v)

    def torque_cap(self, config: Any) -> float:
        """The torque the experiments may use [Nm]: ``min(M_max, config.M_max)``."""
        M = float(config.M_max)
        return M if self.M_max is None else min(M, float(self.M_max))

    def for_drive(self, config: Any) -> DriveLimits:
        """These limits with ``M_max`` the torque cap (:meth:`torque_cap`): concrete numbers for
        every experiment, what a drive written from SPEC 8.1 reads (``M_max`` [Nm], never unset)."""
        return DriveLimits(w_max=self.w_max, travel=self.travel, M_max=self.torque_cap(config))


@dataclass(frozen=True)
class Scenario:
    """A closed-loop experiment, per sample: speed reference ``w_ref`` [rad/s] and disturbance
    torque ``M_dist`` [Nm] added to the torque reference (``N`` each)."""

    w_ref: np.ndarray
    M_dist: np.ndarray

    def __post_init__(self) -> None:
        w, M = np.asarray(self.w_ref, dtype=np.float64), np.asarray(self.M_dist, dtype=np.float64)
        if w.ndim != 1 or w.shape != M.shape or len(w) < 2 or not (np.isfinite(w).all() and np.isfinite(M).all()):
            raise ValueError(f"Scenario: expected finite w_ref and M_dist of one length N >= 2, received "
                             f"shapes {w.shape}, {M.shape}")
        object.__setattr__(self, "w_ref", w)
        object.__setattr__(self, "M_dist", M)

    def __len__(self) -> int:
        return len(self.w_ref)


@runtime_checkable
class SpeedLaw(Protocol):
    """A speed-control law: ``params`` (gains, filter, notch: what a drive loads into its own
    controller), ``reset()`` and ``step(w_meas, w_ref) -> M_ref`` (computed at sample k, applied
    from k+1)."""

    params: dict[str, Any]

    def reset(self) -> None: ...

    def step(self, w_meas: float, w_ref: float) -> float: ...


@runtime_checkable
class Drive(Protocol):
    """SPEC 8.1: what the commissioning chain reaches the plant through."""

    config: Any

    def run_test(self, M_star: float, w_max: float, limits: DriveLimits) -> Record: ...

    def run_closed_loop(self, law: SpeedLaw, scenario: Scenario, limits: DriveLimits) -> Record: ...


def limit_violation(speed: np.ndarray, T_s: float, limits: DriveLimits) -> int | None:
    """The first sample whose measured speed or travel (integrated measured speed = encoder angle
    from the start) passes ``limits``; None when every sample keeps them."""
    w = np.asarray(speed, dtype=np.float64)
    bad = (np.abs(w) > limits.w_max) | (np.abs(np.cumsum(w) * T_s) > limits.travel)
    return int(np.argmax(bad)) if bad.any() else None


class _Stopping:
    """A sim controller that stops at the limits: the inner law's reference until the measured
    speed or travel passes a limit, then the holding torque ``M_hold`` [Nm] (0 on an axis without
    load torque) for ``n_after`` samples and the run ends."""

    def __init__(self, inner: Any, limits: DriveLimits, config: DriveConfig, n_total: int, n_after: int,
                 M_hold: float = 0.0) -> None:
        self.inner, self.limits, self.config, self.M_hold = inner, limits, config, M_hold
        self.n_total, self.n_after = n_total, n_after
        self.abort_at: int | None = None
        self.phi = 0.0
        self.length = torch.zeros((), dtype=torch.int64)

    def reset(self, batch_shape: Any) -> None:
        self.inner.reset(batch_shape)
        self.abort_at, self.phi, self._k = None, 0.0, 0

    def label(self) -> torch.Tensor:
        if hasattr(self.inner, "label"):
            return self.inner.label()
        return torch.zeros((), dtype=torch.int8)

    @property
    def timed_out(self) -> torch.Tensor:
        return getattr(self.inner, "timed_out", torch.zeros(6, dtype=torch.bool))

    def finished(self) -> torch.Tensor:
        if self.abort_at is not None:
            return torch.tensor(self._k + 1 >= self.abort_at + self.n_after)
        inner = self.inner.finished() if hasattr(self.inner, "finished") else torch.tensor(False)
        return torch.as_tensor(inner | (self._k + 1 >= self.n_total))

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        self._k = k
        w = float(w_meas.reshape(-1)[0])
        self.phi += w * self.config.T_s
        if self.abort_at is None and (abs(w) > self.limits.w_max or abs(self.phi) > self.limits.travel):
            self.abort_at = k
        self.length = torch.tensor(k + 1)
        M = self.inner.step(k, w_meas)
        if self.abort_at is not None:
            return torch.full_like(torch.as_tensor(M, dtype=torch.float64), self.M_hold)
        cap = self.limits.torque_cap(self.config)
        return torch.as_tensor(M, dtype=torch.float64).clamp(-cap, cap)


class _LawController:
    """A SPEC 8.1 law over a scenario as a sim controller (one system): ``M_ref[k] =
    law.step(w_meas[k], w_ref[k]) + M_dist[k] + M_hold`` (``M_hold`` [Nm]: the drive's holding torque,
    SPEC 1.1; 0 on an axis without load torque)."""

    def __init__(self, law: SpeedLaw, scenario: Scenario, M_hold: float = 0.0) -> None:
        self.law, self.sc, self.M_hold = law, scenario, M_hold

    def reset(self, batch_shape: Any) -> None:
        self.law.reset()

    def finished(self) -> torch.Tensor:
        return torch.tensor(False)

    def step(self, k: int, w_meas: torch.Tensor) -> torch.Tensor:
        i = min(k, len(self.sc) - 1)
        M = float(self.law.step(float(w_meas.reshape(-1)[0]), float(self.sc.w_ref[i]))) + float(self.sc.M_dist[i])
        return torch.tensor(M + self.M_hold if self.M_hold else M, dtype=torch.float64)


class SimulatedDrive:
    """The project's simulator (SPEC 1) behind the drive interface: one plant ``params`` (a
    one-system :class:`TwoMassParams` or a dict of its seven parameters) on ``config``.

    ``run_test`` runs the fused test kernel; only when the measured record passes a limit is the
    run repeated sample by sample with the stop at the limit (same noise seed: the same run up to
    the stop). ``run_closed_loop`` runs ``sim.simulate`` with the law sample by sample. ``truth()``
    gives the true parameters (evaluation only). ``tail`` [s]: samples recorded after a stop.
    A plant with ``M_L0`` (SPEC 1.1) is held by ``M_hold = M_L0`` (see the module's docstring).
    """

    def __init__(self, params: TwoMassParams | dict[str, float], config: DriveConfig | None = None, *,
                 seed: int = 0, timeout: float = 10.0, tail: float = 0.05) -> None:
        p = params if isinstance(params, TwoMassParams) else TwoMassParams.from_dicts(params)
        if p.J_sigma.numel() != 1:
            raise ValueError(f"SimulatedDrive: expected one plant, received a batch {tuple(p.batch_shape)}")
        self.params = p.reshape(1)
        self.config = config or DriveConfig()
        self.seed, self.timeout, self.tail = int(seed), float(timeout), float(tail)
        self.experiments = 0
        self.M_hold = float(self.params.M_hold[0])  # [Nm] the holding torque (SPEC 1.1; 0 without M_L0)

    def truth(self) -> dict[str, float]:
        """The true parameters (``sim.PARAM_NAMES``, and ``sim.REAL_AXIS_NAMES`` where the plant has
        any): for evaluation, never for a decision."""
        return self.params.to_dicts()[0]

    def _meta(self, rec: Record, aborted: bool) -> Record:
        rec.meta.pop("truth", None)
        rec.meta["aborted"] = aborted
        return rec

    def run_test(self, M_star: float, w_max: float, limits: DriveLimits) -> Record:
        cap = limits.torque_cap(self.config)
        if not (0 < M_star <= cap * (1 + 1e-12)):
            raise ValueError(f"run_test: expected 0 < M_star <= {cap:g} Nm (the torque limit), received {M_star!r}")
        self.experiments += 1
        seed = self.seed + self.experiments
        signal = TestSignalConfig(M_star=float(M_star), w_max=float(w_max), timeout=self.timeout, tail=self.tail)
        resp = simulate_test(self.params, self.config, signal, seed=seed, dtype=torch.float64)
        rec = responses_to_records(resp, self.params, self.config, signal, names=["test"])[0]
        stop = limit_violation(rec.speed, self.config.T_s, limits)
        if stop is None:
            return self._meta(rec, False)
        hold = resp.M_hold
        ctl = _Stopping(SwitchingController(signal, self.config, torch.float64, M_hold=hold), limits, self.config,
                        signal.max_samples(self.config), signal.n_tail(self.config), M_hold=self.M_hold)
        resp = simulate(self.params, self.config, ctl, signal.max_samples(self.config), dtype=torch.float64, seed=seed)
        resp.M_hold = hold
        return self._meta(responses_to_records(resp, self.params, self.config, signal, names=["test"])[0], True)

    def run_closed_loop(self, law: SpeedLaw, scenario: Scenario, limits: DriveLimits) -> Record:
        self.experiments += 1
        n = len(scenario)
        ctl = _Stopping(_LawController(law, scenario, self.M_hold), limits, self.config, n,
                        max(1, round(self.tail / self.config.T_s)), M_hold=self.M_hold)
        resp = simulate(self.params, self.config, ctl, n, dtype=torch.float64, seed=self.seed + self.experiments)
        m = int(resp.length.reshape(-1)[0])
        c = self.config
        meta = {"K_M": c.K_M, "T_Ei": c.T_Ei, "T_s": c.T_s, "encoder_counts": c.encoder_counts, "M_max": c.M_max,
                "M_N": c.M_N, "current_noise_std": c.current_noise_std}
        if self.M_hold != 0.0:
            meta["M_hold"] = self.M_hold
        rec = Record(t=resp.t[:m].numpy().copy(), speed=resp.speed.reshape(-1)[:m].numpy().copy(),
                     current=resp.current.reshape(-1)[:m].numpy().copy(),
                     torque_ref=resp.torque_ref.reshape(-1)[:m].numpy().copy(), meta=meta, name="closed_loop")
        return self._meta(rec, ctl.abort_at is not None)
