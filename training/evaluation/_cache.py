"""The evaluation's cache of per-system results: one JSON file per method and set, keyed by a hash
of everything the results depend on (the set, drive, test signal, the maps, and the source code of
the method's import closure); a file under a key that holds another config is refused, never mixed.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from sim import DriveConfig, TestSignalConfig
from som_torch import atomic_write
from training._json import dumps
from training.errors import UserError
from training.evaluation._sets import EvalSet

#: Bump when the per-system result format or the way a method is run changes (invalidates caches).
CACHE_VERSION = "twomass-eval-v1"

def checkpoints_digest(checkpoints: str | os.PathLike[str]) -> str:
    """SHA-256 of the maps' ``manifest.json`` (which holds each map file's SHA-256)."""
    path = Path(checkpoints) / "manifest.json"
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except FileNotFoundError:
        raise UserError(f"{path}: not found; expected a checkpoint folder with a manifest") from None


#: Top-level packages whose source enters :func:`source_digest`.
_OWN_PACKAGES = ("sim", "training", "som_torch")
#: Modules and packages a method's results depend on (their import closure within
#: :data:`_OWN_PACKAGES` is hashed; a package with all the modules of its folder).
METHOD_ROOTS: dict[str, tuple[str, ...]] = {"som": ("sim", "training.identification"),
                                             "maps": ("sim", "training.identification"),
                                             "iv4": ("sim", "training.evaluation._iv4")}


def _module_file(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, AttributeError, ValueError):  # e.g. a function imported from a module
        return None
    return Path(spec.origin) if spec is not None and spec.origin and spec.origin.endswith(".py") else None


def _imports(name: str, path: Path) -> list[str]:
    """The names module ``name`` (source ``path``) imports statically; ``from a import b`` gives
    ``a`` and ``a.b`` (``a.b`` is skipped later where it is no module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            out += [base] + [f"{base}.{a.name}" for a in node.names]
    return out


def source_digest(roots: Sequence[str]) -> str:
    """SHA-256 over the source files of ``roots`` and of everything they import from this project
    (static walk of ``import`` statements; a package with every module of its folder and its ``*.c``
    sources), so that a code change in the simulator, the analysis or a method invalidates cached
    results even when no version constant was bumped."""
    files: dict[str, Path] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in files or name.split(".")[0] not in _OWN_PACKAGES:
            continue
        path = _module_file(name)
        if path is None:
            continue
        files[name] = path
        todo += _imports(name, path)
        if path.name == "__init__.py":  # the package's modules, and its native sources (the simulator's C kernel)
            todo += [f"{name}.{m.stem}" for m in path.parent.glob("*.py") if m.name != "__init__.py"]
            files.update({f"{name}/{c.name}": c for c in path.parent.glob("*.c")})
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(name.encode() + b"\0" + files[name].read_bytes())
    return h.hexdigest()


def method_config(method: str, eval_set: EvalSet, drive: DriveConfig, signal: TestSignalConfig,
                  checkpoints: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Everything the per-system results of ``method`` on ``eval_set`` depend on (JSON-able)."""
    if method not in METHOD_ROOTS:
        raise ValueError(f"method: expected one of {tuple(METHOD_ROOTS)}, received {method!r}")
    cfg: dict[str, Any] = {"cache_version": CACHE_VERSION, "method": method, "set": eval_set.to_dict(),
                           "drive": asdict(drive), "signal": asdict(signal),
                           "source_sha256": source_digest(METHOD_ROOTS[method])}
    if method in ("som", "maps"):
        from training.identification import FEATURE_VERSION

        if checkpoints is None:
            raise ValueError(f"method_config: expected a checkpoint folder for method {method!r}, received None")
        cfg.update(feature_version=FEATURE_VERSION, checkpoints_manifest_sha256=checkpoints_digest(checkpoints))
    else:
        cfg.update(iv4="identify_iv4 defaults (speed_is_mean, friction, max_iter=10), T_Ei from the record")
    return cfg


def _cache_path(cache_dir: Path, cfg: Mapping[str, Any]) -> Path:
    key = hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()[:20]
    return cache_dir / f"{cfg['set']['name']}_{cfg['method']}_{key}.json"


def load_cached(cache_dir: Path, cfg: Mapping[str, Any], n: int) -> tuple[list[dict[str, Any]], dict[str, Any]] | None:
    """``(results, meta)``: the cached per-system results of ``cfg`` (``n`` of them) and how they
    were computed (``compute_s``, ``workers``, ``loadavg``; see :func:`save_cached`), or ``None``.

    Raises:
        UserError: the file under this key holds another config or another number of systems.
    """
    path = _cache_path(cache_dir, cfg)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: unreadable cache file ({err}); remove it") from None
    if data.get("config") != json.loads(dumps(cfg)) or len(data.get("results", [])) != n:
        raise UserError(f"{path}: cache of another config or size (expected {n} results); remove it or use another --cache")
    return list(data["results"]), dict(data.get("meta", {}))


def save_cached(cache_dir: Path, cfg: Mapping[str, Any], results: Sequence[Mapping[str, Any]],
                meta: Mapping[str, Any] | None = None) -> Path:
    """Write the results of ``cfg`` and ``meta`` (JSON-able notes, e.g. the compute time) atomically."""
    path = _cache_path(cache_dir, cfg)
    text = dumps({"config": cfg, "meta": dict(meta or {}), "results": list(results)})
    atomic_write(path, lambda f: f.write(text), text=True)
    return path
