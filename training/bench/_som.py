"""``twomass bench som``: som_torch's batched online training against MiniSom 2.3.6.

The paper's set-up: maps of 40 x 40 units, 26 active + 3 inactive components, 1800 vectors,
10 epochs, online rule. Each map gets its own synthetic data set (smooth functions of three
latent parameters, which are the inactive components), range-normalized. MiniSom gets the same
normalized data, the same initial weights, a masked distance (the active components) and the
same schedule (its default ``asymptotic_decay`` for sigma and learning rate, gaussian
neighbourhood, random order, ``num_iteration = epochs * N``). QE and TE of both are measured
with som_torch's mask-aware functions on the same data.
"""

from __future__ import annotations

import argparse
import time

import torch

HELP = "benchmark som_torch's online/batch training against MiniSom"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--maps", type=int, default=10, help="maps trained in one batch (default 10)")
    parser.add_argument("--rows", type=int, default=40)
    parser.add_argument("--cols", type=int, default=40)
    parser.add_argument("--samples", type=int, default=1800, help="training vectors per map (default 1800)")
    parser.add_argument("--active", type=int, default=26, help="active components (features)")
    parser.add_argument("--inactive", type=int, default=3, help="inactive components (parameters)")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--sigma", type=float, default=8.0, help="initial neighbourhood radius (default 8)")
    parser.add_argument("--learning-rate", type=float, default=0.5, help="initial learning rate (default 0.5)")
    parser.add_argument("--minisom-maps", type=int, default=3,
                        help="how many of the maps MiniSom also trains (per-map time; default 3, 0 = skip)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for som_torch (default 1)")
    parser.add_argument("--method", choices=["fast", "native", "torch"], default="fast",
                        help="online implementation: fast = native C kernel if it builds, else torch")
    parser.add_argument("--seed", type=int, default=0)


