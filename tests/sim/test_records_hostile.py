"""Records from hostile or careless sources: every problem is one RecordError line that names the
file and, in the CSV, the file's line number; metadata values of any JSON shape; size limits
checked before a file is read; the record metadata's types."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import sim.records as records
from sim import DriveConfig, Record, RecordError, TestSignalConfig, read_record
from sim.records import META_KEYS, as_record, validate

META = {"K_M": 1.0, "T_Ei": 5e-4}
T_S = 2.5e-4
BAD_ROW = 8  # the ninth data row: file line 10 (the header is line 1)


def _lines(n: int = 60, cols: str = "t,speed,current,section", fn=None) -> list[str]:
    """Data lines of a valid record, ``fn(k, fields)`` changing the fields of row ``k``."""
    out = []
    for k in range(n):
        fields = [repr(k * T_S), "1.0", "0.5", "1"][: len(cols.split(","))]
        out.append(",".join(fn(k, fields)) if fn else ",".join(fields))
    return out


def _write(tmp_path, lines: list[str], cols: str = "t,speed,current,section", meta_text: str | None = None,
           name: str = "r", end: str = "\n"):
    (tmp_path / f"{name}.csv").write_bytes((end.join([cols, *lines]) + end).encode())
    (tmp_path / f"{name}.json").write_text(json.dumps(META) if meta_text is None else meta_text)
    return tmp_path / f"{name}.csv"


def _error(path) -> str:
    with pytest.raises(RecordError) as exc:
        read_record(path)
    msg = str(exc.value)
    assert "\n" not in msg and msg.isprintable(), repr(msg)
    return msg


def _at_bad_row(value: str, col: int):
    return lambda k, f: [value if (k == BAD_ROW and i == col) else x for i, x in enumerate(f)]


#: Each kind of row error, its bad value at file line 10.
LINE_10 = {
    "NaN": (_at_bad_row("nan", 1), "column 'speed' has NaN/inf at line 10"),
    "not a number": (_at_bad_row("1.0x", 2), "line 10, column 'current': expected a number, received '1.0x'"),
    "non-uniform time": (_at_bad_row(repr((BAD_ROW + 0.3) * T_S), 0), "non-uniform time step near line 10"),
    "time backwards": (_at_bad_row(repr((BAD_ROW - 2) * T_S), 0), "time is not increasing at line 10"),
    "bad section": (_at_bad_row("9", 3), "column 'section': expected integers 0..6, received 9.0 at line 10"),
    "field count": (lambda k, f: f[:3] if k == BAD_ROW else f, "line 10 has 3 fields, the header has 4"),
}


@pytest.mark.parametrize("numpy_reader", [False, True], ids=["C parser", "numpy"])
@pytest.mark.parametrize("kind", list(LINE_10))
def test_every_row_error_names_the_files_line(tmp_path, monkeypatch, kind, numpy_reader):
    if numpy_reader:  # as without the C parser (no compiler)
        monkeypatch.setattr(records, "parse_numbers", lambda body, ncols: None)
    fn, message = LINE_10[kind]
    assert message in _error(_write(tmp_path, _lines(fn=fn)))
    # blank lines before it and Windows line ends: still the file's line (now 12)
    lines = _lines(fn=fn)
    lines[2:2] = ["", "  "]
    assert message.replace("line 10", "line 12") in _error(_write(tmp_path, lines, end="\r\n"))


def test_in_memory_records_name_the_sample_index():
    t = np.arange(60) * T_S
    speed = np.ones(60)
    speed[BAD_ROW] = np.nan
    with pytest.raises(RecordError, match=f"NaN/inf at index {BAD_ROW}$"):
        validate(Record(t=t, speed=speed, current=np.ones(60), meta=dict(META)))


def test_a_row_never_continues_on_the_next_line(tmp_path):
    """A row with an empty last field is not joined with the next line (``0.002,1.0,`` + ``0.5``)."""
    lines = _lines(cols="t,speed,current")
    lines[BAD_ROW] = lines[BAD_ROW].rsplit(",", 1)[0] + ","
    lines.insert(BAD_ROW + 1, "0.5")
    msg = _error(_write(tmp_path, lines, cols="t,speed,current", end="\r\n"))
    assert "line 10, column 'current': expected a number, received ''" in msg


@pytest.mark.parametrize("header, lines, message", [
    ("t;speed;current", [x.replace(",", ";") for x in _lines(cols="t,speed,current")],
     "line 1 (the header): the file uses ';' as separator (a decimal-comma export?)"),
    ("t,speed,current", [x.replace(",", ";").replace(".", ",") for x in _lines(cols="t,speed,current")],
     "line 2 has 4 fields, the header has 3 (the file uses ';' as separator"),
    ("t,speed,current", [x.replace(".", ",") for x in _lines(cols="t,speed,current")],
     "line 2 has 6 fields, the header has 3 (a decimal-comma export?"),
    ("t\tspeed\tcurrent", [x.replace(",", "\t") for x in _lines(cols="t,speed,current")],
     "the file uses tabs as separator"),
])
def test_other_separators_are_named(tmp_path, header, lines, message):
    msg = _error(_write(tmp_path, lines, cols=header))
    assert message in msg and "export with ',' as separator and '.' as decimal mark" in msg


@pytest.mark.parametrize("cols, meta_text, message", [
    ("t,spe\x00ed,current", None, r"unknown column 'spe\x00ed'"),
    ("t,speed [r\x1b[2Jpm],current", None, r"unknown unit 'r\x1b[2Jpm'"),
    ("t,speed,current", json.dumps({**META, "units": {"speed": "rpm\x00"}}), r"unknown unit 'rpm\x00'"),
    ("t,speed,current", json.dumps({**META, "co\nlour": 1}), r"unknown metadata key(s) 'co\nlour'"),
    ("t,speed,current", json.dumps({**META, "K_M": "1\x00"}), r"received '1\x00'"),
])
def test_control_characters_are_escaped_in_errors(tmp_path, cols, meta_text, message):
    msg = _error(_write(tmp_path, _lines(cols="t,speed,current"), cols=cols, meta_text=meta_text))
    assert message in msg


@pytest.mark.parametrize("key, value, message", [
    ("notes", "[" * 200_000 + "]" * 200_000, "invalid JSON: objects and lists nested too deeply"),
    ("truth", "[" * 500 + "]" * 500, "metadata 'truth'" + "[0]" * 32 + ": objects and lists nested more than 32"),
    ("K_M", "9" * 400, "metadata 'K_M': expected a finite number > 0, received an integer of 400 digits"),
    ("encoder_counts", "9" * 400, "metadata 'encoder_counts': expected a finite number > 0, received an integer"),
    ("notes", "9" * 400, "metadata 'notes': expected a number a float can hold, received an integer of 400 digits"),
    ("T_Ei", "9" * 5000, "invalid JSON (an integer of more than 4300 digits)"),
])
def test_deep_and_huge_json_values_are_one_line_errors(tmp_path, key, value, message):
    meta = {k: v for k, v in META.items() if k != key}
    msg = _error(_write(tmp_path, _lines(), meta_text=json.dumps(meta)[:-1] + f', "{key}": {value}}}'))
    assert msg.startswith(str(tmp_path / "r.json")) and message in msg, msg


def test_metadata_with_a_byte_order_mark_is_read(tmp_path):
    path = _write(tmp_path, _lines(), meta_text="\ufeff" + json.dumps(META))
    assert read_record(path).meta["K_M"] == 1.0


@pytest.mark.parametrize("value", [True, False, [True, False, False, False, False, False], []])
def test_timed_out_is_a_flag_or_a_flag_per_section(tmp_path, value):
    rec = read_record(_write(tmp_path, _lines(), meta_text=json.dumps({**META, "timed_out": value})))
    assert rec.meta["timed_out"] == value
    assert rec.timed_out is any(value if isinstance(value, list) else [value])


@pytest.mark.parametrize("value", [1, "yes", [1, 0], [True] * 7, None])
def test_timed_out_of_another_type_is_refused(tmp_path, value):
    msg = _error(_write(tmp_path, _lines(), meta_text=json.dumps({**META, "timed_out": value})))
    assert "metadata 'timed_out': expected a list of true/false per section" in msg


def _memory_record(**changes) -> Record:
    n = 64
    rec = Record(t=np.arange(n) * T_S, speed=np.sin(np.arange(n) * 0.1), current=np.ones(n), meta=dict(META))
    for k, v in changes.items():
        setattr(rec, k, v)
    return rec


def test_numpy_numbers_in_metadata_are_accepted_as_python_numbers(tmp_path):
    meta = {"K_M": np.float32(0.5), "T_Ei": np.float64(5e-4), "encoder_counts": np.int64(4096), "M_star": np.int32(2),
            "aborted": False, "notes": {"gain": np.float32(2.0), "runs": (np.int16(1), 2)}}
    rec = as_record(_memory_record(meta=meta))
    assert rec.meta["K_M"] == pytest.approx(0.5) and type(rec.meta["K_M"]) is float
    assert type(rec.meta["encoder_counts"]) is int and rec.meta["notes"] == {"gain": 2.0, "runs": [1, 2]}
    records.write_record(tmp_path / "np", rec)  # plain JSON: written and read back
    assert read_record(tmp_path / "np").meta["notes"]["gain"] == 2.0


@pytest.mark.parametrize("meta, message", [
    (None, "metadata: expected a dict (the JSON object of SPEC 3), received None"),
    ({**META, "K_M": True}, "metadata 'K_M': expected a finite number > 0, received True"),
    ({**META, "K_M": 10 ** 400}, "metadata 'K_M': expected a finite number > 0, received an integer of 401 digits"),
    ({**META, 2: 1}, "metadata: expected text keys, received 2"),
    ({**META, "notes": {1: 2}}, "metadata 'notes': expected text keys, received 1"),
    ({**META, "notes": [object()]}, "metadata 'notes'[0]: expected JSON values"),
    ({**META, "format": "twomass-record/2"}, "metadata 'format': expected 'twomass-record/1'"),
])
def test_bad_in_memory_metadata_is_a_record_error(meta, message):
    with pytest.raises(RecordError) as exc:
        as_record(_memory_record(meta=meta))
    assert message in str(exc.value)


@pytest.mark.parametrize("column, values, message", [
    ("speed", np.ma.masked_array(np.ones(64), mask=np.arange(64) == 3), "a masked array"),
    ("current", np.ones(64) + 1j, "expected real numbers, received complex ones"),
    ("speed", np.array(["x"] * 64), "expected numbers"),
])
def test_columns_that_would_lose_values_are_refused(column, values, message):
    for check in (as_record, validate):
        with pytest.raises(RecordError, match=message):
            check(_memory_record(**{column: values}))


def test_records_larger_than_the_limit_are_refused_before_they_are_read(tmp_path, monkeypatch):
    path = _write(tmp_path, _lines())
    with open(path, "r+b") as f:  # a sparse file: its size, no data on disk
        f.truncate(records.MAX_BYTES + 1)
    monkeypatch.setattr(records, "open", None, raising=False)  # opening the file would fail
    assert (f"r.csv: {records.MAX_BYTES + 1} bytes: larger than the 512 MiB ({records.MAX_BYTES} bytes) a record "
            "file may have") in _error(path)
    monkeypatch.undo()
    _write(tmp_path, _lines())
    with open(tmp_path / "r.json", "r+b") as f:
        f.truncate(records.MAX_META_BYTES + 1)
    assert f"r.json: {records.MAX_META_BYTES + 1} bytes: larger than the 1 MiB" in _error(path)


def test_records_of_more_lines_than_the_limit_are_refused_before_they_are_parsed(tmp_path, monkeypatch):
    monkeypatch.setattr(records, "MAX_ROWS", 100)
    monkeypatch.setattr(records, "parse_numbers", None)  # parsing would fail
    assert "101 lines: more than the 100 rows a record may have" in _error(_write(tmp_path, _lines(n=101)))
    monkeypatch.undo()
    monkeypatch.setattr(records, "MAX_ROWS", 100)
    assert len(read_record(_write(tmp_path, _lines(n=100)))) == 100


def test_the_row_limit_is_four_times_the_longest_test_run_of_the_envelope():
    longest = TestSignalConfig().max_samples(DriveConfig(T_s=62.5e-6))  # six 10 s timeouts and the tail
    assert longest == 960_801
    assert records.MAX_ROWS >= 4 * longest and records.MAX_BYTES >= 128 * records.MAX_ROWS


# --- the fuzz test: any JSON value in any metadata key ----------------------------------------------

_JSON = st.recursive(
    st.none() | st.booleans() | st.floats(allow_nan=True, allow_infinity=True) | st.integers()
    | st.integers(min_value=10 ** 300, max_value=10 ** 400) | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=12)
#: Values no JSON library writes from Python objects: given as text.
_RAW = ["[" * 200_000 + "]" * 200_000, "[" * 40 + "1" + "]" * 40, '{"a":' * 50 + "1" + "}" * 50, "9" * 400,
        "-" + "9" * 5000, "NaN", "-Infinity", "1e400", '"a\\u0000b\\n"', '"\\ud800"']
_KEYS = sorted(META_KEYS) + ["colour", ""]


@pytest.fixture(scope="module")
def fuzz_csv(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    return _write(folder, _lines())


def _one_line_or_record(path) -> None:
    try:
        rec = read_record(path)
    except RecordError as err:
        assert "\n" not in str(err) and str(err).isprintable(), repr(str(err))
    else:
        assert isinstance(rec, Record)
        json.dumps(rec.meta)  # what was accepted can be written back


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(key=st.sampled_from(_KEYS), value=st.one_of(_JSON.map(json.dumps), st.sampled_from(_RAW)))
@example(key="K_M", value="9" * 400)
@example(key="notes", value="[" * 200_000 + "]" * 200_000)
@example(key="timed_out", value="true")
def test_any_json_value_in_any_metadata_key_is_answered_or_one_line(fuzz_csv, key, value):
    meta = dict(META)
    meta.pop(key, None)
    fuzz_csv.with_suffix(".json").write_text(json.dumps(meta)[:-1] + f", {json.dumps(key)}: {value}}}")
    _one_line_or_record(fuzz_csv)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(value=st.one_of(_JSON.map(json.dumps), st.sampled_from(_RAW)))
def test_any_json_document_as_metadata_is_answered_or_one_line(fuzz_csv, value):
    fuzz_csv.with_suffix(".json").write_text(value)
    _one_line_or_record(fuzz_csv)
