"""Recall: masked distances, best-matching units, read-out of the inactive components."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._som import SOM, _as_numbers


#: Distances computed at once by :func:`best_matching_units` (float64 elements; 16 MiB): it works
#: through the samples in chunks of this many ``maps x units`` distances.
CHUNK_ELEMENTS = 2**21


def _features(som: SOM, features: torch.Tensor) -> torch.Tensor:
    """Accept ``... x C`` or, when all maps share one active mask, ``... x n_active``;
    return raw ``*batch x M x C`` (inactive columns NaN when they were not given)."""
    f = _as_numbers(features, "features", torch.float64)
    C = som.n_components
    act = som.active.reshape(-1, C)
    n_act = int(act[0].sum())
    if f.dim() == 0:
        raise ValueError(f"features: expected ... x C (C={C}) or ... x n_active ({n_act}), received a scalar")
    if f.shape[-1] != C and f.shape[-1] == n_act and bool((act == act[0]).all()):
        full = torch.full((*f.shape[:-1], C), torch.nan, dtype=torch.float64)
        full[..., act[0]] = f
        f = full
    if f.dim() == 1:
        f = f.unsqueeze(0)  # 1 x C
    if f.shape[-1] != C:
        raise ValueError(f"features: expected ... x C (C={C}) or ... x n_active ({n_act}), received {tuple(f.shape)}")
    return som.check_data(f, "features")


def distances(som: SOM, features: torch.Tensor) -> torch.Tensor:
    """Squared distances over the active, non-NaN components (normalized units),
    float64 ``*batch x M x U``; NaN for a sample with no active non-NaN component (no distance).
    ``features``: raw ``M x C`` or ``*batch x M x C``."""
    return _distances(som, _features(som, features))


def _distances(som: SOM, f: torch.Tensor) -> torch.Tensor:
    """:func:`distances` of raw features ``f`` already accepted by :func:`_features`."""
    x = som.normalize(f)  # *batch x M x C
    B, C, U = som.batch_shape.numel(), som.n_components, som.n_units
    x = x.reshape(B, -1, C)  # B x M x C
    active = som.active.reshape(B, 1, C)
    w = som.weights.reshape(B, U, C).to(torch.float64)  # B x U x C
    nan = torch.isnan(x)
    if bool(nan.any()):  # each sample its own components: the weights' squares per sample
        m = (active & ~nan).to(torch.float64)  # B x M x C
        x = torch.where(nan, 0.0, x) * m
        w2 = m @ (w * w).transpose(1, 2)  # B x M x U
        w2 = torch.where(m.any(-1, keepdim=True), w2, torch.nan)  # no active value: no distance
    else:  # one set of components for all samples: one matrix product less
        x = x * active
        w2 = ((w * w) @ active.to(torch.float64).transpose(1, 2)).transpose(1, 2)  # B x 1 x U
    d2 = w2 - 2.0 * (x @ w.transpose(1, 2)) + (x * x).sum(-1, keepdim=True)  # B x M x U
    return d2.clamp_min(0.0).reshape(*som.batch_shape, -1, U)  # *batch x M x U


def best_matching_units(som: SOM, features: torch.Tensor, k: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Best matches on the active components only (paper eq. 2), NaN features skipped.

    Returns ``(units, dist2)``: long and float64 ``*batch x M`` (``k == 1``) or
    ``*batch x M x k`` (``k > 1``, nearest first). A sample with no active non-NaN component
    has no match: unit ``-1``, distance NaN (so do samples where the weights are NaN)."""
    _check_k(som, k, "k")
    return _best_matching_units(som, features, k)


