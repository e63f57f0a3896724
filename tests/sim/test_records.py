"""Records (SPEC 3): round trip, refusal to overwrite, and one clear error per bad-record case."""

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim import (DriveConfig, Record, RecordError, TestSignalConfig, TwoMassParams, read_record,
                 responses_to_records, simulate_test, write_record)
from sim.records import MIN_SAMPLES, validate


def _record(n: int = 100, with_section: bool = True) -> Record:
    t = np.arange(n) * 2.5e-4
    return Record(t=t, speed=np.sin(t * 50) * 10, current=np.cos(t * 30), torque_ref=np.full(n, 2.0),
                  section=(np.arange(n) * 7 // n).astype(np.int64) if with_section else None,
                  meta={"K_M": 1.0, "T_Ei": 5e-4, "T_s": 2.5e-4, "encoder_counts": 2**20, "M_star": 10.0, "w_max": 100.0})


def test_simulated_records_round_trip(tmp_path):
    drive, signal = DriveConfig(), TestSignalConfig()
    p = TwoMassParams(J_sigma=[0.01, 0.012], V_J=[1.0, 2.0], f_e=[30.0, 100.0], d=[0.02, 0.05],
                      backlash=[0.0, math.radians(0.3)], M_FC=[0.1, 0.2], mu_F=[0.001, 0.0])
    recs = responses_to_records(simulate_test(p, drive, signal), p, drive, signal)
    for rec in recs:
        write_record(tmp_path / rec.name, rec)
        back = read_record(tmp_path / f"{rec.name}.csv")
        assert np.array_equal(back.section, rec.section)
        assert np.allclose(back.t, rec.t, rtol=1e-8, atol=0)
        assert np.allclose(back.speed, rec.speed, rtol=1e-8, atol=1e-9)
        assert np.allclose(back.current, rec.current, rtol=1e-6, atol=1e-9)
        assert np.allclose(back.torque_ref, rec.torque_ref)
        assert back.meta["truth"]["structure"] in ("stiff", "elastic", "elastic_backlash", "stiff_backlash")
        truth = back.meta["truth"]
        # derived values in the truth are consistent: f_e back from C_F, J_M, J_L, D_F
        q = TwoMassParams.from_physical(J_M=truth["J_M"], J_L=truth["J_L"], C_F=truth["C_F"], D_F=truth["D_F"])
        assert float(q.f_e) == pytest.approx(truth["f_e"], rel=1e-12)
        assert back.meta["T_Ei"] == drive.T_Ei and back.meta["K_M"] == drive.K_M
        assert back.t.dtype == np.float64 and back.section.dtype == np.int64


def test_write_refuses_to_overwrite(tmp_path):
    rec = _record()
    write_record(tmp_path / "a", rec)
    with pytest.raises(RecordError, match="exists"):
        write_record(tmp_path / "a", rec)
    write_record(tmp_path / "a", rec, overwrite=True)


def _write_raw(tmp_path, csv_text: str, meta: dict | None) -> str:
    (tmp_path / "r.csv").write_text(csv_text)
    if meta is not None:
        (tmp_path / "r.json").write_text(json.dumps(meta))
    return str(tmp_path / "r.csv")


META = {"K_M": 1.0, "T_Ei": 5e-4}


def _csv(rows: int = 50, cols: str = "t,speed,current", fn=None) -> str:
    lines = [cols]
    for k in range(rows):
        vals = [k * 2.5e-4, 1.0, 0.5][: len(cols.split(","))]
        if fn:
            vals = fn(k, vals)
        lines.append(",".join(repr(v) for v in vals))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("csv_text, meta, message", [
    (_csv(cols="t,current"), META, "missing column 'speed'"),
    (_csv(cols="t,speed"), META, "missing column 'current' or 'torque'"),
    (_csv(fn=lambda k, v: [v[0], float("nan") if k == 7 else v[1], v[2]]), META, "NaN/inf at line 9"),
    (_csv(fn=lambda k, v: [v[0], float("inf") if k == 3 else v[1], v[2]]), META, "NaN/inf"),
    (_csv(fn=lambda k, v: [v[0] + (0.3e-4 if k == 10 else 0.0), v[1], v[2]]), META, "non-uniform time step"),
    (_csv(fn=lambda k, v: [(k + (k >= 20)) * 2.5e-4, v[1], v[2]]), META, "non-uniform time step"),
    (_csv(fn=lambda k, v: [(k if k != 5 else 3) * 2.5e-4, v[1], v[2]]), META, "time is not increasing"),
    (_csv(rows=MIN_SAMPLES - 1), META, "too few samples"),
    (_csv(cols="t,speed [rpm],current"), META, "unknown unit 'rpm'"),
    (_csv(cols="t,speed,current,temperature"), META, "unknown column 'temperature'"),
    (_csv(), {**META, "colour": "red"}, "unknown metadata key"),
    (_csv(), {**META, "units": {"speed": "rpm"}}, "unknown unit 'rpm'"),
    (_csv(), {"T_Ei": 5e-4}, "'K_M' is missing"),
    (_csv(), {"K_M": 1.0}, "'T_Ei'"),
    (_csv(), {**META, "T_s": 1e-3}, "disagrees"),
    (_csv(), {**META, "K_M": -1}, "'K_M'"),
    (_csv(), None, "metadata file not found"),
    ("", META, "empty file"),
    (_csv(cols="t,speed,current,section", fn=lambda k, v: v + [9]), META, "section"),
    (_csv(cols="t,speed,current,section", fn=lambda k, v: v + [1e30]), META, "'section': expected integers 0..6, received 1e+30"),
    (_csv(), {**META, "timed_out": 5}, "'timed_out': expected a list of true/false"),
    (_csv(), {**META, "timed_out": "no"}, "'timed_out'"),
    (_csv(), {**META, "current_noise_std": "low"}, "'current_noise_std'"),
    (_csv(), {**META, "current_noise_std": -1}, "'current_noise_std'"),
    (_csv(), {**META, "encoder_counts": 1e30}, "'encoder_counts': expected an integer up to 2^53"),
])
def test_bad_records_give_clear_one_line_errors(tmp_path, csv_text, meta, message):
    path = _write_raw(tmp_path, csv_text, meta)
    with pytest.raises(RecordError) as exc:
        read_record(path)
    msg = str(exc.value)
    assert message in msg and "\n" not in msg, msg
    assert "r.csv" in msg or "r.json" in msg


def test_time_printed_to_whole_microseconds_at_62_5_us_is_read():
    # 1 us rounding at T_s = 62.5 us puts samples up to 0.016 of a sample off the grid
    n, T_s = 60_000, 62.5e-6
    t = np.round(np.arange(n) * T_s, 6)
    assert np.max(np.abs(t - np.arange(n) * T_s)) / T_s > 0.0079
    rec = validate(Record(t=t, speed=np.zeros(n), current=np.zeros(n), meta=dict(META)))
    assert rec.T_s == pytest.approx(T_s, rel=1e-6)


def test_time_printed_with_too_few_digits_is_refused_with_a_hint():
    t = np.array([float(f"{x:g}") for x in np.arange(40_000) * 62.5e-6])  # 6 digits: 10 us steps above 1 s
    with pytest.raises(RecordError, match=r"samples off the uniform grid .*too few digits"):
        validate(Record(t=t, speed=np.zeros(t.size), current=np.zeros(t.size), meta=dict(META)))


def test_byte_order_mark_and_upper_case_suffix_are_read(tmp_path):
    (tmp_path / "RUN.CSV").write_text("\ufeff" + _csv(), encoding="utf-8")
    (tmp_path / "RUN.json").write_text(json.dumps(META))
    rec = read_record(tmp_path / "RUN.CSV")
    assert rec.name == "RUN" and rec.speed.size == 50


def test_gzip_file_is_named_as_such(tmp_path):
    import gzip
    (tmp_path / "z.csv").write_bytes(gzip.compress(_csv().encode()))
    (tmp_path / "z.json").write_text(json.dumps(META))
    with pytest.raises(RecordError, match="a gzip file"):
        read_record(tmp_path / "z.csv")


def test_missing_file(tmp_path):
    with pytest.raises(RecordError, match="file not found"):
        read_record(tmp_path / "nope.csv")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(MIN_SAMPLES, 300), T_s=st.floats(1e-5, 1e-2),
       speed=st.lists(st.floats(-1e4, 1e4, allow_nan=False, allow_subnormal=False), min_size=1, max_size=5), torque=st.booleans())
