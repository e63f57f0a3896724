"""What an installed wheel holds: the shipped maps as package data found from any folder, every
package, and the prebuilt C kernels under the names the run time looks for (fast: no wheel build;
setuptools' own ``build_py`` lays out the pure-Python part exactly as the wheel does)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tarfile
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _setup_module():
    spec = importlib.util.spec_from_file_location("setup_under_test", REPO / "setup.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # not __main__: declares, does not build
    return module


def test_every_package_is_installed_with_the_maps():
    """setup.py's list holds every package of the tree and the maps' package; pyproject.toml ships
    every file the maps' manifest lists (``*.pt``, ``*.json``)."""
    setup = _setup_module()
    on_disk = {str(p.parent.relative_to(REPO)).replace(os.sep, ".")
               for top in ("som_torch", "sim", "training") for p in (REPO / top).rglob("__init__.py")}
    assert set(setup.packages()) == on_disk | {"training.checkpoints"}
    assert setup.PACKAGE_DIR == {"training.checkpoints": "checkpoints"}
    globs = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    listed = json.loads((REPO / "checkpoints" / "manifest.json").read_text())["files"]
    assert all(any(Path(f).match(g) for g in globs["training.checkpoints"]) for f in [*listed, "manifest.json"])


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The packages and their data as the wheel installs them (setuptools' build_py)."""
    lib = tmp_path_factory.mktemp("lib")
    res = subprocess.run([sys.executable, "setup.py", "-q", "build_py", "--build-lib", str(lib)], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return lib


def test_installed_package_finds_its_maps_from_any_folder(installed):
    """Run from ``/`` with only the installed layout on the path: the default maps are the package
    data, complete by their manifest (the same files as the repository's ``checkpoints/``)."""
    ck = installed / "training" / "checkpoints"
    shipped = json.loads((REPO / "checkpoints" / "manifest.json").read_text())["files"]
    assert sorted(p.name for p in ck.iterdir()) == sorted([*shipped, "manifest.json"])
    code = ("import sys; from training.config import checkpoints_folder; import training; "
            "print(checkpoints_folder()); print(training.__file__)")
    env = {k: v for k, v in os.environ.items() if k != "TWOMASS_CHECKPOINTS"} | {"PYTHONPATH": str(installed)}
    res = subprocess.run([sys.executable, "-S", "-c", code], cwd="/", env=env, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    folder, module = res.stdout.split()
    assert Path(module).is_relative_to(installed) and Path(folder) == ck
    from som_torch import verify_manifest

    assert verify_manifest(Path(folder)) == shipped


def test_checkout_falls_back_to_its_checkpoints_folder(monkeypatch):
    """A checkout or an editable install has no ``training.checkpoints`` package: the repository's folder."""
    from training import config

    monkeypatch.delenv("TWOMASS_CHECKPOINTS", raising=False)
    assert importlib.util.find_spec("training.checkpoints") is None
    assert config.checkpoints_folder() == REPO / "checkpoints"


def test_setup_builds_the_libraries_the_kernels_look_for():
    """setup.py's extension names are the prebuilt names ``CKernel`` looks up, for every kernel,
    both float types and every variant of this machine, from the kernels' own flags."""
    from sim._csv import KERNEL as CSV_KERNEL
    from sim._kernel import KERNEL as SIM_KERNEL
    from som_torch import _prebuilt
    from som_torch._native import KERNEL as SOM_KERNEL
    from training.identification._resonance import KERNEL as RESONANCE_KERNEL

    built = {e.name.rsplit(".", 1)[1]: e for e in _setup_module().kernel_extensions()}
    for kernel in (SIM_KERNEL, CSV_KERNEL, SOM_KERNEL, RESONANCE_KERNEL):
        for variant in _prebuilt.all_variants():
            for real in ("float", "double"):
                flags = (*_prebuilt.portable_flags(kernel.flags), *_prebuilt.variant_flags(variant))
                stem = _prebuilt.library_stem(kernel.name, real, variant, kernel.source.read_text(), flags,
                                              kernel.link_flags)
                ext = built.pop(stem)
                assert "-march=native" not in ext.extra_compile_args and ext.optional
                assert ext.define_macros == [("REAL", real)]
    assert not built


def test_the_sdist_carries_the_contract_and_the_docs(tmp_path):
    """A user of the source distribution has the contract, the docs, the pins and the tests, and no
    compiled kernel of this machine."""
    res = subprocess.run([sys.executable, "setup.py", "-q", "sdist", "--dist-dir", str(tmp_path)], cwd=REPO,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    (archive,) = tmp_path.glob("*.tar.gz")
    with tarfile.open(archive) as tar:
        names = {name.split("/", 1)[1] for name in tar.getnames() if "/" in name}
    expected = {str(p.relative_to(REPO)) for p in (REPO / "docs").rglob("*") if p.is_file()}
    assert expected <= names, sorted(expected - names)
    assert {"docs/contract.md", "README.md", "CHANGELOG.md", "constraints.txt", "tests/test_contract_doc.py",
            "sim/_kernel.c", "checkpoints/manifest.json"} <= names
    assert not any(name.endswith(".so") for name in names)
