"""som_torch: malformed manifests, non-finite weights, wrong-typed headers and hostile pickles are
each refused with one CheckpointError line naming the file; nothing from a hostile file runs."""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import pytest
import torch

import som_torch as st
from som_torch._checkpoint import FORMAT, FORMAT_VERSION, _digest


@pytest.fixture()
def som() -> st.SOM:
    g = torch.Generator().manual_seed(0)
    som = st.SOM(st.Grid(3, 2, "rectangular"), ["f0", "f1", "param"], [True, True, False], batch_shape=(2,))
    st.initialize(som, torch.rand(2, 20, 3, generator=g), "random", 0)
    return som


def _one_line(err: pytest.ExceptionInfo, *words: str) -> str:
    text = str(err.value)
    assert isinstance(err.value, st.CheckpointError) and "\n" not in text, text
    for w in words:
        assert w in text, (w, text)
    return text


# --- manifests ------------------------------------------------------------------------------------
_DIGEST = "DIGEST"  # replaced by a.pt's true SHA-256: only the manifest's form is wrong
_MANIFESTS = {
    "files_list": {"algorithm": "sha256", "files": []},
    "files_null": {"algorithm": "sha256", "files": None},
    "files_string": {"algorithm": "sha256", "files": "a.pt"},
    "files_missing": {"algorithm": "sha256"},
    "files_empty": {"algorithm": "sha256", "files": {}},
    "digest_number": {"algorithm": "sha256", "files": {"a.pt": 5}},
    "digest_null": {"algorithm": "sha256", "files": {"a.pt": None}},
    "digest_short": {"algorithm": "sha256", "files": {"a.pt": "abc"}},
    "digest_object": {"algorithm": "sha256", "files": {"a.pt": {"sha256": _DIGEST}}},
    "algorithm_md5": {"algorithm": "md5", "files": {"a.pt": _DIGEST}},
    "top_level_list": [],
    "top_level_null": None,
    "top_level_string": "files",
}


@pytest.mark.parametrize("case", sorted(_MANIFESTS))
def test_a_malformed_manifest_is_one_line(tmp_path, som, case):
    st.save_checkpoint(tmp_path / "a.pt", som)
    text = json.dumps(_MANIFESTS[case]).replace(_DIGEST, st.file_sha256(tmp_path / "a.pt"))
    (tmp_path / "manifest.json").write_text(text)
    with pytest.raises(st.CheckpointError) as err:
        st.verify_manifest(tmp_path)
    _one_line(err, str(tmp_path / "manifest.json"))


@pytest.mark.parametrize("entry", ["../outside.pt", "sub/../../outside.pt", "ABSOLUTE"])
def test_a_manifest_entry_outside_its_folder_is_refused(tmp_path, som, entry):
    """Even where the file outside exists and its SHA-256 matches."""
    folder = tmp_path / "ck"
    folder.mkdir()
    st.save_checkpoint(tmp_path / "outside.pt", som)
    entry = entry.replace("ABSOLUTE", str(tmp_path / "outside.pt"))
    listing = {"algorithm": "sha256", "files": {entry: st.file_sha256(tmp_path / "outside.pt")}}
    (folder / "manifest.json").write_text(json.dumps(listing))
    with pytest.raises(st.CheckpointError) as err:
        st.verify_manifest(folder)
    _one_line(err, str(folder / "manifest.json"), "expected a relative path inside the folder")


@pytest.mark.parametrize("text", ["{", "[" * 100_000 + "]" * 100_000, "\xff\xfe"])
def test_an_unreadable_manifest_is_one_line(tmp_path, text):
    (tmp_path / "manifest.json").write_bytes(text.encode("latin-1"))
    with pytest.raises(st.CheckpointError) as err:
        st.verify_manifest(tmp_path)
    _one_line(err, "manifest.json: unreadable manifest")


def test_every_required_file_must_be_listed(tmp_path, som):
    st.save_checkpoint(tmp_path / "a.pt", som)
    st.save_checkpoint(tmp_path / "b.pt", som)
    st.write_manifest(tmp_path, files=["a.pt"])
    assert set(st.verify_manifest(tmp_path)) == {"a.pt"}  # nothing required: what it lists, checked
    with pytest.raises(st.CheckpointError) as err:
        st.verify_manifest(tmp_path, required=["a.pt", "b.pt"])
    assert "a.pt" not in _one_line(err, "does not list b.pt").split("does not list", 1)[1]
    st.write_manifest(tmp_path)
    assert set(st.verify_manifest(tmp_path, required=["a.pt", "b.pt"])) == {"a.pt", "b.pt"}


