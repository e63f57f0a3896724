"""Build step of twomass-som (the metadata is in pyproject.toml): the package list, with the shipped
maps as the package ``training.checkpoints`` (folder ``checkpoints/``); and the C kernels, compiled when
the package is built or installed, as plain shared libraries for ctypes (no Python API), once per
float type and variant, beside their ``.c`` file, so that an installed package never needs a
compiler. Names, variants and portable flags: ``som_torch/_prebuilt.py``; each kernel's flags:
its module (``NAME``, ``SOURCE``, ``FLAGS``, ``LINK_FLAGS``). A kernel that fails to build
(no compiler where an sdist is installed) is skipped with a warning: it is then compiled on first
use where a compiler exists, else the torch path runs.
"""

from __future__ import annotations

import ast
import importlib.util
import os
from pathlib import Path

from setuptools import Extension, find_packages, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent
#: The modules that declare a C kernel.
KERNEL_MODULES = ("sim/_kernel.py", "sim/_csv.py", "som_torch/_native.py", "training/identification/_resonance.py")
REALS = ("float", "double")


def packages() -> list[str]:
    """Every package of the tree, and ``training.checkpoints``: the shipped maps, whose folder is the
    repository's top-level ``checkpoints/`` (see :data:`PACKAGE_DIR`)."""
    return [*find_packages(where=str(ROOT), include=["som_torch*", "sim*", "training*"]), "training.checkpoints"]


#: The maps' package lives in the top-level folder (its package data: pyproject.toml).
PACKAGE_DIR = {"training.checkpoints": "checkpoints"}


def _load_prebuilt():
    spec = importlib.util.spec_from_file_location("_prebuilt", ROOT / "som_torch" / "_prebuilt.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build_facts(module: str) -> dict:
    """The plain-literal ``NAME, SOURCE, FLAGS, LINK_FLAGS`` of a kernel module (read, not imported)."""
    wanted, facts = {"NAME", "SOURCE", "FLAGS", "LINK_FLAGS"}, {}
    for node in ast.parse((ROOT / module).read_text()).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
            names = [e.id for e in target.elts] if isinstance(target, ast.Tuple) else [getattr(target, "id", "")]
            if set(names) <= wanted:
                value = ast.literal_eval(node.value)
                facts.update(zip(names, value) if isinstance(target, ast.Tuple) else [(names[0], value)])
    if set(facts) != wanted:
        raise RuntimeError(f"{module}: expected plain-literal build facts, missing {sorted(wanted - set(facts))}")
    return facts


def kernel_extensions() -> list[Extension]:
    pb = _load_prebuilt()
    out = []
    for module in KERNEL_MODULES:
        f = _build_facts(module)
        package = str(Path(module).parent)
        source = f"{package}/{f['SOURCE']}"
        text = (ROOT / source).read_text()
        for variant in pb.all_variants():
            flags = (*pb.portable_flags(f["FLAGS"]), *pb.variant_flags(variant))
            for real in REALS:
                stem = pb.library_stem(f["NAME"], real, variant, text, flags, f["LINK_FLAGS"])
                out.append(Extension(f"{package.replace('/', '.')}.{stem}", sources=[source],
                                     define_macros=[("REAL", real)], extra_compile_args=list(flags),
                                     extra_link_args=list(f["LINK_FLAGS"]), optional=True))
    return out


class BuildKernels(build_ext):
    """``build_ext`` with one temporary folder per library (every library compiles the same ``.c``)."""

    def build_extension(self, ext: Extension) -> None:
        base = self.build_temp
        self.build_temp = os.path.join(base, ext.name)
        try:
            super().build_extension(ext)
        finally:
            self.build_temp = base

    def get_export_symbols(self, ext: Extension) -> list[str]:
        return []  # plain C libraries for ctypes: no PyInit_ function


if __name__ == "__main__":  # as setuptools' build backend runs it; tests import kernel_extensions()
    setup(packages=packages(), package_dir=PACKAGE_DIR, ext_modules=kernel_extensions(),
          cmdclass={"build_ext": BuildKernels})
