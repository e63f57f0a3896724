"""The one JSON conversion of results: numpy/torch scalars as numbers, NaN and inf as ``null``."""

from __future__ import annotations

import json
import math
from typing import Any


#: Deepest nesting :func:`json_safe` converts: results are a few levels deep; deeper values (or a
#: ``to_dict`` that returns itself) are refused with a ``ValueError`` instead of a ``RecursionError``.
MAX_DEPTH = 64


def json_safe(x: Any, _depth: int = 0) -> Any:
    """``x`` with numpy/torch scalars as Python numbers, tuples as lists, NaN/inf as ``None``,
    dataclass-like objects through their ``to_dict()``; anything else unknown as ``str``; nested
    at most :data:`MAX_DEPTH` levels (else ``ValueError``)."""
    if _depth > MAX_DEPTH:
        raise ValueError(f"json_safe: values nested more than {MAX_DEPTH} levels deep")
    if isinstance(x, dict):
        return {str(k): json_safe(v, _depth + 1) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v, _depth + 1) for v in x]
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if hasattr(x, "to_dict") and callable(x.to_dict):
        return json_safe(x.to_dict(), _depth + 1)
    if hasattr(x, "item") and callable(x.item) and getattr(x, "ndim", 0) == 0:  # numpy / torch scalar
        return json_safe(x.item(), _depth + 1)
    if isinstance(x, int):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return str(x)


def dumps(x: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`json_safe` ``(x)`` (strict JSON: never ``NaN``)."""
    return json.dumps(json_safe(x), allow_nan=False, **kwargs)
