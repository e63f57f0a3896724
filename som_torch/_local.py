"""Local linear maps: each unit reads its inactive components out as a linear function of the active
ones around its own weights (Ritter, Martinetz and Schulten's local linear maps), fitted by least
squares on the data that the unit's grid neighbourhood holds."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ._recall import _best_matching_units
from ._som import SOM, LocalLinear

#: Rows summed at once by :func:`fit_local_linear` (its temporaries grow with rows x components^2).
_CHUNK_ROWS = 2048


def shared_mask(som: SOM, name: str) -> torch.Tensor:
    """The one active mask (``C`` flags) that all maps of ``som`` share; a ValueError naming ``name`` otherwise."""
    act = som.active.reshape(-1, som.n_components)  # B x C
    if not bool((act == act[0]).all()):
        raise ValueError(f"{name}: expected one active mask shared by all maps of the batch")
    return act[0]


def check_local(som: SOM, local: LocalLinear) -> LocalLinear:
    """``local`` as ``som``'s dtype and device, its shapes checked against ``som``."""
    if not isinstance(local, LocalLinear):
        raise TypeError(f"local: expected a som_torch.LocalLinear, received {type(local).__name__}")
    mask = shared_mask(som, "local")
    A, T = int(mask.sum()), som.n_components - int(mask.sum())
    shape = (*som.batch_shape, som.n_units, T)
    got = [tuple(t.shape) for t in (local.intercepts, local.slopes, local.lower, local.upper)]
    if got != [shape, (*shape, A), shape, shape]:
        raise ValueError(f"local: expected intercepts, slopes, lower, upper of shapes {shape}, {(*shape, A)}, {shape}, "
                         f"{shape}, received {', '.join(map(str, got))}")
    return local.map(lambda t: t.to(som.device, som.weights.dtype))


def fit_local_linear(som: SOM, data: torch.Tensor, *, radius: float = 1.5,
                     ridge: float | Sequence[float] | torch.Tensor = 1e-3) -> SOM:
    """A copy of ``som`` whose units read out through local linear maps (:class:`LocalLinear`).

    Each unit's model is fitted by least squares on the rows of ``data`` (raw ``N x C`` or
    ``*batch x N x C``; rows with a NaN are left out) whose best-matching unit lies within grid
    distance ``radius`` of it (1.5: the unit and its 8 neighbours on a rectangular grid, 6 on a
    hexagonal one), centred on the unit's weights; ``ridge`` times the row count penalizes the
    slopes (normalized units), not the intercept: one number, or one per active component (``A``,
    in the mask's order: a group of many weakly informative components held closer to zero); the
    read-out stays within the least and greatest value of those rows. A unit whose neighbourhood
    holds no row keeps its weights and gets zero slopes. All maps must share one active mask."""
    if not (isinstance(radius, (int, float)) and radius >= 0):
        raise ValueError(f"radius: expected a grid distance >= 0, received {radius!r}")
    mask = shared_mask(som, "fit_local_linear")
    penalty = torch.diag(torch.cat([torch.zeros(1, dtype=torch.float64), _ridges(ridge, int(mask.sum()))]))
    data = som.check_data(data, min_samples=1)  # *batch x N x C
    B, C, U = som.batch_shape.numel(), som.n_components, som.n_units
    data = data.reshape(B, -1, C)  # B x N x C
    keep = ~torch.isnan(data).any(-1)  # B x N
    units, _ = _best_matching_units(som, data.reshape(*som.batch_shape, -1, C), 1)
    units = units.reshape(B, -1)  # B x N
    x = som.normalize(data.reshape(*som.batch_shape, -1, C)).reshape(B, -1, C)[..., mask]  # B x N x A
    y = data[..., ~mask]  # B x N x T (raw)
    w = som.weights.reshape(B, U, C).to(torch.float64)  # B x U x C
    w_act, w_out = w[..., mask], som.raw_weights.reshape(B, U, C)[..., ~mask]  # B x U x A, B x U x T
    A, T = x.shape[-1], y.shape[-1]
    near = (som.grid.distances2 <= radius * radius + 1e-9).to(torch.float64)  # U x U
    # each row's sums of [1, x][1, x]^T and [1, x] y^T at its best-matching unit (rows in chunks)
    per_unit = torch.zeros(B, U, (1 + A) * (1 + A + T), dtype=torch.float64)
    for n0 in range(0, x.shape[1], _CHUNK_ROWS):
        k = keep[:, n0:n0 + _CHUNK_ROWS].unsqueeze(-1)  # B x n x 1
        xs = x[:, n0:n0 + _CHUNK_ROWS]  # B x n x A
        z = torch.where(k, torch.cat([torch.ones_like(xs[..., :1]), xs], -1), 0.0)  # B x n x (1 + A)
        zy = torch.cat([z, torch.where(k, y[:, n0:n0 + _CHUNK_ROWS], 0.0)], -1)  # B x n x (1 + A + T)
        flat = (z.unsqueeze(-1) * zy.unsqueeze(-2)).flatten(-2)  # B x n x (1 + A)(1 + A + T)
        index = units[:, n0:n0 + _CHUNK_ROWS].clamp_min(0)  # a row without a match has z = 0
        per_unit.scatter_add_(1, index.unsqueeze(-1).expand_as(flat), flat)
    # ... summed over every unit's neighbourhood
    sums = (near @ per_unit).reshape(B, U, 1 + A, 1 + A + T)  # B x U x (1 + A) x (1 + A + T)
    szz, szy = sums[..., : 1 + A], sums[..., 1 + A:]  # sums of [1, x][1, x]^T and of [1, x] y^T
    # centre on the unit: [1, x - w] = S [1, x] with S = [[1, 0], [-w, I]]
    S = torch.eye(1 + A, dtype=torch.float64).repeat(B, U, 1, 1)  # B x U x (1 + A) x (1 + A)
    S[..., 1:, 0] = -w_act
    gram = S @ szz @ S.transpose(-1, -2)
    rhs = S @ szy  # B x U x (1 + A) x T
    n = szz[..., 0, 0]  # B x U: rows per neighbourhood
    gram = gram + n[..., None, None] * penalty
    empty = n < 0.5
    gram = torch.where(empty[..., None, None], torch.eye(1 + A, dtype=torch.float64), gram)
    rhs = torch.where(empty[..., None, None], torch.cat([w_out.unsqueeze(-2), torch.zeros(B, U, A, T, dtype=torch.float64)], -2), rhs)
    solution = torch.linalg.solve(gram, rhs)  # B x U x (1 + A) x T
    lower, upper = _ranges(y, keep, units, near > 0, U)  # B x U x T each
    lower, upper = torch.where(empty[..., None], w_out, lower), torch.where(empty[..., None], w_out, upper)
    out = som.clone()
    out.local = check_local(out, LocalLinear(*(t.reshape(*som.batch_shape, *t.shape[1:]) for t in (
        solution[..., 0, :], solution[..., 1:, :].transpose(-1, -2), lower, upper))))  # *batch x U x ...
    return out


