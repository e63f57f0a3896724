"""Checkpoints (SPEC section 6): one dict of plain tensors + JSON, safe loading, format version,
SHA-256 content hash, atomic writes; and a folder manifest of SHA-256 per file."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import zipfile
from pathlib import Path
from collections.abc import Sequence
from typing import Any

import torch

from ._files import atomic_write
from ._grid import Grid
from ._som import SOM

FORMAT = "som_torch.checkpoint"
FORMAT_VERSION = 1
_TENSORS = ("weights", "active", "offset", "scale")


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
    digest = _digest(header, tensors)
    payload = {**header, "tensors": tensors, "sha256": digest}
    atomic_write(path, lambda f: torch.save(payload, f))
    return digest


def _first_line(err: BaseException) -> str:
    """The first line of ``err``'s message (at most 200 characters; its class name when empty)."""
    lines = str(err).strip().splitlines()
    return lines[0][:200] if lines else type(err).__name__


def _refusal(path: Path, torch_message: str) -> str:
    """One line for a file that ``torch.load(weights_only=True)`` refused: what it holds, and why it
    is not loaded anyway (torch's own advice would run code from the file)."""
    detail = next((ln.split("error:", 1)[1].strip() for ln in torch_message.splitlines() if "Unpickler error:" in ln),
                  torch_message.strip().splitlines()[0] if torch_message.strip() else "unreadable pickle")
    detail = detail.split(". ", 1)[0].rstrip(".")
    return (f"{path}: refused: not a plain-tensor checkpoint ({detail[:200]}); loading it with "
            "torch.load(weights_only=False) would execute code from the file, so do that only for a file from a "
            "source you trust")


def load_checkpoint(path: str | os.PathLike, *, expected_sha256: str | None = None) -> tuple[SOM, dict[str, Any]]:
    """Load with ``torch.load(weights_only=True)`` (no code runs); check format, version and hash.

    Returns ``(som, metadata)``. Raises :class:`CheckpointError` on a corrupt, truncated,
    tampered, foreign or wrong-version file, ``FileNotFoundError`` if absent."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        if zipfile.is_zipfile(path):  # a whole torch.save file holding objects beyond plain tensors
            raise CheckpointError(_refusal(path, str(err))) from None
        raise CheckpointError(f"{path}: corrupt or truncated checkpoint, cannot be read safely ({_first_line(err)})") from None
    except Exception as err:  # noqa: BLE001 - any zip/read failure means an unreadable file
        raise CheckpointError(f"{path}: corrupt or truncated checkpoint, cannot be read safely ({_first_line(err)})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        got = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"{path}: not a {FORMAT} file (format {got!r})")
    version = payload.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {version!r} is not supported (this som_torch reads version {FORMAT_VERSION})")
    try:
        header = {k: payload[k] for k in ("format", "format_version", "grid", "component_names", "metadata_json")}
        tensors = {k: payload["tensors"][k] for k in _TENSORS}
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
    try:
        som = SOM(Grid.from_dict(header["grid"]), header["component_names"], tensors["active"],
                  weights=tensors["weights"], offset=tensors["offset"], scale=tensors["scale"],
                  dtype=tensors["weights"].dtype)
        metadata = json.loads(header["metadata_json"])
    except (ValueError, TypeError, KeyError) as err:
        raise CheckpointError(f"{path}: inconsistent checkpoint ({err})") from None
    return som, metadata


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_manifest(folder: str | os.PathLike, name: str = "manifest.json", files: Sequence[str] | None = None) -> Path:
    """Write ``folder/name``: ``{"files": {relative path: sha256}}`` for the relative paths ``files``,
    else for every regular file in ``folder`` (recursively, hidden files and the manifest itself
    excluded); atomic."""
    folder = Path(folder)
    if files is None:
        files = [p.relative_to(folder).as_posix() for p in folder.rglob("*")
                 if p.is_file() and p.name != name and not any(part.startswith(".") for part in p.relative_to(folder).parts)]
    files = {f: file_sha256(folder / f) for f in sorted(files)}
    text = json.dumps({"algorithm": "sha256", "files": files}, indent=2, sort_keys=True) + "\n"
    out = folder / name
    atomic_write(out, lambda f: f.write(text.encode()))
    return out


def verify_manifest(folder: str | os.PathLike, name: str = "manifest.json") -> dict[str, str]:
    """Check every file listed in ``folder/name`` against its SHA-256; return the listing.
    Raises :class:`CheckpointError` naming each missing or changed file."""
    folder = Path(folder)
    try:
        files = json.loads((folder / name).read_text())["files"]
    except FileNotFoundError:
        raise CheckpointError(f"{folder / name}: manifest not found") from None
    except (ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"{folder / name}: unreadable manifest ({err})") from None
    problems = []
    for rel, digest in files.items():
        p = folder / rel
        if not p.is_file():
            problems.append(f"{rel}: missing")
        elif file_sha256(p) != digest:
            problems.append(f"{rel}: SHA-256 mismatch")
    if problems:
        raise CheckpointError(f"{folder / name}: " + "; ".join(problems))
    return dict(files)