def _best_matching_units(som: SOM, features: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`best_matching_units` with ``k`` already checked."""
    f = _features(som, features)  # *batch x M x C
    M = f.shape[-2]
    shape = (*f.shape[:-1], k)  # *batch x M x k
    units, dist = torch.empty(shape, dtype=torch.long), torch.empty(shape, dtype=torch.float64)
    step = max(1, CHUNK_ELEMENTS // max(1, som.batch_shape.numel() * som.n_units))
    # the samples in chunks: memory flat in M; the results go into buffers allocated up front (small
    # tensors kept per chunk would pin the heap between the chunks' large temporaries: measured
    # 2.6 GB instead of 0.5 GB for 60 000 samples on 4 maps of 1600 units)
    for m0 in range(0, M, step):
        d2 = _distances(som, f[..., m0:m0 + step, :])  # *batch x m x U
        d, i = (d2.min(-1, keepdim=True) if k == 1 else torch.topk(d2, k, dim=-1, largest=False, sorted=True))
        i = torch.where(torch.isnan(d), -1, i)
        units[..., m0:m0 + step, :], dist[..., m0:m0 + step, :] = i, d
    return (units[..., 0], dist[..., 0]) if k == 1 else (units, dist)


def _check_k(som: SOM, k: int, name: str) -> None:
    """``k`` nearest units: an int in ``1 .. U``."""
    if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= som.n_units:
        raise ValueError(f"{name}: expected an int in 1..{som.n_units}, received {k!r}")


@dataclass
class Recall:
    """Result of :func:`recall`.

    units: long ``*batch x M`` best-matching units; distance: float64 ``*batch x M``
    (Euclidean, active components, normalized units); values: float64 ``*batch x M x C``
    raw-unit weights read out (interpolated if asked); the inactive columns are the
    identified parameters; ``component_names`` names the columns. A sample with no active
    non-NaN feature has unit ``-1``, distance NaN and NaN values."""

    units: torch.Tensor
    distance: torch.Tensor
    values: torch.Tensor
    component_names: list[str]

    def __getitem__(self, name: str) -> torch.Tensor:
        """Read-out of one component by name, ``*batch x M``."""
        if name not in self.component_names:
            raise ValueError(f"Recall[{name!r}]: unknown component, expected one of {self.component_names}")
        return self.values[..., self.component_names.index(name)]


def recall(som: SOM, features: torch.Tensor, *, interpolate: int = 1, eps: float = 1e-12,
           local: bool = True) -> Recall:
    """Recall: best match on active components, read-out of all components (raw units).

    ``interpolate = k > 1`` averages the ``k`` nearest units weighted by ``1 / (distance + eps)``.
    Maps with a local linear read-out (``som.local``, :func:`som_torch.fit_local_linear`) read each
    unit's inactive components at the sample, within the range of the unit's data (NaN features
    count as at the unit's weights); ``local=False`` reads the units' own weights instead.
    ``features``: raw ``M x C``, ``*batch x M x C`` or ``... x n_active`` (see :func:`distances`).
    A sample without an active non-NaN feature gets unit ``-1``, distance NaN and NaN values.
    """
    _check_k(som, interpolate, "interpolate")
    f = _features(som, features)  # *batch x M x C
    units, d2 = _best_matching_units(som, f, interpolate)
    w = som.raw_weights  # *batch x U x C
    flat = units.reshape(*som.batch_shape, -1)  # *batch x (M*k)
    picked = torch.gather(w, -2, flat.clamp_min(0).unsqueeze(-1).expand(*flat.shape, som.n_components))  # *batch x (M*k) x C
    if local and som.local is not None:
        picked = _read_local(som, f, flat, picked, interpolate)
    picked = torch.where(flat.unsqueeze(-1) >= 0, picked, torch.nan)  # no match: NaN read-out
    if interpolate == 1:
        return Recall(units, d2.sqrt(), picked, list(som.component_names))
    picked = picked.reshape(*units.shape, som.n_components)  # *batch x M x k x C
    wt = 1.0 / (d2.sqrt() + eps)  # *batch x M x k
    values = (wt.unsqueeze(-1) * picked).sum(-2) / wt.sum(-1, keepdim=True)  # *batch x M x C
    return Recall(units[..., 0], d2[..., 0].sqrt(), values, list(som.component_names))


def _read_local(som: SOM, f: torch.Tensor, flat: torch.Tensor, picked: torch.Tensor, k: int) -> torch.Tensor:
    """``picked`` (``*batch x (M*k) x C``: the ``k`` units ``flat`` of each sample of ``f``, ``*batch x
    M x C``) with its inactive components read through the units' local linear maps."""
    local = som.local
    mask = som.active.reshape(-1, som.n_components)[0]  # C: shared by all maps (checked when fitted)
    u = flat.clamp_min(0)  # *batch x (M*k)

    def at_units(t: torch.Tensor) -> torch.Tensor:  # *batch x U x tail -> *batch x (M*k) x tail
        rows = t.flatten(u.dim())  # *batch x U x prod(tail)
        return torch.gather(rows, -2, u.unsqueeze(-1).expand(*u.shape, rows.shape[-1])).unflatten(
            -1, t.shape[u.dim():]).to(torch.float64)

    x = som.normalize(f)[..., mask].repeat_interleave(k, dim=-2)  # *batch x (M*k) x A: each sample once per unit
    dx = torch.nan_to_num(x - at_units(som.weights[..., mask]), nan=0.0)  # *batch x (M*k) x A
    value = at_units(local.intercepts) + (at_units(local.slopes) @ dx.unsqueeze(-1)).squeeze(-1)  # *batch x (M*k) x T
    out = picked.clone()
    out[..., ~mask] = torch.minimum(torch.maximum(value, at_units(local.lower)), at_units(local.upper))
    return out
