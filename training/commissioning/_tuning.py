"""Fine-tuning of a proposed speed controller by a Nelder-Mead simplex search on the closed loop.

The search runs over log-gains ``x = log([Kp, Ti(, T_f)])`` starting at the proposal
(:class:`training.commissioning._rules.ControllerProposal`), with ``scipy.optimize.minimize(method=
"Nelder-Mead")``. Each cost evaluation runs the closed loop on a plant through a
:class:`ClosedLoopRunner`: :class:`LinearRunner` (the exact sampled linear model, batched
torch) or :class:`SimRunner` (the batched nonlinear simulator ``sim.simulate``; a real drive can
stand in through the same interface). The cost (docs/commissioning.md, "Tuning cost"):

    cost = ITAE_ref + load_weight * ITAE_load
         + overshoot_weight * max(0, overshoot - overshoot_allowed)^2
         + overshoot_weight * max(0, load_overshoot - load_overshoot_allowed)^2
         + oscillation_weight * (E_osc,ref + E_osc,load)

from two closed-loop runs side by side (one batch): (ref) a speed step ``w_step`` from rest, no
load; (load) a constant load torque ``M_L`` from ``t=0`` at zero speed reference (for a linear
plant the same as a load step at a later time; a constant load is what ``sim.simulate`` offers).
Time is normalized by ``T_ref = 1/w_c`` of the proposal, errors by the step size (ref) or the
expected load dip ``M_L/(J_sigma w_c)`` (load); ``load_overshoot`` = speed beyond the reference
after the dip, over the dip; ``E_osc`` = mean square of the speed minus its mean over the last
quarter of each run, over ``w_step^2``. A candidate whose speed is not finite, exceeds
``divergence_factor * w_step``, or ends far from the reference gets the large finite cost
``unstable_cost`` (+ a term that grows with the excursion).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import scipy.optimize
import torch

from ._loop import linear_plant, loop_figures
from ._rules import ControllerProposal

__all__ = [
    "ClosedLoopRunner",
    "LinearRunner",
    "SimRunner",
    "TuningScenario",
    "TuningResult",
    "make_scenario",
    "closed_loop_cost",
    "response_figures",
    "evaluate_gains",
    "tune_controller",
]


class ClosedLoopRunner(Protocol):
    """Runs a sampled speed controller on a plant and returns the measured motor speed.

    ``run(controller, n_samples, load_torque, batch)``: ``controller`` follows the contract
    (``reset(batch_shape)``, ``step(k, w_meas) -> M_ref``); ``load_torque`` is a constant load
    torque per run, ``batch`` [Nm] (or None); ``batch`` runs side by side. Returns the measured
    speed ``batch x n_samples`` [rad/s] (``w_meas[k]`` is what ``step(k, .)`` saw).
    """

    T_s: float

    def run(self, controller: Any, n_samples: int, load_torque: torch.Tensor | None, batch: int) -> torch.Tensor: ...


class LinearRunner:
    """The exact sampled linear two-mass (or one-mass) model as a batched closed-loop plant.

    Same timing as the drive (SPEC 1/2): ``M_ref`` from ``step(k)`` acts from sample ``k+1``
    (zero-order hold); ``w_meas[k]`` = motor angle gained over sample ``k-1`` / ``T_s``, optionally
    quantized by the encoder (``quantize=True``: angle floored to ``2 pi / encoder_counts``).
    No backlash, no Coulomb friction (the linear model of :func:`training.commissioning._loop.linear_plant`).
    """

    def __init__(self, params: Any, drive: Any, *, quantize: bool = False) -> None:
        self.plant = linear_plant(params, drive)
        self.T_s = float(drive.T_s)
        self.quantize = bool(quantize)
        self.q_phi = 2 * math.pi / float(getattr(drive, "encoder_counts", 2**20))
        p = self.plant
        self._Ad, self._Bd, self._Ed = (torch.as_tensor(v, dtype=torch.float64) for v in (p.Ad, p.Bd, p.Ed))
        self._Cd = torch.as_tensor(p.Cd, dtype=torch.float64)

    def run(self, controller: Any, n_samples: int, load_torque: torch.Tensor | None, batch: int) -> torch.Tensor:
        if n_samples < 1 or batch < 1:
            raise ValueError(f"n_samples, batch: expected >= 1, received {n_samples}, {batch}")
        load = torch.zeros(batch, dtype=torch.float64) if load_torque is None else torch.as_tensor(load_torque, dtype=torch.float64)
        load = load.expand(batch) if load.dim() == 0 else load
        if load.shape != (batch,):
            raise ValueError(f"load_torque: expected shape ({batch},), received {tuple(load.shape)}")
        load_x, load_phi = load[:, None] * self._Ed, load * self.plant.Fd
        controller.reset((batch,))
        n = self._Ad.shape[0]
        x = torch.zeros(batch, n, dtype=torch.float64)
        u = torch.zeros(batch, dtype=torch.float64)
        phi = torch.zeros(batch, dtype=torch.float64)
        phi_q_prev = torch.zeros(batch, dtype=torch.float64)
        w_meas = torch.zeros(batch, dtype=torch.float64)
        out: list[torch.Tensor] = []
        AdT, Cd, Dd = self._Ad.T, self._Cd, self.plant.Dd
        for k in range(n_samples):
            out.append(w_meas)
            M_ref = controller.step(k, w_meas)
            dphi = x @ Cd + Dd * u + load_phi
            x = x @ AdT + u[:, None] * self._Bd + load_x
            u = M_ref
            phi = phi + dphi
            if self.quantize:
                phi_q = torch.floor(phi / self.q_phi) * self.q_phi
                w_meas = (phi_q - phi_q_prev) / self.T_s
                phi_q_prev = phi_q
            else:
                w_meas = dphi / self.T_s
            w_meas = torch.nan_to_num(w_meas, nan=1e30, posinf=1e30, neginf=-1e30)
        return torch.stack(out, dim=-1)


class SimRunner:
    """The nonlinear batched simulator (``sim.simulate``) as a closed-loop plant.

    ``params``: a one-system ``sim.TwoMassParams`` (batch shape ``()`` or ``(1,)``) that is
    expanded to the number of runs; ``simulate_kwargs`` go to ``sim.simulate`` unchanged
    (default ``dtype=torch.float64``).
    """

    def __init__(self, params: Any, drive: Any, **simulate_kwargs: Any) -> None:
        import sim  # imported here: the tuner itself does not need the simulator

        if not hasattr(sim, "simulate"):
            raise TypeError("sim.simulate is not available (the closed-loop simulator contract)")
        self._sim = sim
        self.params, self.drive = params, drive
        self.T_s = float(drive.T_s)
        if params.J_sigma.numel() != 1:
            raise ValueError(f"params: expected one system, received batch {tuple(params.J_sigma.shape)}")
        self.kwargs = {"dtype": torch.float64, **simulate_kwargs}

    def _expand(self, batch: int) -> Any:
        return self.params.reshape(1)[torch.zeros(batch, dtype=torch.long)]

    def run(self, controller: Any, n_samples: int, load_torque: torch.Tensor | None, batch: int) -> torch.Tensor:
        params = self._expand(batch)
        kwargs = dict(self.kwargs)
        if load_torque is not None:
            kwargs["load_torque"] = torch.as_tensor(load_torque, dtype=torch.float64).expand(batch)
        resp = self._sim.simulate(params, self.drive, controller, n_samples, **kwargs)
        speed = resp.speed if hasattr(resp, "speed") else resp["speed"]
        return torch.nan_to_num(speed.reshape(batch, -1)[:, :n_samples], nan=1e30, posinf=1e30, neginf=-1e30)


# --------------------------------------------------------------------------- scenario and cost


@dataclass(frozen=True)
class TuningScenario:
    """The closed-loop test: run "ref" (speed step ``w_step`` [rad/s] from rest) and run "load"
    (constant load ``M_L`` [Nm] from ``t=0``, speed reference 0), ``n_segment`` samples each.
    The cost's weights and thresholds as in the module docstring.
    """

    T_s: float
    """Sample time [s]."""
    w_step: float
    """Speed step of the ref run [rad/s]; also the scale of the speed errors."""
    M_L: float
    """Constant load torque of the load run [Nm]."""
    n_segment: int
    """Samples per run."""
    T_ref: float
    """Time scale [s] of the ITAE terms (``1/w_c`` of the proposal)."""
    dip_ref: float
    """Expected load dip [rad/s]: the scale of the load run's error."""
    load_weight: float = 0.5
    """Weight of the load run's ITAE beside the ref run's."""
    overshoot_allowed: float = 0.05
    load_overshoot_allowed: float = 0.2
    """Overshoot of the ref run (over ``w_step``) and recovery overshoot of the load run (over the
    dip) that cost nothing."""
    overshoot_weight: float = 20.0
    oscillation_weight: float = 100.0
    """Weights of the squared overshoot excess and of the ringing in the last quarter of each run."""
    divergence_factor: float = 20.0
    unstable_cost: float = 1e4
    """A run beyond ``divergence_factor * w_step`` (or not settling) costs ``unstable_cost`` and more."""

    def reference(self, batch: int) -> torch.Tensor:
        """Speed references ``2 batch x n_segment`` [rad/s]: ``batch`` ref runs, then ``batch`` load runs."""
        r = torch.zeros(2, batch, self.n_segment, dtype=torch.float64)
        r[0] = self.w_step
        return r.reshape(2 * batch, self.n_segment)

    def load(self, batch: int) -> torch.Tensor:
        """Load torques ``2 batch`` [Nm] (0 for the ref runs, ``M_L`` for the load runs)."""
        return torch.cat([torch.zeros(batch, dtype=torch.float64), torch.full((batch,), float(self.M_L), dtype=torch.float64)])


