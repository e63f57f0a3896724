"""``twomass bench som``: som_torch's online training against MiniSom and XPySom at equal precision
and equal or better quality, one map and many, QE and TE beside each time.

The paper's set-up: maps of 40 x 40 units, 26 active + 3 inactive components, 1800 vectors,
10 epochs. Each map gets its own synthetic data set (smooth functions of three latent parameters,
which are the inactive components), range-normalized. Every implementation starts from the same
initial weights on the same normalized data for the same epochs; QE and TE of all are measured
with som_torch's mask-aware functions on the same data (active components, normalized units).

- **float64 against MiniSom 2.3.6** (online, float64; ``bench`` extra), both at MiniSom's defaults
  for the paper's schedule: ``asymptotic_decay`` of sigma (8) and learning rate (0.5), gaussian,
  random order, ``num_iteration = epochs * N``, a masked ``activation_distance`` (the active
  components). The same rule and schedule: QE and TE differ only by the random order.
- **float32 against XPySom 1.0.7** (batch SOM, float32 only, BLAS on every core; optional:
  ``pip install xpysom==1.0.7``, its lines are skipped when it is absent) in two settings: its
  defaults (exponential decay, ``std_coeff=0.5``: a gaussian of half the width) and MiniSom's
  gaussian (``std_coeff=1``, linear decay); sigma 8 to 1 in both (active components only: it has
  no masked distance). A batch SOM ends each epoch at the neighbourhood-weighted mean, so at the
  same epochs it reaches a lower QE than the online rule on MiniSom's schedule (whose sigma ends
  at 8/3) and a higher TE. Equal quality is therefore set by the schedule, not the epochs: each
  XPySom setting is paired with the online schedule of :data:`MATCHED` (exponential decay of sigma
  and learning rate, the same epochs), and the bench prints whether that run's QE *and* TE (mean
  over the maps) are equal or better than XPySom's. The online rule's work per step does not
  depend on the schedule.

som_torch runs one map (one thread) and ``--maps`` maps in one call (the kernel's threads, one
map per thread: :func:`som_torch._native.threads`); MiniSom and XPySom train one map at a time.
Times are wall and CPU of this process; CPU / wall above 1 means more than one core worked.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch

from training.bench._report import Table, machine_line, write_figures

HELP = ("SOM training: som_torch online vs MiniSom (float64) and XPySom batch (float32) at equal or better QE "
        "and TE, one map and many")

XPYSOM_INSTALL = "pip install xpysom==1.0.7"


@dataclass(frozen=True)
class Schedule:
    """An online schedule: ``schedule`` of som_torch, sigma and learning rate (start, end)."""

    name: str
    sigma: tuple[float, float]
    learning_rate: tuple[float, float]

    def label(self) -> str:
        return (f"{self.name} sigma {self.sigma[0]:.3g}->{self.sigma[1]:.3g}, "
                f"lr {self.learning_rate[0]:.3g}->{self.learning_rate[1]:.3g}")


@dataclass(frozen=True)
class XPySomSetting:
    """One XPySom setting (sigma from ``--sigma`` to 1) and the online schedule paired with it."""

    label: str
    decay: str
    std_coeff: float
    online: Schedule


#: XPySom's settings and the online schedules that reach equal or better QE and TE in the same
#: epochs (their end values; they start at ``--sigma`` and ``--learning-rate``; chosen on the
#: default set-up's maps; every run checks and prints the comparison).
MATCHED = (
    XPySomSetting("defaults: exponential, std_coeff 0.5", "exponential", 0.5,
                  Schedule("exponential", (8.0, 0.3), (0.5, 0.1))),
    XPySomSetting("MiniSom's gaussian: linear, std_coeff 1", "linear", 1.0,
                  Schedule("exponential", (8.0, 1.0), (0.5, 0.1))),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--maps", type=int, default=10, help="maps trained in one som_torch call (default 10)")
    parser.add_argument("--rows", type=int, default=40, help="map rows (default 40)")
    parser.add_argument("--cols", type=int, default=40, help="map columns (default 40)")
    parser.add_argument("--samples", type=int, default=1800, help="training vectors per map (default 1800)")
    parser.add_argument("--active", type=int, default=26, help="active components (features; default 26)")
    parser.add_argument("--inactive", type=int, default=3, help="inactive components (parameters; default 3)")
    parser.add_argument("--epochs", type=int, default=10, help="passes over the vectors (default 10)")
    parser.add_argument("--sigma", type=float, default=8.0, help="initial neighbourhood radius (default 8)")
    parser.add_argument("--learning-rate", type=float, default=0.5, help="initial learning rate (default 0.5)")
    parser.add_argument("--minisom-maps", type=int, default=1,
                        help="maps MiniSom trains, one after the other (default 1; 0 = skip)")
    parser.add_argument("--method", choices=["fast", "native", "torch"], default="fast",
                        help="som_torch online implementation: fast = native C kernel if it builds, else torch")
    parser.add_argument("--seed", type=int, default=0, help="data and initial weights seed (default 0)")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def make_data(maps: int, n: int, n_active: int, n_inactive: int, seed: int) -> torch.Tensor:
    """Synthetic ``maps x n x (n_active + n_inactive)``: features are smooth functions of the
    latent parameters (the inactive columns) plus 1 % noise."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(maps, n, n_inactive, generator=g, dtype=torch.float64)  # maps x n x a
    proj = torch.randn(maps, n_inactive, n_active, generator=g, dtype=torch.float64)  # maps x a x n_active
    phase = torch.rand(maps, 1, n_active, generator=g, dtype=torch.float64) * 6.28
    feats = torch.sin(1.5 * (p @ proj) + phase) + 0.01 * torch.randn(maps, n, n_active, generator=g, dtype=torch.float64)
    return torch.cat([feats, p], dim=-1)  # maps x n x C


