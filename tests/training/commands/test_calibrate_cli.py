"""``twomass calibrate``: a refit from a samples file into a copy of the maps, which then load with
their calibration; an existing calibration is kept unless ``--overwrite``; calibrated for other
maps, the folder is refused."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import som_torch as st
from training.cli import main
from training.identification import CHECKPOINT_FILES, Identifier
from training.learning._confidence import save_samples

from tests.training.learning.test_confidence_fit import _samples

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture()
def maps(tmp_path) -> Path:
    folder = tmp_path / "maps"
    shutil.copytree(REPO / "checkpoints", folder)
    (folder / "confidence.json").unlink()
    st.write_manifest(folder, files=list(CHECKPOINT_FILES))  # the maps as `twomass train` leaves them
    return folder


def test_a_refit_from_samples_writes_a_calibration_the_maps_load_with(maps, tmp_path, capsys) -> None:
    samples = tmp_path / "samples.jsonl"
    save_samples(_samples(400, 0), samples)
    assert Identifier.load(maps).calibration is None  # uncalibrated maps load, without intervals
    assert main(["calibrate", "--checkpoints", str(maps), "--samples", str(samples)]) == 0
    assert "400 calibration answers" in capsys.readouterr().out
    assert Identifier.load(maps).calibration.provenance["n"] == 400
    assert main(["calibrate", "--checkpoints", str(maps), "--samples", str(samples)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["calibrate", "--checkpoints", str(maps), "--samples", str(samples), "--overwrite"]) == 0


def test_a_calibration_of_other_maps_is_refused(maps, tmp_path, capsys) -> None:
    samples = tmp_path / "samples.jsonl"
    save_samples(_samples(300, 1), samples)
    assert main(["calibrate", "--checkpoints", str(maps), "--samples", str(samples)]) == 0
    assert Identifier.load(maps).calibration is not None
    text = (maps / "confidence.json").read_text()
    (maps / "confidence.json").write_text(text.replace('"f_e.pt": "', '"f_e.pt": "0'))  # made for another f_e map
    st.write_manifest(maps, files=[*CHECKPOINT_FILES, "confidence.json"])
    with pytest.raises(ValueError, match="calibrated for other maps"):
        Identifier.load(maps)
    (maps / "confidence.json").write_text(text)  # the manifest's digest no longer matches: tampering is refused
    with pytest.raises(Exception, match="confidence.json"):
        Identifier.load(maps)
    st.write_manifest(maps, files=list(CHECKPOINT_FILES))  # as `twomass train` leaves a folder it trains into
    with pytest.raises(ValueError, match="not listed in the manifest.*twomass calibrate"):
        Identifier.load(maps)


@pytest.mark.parametrize("args, says", [(["--workers", "0"], "--workers: expected >= 1"),
                                        (["--per-drive", "-1"], "--per-drive: expected >= 0"),
                                        (["--per-drive", "0", "--envelope-drives", "0", "--reference", "0"],
                                         "at least 200 calibration answers")])
def test_bad_counts_are_refused_in_one_line(maps, capsys, args, says) -> None:
    assert main(["calibrate", "--checkpoints", str(maps), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1


def test_a_samples_file_of_something_else_is_refused_naming_it(maps, tmp_path, capsys) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"features": [1]}\n')
    assert main(["calibrate", "--checkpoints", str(maps), "--samples", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: line 1: not a calibration sample" in err and len(err.strip().splitlines()) == 1
