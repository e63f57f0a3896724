"""Compile, cache and load a small C kernel; call its functions with checked tensor arguments.

One convention for every C kernel of the project (``som_torch``'s online rule, ``sim``'s fused
integrator):

* the C lives in a ``.c`` file written for one float type ``REAL``; it is compiled once per
  type with ``-DREAL=float`` and ``-DREAL=double`` into two shared libraries (same function
  names in both; the tensors' dtype picks the library);
* each exported function's signature is declared once, in a :class:`CFunction` table; every
  call is checked against it (dtype, shape, contiguity of each tensor) before C sees a pointer
  (in full once per call signature, see :class:`CheckedFunction`);
* libraries prebuilt when the package was built or installed (``setup.py``, portable flags,
  :mod:`som_torch._prebuilt`) lie beside the ``.c`` file and are loaded first: no compiler, no
  warning at run time. Only where none fits (a source checkout, a changed ``.c``) is the kernel
  compiled on first use with its own flags (``-march=native`` allowed) into a cache folder that
  must be owned by the current user and not writable by group or others (a library loaded from it
  runs in this process); the cache key covers the source, flags, compiler, platform and, with
  ``-march=native``, the CPU's flags;
* whatever fails (no compiler, a build error, an unsafe folder) gives one warning line and
  ``None``: the caller falls back to its torch path.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from . import _prebuilt

#: The C type of ``REAL`` for each supported tensor dtype.
REALS: dict[torch.dtype, str] = {torch.float32: "float", torch.float64: "double"}

_SCALARS: dict[str, Any] = {"int": ctypes.c_int, "int32": ctypes.c_int32, "int64": ctypes.c_int64,
                            "double": ctypes.c_double, "REAL": None}  # REAL: the library's float type
_ELEMENTS: dict[str, torch.dtype | None] = {"int8": torch.int8, "int32": torch.int32, "int64": torch.int64,
                                            "double": torch.float64, "REAL": None}
_ARG = re.compile(r"^\s*(\w+)\s*:\s*(\w+)\s*(?:\[([\w\s,]*)\])?\s*(\?)?\s*$")
_BUILD_VERSION = "cbuild-1"  # bump when the build steps change


@dataclass(frozen=True)
class _Arg:
    name: str
    kind: str  # a key of _SCALARS (scalar) or of _ELEMENTS (tensor)
    shape: tuple[str | int, ...] | None  # None: a scalar; dims are sizes or names bound per call
    optional: bool  # a tensor that may be None (NULL)

    @classmethod
    def parse(cls, text: str) -> "_Arg":
        """``"name: int64"`` (scalar), ``"name: REAL[n, 4]"`` (tensor), ``"name: REAL[n]?"`` (or None)."""
        m = _ARG.match(text)
        if m is None or (m[3] is None and m[2] not in _SCALARS) or (m[3] is not None and m[2] not in _ELEMENTS):
            raise ValueError(f"C argument: expected 'name: type' or 'name: type[dims]', received {text!r}")
        dims = None if m[3] is None else tuple(int(d) if d.strip().isdigit() else d.strip()
                                                for d in m[3].split(",") if d.strip())
        return cls(m[1], m[2], dims, m[4] is not None)


@dataclass(frozen=True)
class CFunction:
    """The signature of one exported C function, declared once.

    ``args``: one ``"name: type"`` per C parameter, in order. Scalar types: ``int``, ``int32``,
    ``int64``, ``double``, ``REAL``. Tensors (passed as pointers): ``type[dims]`` with element
    type ``int8``, ``int32``, ``int64``, ``double`` or ``REAL``, dims as sizes or names (a name
    is the value of the scalar argument of that name, else the size first seen for it in this
    call); a trailing ``?`` lets the tensor be ``None`` (a NULL pointer). ``returns``: a scalar
    type or ``None`` (void)."""

    args: tuple[str, ...]
    returns: str | None = None

    def __post_init__(self) -> None:
        self.parsed()  # a malformed declaration fails where it is written
        if self.returns is not None and self.returns not in _SCALARS:
            raise ValueError(f"C return type: expected one of {list(_SCALARS)} or None, received {self.returns!r}")

    def parsed(self) -> tuple[_Arg, ...]:
        return tuple(_Arg.parse(a) for a in self.args)


class CheckedFunction:
    """A loaded C function that checks its arguments against the declared signature, then calls.

    The full check runs once per call signature: the arguments' :meth:`_key` (each tensor's dtype,
    shape, contiguity and whether on the CPU, each size scalar's value, each other argument's
    type) is remembered after a call that passed, and a later call with the same key only builds
    the key and takes the data pointers (som_epoch's 16 arguments: 17 us per call instead of
    41 us, of which 7 us are the ctypes call itself)."""

    _MAX_KEYS = 256  # call signatures remembered per function (then forgotten all at once)

    def __init__(self, name: str, fn: Any, sig: CFunction, dtype: torch.dtype):
        self.name, self._fn, self._args, self._dtype = name, fn, sig.parsed(), dtype
        self._sizes = tuple(a.shape is None and a.kind.startswith("int") for a in self._args)
        self._passed: set[tuple] = set()
        real = ctypes.c_float if dtype == torch.float32 else ctypes.c_double
        fn.argtypes = [ctypes.c_void_p if a.shape is not None else (_SCALARS[a.kind] or real) for a in self._args]
        fn.restype = None if sig.returns is None else (_SCALARS[sig.returns] or real)

    def __call__(self, *values: Any) -> Any:
        if len(values) != len(self._args):
            raise TypeError(f"{self.name}: expected {len(self._args)} arguments, received {len(values)}")
        key = self._key(values)
        if key not in self._passed:
            sizes = {a.name: v for a, v, s in zip(self._args, values, self._sizes) if s}
            for a, v in zip(self._args, values):
                self._check(a, v, sizes)
            if len(self._passed) >= self._MAX_KEYS:
                self._passed.clear()
            self._passed.add(key)
        return self._fn(*(v.data_ptr() if isinstance(v, torch.Tensor) else v for v in values))

    def _key(self, values: tuple) -> tuple:
        """What the check of ``values`` depends on (see the class docstring)."""
        return tuple((v.dtype, v.shape, v.is_cpu, v.is_contiguous()) if isinstance(v, torch.Tensor)
                     else v if size else type(v) for v, size in zip(values, self._sizes))

    def _check(self, arg: _Arg, value: Any, sizes: dict[str, int]) -> Any:
        """The ctypes value of ``value`` for ``arg`` (a tensor's data pointer), or a one-line error."""
        where = f"{self.name}: argument '{arg.name}'"
        if arg.shape is None:
            if isinstance(value, torch.Tensor):
                raise TypeError(f"{where}: expected a Python {arg.kind} scalar, received a tensor")
            return value
        if value is None and arg.optional:
            return None
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{where}: expected a tensor, received {type(value).__name__}")
        dtype = _ELEMENTS[arg.kind] or self._dtype
        if value.dtype != dtype:
            raise TypeError(f"{where}: expected dtype {dtype}, received {value.dtype}")
        expected = [d if isinstance(d, int) else sizes.setdefault(d, value.shape[i] if i < value.dim() else -1)
                    for i, d in enumerate(arg.shape)]
        if list(value.shape) != expected:
            dims = ", ".join(f"{d}={e}" if isinstance(d, str) else str(d) for d, e in zip(arg.shape, expected))
            raise ValueError(f"{where}: expected shape ({dims}), received {tuple(value.shape)}")
        if value.device.type != "cpu" or not value.is_contiguous():
            raise ValueError(f"{where}: expected a contiguous CPU tensor, received "
                             f"{'a non-contiguous' if value.device.type == 'cpu' else 'a ' + value.device.type} tensor")
        return value.data_ptr()


class CLibrary:
    """A kernel's two loaded libraries (``REAL`` = float and double) behind its signature table."""

    def __init__(self, name: str, libs: Mapping[torch.dtype, ctypes.CDLL], functions: Mapping[str, CFunction]):
        self.name = name
        self._functions: dict[tuple[str, torch.dtype], CheckedFunction] = {}
        for fname, sig in functions.items():
            for dtype, lib in libs.items():
                self._functions[fname, dtype] = CheckedFunction(f"{fname}[{REALS[dtype]}]", getattr(lib, fname), sig, dtype)

    def function(self, name: str, dtype: torch.dtype) -> CheckedFunction:
        """The checked C function ``name`` of the library for ``dtype`` (float32 or float64)."""
        fn = self._functions.get((name, dtype))
        if fn is None:
            names = sorted({n for n, _ in self._functions})
            raise ValueError(f"{self.name}: expected a function in {names} and a dtype in "
                             f"{[str(d) for d in REALS]}, received {name!r}, {dtype}")
        return fn


def cpu_id(cpuinfo: str | None = None) -> str:
    """What ``-march=native`` code depends on: a hash of the ``flags`` line of ``/proc/cpuinfo``
    (``cpuinfo`` its text, read when None), else ``platform.machine() + platform.processor()``."""
    flags = _prebuilt.cpu_flags(cpuinfo)
    if not flags:
        return platform.machine() + platform.processor()
    return hashlib.sha256(" ".join(sorted(flags)).encode()).hexdigest()[:16]


def _unsafe(path: Path, owner: int | None = None) -> str | None:
    """Why a library at ``path`` must not be loaded (not owned by ``owner``, default this user, or
    writable by group/others), or None."""
    st = path.stat()
    if owner is None and hasattr(os, "getuid"):
        owner = os.getuid()
    if owner is not None and st.st_uid != owner:
        return f"{path} is owned by uid {st.st_uid}, expected uid {owner}"
    if st.st_mode & 0o022:
        return f"{path} is writable by group/others (mode {oct(st.st_mode & 0o777)})"
    return None


def _last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else "no message"


@dataclass(frozen=True)
class CKernel:
    """A C source compiled per float type into cached shared libraries (see the module docstring).

    ``name``: the libraries' file stem and the name in messages; ``source``: the ``.c`` file;
    ``functions``: the signature table; ``flags``: compile flags (``-fPIC -c`` and ``-DREAL``
    are added); ``link_flags``: for the ``-shared`` link step (compiled objects are linked
    without ``flags``, so ``-ffast-math`` does not link ``crtfastmath.o``, which would flush
    subnormals to zero for the whole process)."""

    name: str
    source: Path
    functions: Mapping[str, CFunction]
    flags: tuple[str, ...]
    link_flags: tuple[str, ...] = ("-lm",)

    def cache_key(self, real: str, compiler: str, cpu: str | None = None) -> str:
        """The library's key: source, flags, ``REAL``, compiler, platform and, with
        ``-march=native``, the CPU (``cpu``, default :func:`cpu_id`)."""
        native = "-march=native" in self.flags
        parts = [_BUILD_VERSION, self.source.read_text(), real, *self.flags, "|", *self.link_flags, compiler,
                 sys.platform, platform.machine(), (cpu_id() if cpu is None else cpu) if native else ""]
        return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]

    def prebuilt(self, real: str, variants: list[str] | None = None) -> Path | None:
        """The library for ``real`` that ``setup.py`` built beside the source, best variant this
        CPU runs first (``variants``: default :func:`som_torch._prebuilt.usable_variants`), or None."""
        text = self.source.read_text()
        for variant in _prebuilt.usable_variants() if variants is None else variants:
            flags = (*_prebuilt.portable_flags(self.flags), *_prebuilt.variant_flags(variant))
            stem = _prebuilt.library_stem(self.name, real, variant, text, flags, self.link_flags)
            path = self.source.with_name(stem + _prebuilt.extension_suffix())
            if path.is_file():
                return path
        return None

    def origin(self, cache_dir: Path) -> str:
        """Where :meth:`load` takes the libraries from: the prebuilt ones' file names when both float
        types are prebuilt, else the run-time build's ``cache_dir`` (for benchmark and bug reports)."""
        prebuilt = [self.prebuilt(real) for real in REALS.values()]
        if all(prebuilt):
            return "prebuilt " + ", ".join(p.name for p in prebuilt)  # type: ignore[union-attr]
        return f"compiled at run time into {cache_dir}"

    def load(self, cache_dir: Path, cc: str | None) -> CLibrary | None:
        """The prebuilt libraries beside the source when both float types are there (no compiler
        needed, no warning); else those built into ``cache_dir`` with the compiler ``cc``
        (``$CC``; None: ``cc``, else ``gcc``); or ``None`` after one warning line."""
        try:
            prebuilt = self._load_prebuilt()
            return prebuilt if prebuilt is not None else self._load(Path(cache_dir), cc)
        except (OSError, subprocess.SubprocessError) as err:
            warnings.warn(f"{self.name}: C kernel unavailable ({err}); using the torch path",
                          RuntimeWarning, stacklevel=3)
            return None

    def _load_prebuilt(self) -> CLibrary | None:
        paths = {dtype: self.prebuilt(real) for dtype, real in REALS.items()}
        if any(p is None for p in paths.values()):
            return None
        owner = self.source.stat().st_uid  # as trusted as the Python code beside it
        libs = {}
        for dtype, path in paths.items():
            why = _unsafe(path, owner)
            if why:
                raise OSError(f"unsafe prebuilt library: {why}")
            libs[dtype] = ctypes.CDLL(str(path))
        return CLibrary(self.name, libs, self.functions)

    def _load(self, cache_dir: Path, cc: str | None) -> CLibrary:
        compiler = shutil.which(cc) if cc else (shutil.which("cc") or shutil.which("gcc"))
        if compiler is None:
            raise OSError(f"no C compiler ({'$CC=' + cc + ' not found' if cc else 'cc/gcc not on PATH'})")
        cache_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        why = _unsafe(cache_dir)
        if why:
            raise OSError(f"unsafe cache folder: {why}")
        libs = {}
        for dtype, real in REALS.items():
            path = cache_dir / f"{self.name}_{real}_{self.cache_key(real, compiler)}.so"
            if not path.exists():
                self._build(path, real, compiler)
            why = _unsafe(path)
            if why:
                raise OSError(f"unsafe cached library: {why}")
            libs[dtype] = ctypes.CDLL(str(path))
        return CLibrary(self.name, libs, self.functions)

    def _build(self, out: Path, real: str, compiler: str) -> None:
        """Compile and link into a private temporary folder beside ``out``, then rename (atomic)."""
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            obj, lib = Path(tmp) / "kernel.o", Path(tmp) / "kernel.so"
            for cmd in ([compiler, *self.flags, f"-DREAL={real}", "-fPIC", "-c", str(self.source), "-o", str(obj)],
                        [compiler, "-shared", str(obj), "-o", str(lib), *self.link_flags]):
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
                if res.returncode != 0:
                    raise OSError(f"C build failed: {_last_line(res.stderr)}")
            os.chmod(lib, 0o755)
            os.replace(lib, out)
