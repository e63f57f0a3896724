"""Named options (neighbourhood functions, schedules) looked up in dicts whose errors list the keys."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TypeVar

import torch

T = TypeVar("T")


def lookup(table: Mapping[str, T], name: str, what: str) -> T:
    """``table[name]``; an unknown name raises ValueError listing the valid keys."""
    if callable(name) and not isinstance(name, str):
        return name  # type: ignore[return-value]
    try:
        return table[name]
    except (KeyError, TypeError):
        raise ValueError(f"{what}: expected one of {sorted(table)}, received {name!r}") from None


# --- neighbourhood functions h(d2, sigma) -> weight in [0, 1] ---------------------------------
# d2: squared grid distances to the best match (any shape); sigma: radius, broadcastable.

def gaussian(d2: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``exp(-d^2 / (2 sigma^2))`` (MiniSom's 'gaussian', separable product = same value)."""
    return torch.exp(d2 / (-2.0 * sigma * sigma))


def bubble(d2: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """1 within grid radius ``sigma`` (inclusive), else 0."""
    return (d2 <= sigma * sigma).to(d2.dtype)


def cut_gaussian(d2: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Gaussian cut to 0 beyond grid radius ``sigma``."""
    return gaussian(d2, sigma) * bubble(d2, sigma)


def epanechnikov(d2: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``max(0, 1 - d^2 / sigma^2)``."""
    return (1.0 - d2 / (sigma * sigma)).clamp_min(0.0)


NEIGHBOURHOODS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "gaussian": gaussian,
    "bubble": bubble,
    "cut_gaussian": cut_gaussian,
    "epanechnikov": epanechnikov,
}


# --- schedules f(start, end, t, total) -> value at step t (t = 0 .. total-1) ------------------
# start, end: B (per map); t: T x 1; result T x B.

def asymptotic(start: torch.Tensor, end: torch.Tensor, t: torch.Tensor, total: int) -> torch.Tensor:
    """``start / (1 + t / (total / 2))``: MiniSom 2.3.6's default ``asymptotic_decay``
    (reaches start/3 at the end; ``end`` is ignored)."""
    return start / (1.0 + t / (total / 2.0))


def linear(start: torch.Tensor, end: torch.Tensor, t: torch.Tensor, total: int) -> torch.Tensor:
    """Straight line from ``start`` (t = 0) to ``end`` (t = total)."""
    return start + (end - start) * (t / total)


def exponential(start: torch.Tensor, end: torch.Tensor, t: torch.Tensor, total: int) -> torch.Tensor:
    """Geometric from ``start`` (t = 0) to ``end`` (t = total); both must be > 0."""
    return start * (end / start) ** (t / total)


def constant(start: torch.Tensor, end: torch.Tensor, t: torch.Tensor, total: int) -> torch.Tensor:
    """``start`` throughout."""
    return start + 0.0 * t


SCHEDULES: dict[str, Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], torch.Tensor]] = {
    "asymptotic": asymptotic,
    "linear": linear,
    "exponential": exponential,
    "constant": constant,
}
