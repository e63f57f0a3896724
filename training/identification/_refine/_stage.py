"""A stage of the refinement as the registry holds it (:data:`._pipeline.STAGES`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Stage:
    """One stage: its ``name`` (also the :class:`._config.RefineConfig` field that holds its
    settings), when it runs (``runs_when``, one line), the frozen dataclass of its settings
    (``settings``) and its entry point (``run``: typed input, typed result)."""

    name: str
    runs_when: str
    settings: type
    run: Callable[..., Any]
