"""The environment variables ``sim`` reads (here and nowhere else).

``TWOMASS_NO_C_KERNEL``
    Any non-empty value disables the fused C kernel; the simulator then runs its torch eager
    twin (same numbers, slower).
``TWOMASS_CACHE``
    The folder of the compiled kernel; default ``~/.cache/twomass-som``.
``CC``
    The C compiler (a name on ``PATH`` or a path); default ``cc``, else ``gcc``.
"""

from __future__ import annotations

import os
from pathlib import Path


def c_kernel_enabled() -> bool:
    """Whether the fused C kernel may be used (``TWOMASS_NO_C_KERNEL`` unset or empty)."""
    return not os.environ.get("TWOMASS_NO_C_KERNEL")


def cache_dir() -> Path:
    """``$TWOMASS_CACHE``, else ``~/.cache/twomass-som``."""
    return Path(os.environ.get("TWOMASS_CACHE") or Path.home() / ".cache" / "twomass-som")


def compiler() -> str | None:
    """``$CC``, or None (the default compiler)."""
    return os.environ.get("CC") or None
