"""An independent two-mass plant in another process, behind the SPEC 8.1 drive interface.

Written apart from ``sim`` (its own explicit integrator, encoder, friction and backlash), so that
the commissioning chain is tried on a plant it did not write. The plant runs as a child process
(``python remote_plant.py --serve``) stepped sample by sample over JSON lines on stdin/stdout;
the adapter :class:`RemoteDrive` runs the test signal's switching law and the speed law locally,
as a drive's firmware would, and stops at the limits. A torque reference computed at sample ``k``
acts over sample ``k+1`` (SPEC 8.1's computation delay); the record's ``torque_ref`` at ``k`` is the
one acting over sample ``k``.

What the chain's models leave out, each an option of :class:`Plant` (:class:`PlantOptions`): a
second-order current loop of a given damping (same sum time constant ``T_Ei``), extra samples of
dead time in front of the current loop, motor-side Coulomb friction. ``variant=True`` is the set
used by the commissioning tests: damping 1 (two equal poles ``T_Ei/2``), one extra sample, 0.3 Nm.

Use: ``twomass commission --drive tests/training/commissioning/remote_plant.py:make_drive --params plant.json``
(the tests' module re-exports this one).
"""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys
from types import SimpleNamespace

from dataclasses import asdict, dataclass

import numpy as np

CONFIG = dict(T_s=2.5e-4, K_M=1.0, T_Ei=5e-4, encoder_counts=2**20, M_N=10.0, M_max=20.0)


@dataclass(frozen=True)
class PlantOptions:
    """The effects the chain's models leave out: ``current_loop_damping`` (None: the SPEC's first-order
    current loop ``1/(1 + s T_Ei)``; else a second-order lag of this damping with the same sum time
    constant), ``extra_delay`` (samples of dead time before the current loop, beyond the drive's
    computation delay), ``motor_coulomb`` [Nm] (motor-side Coulomb friction)."""

    current_loop_damping: float | None = None
    extra_delay: int = 0
    motor_coulomb: float = 0.0

    @classmethod
    def of(cls, variant: bool) -> "PlantOptions":
        """The tests' variant: damping 1, one extra sample, 0.3 Nm (``variant=False``: the reference)."""
        return cls(1.0, 1, 0.3) if variant else cls()


#: The bench's second drive: a second-order current loop (damping 1/sqrt(2)) with one extra sample of delay.
SECOND_ORDER_DELAYED = PlantOptions(current_loop_damping=1 / math.sqrt(2), extra_delay=1)


