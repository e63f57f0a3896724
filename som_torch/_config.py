"""The environment variables ``som_torch`` reads (here and nowhere else).

``SOM_TORCH_NATIVE``
    ``0`` disables the native C kernel of ``method="native"`` / ``"fast"`` (training then uses
    the torch path); any other value, or unset, lets it build and load.
``SOM_TORCH_CACHE``
    The folder of the compiled kernel; default ``$XDG_CACHE_HOME/som_torch``.
``XDG_CACHE_HOME``
    The user's cache folder (default ``~/.cache``), used when ``SOM_TORCH_CACHE`` is unset.
``CC``
    The C compiler (a name on ``PATH`` or a path); default ``cc``, else ``gcc``.
"""

from __future__ import annotations

import os
from pathlib import Path


def native_enabled() -> bool:
    """Whether the native kernel may be used (``SOM_TORCH_NATIVE`` is not ``0``)."""
    return os.environ.get("SOM_TORCH_NATIVE", "1") != "0"


def cache_dir() -> Path:
    """``$SOM_TORCH_CACHE``, else ``$XDG_CACHE_HOME/som_torch``, else ``~/.cache/som_torch``."""
    base = os.environ.get("SOM_TORCH_CACHE")
    if base:
        return Path(base)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "som_torch"


def compiler() -> str | None:
    """``$CC``, or None (the default compiler)."""
    return os.environ.get("CC") or None
