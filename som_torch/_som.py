"""The :class:`SOM` container: weights of a batch of maps, grid, component names, active mask,
per-component normalization."""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from ._grid import Grid


def _as_batch_shape(shape: Sequence[int] | int | torch.Size, name: str = "batch_shape") -> torch.Size:
    if isinstance(shape, int):
        shape = (shape,)
    try:
        size = torch.Size(operator.index(s) for s in shape)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected a tuple of ints, received {shape!r}") from err
    if any(s < 1 for s in size):
        raise ValueError(f"{name}: expected positive batch sizes (at least one map), received {tuple(size)}")
    return size


def _as_numbers(value, name: str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``torch.as_tensor(value, dtype=dtype)``; what is not numbers raises a one-line TypeError naming ``name``."""
    try:
        return torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name}: expected a tensor of numbers, received {type(value).__name__}") from None


@dataclass(frozen=True)
class LocalLinear:
    """Per map and unit, the inactive components' values near the unit.

    intercepts: ``*batch x U x T`` (raw units), the value at the unit's weights; slopes:
    ``*batch x U x T x A`` (raw units per normalized active unit); lower, upper: ``*batch x U x T``
    (raw units), the range of the values the unit's model was fitted on. ``T`` inactive and ``A``
    active components, in the order of the maps' (shared) mask. At a sample whose normalized active
    components are ``x``, unit ``u`` reads ``intercepts[u] + slopes[u] @ (x - w[u, active])``,
    clipped to ``[lower[u], upper[u]]``: a local linear map does not extrapolate beyond its data."""

    intercepts: torch.Tensor
    slopes: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> "LocalLinear":
        """The same read-out with ``fn`` applied to each tensor (indexing, device moves)."""
        return LocalLinear(fn(self.intercepts), fn(self.slopes), fn(self.lower), fn(self.upper))


class SOM:
    """A batch of self-organizing maps sharing one grid and one list of components.

    Attributes:
        grid: the :class:`Grid` (``U = rows * cols`` units).
        component_names: ``C`` names.
        weights: ``*batch x U x C`` in *normalized* units (see :meth:`normalize`).
        active: bool ``*batch x C``: components used for the best match (paper eq. 2);
            inactive ones are trained (eq. 3) and read out at recall. Each map may have its
            own mask, so maps with different feature counts share a batch: pad the unused
            columns (data 0 or NaN) and mark them inactive.
        offset, scale: ``*batch x C``: ``normalized = (raw - offset) / scale``. Identity by
            default; :meth:`fit_normalization` sets them from data. Stored with the map.
        local: the units' local linear read-out (:func:`som_torch.fit_local_linear`) or None.
            Setting ``weights`` or the normalization drops it (it describes the old weights).
    """

    local: LocalLinear | None

    def __init__(
        self,
        grid: Grid,
        component_names: Sequence[str],
        active: Sequence[bool] | torch.Tensor,
        *,
        batch_shape: Sequence[int] | int = (),
        weights: torch.Tensor | None = None,
        offset: torch.Tensor | None = None,
        scale: torch.Tensor | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        if not isinstance(grid, Grid):
            raise TypeError(f"grid: expected a som_torch.Grid, received {type(grid).__name__}")
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise TypeError(f"dtype: expected a floating-point torch dtype (e.g. torch.float32), received {dtype!r}")
        names = [str(n) for n in component_names]
        if len(set(names)) != len(names):
            raise ValueError(f"component_names: expected unique names, received {names}")
        self.grid = grid
        self.component_names = names
        batch_shape = _as_batch_shape(batch_shape)
        C, U = len(names), grid.n_units
        if weights is not None:
            if not isinstance(weights, torch.Tensor) or weights.dim() < 2 or weights.shape[-2:] != (U, C):
                got = tuple(weights.shape) if isinstance(weights, torch.Tensor) else type(weights).__name__
                raise ValueError(f"weights: expected *batch x U x C with U={U}, C={C}, received {got}")
            batch_shape = _as_batch_shape(weights.shape[:-2], "weights")
            self.weights = weights.to(dtype)
        else:
            self.weights = torch.zeros(*batch_shape, U, C, dtype=dtype)
        active_t = torch.as_tensor(active, dtype=torch.bool)
        if active_t.shape[-1:] != (C,):
            raise ValueError(f"active: expected C={C} flags (or *batch x C), received shape {tuple(active_t.shape)}")
        try:
            self.active = active_t.expand(*batch_shape, C).clone()  # *batch x C
        except RuntimeError as err:
            raise ValueError(
                f"active: shape {tuple(active_t.shape)} does not broadcast to batch {tuple(batch_shape)} x C={C}"
            ) from err
        if not bool(self.active.any(-1).all()):
            raise ValueError("active: every map needs at least one active component")
        self.offset = self._per_component(offset, 0.0, "offset")
        self.scale = self._per_component(scale, 1.0, "scale")
        if not bool(torch.isfinite(self.offset).all()):
            raise ValueError("offset: expected finite values")
        if not bool((torch.isfinite(self.scale) & (self.scale > 0)).all()):
            raise ValueError("scale: expected finite positive values")

    def _per_component(self, value: torch.Tensor | None, default: float, name: str) -> torch.Tensor:
        C = self.n_components
        if value is None:
            return torch.full((*self.batch_shape, C), default, dtype=torch.float64)
        t = torch.as_tensor(value, dtype=torch.float64)
        try:
            return t.expand(*self.batch_shape, C).clone()  # *batch x C
        except RuntimeError as err:
            raise ValueError(f"{name}: expected *batch x C = {(*self.batch_shape, C)}, received {tuple(t.shape)}") from err

    @property
    def weights(self) -> torch.Tensor:
        return self._weights

    @weights.setter
    def weights(self, value: torch.Tensor) -> None:
        self._weights = value
        self.local = None  # a local linear read-out describes the old weights

    # --- shapes -------------------------------------------------------------------------
    @property
    def batch_shape(self) -> torch.Size:
        return self.weights.shape[:-2]

    @property
    def n_units(self) -> int:
        return self.grid.n_units

    @property
    def n_components(self) -> int:
        return len(self.component_names)

    def index(self, name: str) -> int:
        try:
            return self.component_names.index(name)
        except ValueError:
            raise KeyError(f"component {name!r} not in {self.component_names}") from None

    def __getitem__(self, idx) -> "SOM":
        """Select maps of the batch (indexing applies to ``batch_shape`` only)."""
        if not self.batch_shape:
            raise IndexError("this SOM has no batch dimension to index")
        w = self.weights[idx]
        if w.dim() < 2 or w.shape[-2:] != self.weights.shape[-2:]:
            raise IndexError(f"index {idx!r} reaches into U x C; index batch dims {tuple(self.batch_shape)} only")
        out = SOM(self.grid, self.component_names, self.active[idx], weights=w.clone(),
                  offset=self.offset[idx], scale=self.scale[idx], dtype=w.dtype)
        if self.local is not None:
            out.local = self.local.map(lambda t: t[idx].clone())
        return out

    def clone(self) -> "SOM":
        out = SOM(self.grid, self.component_names, self.active, weights=self.weights.clone(),
                  offset=self.offset, scale=self.scale, dtype=self.weights.dtype)
        out.local = self.local  # immutable: shared
        return out

    @property
    def device(self) -> torch.device:
        return self.weights.device

    def to(self, device: str | torch.device) -> "SOM":
        """This batch of maps with its tensors on ``device`` (``self`` where they are already)."""
        device = torch.device(device)
        if device == self.device:
            return self
        out = SOM(self.grid, self.component_names, self.active.to(device), weights=self.weights.to(device),
                  offset=self.offset.to(device), scale=self.scale.to(device), dtype=self.weights.dtype)
        if self.local is not None:
            out.local = self.local.map(lambda t: t.to(device))
        return out

    def __repr__(self) -> str:
        return (f"SOM(grid={self.grid.rows}x{self.grid.cols} {self.grid.topology}, batch_shape={tuple(self.batch_shape)}, "
                f"components={self.n_components} ({int(self.active.reshape(-1, self.n_components)[0].sum())} active in map 0), "
                f"dtype={self.weights.dtype})")

    # --- data and normalization ---------------------------------------------------------
    def check_data(self, data: torch.Tensor, name: str = "data", *, min_samples: int = 0) -> torch.Tensor:
        """Broadcast ``data`` (``N x C`` or ``*batch x N x C``) to ``*batch x N x C`` float64 on the maps' device.
        ``min_samples``: the least ``N`` accepted (training and normalization need 1)."""
        if not isinstance(data, torch.Tensor):
            data = _as_numbers(data, name)
        if data.dim() < 2 or data.shape[-1] != self.n_components:
            raise ValueError(
                f"{name}: expected N x C or *batch x N x C with C={self.n_components}, received {tuple(data.shape)}"
            )
        if data.shape[-2] < min_samples:
            raise ValueError(f"{name}: expected at least {min_samples} sample(s), received N={data.shape[-2]}")
        try:
            return data.to(self.device, torch.float64).expand(*self.batch_shape, data.shape[-2], self.n_components)
        except RuntimeError as err:
            raise ValueError(
                f"{name}: shape {tuple(data.shape)} does not broadcast to batch {tuple(self.batch_shape)} x N x C"
            ) from err

    def normalize(self, data: torch.Tensor, *, min_samples: int = 0) -> torch.Tensor:
        """Raw ``*batch x N x C`` -> normalized (float64); ``min_samples`` as in :meth:`check_data`."""
        data = self.check_data(data, min_samples=min_samples)
        return (data - self.offset.unsqueeze(-2)) / self.scale.unsqueeze(-2)

    def denormalize(self, values: torch.Tensor) -> torch.Tensor:
        """Normalized ``*batch x N x C`` -> raw units (float64)."""
        return values.to(torch.float64) * self.scale.unsqueeze(-2) + self.offset.unsqueeze(-2)

    @property
    def raw_weights(self) -> torch.Tensor:
        """Weights in raw units, float64 ``*batch x U x C``."""
        return self.denormalize(self.weights)

    def fit_normalization(self, data: torch.Tensor, mode: str = "range") -> "SOM":
        """Set ``offset``/``scale`` per map and component from ``data`` (NaN ignored).

        ``mode``: ``"range"`` maps [min, max] to [0, 1]; ``"standard"`` to zero mean, unit std;
        ``"none"`` resets to the identity. Constant components get scale 1. Call before training.
        """
        data = self.check_data(data, min_samples=1)
        self.local = None  # a local linear read-out is in the old normalized units
        if mode == "none":
            self.offset.zero_()
            self.scale.fill_(1.0)
            return self
        nan = torch.isnan(data)
        if mode == "range":
            lo = torch.where(nan, torch.inf, data).amin(-2)  # *batch x C
            hi = torch.where(nan, -torch.inf, data).amax(-2)
            offset, scale = lo, hi - lo
        elif mode == "standard":
            offset = torch.nanmean(data, -2)
            sq = torch.where(nan, 0.0, (data - offset.unsqueeze(-2)) ** 2)
            scale = (sq.sum(-2) / (~nan).sum(-2).clamp_min(1)).sqrt()
        else:
            raise ValueError(f"mode: expected one of ['range', 'standard', 'none'], received {mode!r}")
        ok = torch.isfinite(scale) & (scale > 0)
        self.offset = torch.where(torch.isfinite(offset), offset, 0.0)
        self.scale = torch.where(ok, scale, 1.0)
        return self
