"""Weight initialization: random within each component's range (the paper's), linear (PCA)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ._options import lookup
from ._som import SOM


def map_seeds(seed: int | Sequence[int] | torch.Tensor, batch_shape: torch.Size) -> list[int]:
    """One seed per map (flattened batch order). An int ``s`` gives maps ``s, s+1, ...``;
    a sequence/tensor of shape ``*batch`` gives each map its own."""
    B = int(torch.Size(batch_shape).numel())
    if isinstance(seed, int) and not isinstance(seed, bool):
        return [seed + b for b in range(B)]
    t = torch.as_tensor(seed)
    if t.shape != torch.Size(batch_shape) and t.numel() != B:
        raise ValueError(f"seed: expected an int or *batch = {tuple(batch_shape)} seeds, received shape {tuple(t.shape)}")
    return [int(s) for s in t.reshape(-1)]


def init_random(som: SOM, data: torch.Tensor, seed: int | Sequence[int] | torch.Tensor = 0) -> SOM:
    """Uniform random weights within each component's [min, max] of ``data`` (per map, NaN
    ignored; paper section 3.4). ``data``: raw ``N x C`` or ``*batch x N x C``."""
    x = som.normalize(data, min_samples=1)  # *batch x N x C
    B, C, U = som.batch_shape.numel(), som.n_components, som.n_units
    x = x.reshape(B, -1, C)  # B x N x C
    nan = torch.isnan(x)
    lo = torch.where(nan, torch.inf, x).amin(1)  # B x C
    hi = torch.where(nan, -torch.inf, x).amax(1)
    lo = torch.where(torch.isfinite(lo), lo, 0.0)
    hi = torch.where(torch.isfinite(hi), hi, lo)
    w = torch.empty(B, U, C, dtype=torch.float64)
    for b, s in enumerate(map_seeds(seed, som.batch_shape)):
        g = torch.Generator().manual_seed(s)
        w[b] = lo[b] + (hi[b] - lo[b]) * torch.rand(U, C, generator=g, dtype=torch.float64)
    som.weights = w.reshape(*som.batch_shape, U, C).to(som.weights.dtype)  # *batch x U x C
    return som


def init_linear(som: SOM, data: torch.Tensor, seed: int | Sequence[int] | torch.Tensor = 0) -> SOM:
    """Linear initialization: the data mean plus the grid spread along the first two principal
    components (all components; NaN replaced by the column mean), scaled by their standard
    deviations (rows -> 1st PC, columns -> 2nd). Deterministic; ``seed`` is unused."""
    x = som.normalize(data, min_samples=1)
    B, C = som.batch_shape.numel(), som.n_components
    x = x.reshape(B, -1, C)  # B x N x C
    mean = torch.nanmean(x, 1)  # B x C
    mean = torch.where(torch.isnan(mean), 0.0, mean)
    xc = torch.where(torch.isnan(x), 0.0, x - mean[:, None, :])  # B x N x C
    _, sv, vh = torch.linalg.svd(xc, full_matrices=False)  # sv: B x k, vh: B x k x C
    n = max(xc.shape[1] - 1, 1)
    k = min(2, vh.shape[1])
    std = sv[:, :k] / n**0.5  # B x k
    rc = som.grid.coords  # U x 2
    span = rc - rc.mean(0)
    span = span / span.abs().amax(0).clamp_min(1e-12)  # U x 2 in [-1, 1]
    w = mean[:, None, :].expand(B, som.n_units, C).clone()  # B x U x C
    for i in range(k):
        w += span[None, :, i, None] * (std[:, i, None, None] * vh[:, None, i, :])
    som.weights = w.reshape(*som.batch_shape, som.n_units, C).to(som.weights.dtype)  # *batch x U x C
    return som


INITS = {"random": init_random, "linear": init_linear}


def initialize(som: SOM, data: torch.Tensor, method: str = "random", seed: int | Sequence[int] | torch.Tensor = 0) -> SOM:
    """Initialize ``som`` in place by name: one of ``INITS`` ('random', 'linear')."""
    return lookup(INITS, method, "init")(som, data, seed)
