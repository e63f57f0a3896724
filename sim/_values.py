"""Values from outside (JSON metadata, parameter files, a caller's objects): the one JSON reader, the
check of a JSON value's structure, and the one-line description of any value in an error message.

Each is iterative or bounded: no value (a 400-digit integer, lists nested 200 000 levels deep, text
holding NUL bytes or line breaks) costs more than a one-line ``ValueError``/``TypeError``.
"""

from __future__ import annotations

import json
import math
import numbers
import sys
from collections.abc import Mapping
from typing import Any

import numpy as np

#: Deepest nesting of JSON objects and lists :func:`plain` accepts (a record's metadata values are at
#: most one level deep: ``truth`` and ``units`` are objects of numbers and text).
MAX_DEPTH = 32
#: The largest integer a float holds (larger ones are refused as numbers: they overflow a float).
MAX_INT = int(sys.float_info.max)
_SHOWN_CHARS = 60  # characters of a text value quoted in a message


def printable(text: str) -> str:
    """``text`` with its control characters (NUL, line breaks, escape sequences, ...) escaped as
    ``repr`` writes them, so that a message stays one plain line."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def shown(value: Any) -> str:
    """A short one-line description of ``value`` for an error message: numbers and short texts as
    ``repr`` writes them (control characters escaped), long texts cut, a huge integer by its number
    of digits, containers by their size (flat short lists in full)."""
    if value is None:
        return "None"
    if isinstance(value, (bool, np.bool_)):
        return repr(bool(value))
    if isinstance(value, numbers.Integral):
        n = abs(int(value))
        if n.bit_length() <= 64:
            return repr(int(value))
        try:
            return f"an integer of {len(str(n))} digits"
        except ValueError:  # beyond Python's limit of digits for a conversion
            return f"an integer of about {int(math.log10(n)) + 1} digits"
    if isinstance(value, numbers.Real):
        try:
            return repr(float(value))
        except OverflowError:
            return "a number beyond a float's range"
    if isinstance(value, str):
        text = repr(value[:_SHOWN_CHARS])
        return text if len(value) <= _SHOWN_CHARS else f"{text[:-1]}...{text[-1]} ({len(value)} characters)"
    if isinstance(value, Mapping):
        return f"an object of {len(value)} key(s)"
    if isinstance(value, (list, tuple)):
        if len(value) <= 6 and not any(isinstance(v, (Mapping, list, tuple)) for v in value):
            return "[" + ", ".join(shown(v) for v in value) + "]"
        return f"a list of {len(value)} item(s)"
    return f"a {type(value).__name__}"


def loads(text: str) -> Any:
    """``json.loads(text)``; a one-line ``ValueError`` for text that is no JSON, nested too deeply
    for the parser (``RecursionError``) or holding an integer too long to convert."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"invalid JSON ({err.msg} at line {err.lineno} column {err.colno})") from None
    except RecursionError:
        raise ValueError("invalid JSON: objects and lists nested too deeply") from None
    except ValueError:  # an integer beyond Python's limit of digits for a conversion
        raise ValueError(f"invalid JSON (an integer of more than {sys.get_int_max_str_digits()} digits)") from None


def _scalar(value: Any, where: str, place: Any) -> Any:
    """A JSON scalar of ``value`` (numpy scalars as Python numbers), or a ``ValueError`` naming its
    place (``where`` and the keys of ``place``)."""
    if value is None or type(value) in (bool, str, float):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, numbers.Integral):
        n = int(value)
        if abs(n) > MAX_INT:
            raise ValueError(f"{_place(where, place)}: expected a number a float can hold, received {shown(n)}")
        return n
    if isinstance(value, numbers.Real):
        try:
            return float(value)
        except OverflowError:
            raise ValueError(f"{_place(where, place)}: expected a number a float can hold, received "
                             f"{shown(value)}") from None
    raise ValueError(f"{_place(where, place)}: expected JSON values (objects, lists, text, numbers, true/false, "
                     f"null), received {shown(value)}")


def plain(value: Any, where: str) -> Any:
    """A copy of ``value`` made of JSON types only: objects with text keys (any ``Mapping``), lists
    (tuples become lists), text, numbers (numpy scalars become Python numbers; integers beyond a
    float refused), true/false, null; nested at most :data:`MAX_DEPTH` levels. Anything else is a
    one-line ``ValueError`` naming ``where`` and the place inside it (``where['key'][3]``)."""
    root: list[Any] = [None]
    # (value, its container in the copy, its key there, its place as (parent place, key), depth)
    stack: list[tuple[Any, Any, Any, Any, int]] = [(value, root, 0, None, 0)]
    while stack:
        v, parent, key, place, depth = stack.pop()
        if type(v) in (dict, list) or isinstance(v, (Mapping, tuple)):
            if depth >= MAX_DEPTH:
                raise ValueError(f"{_place(where, place)}: objects and lists nested more than {MAX_DEPTH} levels deep")
            if type(v) is dict or isinstance(v, Mapping):
                out: Any = {}
                for k, x in v.items():
                    if not isinstance(k, str):
                        raise ValueError(f"{_place(where, place)}: expected text keys, received {shown(k)}")
                    out[k] = None
                    stack.append((x, out, k, (place, k), depth + 1))
            else:
                out = [None] * len(v)
                stack.extend((x, out, i, (place, i), depth + 1) for i, x in enumerate(v))
            parent[key] = out
        else:
            parent[key] = _scalar(v, where, place)
    return root[0]


def _place(where: str, place: Any) -> str:
    """``where`` followed by the keys of ``place`` (a chain of ``(parent, key)``), e.g. ``where['a'][3]``."""
    keys = []
    while place is not None:
        place, key = place
        keys.append(f"[{key}]" if isinstance(key, int) else f"[{shown(key)}]")
    return where + "".join(reversed(keys))
