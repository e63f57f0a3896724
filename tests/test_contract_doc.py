"""docs/contract.md runs as written: its minimal drive answers the test signal, its record is
identified, the commissioning command completes on it within the limits, its ``--resume`` answerer
carries a folder run to its report; its tables list exactly what the code holds.

Blocks and tables are found by the HTML comment ``<!-- test: NAME -->`` just before them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "contract.md"
_MARK = re.compile(r"<!-- test: ([\w-]+) -->\n")


def _marked() -> dict[str, str]:
    """NAME -> the text from its marker to the next blank line after the block or table it marks."""
    text = DOC.read_text()
    out = {}
    for m in _MARK.finditer(text):
        rest = text[m.end():]
        if rest.startswith("```"):
            end = rest.index("\n```", 3) + 4
        else:  # a table: its lines
            end = len(rest.split("\n\n", 1)[0])
        out[m.group(1)] = rest[:end]
    return out


def _code(name: str) -> str:
    block = _marked()[name]
    assert block.startswith("```"), f"{name}: expected a fenced code block after its marker"
    return block.split("\n", 1)[1].rsplit("```", 1)[0]


def _first_column(name: str) -> list[str]:
    """The first column of the marked table, backquotes removed (header and rule skipped)."""
    rows = _marked()[name].strip().splitlines()[2:]
    return [row.split("|")[1].strip().strip("`") for row in rows]


@pytest.fixture(scope="module")
def identifier():
    from training import Identifier

    return Identifier.load()


@pytest.fixture()
def drive_module(tmp_path, monkeypatch):
    """The document's drive as ``mydrive.py`` in a fresh working folder, imported."""
    (tmp_path / "mydrive.py").write_text(_code("drive"))
    monkeypatch.chdir(tmp_path)
    ns: dict = {"__name__": "mydrive"}
    exec(compile(_code("drive"), str(tmp_path / "mydrive.py"), "exec"), ns)  # noqa: S102 - our own document
    return ns


def test_no_reference_outside_the_repository():
    text = DOC.read_text()
    assert "../shared" not in text and "SPEC" not in text


def test_meta_keys_table_is_the_code():
    from sim.records import META_KEYS

    assert sorted(_first_column("meta-keys")) == sorted(META_KEYS)


def test_meta_example_validates():
    import numpy as np

    import sim
    from sim.records import validate

    meta = json.loads(_code("meta-example"))
    n = 64
    rec = sim.Record(t=np.arange(n) * meta["T_s"], speed=np.zeros(n), current=np.zeros(n), meta=meta)
    assert validate(rec).meta["T_s"] == meta["T_s"]
    for tmo in (True, [True, False]):  # one boolean, or a list per section
        validate(dataclasses.replace(rec, meta={**meta, "timed_out": tmo}))


def test_answer_tables_are_the_code():
    from training.identification import WARNING_CODES
    from training.identification._result import PARAMETER_NAMES, Quality

    assert _first_column("parameters") == list(PARAMETER_NAMES)
    assert _first_column("quality") == [f.name for f in dataclasses.fields(Quality)]
    assert sorted(_first_column("warning-codes")) == sorted(WARNING_CODES)


@pytest.mark.parametrize("notch", [None, (30.0, 0.02, 0.7), (900.0, 0.05, 0.5)])
@pytest.mark.parametrize("T_f", [0.0, 2.5e-4])
def test_law_block_is_the_reference_law(notch, T_f):
    import numpy as np

    from training.commissioning import NotchSpec, PISpeedLaw

    ns: dict = {}
    exec(compile(_code("law"), "contract.md:law", "exec"), ns)  # noqa: S102
    ref = PISpeedLaw(3.4, 0.044, T_s=2.5e-4, M_max=5.0, T_f=T_f, notch=None if notch is None else NotchSpec(*notch))
    ported = ns["SpeedLaw"](ref.params)
    rng = np.random.default_rng(1)
    w_ref = np.repeat(rng.uniform(-3, 3, 20), 100)  # steps large enough to saturate and wind up
    for run in range(2):  # and again after reset()
        ref.reset()
        ported.reset()
        w = 0.0
        for k in range(len(w_ref)):
            a, b = ref.step(w, w_ref[k]), ported.step(w, w_ref[k])
            assert a == pytest.approx(b, rel=1e-12, abs=1e-12), (run, k)
            w += 0.05 * a + 0.01 * rng.standard_normal()  # a crude plant, so that the loop moves
    if notch is not None:
        b, a = NotchSpec(*notch).coefficients(2.5e-4)
        (b0, b1, b2), (a1, a2) = ns["notch_coefficients"](*notch, 2.5e-4)
        assert np.allclose([b0, b1, b2, 1.0, a1, a2], [*b, *a], rtol=1e-13)


def test_drive_test_run_is_identified(drive_module, identifier):
    import sim

    ns = drive_module
    exec(compile(_code("identify"), "contract.md:identify", "exec"), ns)  # noqa: S102
    rec, result = ns["record"], ns["result"]
    assert rec.meta["aborted"] is False and not any(rec.meta["timed_out"])
    assert set(rec.section.tolist()) == set(range(7))  # the six sections and the tail
    assert result.ok, result.error
    assert result.structure == "elastic" and abs(result.parameters.f_e - 30.0) < 3.0
    assert identifier.identify(sim.read_record("toy_run")).ok


def test_drive_stops_at_a_limit(drive_module):
    import sim

    rec = drive_module["make"]().run_test(10.0, 20.0, sim.DriveLimits(w_max=10.0, travel=10.0, M_max=20.0))
    assert rec.meta["aborted"] is True
    stop = int((abs(rec.speed) > 10.0).argmax())
    assert (rec.torque_ref[stop + 1:] == 0).all()


def test_commission_command(drive_module, tmp_path):
    cmd = _code("commission").strip()
    assert cmd.startswith("twomass commission --drive mydrive.py:make")
    argv = [sys.executable, "-m", "training.cli", *shlex.split(cmd)[1:], "--no-progress"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode in (0, 3), out.stderr  # delivered, or a stated refusal
    report = json.loads((tmp_path / "report.json").read_text())["reports"][0]
    assert report["breach"] is None
    assert report["checks"]["within_limits"], report["checks"]
    for run in report["checks"]["runs"]:
        assert run["peak_speed"] <= 20 and run["travel"] <= 5 and run["peak_torque_ref"] <= 20
    assert report["delivered"] is not None or report["permission"]["reason"]


def test_resume_answerer_carries_a_folder_to_its_report(drive_module, identifier, tmp_path):
    import sim
    from training.commissioning import CommissioningConfig, ExperimentPending, FileDrive, commission

    ns = drive_module
    exec(compile(_code("resume"), "contract.md:resume", "exec"), ns)  # noqa: S102
    rig = tmp_path / "rig"
    rig.mkdir()
    config = vars(ns["make"]().config)
    (rig / "drive.json").write_text(json.dumps({"config": config, "limits": {"w_max": 20, "travel": 5}}))
    drive = ns["make"]()
    for _ in range(30):
        try:
            report = commission(FileDrive(rig), sim.DriveLimits(w_max=20, travel=5), identifier=identifier,
                                config=CommissioningConfig(tune=False, drive_timeout=None))
            break
        except ExperimentPending:
            ns["answer"](rig, drive)
    else:
        pytest.fail("the folder run did not end in 30 rounds")
    assert report.breach is None and report.checks["within_limits"]
    assert report.identification.ok
