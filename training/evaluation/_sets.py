"""What the study evaluates (SPEC 7): the sets of systems, the methods and what each one estimates.

- **Sets** (:class:`EvalSet`): the paper's grid (``f_e`` x ``backlash`` cells, ``per_cell``
  systems each; ``J_sigma``, ``V_J``, ``d``, ``M_FC``, ``mu_F`` drawn from the SPEC default
  population) and a random set from the default population.
- **Methods** (:data:`METHODS`): ``som``, our identifier (maps + model-based refinement);
  ``maps``, the maps' answer alone (the paper's method); ``iv4``, the instrumental-variable baseline.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from sim import PARAM_NAMES, PopulationRanges, TwoMassParams, sample_population

#: The paper's grid (section 4, Fig. 10): eigenfrequencies [Hz] and total backlash widths [degree].
GRID_F_E: tuple[float, ...] = (10.0, 20.0, 30.0, 50.0, 80.0, 120.0)
GRID_BACKLASH_DEG: tuple[float, ...] = (0.0, 0.2, 0.5)

#: The methods, in report order.
METHODS: tuple[str, ...] = ("som", "maps", "iv4")
#: Estimates each method delivers (the rest are reported as not available): the SOM all seven
#: population parameters, IV4 the linear two-mass part (no backlash, no friction).
METHOD_PARAMS: dict[str, tuple[str, ...]] = {
    "som": PARAM_NAMES,
    "maps": PARAM_NAMES,
    "iv4": tuple(p for p in PARAM_NAMES if p not in ("backlash", "M_FC", "mu_F")),
}
#: The truth kept per system: the parameters, the stiffness, the class figures of SPEC 1 and the class.
TRUTH_KEYS: tuple[str, ...] = PARAM_NAMES + ("C_F", "s_N", "r_osc", "w_e_T_Ei", "structure")


@dataclass(frozen=True)
class EvalSet:
    """Definition of one evaluation set; equal definitions give equal systems and records.

    ``kind``: ``"grid"`` (``per_cell`` systems per ``f_e`` [Hz] x ``backlash_deg`` [degree]
    cell, cells in ``f_e``-major order) or ``"population"`` (``n`` systems of ``ranges``).
    ``seed`` seeds the population draw; the current noise of record ``i`` uses
    ``noise_seed + i`` (``sim.iter_records``).
    """

    name: str
    kind: str
    seed: int
    n: int = 0
    per_cell: int = 0
    f_e: tuple[float, ...] = ()
    backlash_deg: tuple[float, ...] = ()
    ranges: PopulationRanges = field(default_factory=PopulationRanges)

    def __post_init__(self) -> None:
        if self.kind not in ("grid", "population"):
            raise ValueError(f"EvalSet.kind: expected 'grid' or 'population', received {self.kind!r}")
        if self.kind == "grid":
            if self.per_cell < 1 or not self.f_e or not self.backlash_deg:
                raise ValueError(f"EvalSet {self.name}: expected per_cell >= 1 and non-empty f_e, backlash_deg; "
                                 f"received {self.per_cell}, {self.f_e}, {self.backlash_deg}")
            if min(self.f_e) <= 0 or min(self.backlash_deg) < 0:
                raise ValueError(f"EvalSet {self.name}: expected f_e > 0 Hz and backlash >= 0 degree, "
                                 f"received {self.f_e}, {self.backlash_deg}")
        elif self.n < 1:
            raise ValueError(f"EvalSet {self.name}: expected n >= 1, received {self.n}")

    @property
    def size(self) -> int:
        """Number of systems."""
        return self.per_cell * len(self.f_e) * len(self.backlash_deg) if self.kind == "grid" else self.n

    @property
    def noise_seed(self) -> int:
        return self.seed * 1_000_003 + 17

    def cells(self) -> list[tuple[float, float]]:
        """Grid cells ``(f_e [Hz], backlash [degree])`` in ``f_e``-major order; ``[]`` for a population."""
        return [(f, b) for f in self.f_e for b in self.backlash_deg] if self.kind == "grid" else []

    def params(self) -> TwoMassParams:
        """The systems, batch shape ``(size,)``; for a grid, systems ``k*per_cell .. (k+1)*per_cell - 1``
        form cell ``k``, with ``f_e`` and ``backlash`` fixed and the rest drawn from ``ranges``."""
        p = sample_population(self.size, self.seed, self.ranges)
        if self.kind == "population":
            return p
        cells = self.cells()
        f_e = torch.tensor([c[0] for c in cells for _ in range(self.per_cell)], dtype=torch.float64)
        bl = torch.deg2rad(torch.tensor([c[1] for c in cells for _ in range(self.per_cell)], dtype=torch.float64))
        return TwoMassParams(J_sigma=p.J_sigma, V_J=p.V_J, f_e=f_e, d=p.d, backlash=bl, M_FC=p.M_FC, mu_F=p.mu_F)

    def cell_of(self, i: int) -> tuple[float, float] | None:
        return self.cells()[i // self.per_cell] if self.kind == "grid" else None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["f_e"], d["backlash_deg"] = list(self.f_e), list(self.backlash_deg)
        d["ranges"] = {k: list(v) if isinstance(v, tuple) else v for k, v in d["ranges"].items()}
        return d


def grid_set(per_cell: int = 20, seed: int = 5, *, f_e: Sequence[float] = GRID_F_E,
             backlash_deg: Sequence[float] = GRID_BACKLASH_DEG, ranges: PopulationRanges | None = None) -> EvalSet:
    """The paper's grid: ``len(f_e) * len(backlash_deg)`` cells of ``per_cell`` systems."""
    return EvalSet(name="grid", kind="grid", seed=seed, per_cell=per_cell, f_e=tuple(float(f) for f in f_e),
                   backlash_deg=tuple(float(b) for b in backlash_deg), ranges=ranges or PopulationRanges())


def population_set(n: int = 1000, seed: int = 6, ranges: PopulationRanges | None = None) -> EvalSet:
    """``n`` systems drawn from the (default) population."""
    return EvalSet(name="population", kind="population", seed=seed, n=n, ranges=ranges or PopulationRanges())
