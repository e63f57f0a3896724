"""Seeded population sampler with the SPEC section 1 default ranges (all overridable)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from sim.params import TwoMassParams


@dataclass(frozen=True)
class PopulationRanges:
    """Sampling ranges. ``*_log`` ranges are log-uniform; backlash in degrees (total width)."""

    J_sigma: tuple[float, float] = (0.01, 0.2)  # log-uniform [kg m^2]
    V_J: tuple[float, float] = (0.2, 5.0)  # log-uniform
    f_e: tuple[float, float] = (5.0, 500.0)  # log-uniform [Hz]
    d: tuple[float, float] = (0.005, 0.1)  # uniform
    backlash_deg: tuple[float, float] = (0.02, 1.0)  # log-uniform [degree], total width 2s
    backlash_zero_share: float = 0.3  # share of systems without backlash
    M_FC: tuple[float, float] = (0.0, 0.5)  # uniform [Nm]
    mu_F: tuple[float, float] = (0.0, 0.005)  # uniform [Nm s/rad]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "backlash_zero_share":
                if not (0.0 <= v <= 1.0):
                    raise ValueError(f"PopulationRanges.backlash_zero_share: expected 0..1, received {v}")
                continue
            if len(v) != 2 or not (v[0] <= v[1]):
                raise ValueError(f"PopulationRanges.{f.name}: expected (low, high) with low <= high, received {v}")
            if f.name in ("J_sigma", "V_J", "f_e", "backlash_deg") and v[0] <= 0:
                raise ValueError(f"PopulationRanges.{f.name}: log-uniform range needs low > 0, received {v}")


def _log_uniform(u: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def sample_population(n: int, seed: int, ranges: PopulationRanges | None = None) -> TwoMassParams:
    """``n`` systems (batch shape ``(n,)``) drawn with a private generator seeded by ``seed``."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"sample_population: expected n >= 1 (int), received {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"sample_population: expected an int seed, received {seed!r}")
    r = ranges or PopulationRanges()
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(9, n, generator=g, dtype=torch.float64)
    backlash = torch.deg2rad(_log_uniform(u[4], *r.backlash_deg))
    backlash = torch.where(u[5] < r.backlash_zero_share, torch.zeros_like(backlash), backlash)
    return TwoMassParams(
        J_sigma=_log_uniform(u[0], *r.J_sigma),
        V_J=_log_uniform(u[1], *r.V_J),
        f_e=_log_uniform(u[2], *r.f_e),
        d=r.d[0] + u[3] * (r.d[1] - r.d[0]),
        backlash=backlash,
        M_FC=r.M_FC[0] + u[6] * (r.M_FC[1] - r.M_FC[0]),
        mu_F=r.mu_F[0] + u[7] * (r.mu_F[1] - r.mu_F[0]),
    )
