"""The C-kernel convention (som_torch._cbuild): build per REAL, checked calls, safe cache, CPU key."""

from __future__ import annotations

import os
import shutil
import textwrap

import pytest
import torch

from som_torch import CFunction, CKernel

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler")

_AXPY = textwrap.dedent("""
    #include <stdint.h>
    /* y[i] += a * x[i] for n values; returns n */
    int64_t axpy(int64_t n, REAL a, const REAL *x, REAL *y) {
        for (int64_t i = 0; i < n; ++i) y[i] += a * x[i];
        return n;
    }
""")


@pytest.fixture()
def kernel(tmp_path):
    src = tmp_path / "axpy.c"
    src.write_text(_AXPY)
    return CKernel(name="axpy", source=src, functions={"axpy": CFunction(("n: int64", "a: REAL", "x: REAL[n]",
                                                                           "y: REAL[n]"), returns="int64")},
                   flags=("-O2",))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_both_float_types_built_and_called(kernel, tmp_path, dtype):
    lib = kernel.load(tmp_path / "cache", None)
    assert lib is not None
    x, y = torch.arange(4, dtype=dtype), torch.ones(4, dtype=dtype)
    assert lib.function("axpy", dtype)(4, 0.5, x, y) == 4
    assert y.tolist() == [1.0, 1.5, 2.0, 2.5]


def test_arguments_checked_before_the_call(kernel, tmp_path):
    fn = kernel.load(tmp_path / "cache", None).function("axpy", torch.float64)
    x, y = torch.zeros(4, dtype=torch.float64), torch.zeros(4, dtype=torch.float64)
    with pytest.raises(TypeError, match="argument 'x': expected dtype torch.float64"):
        fn(4, 1.0, x.float(), y)
    with pytest.raises(ValueError, match=r"argument 'y': expected shape \(n=4\), received \(3,\)"):
        fn(4, 1.0, x, y[:3])
    with pytest.raises(ValueError, match="contiguous"):
        fn(2, 1.0, x[::2], y[:2])
    with pytest.raises(TypeError, match="expected 4 arguments"):
        fn(4, 1.0, x)
    with pytest.raises(ValueError, match=r"expected a function in \['axpy'\]"):
        kernel.load(tmp_path / "cache", None).function("nope", torch.float64)



def test_checks_remembered_per_call_signature_only(kernel, tmp_path):
    """A call that passed lets the same signature skip the checks; any other signature is checked."""
    fn = kernel.load(tmp_path / "cache", None).function("axpy", torch.float64)
    x, y = torch.ones(4, dtype=torch.float64), torch.zeros(4, dtype=torch.float64)
    for _ in range(2):
        assert fn(4, 2.0, x, y) == 4
    assert y.tolist() == [4.0] * 4
    with pytest.raises(ValueError, match=r"argument 'x': expected shape \(n=3\), received \(4,\)"):
        fn(3, 1.0, x, y[:3])  # another size scalar
    with pytest.raises(ValueError, match="contiguous"):
        fn(4, 1.0, torch.ones(8, dtype=torch.float64)[::2], y)  # same shape, not contiguous
    with pytest.raises(TypeError, match="expected dtype torch.float64"):
        fn(4, 1.0, x.float(), y)
    with pytest.raises(TypeError, match="expected a Python REAL scalar, received a tensor"):
        fn(4, torch.tensor(1.0), x, y)
    assert y.tolist() == [4.0] * 4  # no failed call reached C

def test_malformed_declaration_fails_where_written():
    with pytest.raises(ValueError, match="C argument"):
        CFunction(("n int64",))


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX permissions")
def test_unsafe_cache_folder_refused_with_one_warning(kernel, tmp_path):
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(0o777)
    with pytest.warns(RuntimeWarning, match="unsafe cache folder"):
        assert kernel.load(folder, None) is None
    assert not list(folder.iterdir())  # nothing was built into it


