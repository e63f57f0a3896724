"""Hostile JSON in ``--params`` (simulate, commission) and in record metadata: a one-line error or
an answer, never a traceback; a bad record in an ``identify`` batch costs only its own answer."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from sim import write_record
from training.cli import main
from training.errors import UserError
from training.params_file import read_params_file

REPO = Path(__file__).resolve().parents[3]
PLANT = {"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.02}
DEEP = "[" * 200_000 + "]" * 200_000
HUGE = "9" * 400


def _with(key: str, value: str) -> str:
    """``PLANT`` as JSON text with ``key`` set to the JSON text ``value``."""
    rest = {k: v for k, v in PLANT.items() if k != key}
    return json.dumps(rest)[:-1] + f", {json.dumps(key)}: {value}}}"


def _refused(source: str, *words: str) -> str:
    with pytest.raises(UserError) as exc:
        read_params_file(source)
    msg = str(exc.value)
    assert "\n" not in msg and msg.isprintable() and all(w in msg for w in words), msg
    return msg


@pytest.mark.parametrize("text, words", [
    (_with("f_e", DEEP), ("--params: invalid JSON: objects and lists nested too deeply",)),
    (_with("f_e", HUGE), ("--params: system 0: 'f_e': expected a finite number, received an integer of 400 digits",)),
    (_with("J_sigma", "9" * 5000), ("invalid JSON (an integer of more than 4300 digits)",)),
    (_with("f_e", "true"), ("'f_e': expected a finite number, received True",)),
    (_with("f_e", "[30, 40]"), ("'f_e': expected a finite number, received [30, 40]",)),
    (_with("name", "null"), ("system 0: 'name': expected a text, received None",)),
    (_with("name", '"../x"'), ("record name '../x': expected a plain file name",)),
    (_with("name", '"a\\u0000b"'), (r"record name 'a\x00b'",)),
    (json.dumps({"J_sigma": [0.05, 0.05], "V_J": [1, 1], "f_e": [30, 1e400], "d": [0.02, 0.02]}),
     ("system 1: 'f_e': expected a finite number, received inf",)),
])
def test_hostile_params_are_one_line_errors(text, words):
    _refused(text, *words)


def test_params_file_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "p.json"
    path.write_text("\ufeff" + json.dumps({**PLANT, "name": "bom"}), encoding="utf-8")
    assert read_params_file(str(path))[1] == ["bom"]


@pytest.mark.parametrize("command", [["simulate", "--out", "o"], ["commission"]])
@pytest.mark.parametrize("value", [DEEP, HUGE])
def test_simulate_and_commission_refuse_hostile_params_in_one_line(tmp_path, capsys, command, value):
    path = tmp_path / "p.json"
    path.write_text(_with("f_e", value))
    argv = [command[0], "--params", str(path), *(["--out", str(tmp_path / "o")] if command[0] == "simulate" else [])]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--params {path}" in err, err
    assert not (tmp_path / "o").exists()


# --- the fuzz test: any JSON value in any key of --params -------------------------------------------

_JSON = st.recursive(
    st.none() | st.booleans() | st.floats(allow_nan=True, allow_infinity=True) | st.integers()
    | st.integers(min_value=10 ** 300, max_value=10 ** 400) | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=12)
_RAW = [DEEP, "[" * 40 + "1" + "]" * 40, HUGE, "-" + "9" * 5000, "NaN", "-Infinity", "1e400", '"a\\u0000b\\n"']
_KEYS = ["J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F", "J_M", "J_L", "C_F", "D_F", "name", "colour"]


def _answered_or_one_line(source: str) -> None:
    try:
        params, names = read_params_file(source)
    except UserError as err:
        assert "\n" not in str(err) and str(err).isprintable(), repr(str(err))
    else:
        assert params.J_sigma.numel() == len(names)


@settings(max_examples=120, deadline=None)
@given(key=st.sampled_from(_KEYS), value=st.one_of(_JSON.map(json.dumps), st.sampled_from(_RAW)))
@example(key="f_e", value=HUGE)
@example(key="name", value="null")
def test_any_json_value_in_any_params_key_is_answered_or_one_line(key, value):
    _answered_or_one_line(_with(key, value))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=st.one_of(_JSON.map(json.dumps), st.sampled_from(_RAW)),
       shape=st.sampled_from(["document", "in a list", "a column"]))
def test_any_json_params_document_is_answered_or_one_line(tmp_path, value, shape):
    text = {"document": value, "in a list": f"[{value}]", "a column": _with("f_e", f"[{value}]")}[shape]
    path = tmp_path / "p.json"
    path.write_text(text)
    _answered_or_one_line(str(path))


# --- a hostile record in an identify batch -------------------------------------------------------------

def test_identify_answers_the_good_records_beside_a_hostile_one(good, tmp_path):
    """``twomass identify good bad good2``: exit 1, both good records answered, one error line for the
    record whose metadata nests 200 000 levels deep (the reader's RecursionError cost the batch before)."""
    for name in ("good", "good2", "bad"):
        write_record(tmp_path / name, good)
    (tmp_path / "bad.json").write_text(json.dumps(good.meta)[:-1] + f', "notes": {DEEP}}}')
    paths = [str(tmp_path / f"{n}.csv") for n in ("good", "bad", "good2")]
    out = tmp_path / "out.jsonl"
    res = subprocess.run([sys.executable, "-m", "training.cli", "identify", *paths, "--no-refine", "--no-progress",
                          "--out", str(out)], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert [x["record"] for x in lines] == paths
    assert "error" not in lines[0] and "error" not in lines[2] and lines[0]["structure"] == lines[2]["structure"]
    assert set(lines[1]) == {"record", "error"}
    assert "bad.json: invalid JSON: objects and lists nested too deeply" in lines[1]["error"]


def test_an_unexpected_error_reading_one_record_is_its_own_failure(monkeypatch):
    from training.identification import _batch

    def reader(path):
        raise RecursionError("maximum recursion depth exceeded")

    monkeypatch.setattr(_batch, "read_record", reader)
    failure = _batch.file_outcome("x.csv")
    assert not failure.ok and failure.error == ("x.csv: unexpected RecursionError reading the record: maximum "
                                                "recursion depth exceeded")


def test_json_safe_refuses_values_nested_beyond_its_limit():
    from training._json import MAX_DEPTH, dumps

    deep: list = []
    for _ in range(5000):
        deep = [deep]
    with pytest.raises(ValueError, match=f"nested more than {MAX_DEPTH} levels"):
        dumps({"notes": deep})


@pytest.mark.parametrize("timed_out", [True, [False, True, False, False, False, False]])
def test_a_drive_saying_timed_out_as_one_flag_or_per_section_is_analysed(good, tmp_path, timed_out):
    """Metadata ``timed_out`` from a drive: one true/false for the run, or one per section."""
    import dataclasses

    from sim import read_record
    from training.identification import Analysis, analyze

    write_record(tmp_path / "run", dataclasses.replace(good, meta={**good.meta, "timed_out": timed_out}))
    record = read_record(tmp_path / "run")
    assert record.timed_out and isinstance(analyze(record), Analysis)