def test_a_manifest_of_nothing_is_not_written(tmp_path):
    with pytest.raises(ValueError, match="lists nothing"):
        st.write_manifest(tmp_path)
    assert not (tmp_path / "manifest.json").exists()


# --- checkpoint contents --------------------------------------------------------------------------
@pytest.mark.parametrize("tensor", ["weights", "offset", "scale"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_values_are_refused_at_load(tmp_path, som, tensor, value):
    """A hash-consistent checkpoint whose weights (or normalization) hold NaN or inf: refused when
    loaded, naming the tensor, not at every recall."""
    getattr(som, tensor).view(-1)[0] = value
    _save_payload(tmp_path / "m.pt", som, json.dumps({}))
    with pytest.raises(st.CheckpointError) as err:
        st.load_checkpoint(tmp_path / "m.pt")
    _one_line(err, str(tmp_path / "m.pt"), f"{tensor}: 1 of")


def _save_payload(path: Path, som: st.SOM, metadata_json: object, **header_changes: object) -> None:
    """A checkpoint with a self-consistent hash (as someone rewriting one would make it), no checks."""
    header = {"format": FORMAT, "format_version": FORMAT_VERSION, "grid": som.grid.to_dict(),
              "component_names": list(som.component_names), "metadata_json": metadata_json, **header_changes}
    tensors = {"weights": som.weights, "active": som.active, "offset": som.offset, "scale": som.scale}
    torch.save({**header, "tensors": tensors, "sha256": _digest(header, tensors)}, path)


@pytest.mark.parametrize("metadata_json, header", [
    ("[]", {}), ("5", {}), ("null", {}), ("[" * 100_000 + "]" * 100_000, {}), (5, {}), (None, {}),
    ("{}", {"grid": "x"}), ("{}", {"grid": None}),
    ("{}", {"grid": {"rows": "3", "cols": 2, "topology": "rectangular"}}),
    ("{}", {"component_names": 5}), ("{}", {"component_names": ["a"]}),
])
def test_a_wrong_typed_header_is_one_line(tmp_path, som, metadata_json, header):
    _save_payload(tmp_path / "m.pt", som, metadata_json, **header)
    with pytest.raises(st.CheckpointError) as err:
        st.load_checkpoint(tmp_path / "m.pt")
    _one_line(err, str(tmp_path / "m.pt"))


# --- hostile pickles ------------------------------------------------------------------------------
class _Evil:
    """Unpickling it would run ``os.system``: the loader must name it and never run it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _write_evil(path: Path, kind: str) -> None:
    payload = {"format": FORMAT, "tensors": {}, "evil": _Evil(path.with_suffix(".ran"))}
    if kind == "zip":
        torch.save(payload, path)
    elif kind == "legacy":
        torch.save(payload, path, _use_new_zipfile_serialization=False)
    else:  # a bare pickle (protocol 4: STACK_GLOBAL, names pushed as strings)
        path.write_bytes(pickle.dumps(payload, protocol=4))


@pytest.mark.parametrize("kind", ["zip", "legacy", "bare"])
def test_a_malicious_pickle_is_refused_by_name(tmp_path, kind, recwarn):
    path = tmp_path / "m.pt"
    _write_evil(path, kind)
    with pytest.raises(st.CheckpointError) as err:
        st.load_checkpoint(path)
    text = _one_line(err, str(path), "refused", f"GLOBAL {os.system.__module__}.system")
    assert "weights_only" not in text and "trust" not in text
    assert not path.with_suffix(".ran").exists()
    assert not [w for w in recwarn if "torch" in str(w.filename)]  # torch's protocol warning is not shown


def test_a_pickled_object_is_named_without_advice(tmp_path):
    """A whole object (not a plain-tensor state) saved by torch: its class is named."""
    import argparse

    path = tmp_path / "m.pt"
    torch.save({"format": FORMAT, "evil": argparse.Namespace(a=1)}, path)
    with pytest.raises(st.CheckpointError) as err:
        st.load_checkpoint(path)
    assert "weights_only" not in _one_line(err, "GLOBAL argparse.Namespace", "nothing from the file was run")