def make_scenario(
    proposal: ControllerProposal,
    drive: Any,
    *,
    w_step: float | None = None,
    load_fraction: float = 0.2,
    settle_factor: float = 25.0,
    max_samples: int = 4000,
    **weights: float,
) -> TuningScenario:
    """Scenario scaled to the proposal: ``T_ref = 1/w_c``, segment ``settle_factor * T_ref``.

    ``w_step`` default: the speed step whose P-kick ``Kp * w_step`` is 20 % of ``M_max`` (so that
    candidates up to ~5x the proposal's gain stay out of the torque limit; at least 50 speed quanta); ``M_L = load_fraction * M_max``; ``dip_ref = M_L / (J_sigma w_c)``.
    Each run holds ``[100, max_samples]`` samples.
    """
    T_s, M_max = float(drive.T_s), float(drive.M_max)
    w_c = proposal.figures.get("w_c", math.nan)
    if not (math.isfinite(w_c) and w_c > 0):
        raise ValueError(f"proposal figures: expected a finite crossover w_c > 0, received {w_c}")
    q_w = 2 * math.pi / (float(getattr(drive, "encoder_counts", 2**20)) * T_s)
    if w_step is None:
        w_step = max(0.2 * M_max / proposal.Kp, 50 * q_w)
    if not w_step > 0:
        raise ValueError(f"w_step: expected > 0 rad/s, received {w_step}")
    mech = proposal.mechanics if proposal.mechanics is not None else None
    J_sigma = mech.J_sigma if mech is not None else proposal.Kp / w_c
    T_ref = 1.0 / w_c
    n_seg = int(min(max(settle_factor * T_ref / T_s, 100), max_samples))
    M_L = load_fraction * M_max
    return TuningScenario(T_s=T_s, w_step=float(w_step), M_L=M_L, n_segment=n_seg, T_ref=T_ref,
                          dip_ref=M_L / (J_sigma * w_c), **weights)


