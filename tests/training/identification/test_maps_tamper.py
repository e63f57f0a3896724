"""Tampered and malformed checkpoint folders: ``Identifier.load`` and ``twomass identify
--checkpoints`` refuse each with one line naming the file and what is wrong (exit 2, no traceback);
the manifest must list every file the maps are loaded from; a hostile pickle is named, never run.

Each case copies the shipped ``checkpoints/`` into ``tmp_path`` and changes the copy; where the
change is to a file's content the manifest is rewritten, so that the content check itself is
what refuses it (as for someone who rewrites the manifest too)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

import som_torch as st
from sim import write_record
from training.cli import main
from training.config import checkpoints_folder
from training.identification import Identifier

REPO = Path(__file__).resolve().parents[3]
#: The files a checkpoint folder holds (the shipped manifest lists them; ``confidence.json``: the
#: calibration of the answers' confidence, tied to the maps).
FILES = ["V_J.pt", "backlash.pt", "confidence.json", "envelope.json", "f_e.pt", "structure.pt"]


@pytest.fixture()
def ck(tmp_path) -> Path:
    """A copy of the shipped checkpoints."""
    folder = tmp_path / "ck"
    shutil.copytree(checkpoints_folder(), folder)
    return folder


@pytest.fixture(scope="module")
def record(good, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("rec")
    write_record(folder / "good", good)
    return folder / "good.csv"


def _manifest(ck: Path) -> None:
    """Rewrite ``ck``'s manifest of ``FILES`` (those present)."""
    st.write_manifest(ck, files=[f for f in FILES if (ck / f).exists()])


def _listing(ck: Path, files: Any) -> None:
    """Write ``ck``'s manifest with ``files`` as its listing, as given."""
    (ck / "manifest.json").write_text(json.dumps({"algorithm": "sha256", "files": files}))


def _resave(ck: Path, name: str, change: Callable[[st.SOM, dict], None]) -> None:
    """Change the map ``name``'s SOM or metadata and save it as a valid checkpoint (new hash)."""
    som, meta = st.load_checkpoint(ck / f"{name}.pt")
    change(som, meta)
    st.save_checkpoint(ck / f"{name}.pt", som, meta)


def _set(*keys: str, value: Any = None, delete: bool = False) -> Callable[[st.SOM, dict], None]:
    def change(som: st.SOM, meta: dict) -> None:
        obj = meta
        for k in keys[:-1]:
            obj = obj[k]
        if delete:
            del obj[keys[-1]]
        else:
            obj[keys[-1]] = value
    return change


def _weights(value: float, every: bool = False) -> Callable[[st.SOM, dict], None]:
    def change(som: st.SOM, meta: dict) -> None:
        if every:
            som.weights.fill_(value)
        else:
            som.weights.view(-1)[7] = value
    return change


#: Map metadata that ``twomass train`` never writes: (map, change, word the error must name).
METADATA = {
    "no_map": ("f_e", _set("map", delete=True), "map"),
    "map_number": ("f_e", _set("map", value=5), "map"),
    "spec_string": ("f_e", _set("spec", value="x"), "spec"),
    "spec_null": ("structure", _set("spec", value=None), "spec"),
    "spec_features_string": ("f_e", _set("spec", "features", value="log10_f_fit"), "spec.features"),
    "spec_features_numbers": ("f_e", _set("spec", "features", value=[1, 2]), "spec.features"),
    "spec_no_targets": ("V_J", _set("spec", "targets", delete=True), "spec.targets"),
    "spec_subset_list": ("f_e", _set("spec", "subset", value=["visible"]), "spec.subset"),
    "no_distance_quantiles": ("f_e", _set("distance_quantiles", delete=True), "distance_quantiles"),
    "distance_quantiles_string": ("f_e", _set("distance_quantiles", value="x"), "distance_quantiles"),
    "no_q99": ("backlash", _set("distance_quantiles", "0.99", delete=True), "distance_quantiles.0.99"),
    "q99_string": ("f_e", _set("distance_quantiles", "0.99", value="a"), "distance_quantiles.0.99"),
    "q99_nan": ("f_e", _set("distance_quantiles", "0.99", value=math.nan), "distance_quantiles.0.99"),
    "q99_zero": ("f_e", _set("distance_quantiles", "0.99", value=0), "distance_quantiles.0.99"),
    "q99_negative": ("f_e", _set("distance_quantiles", "0.99", value=-1.0), "distance_quantiles.0.99"),
    "q99_bool": ("f_e", _set("distance_quantiles", "0.99", value=True), "distance_quantiles.0.99"),
    "q99_huge": ("f_e", _set("distance_quantiles", "0.99", value=10 ** 400), "distance_quantiles.0.99"),
    "no_train_config": ("f_e", _set("train_config", delete=True), "train_config"),
    "train_config_list": ("f_e", _set("train_config", value=[]), "train_config"),
    "interpolate_string": ("f_e", _set("train_config", "interpolate", value="4"), "train_config.interpolate"),
    "interpolate_zero": ("f_e", _set("train_config", "interpolate", value=0), "train_config.interpolate"),
    "interpolate_fraction": ("f_e", _set("train_config", "interpolate", value=2.5), "train_config.interpolate"),
    "interpolate_beyond_units": ("f_e", _set("train_config", "interpolate", value=10 ** 6), "train_config.interpolate"),
    "no_dataset": ("structure", _set("dataset", delete=True), "dataset"),
    "dataset_string": ("structure", _set("dataset", value="x"), "dataset"),
    "quality_null": ("f_e", _set("quality", value=None), "quality"),
    "weights_one_nan": ("f_e", _weights(math.nan), "weights"),
    "weights_all_nan": ("V_J", _weights(math.nan, every=True), "weights"),
    "weights_inf": ("structure", _weights(math.inf), "weights"),
}


