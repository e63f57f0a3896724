"""Reading plant parameters from a JSON file (``twomass simulate --params``, ``commission --params``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from training.errors import UserError


def read_params_file(path: Path, name_prefix: str = "sys") -> tuple[Any, list[str]]:
    """``(TwoMassParams, names)`` from a JSON object (one system) or a list of objects with the keys
    of ``TwoMassParams.from_dicts`` and an optional ``name`` (default ``<prefix><index>``).

    Raises :class:`UserError` with one line for a missing file, bad JSON, unknown keys, duplicate
    names or values outside the physical range (``TwoMassParams`` checks the ranges)."""
    from sim import TwoMassParams

    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except json.JSONDecodeError as err:
        raise UserError(f"{path}: invalid JSON ({err.msg} at line {err.lineno})") from None
    rows = [data] if isinstance(data, dict) else data
    if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
        raise UserError(f"{path}: expected an object or a non-empty list of objects")
    names = [str(r.get("name", f"{name_prefix}{i:05d}")) for i, r in enumerate(rows)]
    if len(set(names)) != len(names):
        raise UserError(f"{path}: duplicate system names")
    try:
        params = TwoMassParams.from_dicts([{k: v for k, v in r.items() if k != "name"} for r in rows])
    except (TypeError, ValueError) as err:
        raise UserError(f"{path}: {err}") from None
    return params, names
