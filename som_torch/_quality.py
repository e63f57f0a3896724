"""Mask-aware quality measures: quantization and topographic error, U-matrix, hits, degree of order."""

from __future__ import annotations

import torch

from ._recall import best_matching_units, distances
from ._som import SOM


def _has_active(som: SOM, data: torch.Tensor) -> torch.Tensor:
    """Bool ``*batch x N``: the sample has at least one active, non-NaN component."""
    x = som.check_data(data)
    return (~torch.isnan(x) & som.active.unsqueeze(-2)).any(-1)


def quantization_error(som: SOM, data: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean distance from each sample to its best match over the active, non-NaN
    components (normalized units), float64 ``*batch``. Samples without any active value are
    skipped; a map with no such sample (e.g. ``N = 0``) gets NaN."""
    _, d2 = best_matching_units(som, data)  # *batch x N
    ok = _has_active(som, data)
    return torch.where(ok, d2.sqrt(), 0.0).sum(-1) / ok.sum(-1)  # 0 / 0 = NaN: no sample


def topographic_error(som: SOM, data: torch.Tensor) -> torch.Tensor:
    """Share of samples whose best and second-best units (active components) are not grid
    neighbours (rectangular: 8-neighbourhood as MiniSom; hexagonal: 6), float64 ``*batch``.
    Samples without any active value are skipped; a map with no such sample (e.g. ``N = 0``) gets NaN."""
    if som.n_units < 2:
        raise ValueError("topographic_error: needs at least 2 units")
    units, _ = best_matching_units(som, data, k=2)  # *batch x N x 2 (-1: no match)
    u = units.clamp_min(0)
    error = (~som.grid.adjacency[u[..., 0], u[..., 1]]).to(torch.float64)  # *batch x N
    error = torch.where(units[..., 0] >= 0, error, torch.nan)  # no match (NaN weights): NaN
    ok = _has_active(som, data)
    return torch.where(ok, error, 0.0).sum(-1) / ok.sum(-1)  # 0 / 0 = NaN: no sample


def hit_counts(som: SOM, data: torch.Tensor) -> torch.Tensor:
    """Samples per unit (best match on active components), long ``*batch x rows x cols``."""
    units, _ = best_matching_units(som, data)  # *batch x N (-1: no match, no hit)
    B = som.batch_shape.numel()
    hits = torch.zeros(B, som.n_units, dtype=torch.long)
    hits.scatter_add_(1, units.clamp_min(0).reshape(B, -1), (units >= 0).reshape(B, -1).long())  # B x U
    return hits.reshape(*som.batch_shape, som.grid.rows, som.grid.cols)  # *batch x rows x cols


def u_matrix(som: SOM) -> torch.Tensor:
    """Mean Euclidean distance (active components, normalized units) from each unit to its grid
    neighbours, float64 ``*batch x rows x cols``."""
    w = som.weights.to(torch.float64) * som.active.unsqueeze(-2)  # *batch x U x C
    i, j = som.grid.edges.unbind(-1)  # E, E
    d = (w[..., i, :] - w[..., j, :]).norm(dim=-1)  # *batch x E
    total = torch.zeros(*som.batch_shape, som.n_units, dtype=torch.float64)
    total.index_add_(-1, i, d).index_add_(-1, j, d)
    deg = som.grid.adjacency.sum(-1).to(torch.float64)  # U
    return (total / deg).reshape(*som.batch_shape, som.grid.rows, som.grid.cols)


def degree_of_order(som: SOM) -> torch.Tensor:
    """Smoothness of each component map, float64 ``*batch x C``:
    ``1 - mean_{neighbours i,j} (w_i - w_j)^2 / (2 var_u(w))``. 1 = perfectly smooth; about 0 for
    weights shuffled over the grid; constant components give 1."""
    w = som.weights.to(torch.float64)  # *batch x U x C
    i, j = som.grid.edges.unbind(-1)
    msd = ((w[..., i, :] - w[..., j, :]) ** 2).mean(-2)  # *batch x C
    var = w.var(-2, unbiased=False)  # *batch x C
    return torch.where(var > 0, 1.0 - msd / (2.0 * var).clamp_min(1e-300), torch.ones_like(var))


def quality_report(som: SOM, data: torch.Tensor) -> dict:
    """JSON-able summary: per map ``quantization_error``, ``topographic_error``, and
    ``degree_of_order`` per component name (lists follow the flattened batch)."""
    qe = quantization_error(som, data).reshape(-1)
    te = topographic_error(som, data).reshape(-1)
    order = degree_of_order(som).reshape(-1, som.n_components)
    return {
        "quantization_error": [float(v) for v in qe],
        "topographic_error": [float(v) for v in te],
        "degree_of_order": [dict(zip(som.component_names, map(float, row))) for row in order],
    }


__all__ = ["quantization_error", "topographic_error", "hit_counts", "u_matrix", "degree_of_order",
           "quality_report", "distances"]