def _ridges(ridge: float | Sequence[float] | torch.Tensor, A: int) -> torch.Tensor:
    """``ridge`` as ``A`` positive float64 penalties; a ValueError (one line) otherwise."""
    scalar = isinstance(ridge, (int, float)) and not isinstance(ridge, bool)
    try:
        f64 = torch.float64
        r = torch.full((A,), float(ridge), dtype=f64) if scalar else torch.as_tensor(ridge, dtype=f64)
    except (TypeError, ValueError, RuntimeError):
        r = None
    if r is None or r.shape != (A,) or not bool((r > 0).all()):  # NaN fails > 0
        raise ValueError(f"ridge: expected a positive number or {A} positive numbers (one per active component), "
                         f"received {ridge!r}")
    return r


def _ranges(y: torch.Tensor, keep: torch.Tensor, units: torch.Tensor, near: torch.Tensor,
            U: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The least and greatest ``y`` (``B x N x T``) of the kept rows whose unit (``units``, ``B x N``)
    lies in each unit's neighbourhood (``near``, bool ``U x U``): ``B x U x T`` each (inf, -inf where none)."""
    B, T = y.shape[0], y.shape[-1]
    index = units.clamp_min(0).unsqueeze(-1).expand_as(y)  # B x N x T (a row without a match is not kept)
    u, v = near.nonzero().unbind(-1)  # the pairs (unit, a unit of its neighbourhood)
    out = []
    for fill, reduce in ((torch.inf, "amin"), (-torch.inf, "amax")):
        at_unit = torch.full((B, U, T), fill, dtype=torch.float64).scatter_reduce_(
            1, index, torch.where(keep.unsqueeze(-1), y, fill), reduce)  # B x U x T: each unit's own rows
        out.append(torch.full((B, U, T), fill, dtype=torch.float64).scatter_reduce_(
            1, u.view(1, -1, 1).expand(B, -1, T), at_unit[:, v], reduce))  # pooled over the neighbourhood
    return out[0], out[1]
