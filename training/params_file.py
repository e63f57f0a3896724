"""Plant parameters from JSON (``twomass simulate --params``, ``commission --params``, ``demo --params``).

Accepted shapes: one object (one system), a list of objects (row-wise), or one object of equal-length
lists (column-wise, as ``pandas.DataFrame.to_json(orient="list")`` writes), each with the keys of
``TwoMassParams.from_dicts`` (each a finite number: JSON numbers, not true/false, not beyond a
float's range) and an optional ``name`` (a plain file name: the system's records and pages are
named by it). A UTF-8 byte-order mark is allowed.
"""

from __future__ import annotations

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


def _checked(rows: list[dict[str, Any]], src: str, name_prefix: str) -> tuple[list[dict[str, Any]], list[str]]:
    """The parameter rows (without ``name``; the values of parameter keys as Python numbers, other
    keys left to ``TwoMassParams.from_dicts``, which names them) and the system names; a
    :class:`UserError` naming the system and key for a value that is no finite number (a name that
    is no text)."""
    from sim._values import shown
    from sim.params import _DICT_KEYS, check_real
    from training._checks import record_name

    params, names = [], []
    for i, row in enumerate(rows):
        name = row.get("name", f"{name_prefix}{i:05d}")
        if not isinstance(name, str):
            raise UserError(f"{src}: system {i}: 'name': expected a text, received {shown(name)}")
        names.append(record_name(f"{src}: system {i}", name))  # records and pages are named by it
        try:
            params.append({k: check_real(f"system {i}: {shown(k)}", v) if k in _DICT_KEYS else v
                           for k, v in row.items() if k != "name"})
        except TypeError as err:
            raise UserError(f"{src}: {err}") from None
    return params, names


def read_params_file(source: str | os.PathLike[str], name_prefix: str = "sys") -> tuple[Any, list[str]]:
    """``(TwoMassParams, names)`` from a JSON file, or from JSON text (a string starting with ``{`` or
    ``[``). Names default to ``<prefix><index>``.

    Raises :class:`UserError` with one line for a missing file, bad JSON (nested too deeply, too,
    or an integer too long), unknown keys, values that are no finite numbers, names that are no
    plain file names, duplicate names or values outside the physical range (``TwoMassParams``
    checks the ranges)."""
    from sim import TwoMassParams
    from sim._values import loads, printable

    text = str(source)
    src = "--params"
    if not (isinstance(source, str) and text.lstrip().startswith(("{", "["))):
        src = printable(f"--params {text}")
        try:
            text = Path(source).read_text(encoding="utf-8-sig")
        except FileNotFoundError:
            raise UserError(f"{src}: file not found") from None
        except OSError as err:
            raise UserError(f"{src}: cannot read ({err.strerror})") from None
        except UnicodeDecodeError:
            raise UserError(f"{src}: cannot read: not UTF-8 text") from None
    try:
        data = loads(text)
    except ValueError as err:
        raise UserError(f"{src}: {err}") from None
    rows, names = _checked(_rows(data, src), src, name_prefix)
    if len(set(names)) != len(names):
        raise UserError(f"{src}: duplicate system names")
    try:
        params = TwoMassParams.from_dicts(rows)
    except (TypeError, ValueError) as err:
        raise UserError(printable(f"{src}: {err}")) from None
    return params, names
