"""The baseline of ``twomass bench sim``: the SPEC 2 switching test in plain vectorized numpy.

What a competent user writes without our kernel: every operation an array op over all systems,
fixed-step RK4 with ``S`` substeps per sample, the same model (two-mass plant, backlash dead zone,
Coulomb + viscous load friction with stiction, first-order current loop with its torque floor,
encoder quantization) and the same switching controller. It does the arithmetic of
``sim/_kernel.c`` operation for operation (Kahan-compensated state updates included), so the
comparison is of equal work at equal precision, and the tests check it against the kernel's output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim._integrate_fast import TORQUE_FLOOR

#: add/sub/mul per system-substep here, counted as written: 7 (shaft torque, friction) + 4 x 15
#: (the RK4 stages' right-hand sides) + 24 (stage states) + 7 (motor-angle increment) + 41 (four
#: Kahan updates, the stop test's product). Compares, min/max, selects and signs are not counted.
#: The kernel does the same arithmetic in 129 (``sim._kernel.FLOPS_PER_SUBSTEP``): stage 1 shares
#: the mode decision's shaft torque, net torque and ``w_M - w_L``, and ``ddphi`` is ``w_M - w_L``.
#: (SPEC 1.1's motor friction, which the kernel runs in blocks of their own, is not modelled here.)
FLOPS_PER_SUBSTEP = 139


@dataclass
class TestOutput:
    """The recorded channels ``n x nk`` (float dtype; section int8, -1 once a system finished) of the
    first ``nk`` samples."""

    speed: np.ndarray
    torque: np.ndarray
    torque_ref: np.ndarray
    section: np.ndarray


def switching_test(coef: dict[str, np.ndarray], S: int, consts: tuple[float, float, float, float],
                   encoder: tuple[float, float], levels: tuple[float, float, float, float], M_max: float,
                   n_timeout: int, n_tail: int, nk: int) -> TestOutput:
    """The first ``nk`` samples of the switching test for ``n`` systems.

    ``coef``: ``iJM, iJL, CF, DF, s, MFC, muF, Mext`` (``n``, float32 or float64: the working
    dtype); ``consts``: ``dt, h, k6, 1/T_Ei``; ``encoder``: speed quantum and counts per radian;
    ``levels``: ``M*, M_low, w_max, w_low`` (``sim.TestSignalConfig.levels``)."""
    dt_ = coef["iJM"].dtype
    iJM, iJL, CF, DF, s, MFC, muF, Mext = (coef[k] for k in ("iJM", "iJL", "CF", "DF", "s", "MFC", "muF", "Mext"))
    dt, h, k6, iTE = (dt_.type(v) for v in consts)
    Mstar, Mlow, wmax, wlow = (dt_.type(v) for v in levels)
    Mmax, two, zero, floor = dt_.type(M_max), dt_.type(2), dt_.type(0), dt_.type(TORQUE_FLOOR)
    qw, scale = encoder
    n = iJM.size
    wM, wL, dp, MM, Mref = (np.zeros(n, dt_) for _ in range(5))
    cwM, cwL, cdp, cMM = (np.zeros(n, dt_) for _ in range(4))
    phi, cntp = np.zeros(n), np.zeros(n)
    sec, cnt, nI, nIV = np.ones(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.int32)
    out = TestOutput(*(np.empty((n, nk), dt_) for _ in range(3)), np.empty((n, nk), np.int8))

    def shaft(wM, wL, dp):
        e = dp - np.minimum(np.maximum(dp, -s), s)
        return CF * e + np.where(e != 0, DF * (wM - wL), zero)

    def rhs(wM, wL, dp, MM, stuck, fric):
        MS = shaft(wM, wL, dp)
        return ((MM - MS) * iJM, np.where(stuck, zero, (MS - Mext - fric - muF * wL) * iJL), wM - wL,
                (Mref - MM) * iTE)

    def kahan(x, k1, k2, k3, k4, comp):
        y = k6 * (k1 + two * k2 + two * k3 + k4) - comp
        t = x + y
        return t, (t - x) - y

    for k in range(nk):
        # measure, record, controller (its new reference applies from the next sample)
        c = np.floor(phi * scale)
        w = ((c - cntp) * qw).astype(dt_)
        cntp = c
        out.speed[:, k], out.torque[:, k], out.torque_ref[:, k] = w, MM, Mref
        out.section[:, k] = np.where(sec == 7, 0, np.where(sec == 8, -1, sec))  # -1: finished (padding)
        active = sec < 8
        t = cnt + 1
        end = np.select([sec == 1, sec == 2, sec == 3, sec == 4, sec == 5, sec == 6],
                        [w >= wmax, (t >= nI) | (w <= wlow), w <= zero, w <= -wmax, (t >= nIV) | (w >= -wlow),
                         w >= zero], t >= n_tail)
        end |= (sec <= 6) & (t >= n_timeout)
        end &= active
        nI = np.where(end & (sec == 1), t, nI)
        nIV = np.where(end & (sec == 4), t, nIV)
        sec = np.where(end, sec + 1, sec)
        cnt = np.where(end, 0, np.where(active, t, cnt))
        mr = np.select([sec == 1, sec == 3, sec == 4, sec == 6], [Mstar, -Mlow, -Mstar, Mlow], zero).astype(dt_)
        new_ref = np.where(active, np.clip(mr, -Mmax, Mmax), Mref)
        # S RK4 substeps with the applied reference (mode frozen over a substep)
        inc = np.zeros(n, dt_)
        for _ in range(S):
            net = shaft(wM, wL, dp) - Mext
            rest = wL == 0
            stuck = rest & (np.abs(net) <= MFC)
            sgn = np.where(rest, np.sign(net), np.sign(wL))
            fric = MFC * sgn
            a1, b1, c1, d1 = rhs(wM, wL, dp, MM, stuck, fric)
            wM2, wL2, dp2, MM2 = wM + h * a1, wL + h * b1, dp + h * c1, MM + h * d1
            a2, b2, c2, d2 = rhs(wM2, wL2, dp2, MM2, stuck, fric)
            wM3, wL3, dp3, MM3 = wM + h * a2, wL + h * b2, dp + h * c2, MM + h * d2
            a3, b3, c3, d3 = rhs(wM3, wL3, dp3, MM3, stuck, fric)
            wM4, wL4, dp4, MM4 = wM + dt * a3, wL + dt * b3, dp + dt * c3, MM + dt * d3
            a4, b4, c4, d4 = rhs(wM4, wL4, dp4, MM4, stuck, fric)
            inc = inc + k6 * (wM + two * wM2 + two * wM3 + wM4)
            wM, cwM = kahan(wM, a1, a2, a3, a4, cwM)
            t_wL, c_wL = kahan(wL, b1, b2, b3, b4, cwL)
            stop = stuck | (t_wL * sgn < 0)  # a load that changed sign against its friction stops
            wL, cwL = np.where(stop, zero, t_wL), np.where(stop, zero, c_wL)
            dp, cdp = kahan(dp, c1, c2, c3, c4, cdp)
            t_MM, c_MM = kahan(MM, d1, d2, d3, d4, cMM)
            gone = np.abs(t_MM) < floor  # the decayed current-loop torque is 0 (sim.TORQUE_FLOOR's rule)
            MM, cMM = np.where(gone, zero, t_MM), np.where(gone, zero, c_MM)
        phi = phi + inc.astype(np.float64)
        Mref = new_ref
    return out