def test_round_trip_property(tmp_path, n, T_s, speed, torque):
    t = np.arange(n) * T_s
    sp = np.resize(np.array(speed), n)
    rec = Record(t=t, speed=sp, meta={"T_Ei": 5e-4, "K_M": 0.5},
                 **({"torque": sp * 0.1} if torque else {"current": sp * 0.2}))
    write_record(tmp_path / "p", rec, overwrite=True)
    back = read_record(tmp_path / "p")
    assert np.allclose(back.speed, rec.speed, rtol=1e-8, atol=1e-8)
    assert back.meta["T_s"] == pytest.approx(T_s, rel=1e-6)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet="tsped,curn0123456789.-e\n[]/ ", max_size=400))
def test_parser_only_raises_record_error_on_garbage(tmp_path, text):
    (tmp_path / "g.csv").write_text(text)
    (tmp_path / "g.json").write_text(json.dumps(META))
    try:
        read_record(tmp_path / "g")
    except RecordError as err:
        assert "\n" not in str(err)


_NUMBER = st.one_of(st.floats(allow_nan=False, allow_infinity=False, width=64), st.integers(-10**12, 10**12))


@settings(max_examples=80, deadline=None)
@given(rows=st.lists(st.lists(_NUMBER, min_size=3, max_size=3), max_size=30),
       fmt=st.sampled_from(["%r", "%.17g", "%.7g", "%.3e", "%d"]), end=st.sampled_from(["\n", "\r\n"]),
       pad=st.sampled_from(["", " "]), blank=st.booleans())
