"""Checkpoints (SPEC section 6): one dict of plain tensors + JSON, safe loading, format version,
SHA-256 content hash, atomic writes; and a folder manifest of SHA-256 per file."""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import pickletools
import re
import warnings
import zipfile
from collections.abc import Iterable, Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import torch

from ._files import atomic_write
from ._grid import Grid
from ._local import LocalLinear, check_local
from ._som import SOM

FORMAT = "som_torch.checkpoint"
FORMAT_VERSION = 2
#: The versions this som_torch reads: 1 has no local linear read-out.
_READS = (1, 2)
_TENSORS = ("weights", "active", "offset", "scale")
_LOCAL = ("local_intercepts", "local_slopes", "local_lower", "local_upper")  # present where the maps have a local linear read-out


class CheckpointError(ValueError):
    """A checkpoint or manifest that cannot be trusted; the message names the file and the reason."""


def _digest(header: dict, tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    for name in sorted(tensors):
        t = tensors[name].contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def save_checkpoint(path: str | os.PathLike, som: SOM, extra_metadata: dict[str, Any] | None = None) -> str:
    """Write ``som`` and JSON-able ``extra_metadata`` atomically; return the content SHA-256."""
    metadata = dict(extra_metadata or {})
    try:
        metadata_json = json.dumps(metadata, sort_keys=True)
    except (TypeError, ValueError) as err:
        raise TypeError(f"extra_metadata: expected JSON-able values ({err})") from None
    header = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "grid": som.grid.to_dict(),
        "component_names": list(som.component_names),
        "metadata_json": metadata_json,
    }
    tensors = {"weights": som.weights.detach().cpu().contiguous(), "active": som.active.contiguous(),
               "offset": som.offset.contiguous(), "scale": som.scale.contiguous()}
    if som.local is not None:
        tensors |= {name: getattr(som.local, name.removeprefix("local_")).detach().cpu().contiguous()
                    for name in _LOCAL}
    digest = _digest(header, tensors)
    payload = {**header, "tensors": tensors, "sha256": digest}
    atomic_write(path, lambda f: torch.save(payload, f))
    return digest


def _detail(err: BaseException) -> str:
    """The first sentence of ``err``'s message that says what is wrong (at most 200 characters): the
    lines of torch's advice and documentation are left out (its advice for a refused pickle is to
    load it in a way that runs code from the file); the class name when nothing else is left."""
    advice = ("weights_only", "weights only", "torch.load", "https://")
    lines = [ln.split("Unpickler error:", 1)[-1].strip() for ln in str(err).splitlines()]
    kept = [ln.split(". ", 1)[0] for ln in lines if ln and not any(a in ln.lower() for a in advice)]
    return kept[0][:200] if kept else type(err).__name__


#: String-pushing opcodes (their argument is the string) and the memo's opcodes, for naming the
#: globals of a pickle's ``STACK_GLOBAL`` (protocol 4: module and name are the two strings before it).
_STRINGS = {"STRING", "BINSTRING", "SHORT_BINSTRING", "UNICODE", "SHORT_BINUNICODE", "BINUNICODE", "BINUNICODE8"}
_PUTS = {"PUT", "BINPUT", "LONG_BINPUT"}
_GETS = {"GET", "BINGET", "LONG_BINGET"}


def _pickle_globals(data: bytes) -> list[str]:
    """``module.name`` of each global that the pickle stream ``data`` would import, read opcode by
    opcode with :func:`pickletools.genops` (nothing is unpickled, no code runs); successive pickles
    (the legacy torch format) are read until the first byte that is not one."""
    found: list[str] = []
    stream = io.BytesIO(data)
    while stream.tell() < len(data):
        pushed: list[str | None] = []  # what the opcodes pushed, strings by value
        memo: dict[int, str | None] = {}
        try:
            for op, arg, _ in pickletools.genops(stream):
                if op.name == "GLOBAL" or op.name == "INST":
                    found.append(".".join(str(arg).split(" ", 1)))
                elif op.name == "STACK_GLOBAL":
                    module, name = ([None, None] + pushed)[-2:]
                    found.append(f"{module or '?'}.{name or '?'}")
                elif op.name == "MEMOIZE":
                    memo[len(memo)] = pushed[-1] if pushed else None
                elif op.name in _PUTS:
                    memo[int(arg)] = pushed[-1] if pushed else None
                elif op.name in _GETS:
                    pushed.append(memo.get(int(arg)))
                elif op.name in _STRINGS:
                    pushed.append(arg if isinstance(arg, str) else arg.decode("latin-1"))
                elif op.stack_after:
                    pushed.append(None)
        except Exception:  # noqa: BLE001 - the rest is no pickle (the legacy format's raw storages)
            break
    return found