def test_missing_compiler_gives_none_and_a_warning(kernel, tmp_path):
    with pytest.warns(RuntimeWarning, match="no C compiler"):
        assert kernel.load(tmp_path / "cache", "no-such-compiler-xyz") is None


def test_native_code_keyed_on_the_cpu(tmp_path):
    src = tmp_path / "k.c"
    src.write_text(_AXPY)
    fn = {"axpy": CFunction(("n: int64", "a: REAL", "x: REAL[n]", "y: REAL[n]"), returns="int64")}
    native = CKernel("k", src, fn, flags=("-O2", "-march=native"))
    portable = CKernel("k", src, fn, flags=("-O2",))
    assert native.cache_key("float", "cc", cpu="a") != native.cache_key("float", "cc", cpu="b")
    assert portable.cache_key("float", "cc", cpu="a") == portable.cache_key("float", "cc", cpu="b")
    assert native.cache_key("float", "cc", cpu="a") != native.cache_key("double", "cc", cpu="a")


def _prebuild(kernel: CKernel, variant: str = "") -> None:
    """What setup.py does for one kernel: a portable library per REAL beside the source, named by
    :func:`som_torch._prebuilt.library_stem`."""
    import subprocess

    from som_torch import _prebuilt

    cc = shutil.which("cc") or shutil.which("gcc")
    flags = (*_prebuilt.portable_flags(kernel.flags), *_prebuilt.variant_flags(variant))
    for real in ("float", "double"):
        stem = _prebuilt.library_stem(kernel.name, real, variant, kernel.source.read_text(), flags, kernel.link_flags)
        out = kernel.source.with_name(stem + _prebuilt.extension_suffix())
        subprocess.run([cc, *flags, f"-DREAL={real}", "-fPIC", "-shared", str(kernel.source), "-o", str(out),
                        *kernel.link_flags], check=True)


def test_prebuilt_library_needs_no_compiler_and_no_cache(kernel, tmp_path, recwarn):
    """Libraries built with the package are loaded first: no compiler, no cache folder, no warning."""
    _prebuild(kernel)
    cache = tmp_path / "cache"
    lib = kernel.load(cache, "no-such-compiler-xyz")
    assert lib is not None and not cache.exists() and not recwarn.list
    y = torch.zeros(2, dtype=torch.float32)
    assert lib.function("axpy", torch.float32)(2, 2.0, torch.ones(2), y) == 2 and y.tolist() == [2.0, 2.0]


def test_prebuilt_library_of_another_source_is_not_used(kernel, tmp_path):
    """A checkout whose .c changed after the build: the stale library is not found (name keyed on the source)."""
    _prebuild(kernel)
    kernel.source.write_text(_AXPY.replace("y[i] += a * x[i]", "y[i] -= a * x[i]"))
    assert kernel.prebuilt("float") is None
    with pytest.warns(RuntimeWarning, match="no C compiler"):
        assert kernel.load(tmp_path / "cache", "no-such-compiler-xyz") is None


def test_prebuilt_variants_follow_the_cpu():
    from som_torch import _prebuilt

    v3, v4 = _prebuilt.NEEDS["x86_64_v3"], _prebuilt.NEEDS["x86_64_v4"]
    assert _prebuilt.usable_variants("x86_64", v4) == ["x86_64_v4", "x86_64_v3", ""]
    assert _prebuilt.usable_variants("x86_64", v4 - {"avx512vl"}) == ["x86_64_v3", ""]
    assert _prebuilt.usable_variants("x86_64", v3) == ["x86_64_v3", ""]
    assert _prebuilt.usable_variants("x86_64", v3 - {"avx2"}) == [""]
    assert _prebuilt.usable_variants("aarch64", v3) == [""]
    assert _prebuilt.portable_flags(("-O3", "-march=native", "-fopenmp")) == ("-O3", "-fopenmp")
    assert _prebuilt.cpu_flags("processor: 0\nflags\t\t: fpu avx2 fma\n") == frozenset({"fpu", "avx2", "fma"})