def test_fast_number_parser_equals_loadtxt(rows, fmt, end, pad, blank):
    """The C parser of the record reader gives numpy's numbers, bit for bit, or declines (None)."""
    import io

    from sim._csv import parse_numbers

    def field(v):
        return fmt % (int(v) if fmt == "%d" and abs(v) < 1e15 else v) if fmt != "%r" else repr(float(v))

    lines = [",".join(pad + field(v) + pad for v in row) for row in rows]
    if blank and lines:
        lines.insert(len(lines) // 2, "")
    body = end.join(lines) + (end if rows else "")
    got = parse_numbers(body.encode(), 3)
    expected = np.loadtxt(io.StringIO(body), delimiter=",", dtype=np.float64, ndmin=2) if rows else np.zeros((0, 3))
    assert got is not None
    assert got.shape == expected.reshape(-1, 3).shape
    assert np.array_equal(got, expected.reshape(-1, 3))


_DECIMAL = st.builds(lambda sign, whole, frac, exp: f"{sign}{whole}{frac}{exp}",
                     st.sampled_from(["", "-", "+"]), st.text("0123456789", max_size=21),
                     st.one_of(st.just(""), st.text("0123456789", max_size=21).map(lambda d: "." + d)),
                     st.one_of(st.just(""), st.builds(lambda e, x: f"{e}{x}", st.sampled_from(["e", "E", "e-", "e+"]),
                                                      st.integers(0, 330))))


@settings(max_examples=300, deadline=None)
@given(numbers=st.lists(_DECIMAL.filter(lambda t: any(c.isdigit() for c in t.split("e")[0].split("E")[0])),
                        min_size=3, max_size=3))
def test_fast_number_parser_rounds_decimals_as_python(numbers):
    """Plain decimals of up to 21 + 21 digits and exponents to 330, inside and outside the parser's
    exact fast path (|exponent| <= 22, mantissa <= 2^53): Python's float, bit for bit."""
    from sim._csv import parse_numbers

    got = parse_numbers((",".join(numbers) + "\n").encode(), 3)
    assert got is not None
    assert [v.hex() for v in got[0]] == [float(t).hex() for t in numbers]


def test_fast_number_parser_rounds_decimals_next_to_a_midpoint_as_python():
    """17-19 digit decimals at, just above and just below the midpoint of two neighbouring doubles
    (where rounding twice, to 64 bits and then to 53, could differ from rounding once), and the %.17g
    time column of records: Python's float, bit for bit."""
    import math
    import random
    from decimal import Decimal, localcontext

    from sim._csv import parse_numbers

    rng = random.Random(11)
    texts = ["%.17g" % (k * T_s) for T_s in (2.5e-4, 1e-3, 6.25e-5, 5.1e-4) for k in range(0, 4000, 3)]
    with localcontext() as ctx:
        ctx.prec = 60
        for _ in range(1500):
            x = rng.uniform(1.0, 10.0) * 10.0 ** rng.randint(-20, 12)
            mid = (Decimal(x) + Decimal(math.nextafter(x, math.inf))) / 2  # exact
            for digits in (17, 18, 19):
                at = Decimal(f"{mid:.{digits - 1}e}")
                step = Decimal(10) ** (at.adjusted() - digits + 1)
                texts += [f"{v:.{digits - 1}e}" for v in (at - step, at, at + step)]
    got = parse_numbers(("\n".join(texts) + "\n").encode(), 1)
    assert got is not None
    assert [v.hex() for v in got[:, 0]] == [float(t).hex() for t in texts]


@pytest.mark.parametrize("body", ["1,2\n", "1,2,3,4\n", "1,,3\n", "1,2,x\n", "# c\n1,2,3\n", "1;2;3\n", "1,2,3 4\n",
                                  "0x1p3,2,3\n", "1.5e,2,3\n"])
def test_fast_number_parser_declines_what_is_not_plain_rows(body):
    from sim._csv import parse_numbers

    assert parse_numbers(body.encode(), 3) is None


@settings(max_examples=80, deadline=None)
@given(rows=st.lists(st.tuples(st.floats(allow_nan=False, allow_infinity=False), st.floats(-1e6, 1e6),
                               st.integers(-10, 10)), max_size=25),
       digits=st.tuples(st.sampled_from([17, 12, 7, 3]), st.sampled_from([17, 7])))
def test_fast_number_formatter_writes_what_savetxt_writes(rows, digits):
    """The C formatter of the record writer gives numpy's text, byte for byte, or declines (None)."""
    import io

    from sim._csv import format_numbers

    data = np.array(rows, dtype=np.float64).reshape(-1, 3)
    buf = io.StringIO()
    np.savetxt(buf, data, fmt=[f"%.{digits[0]}g", f"%.{digits[1]}g", "%d"], delimiter=",")
    assert format_numbers(data, [digits[0], digits[1], 0]) == buf.getvalue()