def _file_globals(path: Path) -> list[str]:
    """The globals that the pickle(s) of the torch file ``path`` would import (:func:`_pickle_globals`
    of a zip archive's ``*.pkl`` members, else of the whole file); empty where it cannot be read."""
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as z:
                return [g for n in z.namelist() if n.endswith(".pkl") for g in _pickle_globals(z.read(n))]
        return _pickle_globals(path.read_bytes())
    except (OSError, zipfile.BadZipFile, RuntimeError, ValueError):
        return []


def _plain(ref: str) -> bool:
    """Whether the global ``ref`` is one a plain-tensor checkpoint names (torch's tensor rebuild,
    a storage class, the ordered dict of a tensor's hooks)."""
    module, _, name = ref.rpartition(".")
    return ((module == "torch" and name.endswith("Storage"))
            or (module == "torch._utils" and name.startswith("_rebuild_")) or ref == "collections.OrderedDict")


def _unreadable(path: Path, err: Exception) -> str:
    """One line for a file that ``torch.load(weights_only=True)`` did not load: the globals it would
    have imported beyond a plain-tensor checkpoint's, named (``GLOBAL posix.system``), else what
    torch found wrong; never advice to load the file some other way."""
    if isinstance(err, pickle.UnpicklingError):  # torch refused the pickle (or could not parse it)
        refs = list(dict.fromkeys(g for g in _file_globals(path) if not _plain(g)))
        if refs:
            shown = ", ".join(f"GLOBAL {g}" for g in refs[:4]) + (f" and {len(refs) - 4} more" if len(refs) > 4 else "")
            return (f"{path}: refused: not a plain-tensor checkpoint: its pickle names {shown}, which unpickling "
                    "would import and call; nothing from the file was run")
        if zipfile.is_zipfile(path):
            return f"{path}: refused: not a plain-tensor checkpoint ({_detail(err)}); nothing from the file was run"
    return f"{path}: corrupt or truncated checkpoint, cannot be read safely ({_detail(err)})"


#: Tensors whose values must all be finite: a NaN or inf weight would fail every recall, late.
_FINITE = ("weights", "offset", "scale") + _LOCAL