@dataclass
class Run:
    """One implementation's figures: wall and CPU time [s] for ``maps`` maps, QE and TE per map."""

    label: str
    schedule: str
    precision: str
    maps: int
    threads: int
    wall: float
    cpu: float
    qe: list[float]
    te: list[float]

    def per_map(self) -> float:
        return self.wall / self.maps


def _timed(fn: Callable[[], None]) -> tuple[float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def _quality(som, data) -> tuple[list[float], list[float]]:
    import som_torch as st

    return st.quantization_error(som, data).tolist(), st.topographic_error(som, data).tolist()


def _as(som, dtype: torch.dtype):
    """A copy of ``som`` with its weights in ``dtype``."""
    import som_torch as st

    return st.SOM(som.grid, som.component_names, som.active, weights=som.weights.to(dtype), offset=som.offset,
                  scale=som.scale, dtype=dtype)


def _xpysom():
    """The XPySom class, or None when not installed (it prints a CuPy warning on import: swallowed)."""
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            from xpysom import XPySom
        except ImportError:
            return None
    return XPySom


def _mean(values: list[float]) -> float:
    return sum(values) / len(values)


def _verdict(ours: Run, theirs: Run) -> str:
    """Speed-up per map and the quality comparison on the maps both trained (mean QE and TE)."""
    k = min(ours.maps, theirs.maps)
    qo, qt, to, tt = (_mean(v[:k]) for v in (ours.qe, theirs.qe, ours.te, theirs.te))
    ok = "yes" if qo <= qt and to <= tt else "NO"
    return (f"{theirs.per_map() / ours.per_map():.1f}x per map; QE {qo:.4f} vs {qt:.4f}, TE {to:.4f} vs {tt:.4f} "
            f"(mean over {k} map(s)): equal or better: {ok}")


@dataclass(frozen=True)
class _Setup:
    """What every implementation starts from: the data (``maps x N x C``), its normalized twin
    (``xn``), the initial maps (``init``), the som_torch method and the command's arguments."""

    args: argparse.Namespace
    data: torch.Tensor
    xn: torch.Tensor
    init: Any
    method: str

    @property
    def maps(self) -> int:
        return int(self.args.maps)


def _check_args(args: argparse.Namespace) -> None:
    """A ``ValueError`` naming the first option out of range."""
    from training._checks import finite_number, seed

    for name in ("maps", "rows", "cols", "samples", "active", "epochs"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: expected a positive integer, received {getattr(args, name)}")
    if args.inactive < 0:
        raise ValueError(f"--inactive: expected an integer >= 0, received {args.inactive}")
    finite_number("--sigma", args.sigma)
    finite_number("--learning-rate", args.learning_rate)
    seed("--seed", args.seed)


def _setup(args: argparse.Namespace) -> _Setup:
    """The data, the initial maps (range-normalized, random initial weights) and the method."""
    import som_torch as st
    from som_torch import _native

    names = [f"feature_{i}" for i in range(args.active)] + [f"param_{i}" for i in range(args.inactive)]
    active = [True] * args.active + [False] * args.inactive
    data = make_data(args.maps, args.samples, args.active, args.inactive, args.seed)
    init = st.SOM(st.Grid(args.rows, args.cols), names, active, batch_shape=(args.maps,), dtype=torch.float64)
    init.fit_normalization(data, "range")
    st.init_random(init, data, args.seed)
    method = args.method
    if method == "fast":
        method = "native" if _native.available() else "torch"
    return _Setup(args, data, init.normalize(data), init, method)


def _online(setup: _Setup, n_maps: int, dtype: torch.dtype, sched: Schedule) -> Run:
    """som_torch's online training of the first ``n_maps`` maps in one call."""
    import som_torch as st
    from som_torch import _native

    args, method = setup.args, setup.method
    som = _as(setup.init[:n_maps], dtype)
    train = lambda: st.train_online(som, setup.data[:n_maps], epochs=args.epochs, learning_rate=sched.learning_rate,  # noqa: E731
                                    sigma=sched.sigma, schedule=sched.name, neighbourhood="gaussian",
                                    seed=args.seed, method=method)
    wall, cpu = _timed(train)
    threads = _native.threads(n_maps) if method == "native" else 1
    return Run(f"som_torch online ({method})", sched.label(), str(dtype)[6:], n_maps, threads, wall, cpu,
               *_quality(som, setup.data[:n_maps]))


def _minisom(setup: _Setup, paper: Schedule, k: int) -> Run | None:
    """MiniSom on the first ``k`` maps, one after the other; None when it is not installed."""
    import numpy as np

    try:
        from minisom import MiniSom
    except ImportError:
        print("MiniSom not installed (pip install 'minisom==2.3.6', extra `bench`): its lines are skipped")
        return None
    args, init, xn = setup.args, setup.init, setup.xn
    R, K, C = args.rows, args.cols, args.active + args.inactive
    steps = args.epochs * args.samples
    ref = init[:k].clone()
    masked = lambda x, w: np.linalg.norm(x[:args.active] - w[..., :args.active], axis=-1)  # noqa: E731
    wall = cpu = 0.0
    for b in range(k):
        ms = MiniSom(R, K, C, sigma=args.sigma, learning_rate=args.learning_rate,
                     neighborhood_function="gaussian", activation_distance=masked, random_seed=args.seed + b)
        ms._weights = init.weights[b].reshape(R, K, C).numpy().copy()
        w, c = _timed(lambda: ms.train(xn[b].numpy(), steps, random_order=True))  # noqa: B023
        wall, cpu = wall + w, cpu + c
        ref.weights[b] = torch.from_numpy(ms.get_weights().reshape(-1, C))
    return Run("MiniSom 2.3.6 online", paper.label(), "float64", k, 1, wall, cpu, *_quality(ref, setup.data[:k]))


def _xpysom_run(setup: _Setup, XPySom: Any, setting: XPySomSetting) -> Run:
    """XPySom's batch training of every map in ``setting``, one after the other (BLAS on every core)."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    args, init, xn = setup.args, setup.init, setup.xn
    R, K, cpus = args.rows, args.cols, os.cpu_count() or 1
    ref = init.clone()
    wall = cpu = 0.0
    for b in range(setup.maps):
        xs = XPySom(R, K, args.active, sigma=args.sigma, sigmaN=1.0, decay_function=setting.decay,
                    neighborhood_function="gaussian", std_coeff=setting.std_coeff, random_seed=args.seed + b)
        xs._weights = init.weights[b, :, :args.active].reshape(R, K, -1).numpy().astype(np.float32)
        with threadpool_limits(limits=cpus, user_api="blas"):
            w, c = _timed(lambda: xs.train(xn[b, :, :args.active].numpy(), args.epochs))  # noqa: B023
        wall, cpu = wall + w, cpu + c
        ref.weights[b, :, :args.active] = torch.from_numpy(np.asarray(xs.get_weights(), np.float64)
                                                           .reshape(-1, args.active))
    return Run("XPySom 1.0.7 batch", f"{setting.decay} sigma {args.sigma:g}->1, std_coeff "
               f"{setting.std_coeff:g}", "float32", setup.maps, cpus, wall, cpu, *_quality(ref, setup.data))


def run(args: argparse.Namespace) -> int:
    import som_torch as st
    from som_torch import _native

    _check_args(args)
    setup = _setup(args)
    M, steps = args.maps, args.epochs * args.samples
    paper = Schedule("asymptotic", (args.sigma, args.sigma / 3), (args.learning_rate, args.learning_rate / 3))
    print(machine_line())
    print(f"set-up: maps of {args.rows} x {args.cols}, {args.active} active + {args.inactive} inactive components, "
          f"{args.samples} vectors, {args.epochs} epochs ({steps} steps per map), gaussian; som_torch online method "
          f"{setup.method}, kernel {_native.library()}, {_native.threads(M)} thread(s) for {M} maps; times: wall and "
          "CPU of this process", flush=True)
    for dtype in (torch.float64, torch.float32):  # build/load the kernels untimed
        st.train_online(_as(setup.init[:1], dtype), setup.data[:1, :2], epochs=1, method=setup.method)
    runs = [_online(setup, 1, torch.float64, paper), _online(setup, M, torch.float64, paper)]
    verdicts = []
    k = min(args.minisom_maps, M)
    minisom = _minisom(setup, paper, k) if k > 0 else None
    if minisom is not None:
        runs.append(minisom)
        verdicts += [f"som_torch online float64 vs MiniSom (float64), {paper.label()}, {n} map(s) per call: "
                     f"{_verdict(ours, minisom)}" for n, ours in ((1, runs[0]), (M, runs[1]))]
    XPySom = _xpysom()
    if XPySom is None:
        print(f"XPySom not installed ({XPYSOM_INSTALL}; not in the `bench` extra): its lines are skipped")
    for setting in MATCHED:
        sched = replace(setting.online, sigma=(args.sigma, setting.online.sigma[1]),
                        learning_rate=(args.learning_rate, setting.online.learning_rate[1]))
        ours = [_online(setup, 1, torch.float32, sched), _online(setup, M, torch.float32, sched)]
        runs += ours
        if XPySom is None:
            continue
        runs.append(_xpysom_run(setup, XPySom, setting))
        verdicts += [f"som_torch online float32, {sched.label()}, vs XPySom (float32) {setting.label}, {n} map(s) "
                     f"per call: {_verdict(our, runs[-1])}" for n, our in ((1, ours[0]), (M, ours[1]))]
    _report(args, runs, verdicts)
    return 0


def _report(args: argparse.Namespace, runs: list[Run], verdicts: list[str]) -> None:
    """The table of the runs, the verdicts, the command line; the JSON file where asked for."""
    table = Table(["implementation", "precision", "maps", "threads", "schedule", "wall s", "CPU s", "CPU/wall",
                   "s/map", "QE", "TE"])
    for r in runs:
        table.add(r.label, r.precision, r.maps, r.threads, r.schedule, f"{r.wall:.2f}", f"{r.cpu:.2f}",
                  f"{r.cpu / r.wall:.2f}", f"{r.per_map():.3f}", f"{_mean(r.qe):.4f}", f"{_mean(r.te):.4f}")
    print(table.render())
    print("QE, TE: mean over the row's maps (map 0 alone where maps = 1), active components, normalized units; "
          "CPU/wall near the thread count: every thread worked")
    for line in verdicts:
        print(line)
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, {"runs": [vars(r) for r in runs], "verdicts": verdicts})
