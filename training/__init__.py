"""twomass-som: what mechanic hangs on a motor shaft, from one test run (SPEC sections 4-9).

The names an app uses, re-exported from the rooms that hold them (imported on first use, so that
``twomass --help`` does not pay for torch)::

    from training import Identifier
    result = Identifier.load().identify_file("run.csv")

Rooms: :mod:`training.identification` (record -> result), :mod:`training.learning` (population ->
trained maps), :mod:`training.evaluation` (the paper's study, IV4), :mod:`training.commissioning`
(the self-commissioning chain), :mod:`training.commands` (the ``twomass`` subcommands),
:mod:`training.bench` (performance figures).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "Identifier": "training.identification",
    "IdentificationResult": "training.identification",
    "IdentificationFailure": "training.identification",
    "analyze": "training.identification",
    "fit_one_mass": "training.identification",
    "detect_sections": "training.identification",
    "commission": "training.commissioning",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'training' has no attribute {name!r}; public names: {', '.join(__all__)}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