def _check_finite(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    """A :class:`CheckpointError` naming the first of :data:`_FINITE` in ``tensors`` with a NaN or inf."""
    for name in (n for n in _FINITE if n in tensors):
        t = tensors[name]
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise CheckpointError(f"{path}: {name}: {bad} of {t.numel()} values are NaN or infinite; the maps cannot "
                                  "be used")


def _som(header: dict[str, Any], tensors: dict[str, torch.Tensor]) -> SOM:
    """The maps a checked checkpoint holds, with their local linear read-out where it has one."""
    som = SOM(Grid.from_dict(header["grid"]), header["component_names"], tensors["active"], weights=tensors["weights"],
              offset=tensors["offset"], scale=tensors["scale"], dtype=tensors["weights"].dtype)
    if "local_slopes" in tensors:
        som.local = check_local(som, LocalLinear(*(tensors[name] for name in _LOCAL)))
    return som


def load_checkpoint(path: str | os.PathLike, *, expected_sha256: str | None = None) -> tuple[SOM, dict[str, Any]]:
    """Load with ``torch.load(weights_only=True)`` (no code runs); check format, version and hash.

    Returns ``(som, metadata)``. Raises :class:`CheckpointError` on a corrupt, truncated,
    tampered, foreign or wrong-version file, ``FileNotFoundError`` if absent."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        with warnings.catch_warnings():  # torch's warnings about a foreign pickle: the error says what matters
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - a refused pickle, or any zip/read failure: an unreadable file
        raise CheckpointError(_unreadable(path, err)) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        got = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{path}: not a {FORMAT} file (format {got!r})")
    version = payload.get("format_version")
    if version not in _READS:
        raise CheckpointError(f"{path}: format version {version!r} is not supported (this som_torch reads versions "
                              f"{', '.join(map(str, _READS))})")
    try:
        header = {k: payload[k] for k in ("format", "format_version", "grid", "component_names", "metadata_json")}
        tensors = {k: payload["tensors"][k] for k in _TENSORS}
        tensors |= {k: t for k, t in payload["tensors"].items() if k in _LOCAL}
        stored = str(payload["sha256"])
    except (KeyError, TypeError) as err:
        raise CheckpointError(f"{path}: incomplete checkpoint, missing entry {err}") from None
    if not all(isinstance(t, torch.Tensor) for t in tensors.values()):
        raise CheckpointError(f"{path}: incomplete checkpoint, tensors expected under {list(_TENSORS)}")
    computed = _digest(header, tensors)
    if computed != stored:
        raise CheckpointError(f"{path}: content hash mismatch (stored {stored[:12]}..., computed {computed[:12]}...): file was modified or damaged")
    if expected_sha256 is not None and expected_sha256 != stored:
        raise CheckpointError(f"{path}: content hash {stored[:12]}... differs from the expected {expected_sha256[:12]}...")
    _check_finite(path, tensors)
    try:
        som = _som(header, tensors)
        metadata = json.loads(header["metadata_json"])
    except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as err:
        raise CheckpointError(f"{path}: inconsistent checkpoint ({_detail(err)})") from None
    if not isinstance(metadata, dict):
        raise CheckpointError(f"{path}: metadata: expected a JSON object, received {type(metadata).__name__}")
    return som, metadata


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_manifest(folder: str | os.PathLike, name: str = "manifest.json", files: Sequence[str] | None = None) -> Path:
    """Write ``folder/name``: ``{"algorithm": "sha256", "files": {relative path: sha256}}`` for the
    relative paths ``files``, else for every regular file in ``folder`` (recursively, hidden files
    and the manifest itself excluded); atomic. A manifest that would list no file is refused
    (``ValueError``): it would check nothing."""
    folder = Path(folder)
    if files is None:
        files = [p.relative_to(folder).as_posix() for p in folder.rglob("*")
                 if p.is_file() and p.name != name and not any(part.startswith(".") for part in p.relative_to(folder).parts)]
    if not files:
        raise ValueError(f"{folder / name}: no file to list; a manifest that lists nothing checks nothing")
    files = {f: file_sha256(folder / f) for f in sorted(files)}
    text = json.dumps({"algorithm": "sha256", "files": files}, indent=2, sort_keys=True) + "\n"
    out = folder / name
    atomic_write(out, lambda f: f.write(text.encode()))
    return out


#: A SHA-256 as the manifest lists it: 64 lower-case hex digits.
_SHA256 = re.compile(r"[0-9a-f]{64}")


def _shown(value: Any) -> str:
    """``value`` for an error line: its repr, at most 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _read_manifest(path: str | os.PathLike) -> dict[str, str]:
    """The listing of the manifest ``path``: relative path -> SHA-256. The file must be the JSON
    object that :func:`write_manifest` writes, ``{"algorithm": "sha256", "files": {path: digest}}``,
    listing at least one file, each a relative path inside the folder with a 64-hex-digit digest.
    Raises :class:`CheckpointError` (one line naming the manifest and what is wrong)."""
    path = Path(path)
    try:
        data = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise CheckpointError(f"{path}: manifest not found") from None
    except (OSError, ValueError, RecursionError) as err:  # unreadable, not UTF-8, not JSON, nested too deep
        raise CheckpointError(f"{path}: unreadable manifest ({_detail(err)})") from None
    if not isinstance(data, dict):
        raise CheckpointError(f'{path}: expected a JSON object {{"algorithm": "sha256", "files": {{...}}}}, '
                              f"received {_shown(data)}")
    if data.get("algorithm") != "sha256":
        raise CheckpointError(f"{path}: algorithm: expected 'sha256', received {_shown(data.get('algorithm'))}")
    files = data.get("files")
    if not isinstance(files, dict):
        raise CheckpointError(f"{path}: files: expected an object of relative path -> SHA-256, received "
                              f"{_shown(files)}")
    if not files:
        raise CheckpointError(f"{path}: files: lists no file, so it checks nothing")
    for rel, digest in files.items():
        parts = PurePosixPath(rel).parts
        if not rel or rel.startswith("/") or "\\" in rel or ".." in parts:
            raise CheckpointError(f"{path}: files: {_shown(rel)}: expected a relative path inside the folder")
        if not isinstance(digest, str) or not _SHA256.fullmatch(digest):
            raise CheckpointError(f"{path}: files: {_shown(rel)}: expected a SHA-256 of 64 lower-case hex digits, "
                                  f"received {_shown(digest)}")
    return dict(files)


def verify_manifest(folder: str | os.PathLike, name: str = "manifest.json",
                    required: Iterable[str] = ()) -> dict[str, str]:
    """Check every file listed in ``folder/name`` (:func:`_read_manifest`) against its SHA-256;
    return the listing. ``required``: the relative paths the caller will read, each of which the
    manifest must list (a file left off the listing would be read unchecked).
    Raises :class:`CheckpointError` naming each unlisted, missing or changed file."""
    folder = Path(folder)
    files = _read_manifest(folder / name)
    unlisted = [rel for rel in required if rel not in files]
    if unlisted:
        raise CheckpointError(f"{folder / name}: does not list {', '.join(unlisted)}; every file that is loaded "
                              "must be listed with its SHA-256")
    problems = []
    for rel, digest in files.items():
        p = folder / rel
        if not p.is_file():
            problems.append(f"{rel}: missing")
        elif file_sha256(p) != digest:
            problems.append(f"{rel}: SHA-256 mismatch")
    if problems:
        raise CheckpointError(f"{folder / name}: " + "; ".join(problems))
    return files
