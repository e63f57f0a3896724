"""Accurate reference path: adaptive Dormand-Prince (torchdiffeq) with event restarts, float64.

Per system and per sample interval the ODE is integrated with ``dopri5`` (``rtol=1e-10``,
``atol=1e-12``) and restarted at every discontinuity:

* sample instants (the torque reference steps there: every interval is its own solve);
* contact / separation of the backlash (``|dphi| = s``; the damping term switches);
* stick -> slip (``|M_S - M_ext|`` reaches ``M_FC``) and slip -> stick (``w_L`` reaches 0;
  the load is then set to rest and stick or slip is decided from the shaft torque); ``M_ext`` is
  the constant load torque ``M_L0`` (SPEC 1.1), plus :func:`sim.simulate`'s external load torque;
* the motor's likewise where it has Coulomb friction (SPEC 1.1, ``M_FCM > 0``): stick -> slip
  (``|M_M - M_S|`` reaches ``M_FCM``), slip -> stick (``w_M`` reaches 0). Its viscous friction
  ``mu_FM w_M`` is part of the right-hand side.

The friction modes are discrete states carried between segments, so stiction is exact up to the
event-time tolerance. Without motor friction the right-hand side is SPEC 1's, operation for operation.
Slow (Python loop per system and segment): meant for tests and checks.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchdiffeq import odeint

from sim._integrate_fast import FastState
from sim.params import DriveConfig, TwoMassParams

_EPS_W = 1e-12  # rad/s: a sliding load counts as stopped once it passes this past zero
_EPS_M = 1e-12  # Nm: break-away margin over M_FC


def _friction_mode(w: float, net: float, limit: float, forced: float | None) -> tuple[bool, float]:
    """``(stuck, sign)`` of a body with Coulomb friction ``limit`` [Nm] at the start of a segment:
    the ``forced`` sign of a break-away; stuck at rest while ``|net| <= limit``; else sliding in
    the direction of its speed ``w`` (at rest: of its net torque ``net``)."""
    if forced is not None:
        return False, forced
    if w == 0.0 and abs(net) <= limit:
        return True, 0.0
    return False, ((1.0 if w > 0 else -1.0) if w != 0.0 else (1.0 if net > 0 else -1.0))


def _rest_or_break(y: torch.Tensor, k: int, stuck: bool, g: Callable[[torch.Tensor], torch.Tensor],
                   net: Callable[[torch.Tensor], float], sliding: bool = True) -> float | None:
    """After a segment that ended at an event, state ``y``'s speed ``k`` of a body: a stuck body
    stays at rest and breaks away (the sign returned) where its event ``g`` fired, in the direction
    of its net torque ``net``; a sliding one (where ``sliding``) whose event fired has stopped: at
    rest, stick or slip decided by the next segment. ``None``: no break-away."""
    if stuck:
        y[k] = 0.0
        if float(g(y)) <= 0.0:
            return 1.0 if net(y) > 0 else -1.0
    elif sliding and float(g(y)) <= 0.0:
        y[k] = 0.0
    return None


class ReferenceIntegrator:
    """Advances a :class:`FastState` (float64) by one sample interval with torchdiffeq."""

    def __init__(self, params: TwoMassParams, drive: DriveConfig, M_ext: torch.Tensor | None = None,
                 rtol: float = 1e-10, atol: float = 1e-12):
        f = lambda t: t.reshape(-1).to(torch.float64).tolist()  # noqa: E731
        self.J_M, self.J_L, self.C_F, self.D_F = f(params.J_M), f(params.J_L), f(params.C_F), f(params.D_F)
        self.s, self.M_FC, self.mu_F = f(params.s), f(params.M_FC), f(params.mu_F)
        self.M_FCM, self.mu_FM = f(params.M_FCM), f(params.mu_FM)
        ext = params.M_L0 if M_ext is None else params.M_L0 + torch.as_tensor(M_ext, dtype=torch.float64)
        self.M_ext = f(ext.expand(params.batch_shape))
        self.T_s, self.T_Ei = drive.T_s, drive.T_Ei
        self.rtol, self.atol = rtol, atol
        self.segments = 0

    def _shaft(self, i: int, dphi: torch.Tensor, dw: torch.Tensor) -> torch.Tensor:
        s = self.s[i]
        e = dphi - torch.clamp(dphi, -s, s)
        return self.C_F[i] * e + torch.where(e != 0, self.D_F[i] * dw, torch.zeros_like(e))

    def _advance_one(self, i: int, y: torch.Tensor, M_ref: float) -> torch.Tensor:
        """y = [w_M, w_L, dphi, M_M, phi_M] at the start of the interval -> at its end."""
        T, t = self.T_s, 0.0
        J_M, J_L, s, M_FC, mu_F, M_ext = self.J_M[i], self.J_L[i], self.s[i], self.M_FC[i], self.mu_F[i], self.M_ext[i]
        M_FCM, mu_FM = self.M_FCM[i], self.mu_FM[i]
        motor_coulomb, motor_friction = M_FCM > 0, M_FCM > 0 or mu_FM != 0
        forced_sgn = forced_sgnM = None  # the sign a body breaks away with, for the next segment
        while T - t > 1e-15:
            M_S0 = float(self._shaft(i, y[2], y[0] - y[1]))
            net0 = M_S0 - M_ext
            stuck, sgn = _friction_mode(float(y[1]), net0, M_FC, forced_sgn)
            fric = M_FC * sgn
            # the motor's mode (SPEC 1.1), where it has Coulomb friction
            stuckM, sgnM = (_friction_mode(float(y[0]), float(y[3]) - M_S0, M_FCM, forced_sgnM) if motor_coulomb
                            else (False, 0.0))
            fricM = M_FCM * sgnM

            def rhs(_t, yy, stuck=stuck, fric=fric, stuckM=stuckM, fricM=fricM):
                M_S = self._shaft(i, yy[2], yy[0] - yy[1])
                dwL = torch.zeros_like(M_S) if stuck else (M_S - M_ext - fric - mu_F * yy[1]) / J_L
                if stuckM:
                    dwM = torch.zeros_like(M_S)
                elif motor_friction:
                    dwM = (yy[3] - M_S - fricM - mu_FM * yy[0]) / J_M
                else:
                    dwM = (yy[3] - M_S) / J_M
                return torch.stack([dwM, dwL, yy[0] - yy[1], (M_ref - yy[3]) / self.T_Ei, yy[0]])

            def g_fric(yy, stuck=stuck, sgn=sgn):
                if stuck:
                    net = self._shaft(i, yy[2], yy[0] - yy[1]) - M_ext
                    return M_FC + _EPS_M - net.abs()
                return yy[1] * sgn + _EPS_W

            def g_fricM(yy, stuckM=stuckM, sgnM=sgnM):
                if stuckM:
                    return M_FCM + _EPS_M - (yy[3] - self._shaft(i, yy[2], yy[0] - yy[1])).abs()
                return yy[0] * sgnM + _EPS_W

            g_c0 = float(y[2].abs() - s) if s > 0 else 0.0
            sign_c = 1.0 if g_c0 > 0 else (-1.0 if g_c0 < 0 else 0.0)
            t_start = t

            def event_fn(tt, yy, sign_c=sign_c, t_start=t_start):
                parts = [g_fric(yy), (T - t_start) - tt]
                if motor_coulomb:
                    parts.append(g_fricM(yy))
                if sign_c != 0.0:
                    parts.append(sign_c * (yy[2].abs() - s))
                return torch.min(torch.stack([torch.as_tensor(p, dtype=torch.float64) for p in parts]))

            tt = torch.tensor([0.0, 2.0 * T], dtype=torch.float64)
            t_ev, sol = odeint(rhs, y, tt, event_fn=event_fn, method="dopri5", rtol=self.rtol, atol=self.atol,
                               options={"first_step": min(T, 1e-5)})
            self.segments += 1
            dt_seg = min(float(t_ev), T - t)
            y = sol[-1].clone()
            t += dt_seg
            if T - t <= 1e-15:
                break
            # the load, then the motor: at rest where it stopped, or breaking away from rest
            forced_sgn = _rest_or_break(y, 1, stuck, g_fric,
                                        lambda yy: float(self._shaft(i, yy[2], yy[0] - yy[1])) - M_ext)
            forced_sgnM = _rest_or_break(y, 0, stuckM, g_fricM,
                                         lambda yy: float(yy[3]) - float(self._shaft(i, yy[2], yy[0] - yy[1])),
                                         sliding=motor_coulomb)
        if stuck:
            y[1] = 0.0
        if stuckM:
            y[0] = 0.0
        return y

    def advance(self, x: FastState, M_ref_applied: torch.Tensor) -> None:
        """One sample for every system, in place (``x`` in float64)."""
        M = M_ref_applied.reshape(-1).tolist()
        with torch.no_grad():
            for i in range(x.w_M.numel()):
                y = torch.stack([x.w_M[i], x.w_L[i], x.dphi[i], x.M_M[i], x.phi[i]]).to(torch.float64)
                y = self._advance_one(i, y, M[i])
                x.w_M[i], x.w_L[i], x.dphi[i], x.M_M[i], x.phi[i] = y[0], y[1], y[2], y[3], y[4]