class Plant:
    """Two-mass plant (SI): current loop, shaft with backlash (dead zone ``+-s``), load Coulomb
    friction with stiction and viscous friction, optional motor Coulomb friction; semi-implicit
    Euler with ``S`` substeps per sample; encoder speed; current with 0.01 A noise."""

    def __init__(self, p: dict, options: PlantOptions, seed: int = 0) -> None:
        J, V, f_e, d = p["J_sigma"], p["V_J"], p["f_e"], p["d"]
        self.J_M, self.J_L = J / (1 + V), J * V / (1 + V)
        w_0 = 2 * math.pi * f_e / math.sqrt(1 - d * d)
        self.C = w_0 * w_0 * self.J_M * self.J_L / J
        self.D = 2 * d * self.C / w_0
        self.s, self.M_FC, self.mu = p["backlash"] / 2, p["M_FC"], p["mu_F"]
        self.M_FCm = options.motor_coulomb
        self.damping, self.delay = options.current_loop_damping, options.extra_delay
        T_s, T_Ei = CONFIG["T_s"], CONFIG["T_Ei"]
        self.S = max(8, math.ceil(T_s * w_0 * 4), math.ceil(8 * T_s / T_Ei))
        self.h = T_s / self.S
        self.q = 2 * math.pi / CONFIG["encoder_counts"]
        self.rng = random.Random(seed)
        self.reset()

    def reset(self) -> None:
        self.M = self.M1 = self.wM = self.wL = self.tw = self.phi = 0.0
        self.cnt = 0
        self.queue = [0.0] * self.delay
        self.peaks = {"w_M": 0.0, "w_L": 0.0, "phi_M": 0.0}

    def _friction(self, w: float, drive: float, F: float) -> tuple[float, bool]:
        """Coulomb friction torque on a body at speed ``w`` under the driving torque ``drive``;
        True when it sticks (at rest and the friction holds it)."""
        if w == 0.0 and abs(drive) <= F:
            return drive, True
        return F * (1.0 if (w if w != 0.0 else drive) > 0 else -1.0), False

    def step(self, M_ref: float) -> tuple[float, float]:
        """Apply ``M_ref`` over one sample; return (measured speed, measured current) at the next sample."""
        self.queue.append(M_ref)
        u = self.queue.pop(0)
        h, T = self.h, CONFIG["T_Ei"]
        for _ in range(self.S):
            if self.damping is None:
                self.M += h * (u - self.M) / T
            else:  # M'' = w^2 (u - M) - 2 D w M', w = 2 D / T (sum time constant T)
                D = self.damping
                w = 2 * D / T
                self.M1 += h * (w * w * (u - self.M) - 2 * D * w * self.M1)
                self.M += h * self.M1
            x = self.tw
            MS = 0.0 if abs(x) <= self.s else self.C * (x - math.copysign(self.s, x)) + self.D * (self.wM - self.wL)
            fm, stuck_m = self._friction(self.wM, self.M - MS, self.M_FCm)
            wM = 0.0 if stuck_m else self.wM + h * (self.M - MS - fm) / self.J_M
            if self.wM != 0.0 and wM * self.wM < 0 and self.M_FCm > 0:
                wM = 0.0
            fl, stuck_l = self._friction(self.wL, MS - self.mu * self.wL, self.M_FC)
            wL = 0.0 if stuck_l else self.wL + h * (MS - fl - self.mu * self.wL) / self.J_L
            if self.wL != 0.0 and wL * self.wL < 0 and self.M_FC > 0:
                wL = 0.0
            self.wM, self.wL = wM, wL
            self.tw += h * (self.wM - self.wL)
            self.phi += h * self.wM
        pk = self.peaks
        pk["w_M"], pk["w_L"], pk["phi_M"] = max(pk["w_M"], abs(self.wM)), max(pk["w_L"], abs(self.wL)), max(pk["phi_M"], abs(self.phi))
        cnt = math.floor(self.phi / self.q)
        w = (cnt - self.cnt) * self.q / CONFIG["T_s"]
        self.cnt = cnt
        return w, self.M / CONFIG["K_M"] + 0.01 * self.rng.gauss(0.0, 1.0)


def serve() -> None:
    """The plant process: first line the plant (``{"params": {...}, "options": {...}}``), then per
    line ``{"M": M_ref}`` -> ``[w, i]``, ``{"reset": 1}`` -> ``{}``, ``{"peaks": 1}`` -> the true peaks."""
    first = json.loads(sys.stdin.readline())
    plant = Plant(first["params"], PlantOptions(**first["options"]), first.get("seed", 0))
    out = sys.stdout
    for line in sys.stdin:
        msg = json.loads(line)
        if "M" in msg:
            out.write(json.dumps(plant.step(msg["M"])) + "\n")
        elif "reset" in msg:
            plant.reset()
            out.write("{}\n")
        else:
            out.write(json.dumps(plant.peaks) + "\n")
        out.flush()


