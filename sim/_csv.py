"""The records' number parser and formatter (``_csv.c``): their signatures and loader.

``parse_rows`` reads rows of comma-separated numbers, each the double ``strtod`` gives (Python's
``float``): by Clinger's exact fast path, on x86 decimals of up to 19 digits such as the ``%.17g``
time column by an x87 extended-precision path that declines the values next to a midpoint of two
doubles, else by ``strtod`` itself (7-9x numpy's ``loadtxt`` on these records; the time column
took 2 of 3.2 ms per record through ``strtod``, 1 ms now); ``format_rows`` writes them with
``snprintf`` (the text ``numpy.savetxt`` writes with the same ``%.Ng`` / ``%d`` formats, several
times faster). Built and loaded like the simulator's kernel (:mod:`sim._kernel`); where it cannot
be loaded, or a row is not plain numbers, :func:`parse_numbers` and :func:`format_numbers` return
``None`` and the records module uses numpy, which also words the errors.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from som_torch import CFunction, CKernel, CLibrary

from sim import _config

#: Build facts as plain literals (``setup.py`` reads them without importing torch).
NAME, SOURCE = "twomass_csv", "_csv.c"
FLAGS = ("-O2", "-std=c99")
LINK_FLAGS = ("-lm",)

KERNEL = CKernel(
    name=NAME,
    source=Path(__file__).with_name(SOURCE),
    functions={"parse_rows": CFunction(("n: int64", "text: int8[m]", "ncols: int32", "rows: int64",
                                        "out: double[rows, ncols]"), returns="int64"),
               "format_rows": CFunction(("rows: int64", "ncols: int32", "data: double[rows, ncols]",
                                         "digits: int32[ncols]", "cap: int64", "out: int8[cap]"), returns="int64")},
    flags=FLAGS,
    link_flags=LINK_FLAGS,
)


@lru_cache(maxsize=1)
def _load() -> CLibrary | None:
    return _config.load_c_kernel(KERNEL)


def parse_numbers(body: bytes, ncols: int) -> np.ndarray | None:
    """``rows x ncols`` float64 of the comma-separated rows in ``body`` (the CSV without its header),
    or ``None`` where the parser is unavailable or a row is not ``ncols`` plain numbers."""
    lib = _load()
    if lib is None:
        return None
    buf = bytearray(body)
    buf.append(0)  # strtod stops at the NUL
    text = torch.frombuffer(buf, dtype=torch.int8)
    rows = body.count(b"\n") + 1
    out = torch.empty(rows, ncols, dtype=torch.float64)
    got = lib.function("parse_rows", torch.float64)(len(body), text, ncols, rows, out)
    return out[:got].numpy() if got >= 0 else None


def format_numbers(data: np.ndarray, digits: list[int]) -> str | None:
    """The rows of ``data`` (``rows x ncols`` float64) as CSV text, column ``c`` in ``%.{digits[c]}g``
    (``0``: ``%d``), or ``None`` where the formatter is unavailable."""
    lib = _load()
    if lib is None:
        return None
    data = torch.from_numpy(np.ascontiguousarray(data, dtype=np.float64))
    cap = 32 * data.numel() + 16  # %.17g of a double is at most 24 characters, plus the separator
    out = torch.empty(cap, dtype=torch.int8)
    n = lib.function("format_rows", torch.float64)(data.shape[0], data.shape[1], data,
                                                    torch.tensor(digits, dtype=torch.int32), cap, out)
    return None if n < 0 else out[:n].numpy().tobytes().decode("ascii")