def closed_loop_cost(speed: torch.Tensor, sc: TuningScenario) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Cost of measured speeds ``*batch x 2 x n_segment`` [rad/s] (ref run, load run) under ``sc``.

    Returns ``(cost *batch, terms)`` with terms ``itae_ref, itae_load, overshoot, osc, unstable``
    ``load_overshoot`` (each ``*batch``). Dimensionless; large finite ``sc.unstable_cost`` (+ log excursion) for a
    diverging or non-settling candidate.
    """
    if speed.dim() < 2 or speed.shape[-2:] != (2, sc.n_segment):
        raise ValueError(f"speed: expected shape *batch x 2 x {sc.n_segment}, received {tuple(speed.shape)}")
    w = speed.to(torch.float64)
    n = sc.n_segment
    dt_n = sc.T_s / sc.T_ref
    tau = torch.arange(n, dtype=torch.float64) * dt_n
    seg1, seg2 = w[..., 0, :], w[..., 1, :]
    e1 = (sc.w_step - seg1) / sc.w_step
    e2 = seg2 / sc.dip_ref
    itae_ref = (tau * e1.abs()).sum(-1) * dt_n
    itae_load = (tau * e2.abs()).sum(-1) * dt_n
    overshoot = (seg1.max(-1).values / sc.w_step - 1.0).clamp_min(0.0)
    # recovery overshoot after the load step, relative to the dip (ringing of a low-margin loop)
    dip = (-seg2.min(-1).values).clamp_min(1e-12)
    load_overshoot = seg2.max(-1).values.clamp_min(0.0) / dip
    q = max(n // 4, 4)
    tail1, tail2 = seg1[..., -q:], seg2[..., -q:]
    osc = ((tail1 - tail1.mean(-1, keepdim=True)) ** 2).mean(-1) / sc.w_step**2 \
        + ((tail2 - tail2.mean(-1, keepdim=True)) ** 2).mean(-1) / sc.w_step**2
    excursion = w.abs().amax((-2, -1)) / sc.w_step
    end_error = torch.maximum((tail1.mean(-1) - sc.w_step).abs(), tail2.mean(-1).abs()) / sc.w_step
    unstable = ~torch.isfinite(w).all(-1).all(-1) | (excursion > sc.divergence_factor) | (end_error > 0.5)
    cost = itae_ref + sc.load_weight * itae_load \
        + sc.overshoot_weight * (overshoot - sc.overshoot_allowed).clamp_min(0.0) ** 2 \
        + sc.overshoot_weight * (load_overshoot - sc.load_overshoot_allowed).clamp_min(0.0) ** 2 \
        + sc.oscillation_weight * osc
    bad = sc.unstable_cost + torch.log1p(torch.nan_to_num(excursion, nan=1e30, posinf=1e30).clamp(max=1e30))
    cost = torch.where(unstable | ~torch.isfinite(cost), bad, cost)
    return cost, {"itae_ref": itae_ref, "itae_load": itae_load, "overshoot": overshoot,
                  "load_overshoot": load_overshoot, "osc": osc,
                  "unstable": unstable.to(torch.float64)}


def response_figures(speed: torch.Tensor, sc: TuningScenario) -> dict[str, float]:
    """Figures of one candidate's runs ``2 x n_segment`` [rad/s]: ``rise_time`` (10-90 %) [s],
    ``overshoot_pct``, ``settling_time`` (2 % band) [s] of the ref run; ``load_dip`` [rad/s] (largest
    speed drop in the load run), ``load_recovery_time`` [s] (back inside 2 % of ``w_step``)."""
    w = speed.detach().to(torch.float64).reshape(2, -1).numpy()
    n, T_s, r = sc.n_segment, sc.T_s, sc.w_step
    y1 = w[0] / r
    def first(mask: np.ndarray) -> float:
        return float(np.argmax(mask)) * T_s if mask.any() else math.inf
    t10, t90 = first(y1 >= 0.1), first(y1 >= 0.9)
    out1 = np.nonzero(np.abs(y1 - 1) > 0.02)[0]
    settle = math.inf if len(out1) and out1[-1] == n - 1 else (float(out1[-1] + 1) * T_s if len(out1) else 0.0)
    y2 = w[1]
    out2 = np.nonzero(np.abs(y2 / r) > 0.02)[0]
    rec = math.inf if len(out2) and out2[-1] == n - 1 else (float(out2[-1] + 1) * T_s if len(out2) else 0.0)
    return {
        "rise_time": t90 - t10,
        "overshoot_pct": float(max(0.0, y1.max() - 1.0) * 100.0),
        "settling_time": settle,
        "load_dip": float(-y2.min()),
        "load_recovery_time": rec,
    }


def evaluate_gains(
    runner: ClosedLoopRunner,
    proposal: ControllerProposal,
    drive: Any,
    sc: TuningScenario,
    Kp: torch.Tensor,
    Ti: torch.Tensor,
    T_f: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """Cost of ``B`` candidate gain sets at once (tensors ``B``), both runs in one batch of ``2B``.

    Returns ``(cost B, terms, speed B x 2 x n_segment)``."""
    Kp = torch.as_tensor(Kp, dtype=torch.float64).reshape(-1)
    Ti = torch.as_tensor(Ti, dtype=torch.float64).reshape(-1)
    T_f = torch.full_like(Kp, proposal.T_f) if T_f is None else torch.as_tensor(T_f, dtype=torch.float64).reshape(-1)
    if not (Kp.shape == Ti.shape == T_f.shape):
        raise ValueError(f"Kp, Ti, T_f: expected one shape, received {tuple(Kp.shape)}, {tuple(Ti.shape)}, {tuple(T_f.shape)}")
    B = Kp.shape[0]
    two = lambda v: torch.cat([v, v])  # noqa: E731
    ctrl = proposal.build(drive, w_ref=sc.reference(B), Kp=two(Kp), Ti=two(Ti), T_f=two(T_f))
    speed = runner.run(ctrl, sc.n_segment, sc.load(B), 2 * B).reshape(2, B, sc.n_segment).transpose(0, 1)
    cost, terms = closed_loop_cost(speed, sc)
    return cost, terms, speed


@dataclass
class TuningResult:
    """Outcome of :func:`tune_controller`.

    ``controller``: the tuned :class:`ControllerProposal` (gains, linear-model figures where the
    mechanics are known); ``proposal``: the start; ``cost_proposal``, ``cost_tuned``;
    ``history``: one dict per cost evaluation (``Kp, Ti, T_f, cost``); ``figures_before`` /
    ``figures_after``: :func:`response_figures` on the runner plus the cost terms; ``stable``:
    the check of the result (runner response settled, and linear-model poles inside the unit
    circle where a linear model exists); ``message`` / ``warnings``.
    """

    controller: ControllerProposal
    proposal: ControllerProposal
    cost_proposal: float
    cost_tuned: float
    history: list[dict[str, float]]
    figures_before: dict[str, float]
    figures_after: dict[str, float]
    scenario: TuningScenario
    stable: bool
    n_evaluations: int
    message: str
    warnings: list[str] = field(default_factory=list)


def tune_controller(
    proposal: ControllerProposal,
    runner: ClosedLoopRunner,
    drive: Any,
    *,
    scenario: TuningScenario | None = None,
    tune_filter: bool | None = None,
    max_evaluations: int = 60,
    span: float = 20.0,
    initial_step: float = 0.4,
    xatol: float = 0.01,
    fatol: float = 1e-4,
    progress: Callable[[int, float], None] | None = None,
    min_phase_margin: float | None = 40.0,
    margin_weight: float = 1.0,
) -> TuningResult:
    """Nelder-Mead on ``log([Kp, Ti(, T_f)])`` from ``proposal`` on the closed loop of ``runner``.

    Args:
        proposal: start (its ``Kp, Ti, T_f``, notch kept fixed).
        runner: the plant (:class:`LinearRunner`, :class:`SimRunner`, or a real drive adapter).
        drive: DriveConfig (``T_s``, ``M_max``).
        scenario: the test (default :func:`make_scenario` of the proposal).
        tune_filter: search ``T_f`` too (default: when the proposal has a filter).
        max_evaluations: cost evaluations of the simplex search (``maxfev``).
        span: each gain stays within ``[start / span, start * span]`` (bounds in log space).
        initial_step: initial simplex edge in log units (0.4 = x1.5).
        xatol, fatol: scipy Nelder-Mead tolerances (log units, cost).
        progress: optional callback ``(evaluation, cost)``.
        min_phase_margin: robustness guard [deg] on the identified linear model (where the
            proposal carries mechanics): a candidate below it gets ``margin_weight * (deficit/10 deg)``
            added, so the search cannot trade robustness for speed in a regime where the response
            hides it (torque limit). None: response-only cost.

    Returns :class:`TuningResult`; the tuned cost is never above the proposal's (the proposal is
    kept when the search does not improve it or its result fails the stability check).
    """
    if max_evaluations < 1:
        raise ValueError(f"max_evaluations: expected >= 1, received {max_evaluations}")
    if not span > 1:
        raise ValueError(f"span: expected > 1, received {span}")
    sc = scenario or make_scenario(proposal, drive)
    use_f = (proposal.T_f > 0) if tune_filter is None else bool(tune_filter)
    if use_f and proposal.T_f <= 0:
        raise ValueError("tune_filter=True needs a proposal with T_f > 0 (log search)")
    x0 = np.log([proposal.Kp, proposal.Ti] + ([proposal.T_f] if use_f else []))
    history: list[dict[str, float]] = []
    runs: dict[str, tuple[float, dict[str, torch.Tensor], torch.Tensor]] = {}  # "first" and "best" evaluations

    def gains(x: np.ndarray) -> tuple[float, float, float]:
        return float(math.exp(x[0])), float(math.exp(x[1])), float(math.exp(x[2])) if use_f else proposal.T_f

    def f(x: np.ndarray) -> float:
        Kp, Ti, T_f = gains(x)
        c, terms, speed = evaluate_gains(runner, proposal, drive, sc, torch.tensor([Kp]), torch.tensor([Ti]), torch.tensor([T_f]))
        cost = float(c[0])
        run = (cost, {k: v[0] for k, v in terms.items()}, speed[0])
        if min_phase_margin is not None and proposal.mechanics is not None and cost < sc.unstable_cost:
            figs = loop_figures(proposal.mechanics, drive, Kp, Ti, T_f, proposal.notch, n_freq=400)
            pm = figs["phase_margin"] if figs["stable"] else -180.0
            if not math.isfinite(pm) or pm < min_phase_margin:
                deficit = (min_phase_margin - pm) if math.isfinite(pm) else 180.0
                cost += margin_weight * deficit / 10.0
        history.append({"Kp": Kp, "Ti": Ti, "T_f": T_f, "cost": cost})
        if not history[:-1]:
            runs["first"] = run
        if "best" not in runs or cost < runs["best"][0]:
            runs["best"] = run
        if progress is not None:
            progress(len(history), cost)
        return cost

    simplex = np.vstack([x0] + [x0 + initial_step * np.eye(len(x0))[i] for i in range(len(x0))])
    bounds = [(xi - math.log(span), xi + math.log(span)) for xi in x0]
    cost0 = f(x0)
    res = scipy.optimize.minimize(
        f, x0, method="Nelder-Mead", bounds=bounds,
        options={"maxfev": max_evaluations, "initial_simplex": simplex, "xatol": xatol, "fatol": fatol},
    )
    best = min(history, key=lambda h: h["cost"])
    warnings: list[str] = []
    # stability check of the result: response settled (finite cost below the guard) and, where a
    # linear model exists, all closed-loop poles inside the unit circle
    cand = replace(proposal, Kp=best["Kp"], Ti=best["Ti"], T_f=best["T_f"])
    stable = best["cost"] < sc.unstable_cost
    if proposal.mechanics is not None:
        figs = loop_figures(proposal.mechanics, drive, cand.Kp, cand.Ti, cand.T_f, cand.notch)
        cand = replace(cand, figures=figs)
        stable = stable and bool(figs["stable"])
    if not stable or best["cost"] > cost0:
        warnings.append("tuning kept the proposal: the search result failed the stability check or did not improve the cost")
        cand, best_cost = proposal, cost0
        stable = cost0 < sc.unstable_cost
    else:
        best_cost = best["cost"]
        cand = replace(cand, rules=cand.rules + (
            f"T1 Nelder-Mead fine-tuning: Kp {proposal.Kp:.4g} -> {cand.Kp:.4g}, Ti {proposal.Ti:.4g} -> {cand.Ti:.4g}, "
            f"T_f {proposal.T_f:.3g} -> {cand.T_f:.3g}; cost {cost0:.4g} -> {best_cost:.4g}",))
    _, terms0, sp0 = runs["first"]
    _, terms1, sp1 = runs["first"] if cand is proposal else runs["best"]
    before = {**response_figures(sp0, sc), **{k: float(v) for k, v in terms0.items()}, "cost": cost0}
    after = {**response_figures(sp1, sc), **{k: float(v) for k, v in terms1.items()}, "cost": best_cost}
    return TuningResult(
        controller=cand, proposal=proposal, cost_proposal=cost0, cost_tuned=best_cost, history=history,
        figures_before=before, figures_after=after, scenario=sc, stable=stable,
        n_evaluations=len(history), message=str(res.message), warnings=warnings,
    )
