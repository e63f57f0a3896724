"""Plant parameters from JSON (``twomass simulate --params``, ``commission --params``, ``demo --params``).

Accepted shapes: one object (one system), a list of objects (row-wise), or one object of equal-length
lists (column-wise, as ``pandas.DataFrame.to_json(orient="list")`` writes), each with the keys of
``TwoMassParams.from_dicts`` and an optional ``name``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from training.errors import UserError


def _rows(data: Any, src: str) -> list[dict[str, Any]]:
    """The systems of ``data`` as a list of row objects."""
    if isinstance(data, dict) and data and all(isinstance(v, list) for v in data.values()):  # column-wise
        lengths = {k: len(v) for k, v in data.items()}
        if len(set(lengths.values())) != 1:
            raise UserError(f"{src}: column-wise parameters need columns of one length, received {lengths}")
        return [{k: v[i] for k, v in data.items()} for i in range(next(iter(lengths.values())))]
    rows = [data] if isinstance(data, dict) else data
    if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
        raise UserError(f"{src}: expected an object, a non-empty list of objects or an object of lists")
    return rows


def read_params_file(source: str | os.PathLike[str], name_prefix: str = "sys") -> tuple[Any, list[str]]:
    """``(TwoMassParams, names)`` from a JSON file, or from JSON text (a string starting with ``{`` or
    ``[``). Names default to ``<prefix><index>``.

    Raises :class:`UserError` with one line for a missing file, bad JSON, unknown keys, duplicate
    names or values outside the physical range (``TwoMassParams`` checks the ranges)."""
    from sim import TwoMassParams

    text = str(source)
    src = "--params"
    if not (isinstance(source, str) and text.lstrip().startswith(("{", "["))):
        src = f"--params {text}"
        try:
            text = Path(source).read_text()
        except FileNotFoundError:
            raise UserError(f"{src}: file not found") from None
        except OSError as err:
            raise UserError(f"{src}: cannot read ({err.strerror})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise UserError(f"{src}: invalid JSON ({err.msg} at line {err.lineno} column {err.colno})") from None
    rows = _rows(data, src)
    names = [str(r.get("name", f"{name_prefix}{i:05d}")) for i, r in enumerate(rows)]
    if len(set(names)) != len(names):
        raise UserError(f"{src}: duplicate system names")
    try:
        params = TwoMassParams.from_dicts([{k: v for k, v in r.items() if k != "name"} for r in rows])
    except (TypeError, ValueError) as err:
        raise UserError(f"{src}: {err}") from None
    return params, names