def _tamper_map(ck: Path, case: str) -> tuple[str, str]:
    name, change, word = METADATA[case]
    _resave(ck, name, change)
    _manifest(ck)
    return f"{name}.pt", word


def _envelope(change: Callable[[dict], Any]) -> Callable[[Path], None]:
    def tamper(ck: Path) -> None:
        data = json.loads((ck / "envelope.json").read_text())
        change(data)
        (ck / "envelope.json").write_text(json.dumps(data))
    return tamper


def _env_set(part: str, key: str, value: Any = None, delete: bool = False) -> Callable[[Path], None]:
    return _envelope(lambda d: d[part].pop(key) if delete else d[part].__setitem__(key, value))


#: envelope.json changes: (change, word the error must name).
ENVELOPE = {
    "trained_T_s_strings": (_env_set("trained", "T_s", ["a", 1e-3]), "trained.T_s"),
    "trained_T_s_number": (_env_set("trained", "T_s", 5), "trained.T_s"),
    "trained_T_s_three": (_env_set("trained", "T_s", [1e-4, 1e-3, 1e-2]), "trained.T_s"),
    "trained_T_s_reversed": (_env_set("trained", "T_s", [1e-3, 1e-4]), "trained.T_s"),
    "trained_T_s_nan": (_env_set("trained", "T_s", [math.nan, 1e-3]), "trained.T_s"),
    "trained_T_s_bool": (_env_set("trained", "T_s", [True, 1e-3]), "trained.T_s"),
    "envelope_f_e_huge": (_env_set("envelope", "f_e", [5.0, 10 ** 400]), "envelope.f_e"),
    "trained_without_T_s": (_env_set("trained", "T_s", delete=True), "T_s"),
    "trained_without_current_noise": (_env_set("trained", "current_noise", delete=True), "current_noise"),
    "envelope_without_f_e": (_env_set("envelope", "f_e", delete=True), "f_e"),
    "envelope_without_d": (_env_set("envelope", "d", delete=True), "'d'"),
    "trained_null": (_envelope(lambda d: d.__setitem__("trained", None)), "trained"),
    "no_format": (_envelope(lambda d: d.pop("format")), "format"),
    "nested_deep": (lambda ck: (ck / "envelope.json").write_text("[" * 100_000 + "]" * 100_000), "unreadable"),
}


def _tamper_envelope(ck: Path, case: str) -> tuple[str, str]:
    change, word = ENVELOPE[case]
    change(ck)
    _manifest(ck)
    return "envelope.json", word


def _changed_map_unlisted(ck: Path) -> None:
    _resave(ck, "f_e", lambda som, meta: som.weights.mul_(1.5))  # a valid map with other answers
    _listing(ck, {f: st.file_sha256(ck / f) for f in FILES if f != "f_e.pt"})


def _changed_envelope_unlisted(ck: Path) -> None:
    _env_set("trained", "T_s", [1e-6, 1.0])(ck)  # every drive inside the trained range
    _listing(ck, {f: st.file_sha256(ck / f) for f in FILES if f != "envelope.json"})


def _envelope_removed(ck: Path) -> None:
    (ck / "envelope.json").unlink()
    _manifest(ck)


def _changed_listed(ck: Path) -> None:
    with open(ck / "f_e.pt", "ab") as f:
        f.write(b"\0")


#: Manifest changes: (change, words the error must name).
MANIFEST = {
    "map_unlisted_and_changed": (_changed_map_unlisted, ("manifest.json", "does not list f_e.pt")),
    "envelope_unlisted_and_changed": (_changed_envelope_unlisted, ("manifest.json", "does not list envelope.json")),
    "envelope_removed": (_envelope_removed, ("manifest.json", "does not list envelope.json")),
    "files_empty": (lambda ck: _listing(ck, {}), ("manifest.json", "files")),
    "files_list": (lambda ck: _listing(ck, []), ("manifest.json", "files")),
    "files_null": (lambda ck: _listing(ck, None), ("manifest.json", "files")),
    "files_string": (lambda ck: _listing(ck, "f_e.pt"), ("manifest.json", "files")),
    "digest_number": (lambda ck: _listing(ck, {f: 5 for f in FILES}), ("manifest.json", "SHA-256")),
    "file_changed": (_changed_listed, ("f_e.pt: SHA-256 mismatch",)),
}


