"""Map grids: unit coordinates, squared grid distances and adjacency (rectangular, hexagonal)."""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from functools import cached_property

import torch

TOPOLOGIES = ("rectangular", "hexagonal")


@dataclass(frozen=True)
class Grid:
    """A ``rows x cols`` grid of units; unit ``u = row * cols + col``.

    Rectangular units sit at ``(row, col)``. Hexagonal units sit at
    ``(row * sqrt(3)/2, col + 0.5 * (row % 2))`` (odd rows shifted right), so every
    unit has six neighbours at distance 1.
    """

    rows: int
    cols: int
    topology: str = "rectangular"

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"Grid.{name}: expected a positive int, received {value!r}")
        if self.topology not in TOPOLOGIES:
            raise ValueError(f"Grid.topology: expected one of {TOPOLOGIES}, received {self.topology!r}")

    @property
    def n_units(self) -> int:
        return self.rows * self.cols

    @cached_property
    def axes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The unit positions as a product, float64: the row coordinate of each row (``rows``) and
        the column coordinate of each column on even and on odd rows (``2 x cols``; hexagonal grids
        shift odd rows by half a unit). Unit ``(r, c)`` lies at ``(y[r], x[r % 2, c])``."""
        y = torch.arange(self.rows, dtype=torch.float64)
        x = torch.arange(self.cols, dtype=torch.float64).repeat(2, 1)  # 2 x cols
        if self.topology == "hexagonal":
            x[1] += 0.5
            y = y * (math.sqrt(3.0) / 2.0)
        return y, x

    @cached_property
    def coords(self) -> torch.Tensor:
        """Unit positions, float64 ``U x 2`` (row axis, column axis)."""
        y, x = self.axes
        r = torch.arange(self.rows).repeat_interleave(self.cols)  # U: each unit's row
        c = torch.arange(self.cols).repeat(self.rows)  # U: each unit's column
        return torch.stack([y[r], x[r % 2, c]], dim=-1)  # U x 2

    @cached_property
    def distances2(self) -> torch.Tensor:
        """Squared grid distances between units, float64 ``U x U``."""
        r, c = self.coords.unbind(-1)  # U each
        dr, dc = r[:, None] - r[None, :], c[:, None] - c[None, :]  # U x U each
        return dr.mul_(dr).add_(dc.mul_(dc))

    @cached_property
    def adjacency(self) -> torch.Tensor:
        """Bool ``U x U``: neighbours on the grid (rectangular: 8 incl. diagonals, as MiniSom's
        topographic error; hexagonal: the 6 at distance 1). A unit is not its own neighbour."""
        limit = 2.0 + 1e-6 if self.topology == "rectangular" else 1.0 + 1e-6
        adj = self.distances2 <= limit
        adj.fill_diagonal_(False)
        return adj

    @cached_property
    def edges(self) -> torch.Tensor:
        """Long ``E x 2``: each adjacent pair ``(i, j)`` once, ``i < j``."""
        return torch.triu(self.adjacency, diagonal=1).nonzero()

    def to_dict(self) -> dict:
        return {"rows": self.rows, "cols": self.cols, "topology": self.topology}

    @classmethod
    def from_dict(cls, d: dict) -> "Grid":
        """The grid of :meth:`to_dict`; ``rows``/``cols`` must be integers (``3.7`` is refused, not truncated)."""
        try:
            rows, cols, topology = d["rows"], d["cols"], d["topology"]
        except (KeyError, TypeError):
            raise ValueError(f"Grid.from_dict: expected a dict with rows, cols, topology, received {d!r}") from None
        return cls(_as_int(rows), _as_int(cols), str(topology))


def _as_int(value: object) -> object:
    """An integer-like ``value`` (e.g. numpy's) as an int; anything else unchanged, for ``Grid`` to refuse."""
    if isinstance(value, bool):
        return value
    try:
        return operator.index(value)
    except TypeError:
        return value
