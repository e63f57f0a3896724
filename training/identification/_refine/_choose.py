"""The choice: the finalists of the window searches compete on the whole record
(:class:`ChooseSettings`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training._settings import AT_LEAST_ONE, check_settings
from training.identification._refine._problem import RefineProblem
from training.identification._refine._replay import BatchSettings, detrend_basis, detrended_energy, packed_errors
from training.identification._refine._stage import Stage


@dataclass(frozen=True)
class ChooseSettings:
    """The maps' answer and the ``finalists`` best of the exploration (of the rescue or the climb
    where it won; the rattle adds its own) compete on the plain detrended error over the whole
    record, simulated exactly (more rounds there were measured not to help)."""

    finalists: int = 12  # the winning window search's best models that compete

    def __post_init__(self) -> None:
        check_settings(self, {"finalists": AT_LEAST_ONE})


@dataclass(frozen=True)
class Choice:
    """One record's choice: its ``finalists`` ``F x 4`` (row 0 the maps' answer), their
    whole-record detrended errors ``cost`` (``F``) over the detrending ``basis``, and the measured
    speed's own detrended energy (``measured``)."""

    finalists: np.ndarray
    cost: np.ndarray
    basis: list[tuple[int, int, np.ndarray]]
    measured: float

    @property
    def best(self) -> np.ndarray:
        """The finalist of the lowest whole-record error."""
        return self.finalists[int(np.argmin(self.cost))]


def choose(problems: list[RefineProblem], finalists: list[np.ndarray], batch: BatchSettings) -> list[Choice]:
    """Each problem's :class:`Choice` among its ``finalists``; the records on the same drive and
    of similar length run packed in one replay."""
    costs: list[np.ndarray] = [np.empty(0)] * len(problems)
    bases = [detrend_basis(p.segments) for p in problems]  # the whole record's sections and tail
    for i, E in packed_errors(problems, dict(enumerate(finalists)), batch):
        costs[i] = detrended_energy(E, bases[i])
    measured = [float(detrended_energy(p.speed[:, None], b)[0]) for p, b in zip(problems, bases)]
    return [Choice(f, c, b, m) for f, c, b, m in zip(finalists, costs, bases, measured)]


STAGE = Stage("choose", "always: the finalists of every refined record", ChooseSettings, choose)