def _tamper_manifest(ck: Path, case: str) -> tuple[str, ...]:
    change, words = MANIFEST[case]
    change(ck)
    return words


def _load_refused(ck: Path) -> str:
    with pytest.raises(st.CheckpointError) as err:
        Identifier.load(ck)
    text = str(err.value)
    assert "\n" not in text, text
    return text


@pytest.mark.parametrize("case", sorted(METADATA))
def test_malformed_map_metadata_is_refused_at_load(ck, case):
    file, word = _tamper_map(ck, case)
    text = _load_refused(ck)
    assert str(ck / file) in text and word in text, text


@pytest.mark.parametrize("case", sorted(ENVELOPE))
def test_a_malformed_envelope_is_refused_naming_the_file_and_key(ck, case):
    file, word = _tamper_envelope(ck, case)
    text = _load_refused(ck)
    assert str(ck / file) in text and word in text, text


@pytest.mark.parametrize("case", sorted(MANIFEST))
def test_the_manifest_must_list_every_file_the_maps_need(ck, case):
    words = _tamper_manifest(ck, case)
    text = _load_refused(ck)
    assert all(w in text for w in words), (words, text)


def test_the_shipped_manifest_lists_every_file_loaded():
    from training.identification import CHECKPOINT_FILES

    listed = json.loads((checkpoints_folder() / "manifest.json").read_text())["files"]
    assert sorted([*CHECKPOINT_FILES, "confidence.json"]) == sorted(listed) == FILES
    assert st.verify_manifest(checkpoints_folder(), required=[*CHECKPOINT_FILES, "confidence.json"]) == listed


class _Evil:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _evil_map(ck: Path, legacy: bool) -> None:
    """``f_e.pt`` replaced by a pickle that would run ``os.system`` (manifest rewritten to match)."""
    payload = {"format": "som_torch.checkpoint", "evil": _Evil(ck / "ran")}
    torch.save(payload, ck / "f_e.pt", _use_new_zipfile_serialization=not legacy)
    _manifest(ck)


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
def test_a_malicious_pickle_is_named_and_not_run(ck, legacy):
    _evil_map(ck, legacy)
    text = _load_refused(ck)
    assert str(ck / "f_e.pt") in text and f"GLOBAL {os.system.__module__}.system" in text, text
    assert "weights_only" not in text and not (ck / "ran").exists()


# --- through the CLI: exit 2, one line, no traceback -------------------------------------------
_CLI_CASES = {
    "no_map": lambda ck: _tamper_map(ck, "no_map")[0],
    "spec_string": lambda ck: _tamper_map(ck, "spec_string")[0],
    "q99_string": lambda ck: _tamper_map(ck, "q99_string")[0],
    "weights_all_nan": lambda ck: _tamper_map(ck, "weights_all_nan")[0],
    "envelope_strings": lambda ck: _tamper_envelope(ck, "trained_T_s_strings")[0],
    "envelope_without_f_e": lambda ck: _tamper_envelope(ck, "envelope_without_f_e")[0],
    "files_null": lambda ck: _tamper_manifest(ck, "files_null") and "manifest.json",
    "files_list": lambda ck: _tamper_manifest(ck, "files_list") and "manifest.json",
    "map_unlisted_and_changed": lambda ck: _tamper_manifest(ck, "map_unlisted_and_changed") and "f_e.pt",
    "evil_legacy": lambda ck: _evil_map(ck, legacy=True) or "f_e.pt",
}


@pytest.mark.parametrize("case", sorted(_CLI_CASES))
def test_identify_refuses_a_tampered_folder_in_one_line(ck, record, case, capsys):
    file = _CLI_CASES[case](ck)
    assert main(["identify", str(record), "--checkpoints", str(ck), "--no-progress"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == "" and len(lines) == 1, captured.err
    assert lines[0].startswith("twomass identify: error: ") and file in lines[0], lines[0]
    assert "weights_only" not in lines[0]


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
def test_identify_process_refuses_a_malicious_pickle_in_one_line(ck, record, legacy):
    """The whole process: nothing but the one error line on stderr (torch's warnings included)."""
    _evil_map(ck, legacy)
    res = subprocess.run([sys.executable, "-m", "training.cli", "identify", str(record), "--checkpoints", str(ck),
                          "--no-progress"], capture_output=True, text=True, timeout=120, cwd=REPO)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and res.stdout == "" and len(lines) == 1, res.stderr
    assert "GLOBAL posix.system" in lines[0] or "GLOBAL nt.system" in lines[0], lines[0]
    assert "weights_only" not in lines[0] and "Traceback" not in res.stderr and not (ck / "ran").exists()