class RemoteDrive:
    """SPEC 8.1 drive around the plant process. ``experiments``: per experiment its kind and the
    plant's true peaks ``w_M, w_L, phi_M`` (for the evaluation; the chain never sees them)."""

    def __init__(self, params: dict, variant: bool = False, seed: int = 0, timeout: float = 2.0,
                 options: PlantOptions | None = None) -> None:
        """``options`` (default: :meth:`PlantOptions.of` ``variant``) overrides ``variant``."""
        self.config = SimpleNamespace(**CONFIG)
        self.options = PlantOptions.of(variant) if options is None else options
        self.params, self.timeout = dict(params), timeout
        self.proc = subprocess.Popen([sys.executable, __file__, "--serve"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._send({"params": self.params, "options": asdict(self.options), "seed": seed}, reply=False)
        self.experiments: list[dict] = []

    def _send(self, msg: dict, reply: bool = True):
        self.proc.stdin.write(json.dumps(msg) + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline()) if reply else None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            self.proc.wait(timeout=10)

    def truth(self) -> dict:
        o = self.options
        return {**self.params, "current_loop_damping": o.current_loop_damping, "extra_delay": o.extra_delay,
                "motor_coulomb": o.motor_coulomb}

    def _run(self, law, n_max: int, limits, kind: str, meta: dict):
        """Sample loop: ``law(k, w) -> (M_ref, section or None, done)``; stop at the limits."""
        T_s, cap = CONFIG["T_s"], min(CONFIG["M_max"], limits.M_max or math.inf)
        self._send({"reset": 1})
        w = phi = M_ref = i = 0.0  # M_ref: computed at the sample before, applied over this one (SPEC 8.1)
        rows, stop = [], None
        for k in range(n_max):
            M_cmd, sec, done = law(k, w)
            rows.append((k * T_s, w, i, M_ref, sec))
            if done:
                break
            phi += w * T_s
            if stop is None and (abs(w) > limits.w_max or abs(phi) > limits.travel):
                stop = k
            if stop is not None and k >= stop + 200:
                break
            w, i = self._send({"M": M_ref})
            M_ref = 0.0 if stop is not None else max(-cap, min(cap, M_cmd))
        import sim  # only for the record type the interface returns

        t, sp, cur, tr, sec = (np.array([r[j] if r[j] is not None else 0 for r in rows], dtype=float) for j in range(5))
        self.experiments.append({"kind": kind, **self._send({"peaks": 1})})
        meta = {"K_M": 1.0, "T_Ei": CONFIG["T_Ei"], "T_s": T_s, "encoder_counts": CONFIG["encoder_counts"],
                "M_max": CONFIG["M_max"], "M_N": CONFIG["M_N"], "aborted": stop is not None, **meta}
        return sim.Record(t=t, speed=sp, current=cur, torque_ref=tr, meta=meta, name=kind,
                          section=sec.astype(np.int64) if kind == "test" else None)

    def run_test(self, M_star, w_max, limits):
        """The six-section switching test (SPEC 2), written here from the table."""
        n_to, n_tail = round(self.timeout / CONFIG["T_s"]), round(0.05 / CONFIG["T_s"])
        st = {"sec": 1, "cnt": 0, "n1": 0, "n4": 0, "tmo": [False] * 6}
        level = {1: M_star, 2: 0.0, 3: -0.7 * M_star, 4: -M_star, 5: 0.0, 6: 0.7 * M_star, 7: 0.0}
        end = {1: lambda w, c: w >= w_max, 2: lambda w, c: c >= st["n1"] or w <= 0.2 * w_max, 3: lambda w, c: w <= 0,
               4: lambda w, c: w <= -w_max, 5: lambda w, c: c >= st["n4"] or w >= -0.2 * w_max, 6: lambda w, c: w >= 0,
               7: lambda w, c: c >= n_tail}

        def law(k, w):
            q = st["sec"]
            label = 0 if q == 7 else q
            c = st["cnt"] + 1
            fin = end[q](w, c)
            if q <= 6 and not fin and c >= n_to:
                st["tmo"][q - 1], fin = True, True
            if fin:
                if q in (1, 4):
                    st["n1" if q == 1 else "n4"] = c
                st["sec"], st["cnt"] = q + 1, 0
            else:
                st["cnt"] = c
            return level.get(st["sec"], 0.0), label, q == 8
        rec = self._run(lambda k, w: law(k, w) if st["sec"] <= 7 else (0.0, 0, True), 6 * n_to + n_tail + 2, limits, "test",
                        {"M_star": M_star, "w_max": w_max})
        rec.meta["timed_out"] = st["tmo"]
        return rec

    def run_closed_loop(self, law, scenario, limits):
        law.reset()
        w_ref, M_dist = scenario.w_ref, scenario.M_dist
        return self._run(lambda k, w: (law.step(w, w_ref[k]) + M_dist[k], None, False), len(w_ref), limits, "closed_loop", {})


def make_drive(plant: dict | None = None, variant: bool = False, options: PlantOptions | None = None) -> RemoteDrive:
    """The factory for ``twomass commission --drive``: one plant (default: an elastic 30 Hz one)."""
    return RemoteDrive(plant or dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.03, backlash=0.0, M_FC=0.2, mu_F=0.001), variant,
                       options=options)


def make_variant_drive(plant: dict | None = None) -> RemoteDrive:
    """:func:`make_drive` with the variant: 2nd-order current loop, one extra sample delay, motor friction 0.3 Nm."""
    return make_drive(plant, variant=True)


if __name__ == "__main__" and sys.argv[1:] == ["--serve"]:
    serve()
