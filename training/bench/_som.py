"""``twomass bench som``: som_torch's online training against MiniSom and XPySom, QE and TE beside each time.

The paper's set-up: maps of 40 x 40 units, 26 active + 3 inactive components, 1800 vectors,
10 epochs, online rule. Each map gets its own synthetic data set (smooth functions of three
latent parameters, which are the inactive components), range-normalized. All implementations
start from the same initial weights on the same normalized data; QE and TE of all are measured
with som_torch's mask-aware functions on the same data.

- som_torch online (native kernel where it builds): one map, and ``--maps`` maps in one call;
  float64 (MiniSom's precision) and float32 (the toolkit's default).
- MiniSom 2.3.6 (float64, online): a masked ``activation_distance`` (the active components) and
  the same schedule (``asymptotic_decay`` of sigma and learning rate, gaussian, random order,
  ``num_iteration = epochs * N``); one process trains one map at a time.
- XPySom 1.0.7 (batch SOM, float32 only, BLAS on every core): the active components only (it has
  no masked distance), gaussian of MiniSom's width (``std_coeff=1``), sigma linear to 1.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from training.bench._report import Table, machine_line, write_figures

HELP = "SOM training: som_torch online vs MiniSom (float64) and XPySom (batch), one map and many, QE and TE"

XPYSOM_INSTALL = "pip install xpysom==1.0.7"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--maps", type=int, default=10, help="maps trained in one som_torch call (default 10)")
    parser.add_argument("--rows", type=int, default=40)
    parser.add_argument("--cols", type=int, default=40)
    parser.add_argument("--samples", type=int, default=1800, help="training vectors per map (default 1800)")
    parser.add_argument("--active", type=int, default=26, help="active components (features)")
    parser.add_argument("--inactive", type=int, default=3, help="inactive components (parameters)")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--sigma", type=float, default=8.0, help="initial neighbourhood radius (default 8)")
    parser.add_argument("--learning-rate", type=float, default=0.5, help="initial learning rate (default 0.5)")
    parser.add_argument("--minisom-maps", type=int, default=1,
                        help="maps MiniSom trains, one after the other (default 1; 0 = skip)")
    parser.add_argument("--method", choices=["fast", "native", "torch"], default="fast",
                        help="som_torch online implementation: fast = native C kernel if it builds, else torch")
    parser.add_argument("--seed", type=int, default=0)
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
    """One implementation's figures: wall and CPU time [s] for ``maps`` maps, mean QE and TE."""

    label: str
    precision: str
    maps: int
    threads: int
    wall: float
    cpu: float
    qe: float
    te: float