def make_data(maps: int, n: int, n_active: int, n_inactive: int, seed: int) -> torch.Tensor:
    """Synthetic ``maps x n x (n_active + n_inactive)``: features are smooth functions of the
    latent parameters (the inactive columns) plus 1 % noise."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(maps, n, n_inactive, generator=g, dtype=torch.float64)  # maps x n x a
    proj = torch.randn(maps, n_inactive, n_active, generator=g, dtype=torch.float64)  # maps x a x n_active
    phase = torch.rand(maps, 1, n_active, generator=g, dtype=torch.float64) * 6.28
    feats = torch.sin(1.5 * (p @ proj) + phase) + 0.01 * torch.randn(maps, n, n_active, generator=g, dtype=torch.float64)
    return torch.cat([feats, p], dim=-1)  # maps x n x C


def run(args: argparse.Namespace) -> int:
    import som_torch as st
    from som_torch import _native

    for name in ("maps", "rows", "cols", "samples", "active", "epochs"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: expected a positive integer, received {getattr(args, name)}")
    C = args.active + args.inactive
    names = [f"feature_{i}" for i in range(args.active)] + [f"param_{i}" for i in range(args.inactive)]
    active = [True] * args.active + [False] * args.inactive
    data = make_data(args.maps, args.samples, args.active, args.inactive, args.seed)
    som = st.SOM(st.Grid(args.rows, args.cols), names, active, batch_shape=(args.maps,))
    som.fit_normalization(data, "range")
    st.init_random(som, data, args.seed)
    init = som.clone()
    xn = som.normalize(data)  # maps x N x C, normalized
    steps = args.epochs * args.samples
    print(f"set-up: {args.maps} maps of {args.rows} x {args.cols}, {args.active} active + {args.inactive} inactive "
          f"components, {args.samples} vectors, {args.epochs} epochs ({steps} steps/map), sigma {args.sigma}, "
          f"learning rate {args.learning_rate}, asymptotic decay, gaussian; torch {torch.__version__}, "
          f"{args.threads} thread(s); times: wall (CPU of this process)")
    method = args.method
    if method == "fast":
        method = "native" if _native.available() else "torch"
    if method == "native":  # build/load the kernel outside the timing (cached after the first run)
        st.train_online(init.clone()[:1], data[:1, :2], epochs=1, method="native")

    t0, c0 = time.perf_counter(), time.process_time()
    st.train_online(som, data, epochs=args.epochs, learning_rate=args.learning_rate, sigma=args.sigma,
                    schedule="asymptotic", neighbourhood="gaussian", seed=args.seed, method=method,
                    num_threads=args.threads)
    t_online, c_online = time.perf_counter() - t0, time.process_time() - c0
    qe, te = st.quantization_error(som, data), st.topographic_error(som, data)

    batch = init.clone()
    t0, c0 = time.perf_counter(), time.process_time()
    st.train_batch(batch, data, epochs=args.epochs, sigma=(args.sigma, 1.0), schedule="linear",
                   num_threads=args.threads)
    t_batch, c_batch = time.perf_counter() - t0, time.process_time() - c0
    qe_b, te_b = st.quantization_error(batch, data), st.topographic_error(batch, data)

    M = args.maps
    print(f"som_torch online : {t_online:7.2f} s ({c_online:7.2f} s CPU) for {M} maps = "
          f"{t_online / M:7.3f} s/map ({c_online / M:.3f}); QE {qe.mean():.4f}, TE {te.mean():.4f} "
          f"(mean over maps; method {method})")
    print(f"som_torch batch  : {t_batch:7.2f} s ({c_batch:7.2f} s CPU) for {M} maps = "
          f"{t_batch / M:7.3f} s/map ({c_batch / M:.3f}); QE {qe_b.mean():.4f}, TE {te_b.mean():.4f} "
          f"(batch SOM, sigma {args.sigma} -> 1 linear)")

    k = min(args.minisom_maps, args.maps)
    if k <= 0:
        return 0
    try:
        import numpy as np
        from minisom import MiniSom
    except ImportError:
        print("minisom not installed (pip install -c constraints.txt 'minisom==2.3.6'): MiniSom comparison skipped")
        return 0
    n_act = args.active

    def masked(x, w):  # Euclidean distance over the active (first n_act) components
        return np.linalg.norm(x[:n_act] - w[..., :n_act], axis=-1)

    ref = init[:k].clone()
    t_mini = c_mini = 0.0
    for b in range(k):
        ms = MiniSom(args.rows, args.cols, C, sigma=args.sigma, learning_rate=args.learning_rate,
                     neighborhood_function="gaussian", activation_distance=masked, random_seed=args.seed + b)
        ms._weights = init.weights[b].to(torch.float64).reshape(args.rows, args.cols, C).numpy().copy()
        x = xn[b].numpy()
        t0, c0 = time.perf_counter(), time.process_time()
        ms.train(x, steps, random_order=True)
        t_mini, c_mini = t_mini + time.perf_counter() - t0, c_mini + time.process_time() - c0
        ref.weights[b] = torch.from_numpy(ms.get_weights().reshape(-1, C)).to(ref.weights.dtype)
    qe_m, te_m = st.quantization_error(ref, data[:k]), st.topographic_error(ref, data[:k])
    print(f"MiniSom 2.3.6    : {t_mini:7.2f} s ({c_mini:7.2f} s CPU) for {k} maps = "
          f"{t_mini / k:7.3f} s/map ({c_mini / k:.3f}); QE {qe_m.mean():.4f}, TE {te_m.mean():.4f} "
          f"(mean over its {k} maps)")
    print(f"same {k} maps     : som_torch QE {qe[:k].mean():.4f}, TE {te[:k].mean():.4f}")
    dq = (qe[:k].mean() / qe_m.mean() - 1) * 100
    dte = te[:k].mean() - te_m.mean()
    print(f"speed-up per map : {(t_mini / k) / (t_online / M):.1f}x wall, "
          f"{(c_mini / k) / max(c_online / M, 1e-9):.1f}x CPU (online); "
          f"QE difference {dq:+.2f} %, TE difference {dte:+.4f} (som_torch - MiniSom, same maps)")
    return 0
