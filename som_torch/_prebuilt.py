"""The C kernels' prebuilt libraries: what ``setup.py`` compiles when the package is built or
installed, and which of them :class:`som_torch.CKernel` loads at run time (no compiler needed).

Standard library only: ``setup.py`` loads this file by its path, without torch.

* Flags: the kernel's own flags without ``-march=native``/``-mtune=native`` (:func:`portable_flags`),
  so that a wheel runs on every CPU of its architecture; plus, per architecture, optional
  :data:`VARIANTS` for newer CPUs (x86-64: ``-march=x86-64-v4``, AVX-512; ``-march=x86-64-v3``,
  AVX2 + FMA). The run-time build with ``-march=native`` is never needed, only the fallback where
  no prebuilt library fits.
* Name: ``_<kernel>_<REAL>[_<variant>]_<key>`` + the interpreter's extension suffix, beside the
  kernel's ``.c`` file; ``key`` hashes the source, ``REAL``, the flags and the variant, so a library
  built from another source or with other flags is never found (an editable checkout whose ``.c``
  changed falls back to the run-time build until it is reinstalled).
"""

from __future__ import annotations

import hashlib
import platform
import sysconfig
from collections.abc import Sequence
from pathlib import Path

#: Builds made beside the base build, per ``platform.machine()``: variant -> extra compile flags.
#: Best first: a CPU runs the first whose :data:`NEEDS` it has.
VARIANTS: dict[str, dict[str, tuple[str, ...]]] = {
    "x86_64": {"x86_64_v4": ("-march=x86-64-v4",), "x86_64_v3": ("-march=x86-64-v3",)}}
_V3 = frozenset({"avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave"})
#: The ``/proc/cpuinfo`` flags a variant needs (x86-64-v3: AVX, AVX2, BMI1/2, F16C, FMA, LZCNT, MOVBE;
#: x86-64-v4: those and AVX-512 F, BW, CD, DQ, VL).
NEEDS: dict[str, frozenset[str]] = {
    "x86_64_v4": _V3 | {"avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"}, "x86_64_v3": _V3}
_NATIVE = ("-march=native", "-mtune=native")
_VERSION = "prebuilt-1"  # bump when the build steps change


def portable_flags(flags: Sequence[str]) -> tuple[str, ...]:
    """``flags`` without the ones that tie the code to the building machine's CPU."""
    return tuple(f for f in flags if f not in _NATIVE)


def variant_flags(variant: str, machine: str | None = None) -> tuple[str, ...]:
    """The extra flags of ``variant`` (``""``: the base build, none)."""
    return VARIANTS.get(machine or platform.machine(), {}).get(variant, ()) if variant else ()


def library_stem(name: str, real: str, variant: str, source_text: str, flags: Sequence[str],
                 link_flags: Sequence[str]) -> str:
    """The file stem of a prebuilt library (see the module docstring)."""
    key = hashlib.sha256("\n".join([_VERSION, source_text, real, variant, *flags, "|", *link_flags]).encode())
    return f"_{name}_{real}{'_' + variant if variant else ''}_{key.hexdigest()[:12]}"


def extension_suffix() -> str:
    """The interpreter's suffix of compiled modules (``.cpython-311-x86_64-linux-gnu.so``)."""
    return str(sysconfig.get_config_var("EXT_SUFFIX") or ".so")


def cpu_flags(cpuinfo: str | None = None) -> frozenset[str]:
    """The CPU's feature flags from ``/proc/cpuinfo`` (``cpuinfo`` its text); empty when unknown."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return frozenset()
    line = next((ln for ln in cpuinfo.splitlines() if ln.startswith("flags")), "")
    return frozenset(line.split(":", 1)[-1].split())


def usable_variants(machine: str | None = None, flags: frozenset[str] | None = None) -> list[str]:
    """The variants this CPU runs, best first, ending with the base build ``""``."""
    flags = cpu_flags() if flags is None else flags
    extra = VARIANTS.get(machine or platform.machine(), {})
    return [v for v in extra if NEEDS.get(v, frozenset()) <= flags] + [""]


def all_variants(machine: str | None = None) -> list[str]:
    """Every variant ``setup.py`` builds on ``machine``: the extra ones and the base build ``""``."""
    return [*VARIANTS.get(machine or platform.machine(), {}), ""]