def _timed(fn: Callable[[], None]) -> tuple[float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def _quality(som, data) -> tuple[float, float]:
    import som_torch as st

    return float(st.quantization_error(som, data).mean()), float(st.topographic_error(som, data).mean())


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


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import som_torch as st
    from som_torch import _native
    from threadpoolctl import threadpool_limits

    for name in ("maps", "rows", "cols", "samples", "active", "epochs"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: expected a positive integer, received {getattr(args, name)}")
    C, R, K, M = args.active + args.inactive, args.rows, args.cols, args.maps
    names = [f"feature_{i}" for i in range(args.active)] + [f"param_{i}" for i in range(args.inactive)]
    active = [True] * args.active + [False] * args.inactive
    data = make_data(M, args.samples, args.active, args.inactive, args.seed)
    init = st.SOM(st.Grid(R, K), names, active, batch_shape=(M,), dtype=torch.float64)
    init.fit_normalization(data, "range")
    st.init_random(init, data, args.seed)
    xn = init.normalize(data)  # maps x N x C, normalized
    steps = args.epochs * args.samples
    method = args.method
    if method == "fast":
        method = "native" if _native.available() else "torch"
    cpus = os.cpu_count() or 1
    print(machine_line())
    print(f"set-up: maps of {R} x {K}, {args.active} active + {args.inactive} inactive components, {args.samples} "
          f"vectors, {args.epochs} epochs ({steps} steps per map), sigma {args.sigma}, learning rate "
          f"{args.learning_rate}, asymptotic decay, gaussian; som_torch online method {method} (one thread); "
          "times: wall and CPU of this process", flush=True)

    def online(n_maps: int, dtype: torch.dtype) -> Run:
        som = _as(init[:n_maps], dtype)
        train = lambda: st.train_online(som, data[:n_maps], epochs=args.epochs, learning_rate=args.learning_rate,  # noqa: E731
                                        sigma=args.sigma, schedule="asymptotic", neighbourhood="gaussian",
                                        seed=args.seed, method=method)
        wall, cpu = _timed(train)
        return Run(f"som_torch online ({method})", str(dtype)[6:], n_maps, 1, wall, cpu, *_quality(som, data[:n_maps]))

    st.train_online(init[:1].clone(), data[:1, :2], epochs=1, method=method)  # build/load the kernels untimed
    st.train_online(_as(init[:1], torch.float32), data[:1, :2], epochs=1, method=method)
    runs = [online(1, torch.float64), online(M, torch.float64), online(1, torch.float32), online(M, torch.float32)]

    k = min(args.minisom_maps, M)
    if k > 0:
        try:
            from minisom import MiniSom
        except ImportError:
            MiniSom = None
            print("MiniSom not installed (pip install 'minisom==2.3.6', extra `bench`): its lines are skipped")
        if MiniSom is not None:
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
            runs.append(Run("MiniSom 2.3.6 online", "float64", k, 1, wall, cpu, *_quality(ref, data[:k])))

    XPySom = _xpysom()
    if XPySom is None:
        print(f"XPySom not installed ({XPYSOM_INSTALL}; not in the `bench` extra): its lines are skipped")
    else:
        for n_maps in sorted({1, M}):
            ref = init[:n_maps].clone()
            wall = cpu = 0.0
            for b in range(n_maps):
                xs = XPySom(R, K, args.active, sigma=args.sigma, sigmaN=1.0, decay_function="linear",
                            neighborhood_function="gaussian", std_coeff=1.0, random_seed=args.seed + b)
                xs._weights = init.weights[b, :, :args.active].reshape(R, K, -1).numpy().astype(np.float32)
                with threadpool_limits(limits=cpus, user_api="blas"):
                    w, c = _timed(lambda: xs.train(xn[b, :, :args.active].numpy(), args.epochs))  # noqa: B023
                wall, cpu = wall + w, cpu + c
                ref.weights[b, :, :args.active] = torch.from_numpy(np.asarray(xs.get_weights(), np.float64)
                                                                   .reshape(-1, args.active))
            runs.append(Run("XPySom 1.0.7 batch", "float32", n_maps, cpus, wall, cpu, *_quality(ref, data[:n_maps])))

    table = Table(["implementation", "precision", "maps", "threads", "wall s", "CPU s", "s/map", "QE", "TE"])
    for r in runs:
        table.add(r.label, r.precision, r.maps, r.threads, f"{r.wall:.2f}", f"{r.cpu:.2f}", f"{r.wall / r.maps:.3f}",
                  f"{r.qe:.4f}", f"{r.te:.4f}")
    print(table.render())
    print("QE, TE: mean over the row's maps (map 0 alone where maps = 1), active components, normalized units")
    per_map = lambda who, prec: [r.wall / r.maps for r in runs if r.label.startswith(who) and r.precision == prec]  # noqa: E731
    for who, prec in (("MiniSom", "float64"), ("XPySom", "float32")):
        if per_map(who, prec):  # at equal precision: our one-map and many-map runs against their best per map
            theirs, ours = min(per_map(who, prec)), per_map("som_torch", prec)
            print(f"som_torch online {prec} per map vs {who} ({prec}): {theirs / ours[0]:.1f}x (1 map per call), "
                  f"{theirs / ours[-1]:.1f}x ({M} maps per call)")
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, {"runs": [vars(r) for r in runs]})
    return 0
