"""Records in the SPEC section 3 format: ``NAME.csv`` (uniform samples) + ``NAME.json`` (metadata).

CSV: a header row ``t, speed`` and ``current`` or ``torque``; optional ``torque_ref``, ``section``
(integers 0..6); one row of numbers per line, ``,`` between them and ``.`` as decimal mark. A header
cell may carry its unit as ``name [unit]``; it must then be the SI unit of the column.

JSON metadata (one object; numbers are finite, Python or numpy numbers for in-memory records), checked
by :func:`sim._meta.check_meta` and read typed as ``Record.info`` (:class:`RecordMeta`):

* ``T_Ei`` [s] current-loop time constant, > 0 (required);
* ``K_M`` [Nm/A] torque constant, > 0 (required when only ``current`` is given);
* ``T_s`` [s] sample time, > 0 (optional; else from ``t``, with which it must agree);
* ``encoder_counts`` counts per revolution, an integer 1..2^53; ``M_star``, ``M_N``, ``M_max`` [Nm]
  test, rated and maximum torque, ``w_max`` [rad/s] the test's speed limit: each > 0, optional;
* ``current_noise_std`` [A] >= 0; ``aborted``: true/false, the drive stopped the run at a limit;
* ``M_hold`` [Nm], any sign (SPEC 1.1): the torque that held the axis at rest before the test, and
  around which its levels ran (``M_hold + level``); absent: the plain levels;
* ``timed_out``: true/false (a section of the run ended by its safety timeout) or a list of
  true/false, one per section (at most 6);
* ``units``: an object of column -> its SI unit; ``format``: ``"twomass-record/1"``;
* ``notes``: any JSON; ``truth`` (simulated records): an object of the true parameters, derived
  values and the class name.

Objects and lists nest at most :data:`sim._values.MAX_DEPTH` levels. A record file holds at most
:data:`MAX_ROWS` lines and :data:`MAX_BYTES` bytes, its metadata :data:`MAX_META_BYTES`: larger files
are refused before they are read. Every problem raises :class:`RecordError` with a one-line message
naming the file; a place in the CSV is its line number (the header is line 1, the first row line 2),
a sample of an in-memory record its index (from 0).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from som_torch import atomic_write

from sim._csv import format_numbers, parse_numbers
from sim._meta import (FORMAT, MAX_ENCODER_COUNTS, MAX_TIMED_OUT, META_KEYS, UNIFORM_TOL, UNITS,  # noqa: F401 (the face)
                       RecordError, RecordMeta, any_timed_out, check_meta, record_error)
from sim._signal import TestSignalConfig
from sim._values import loads, shown
from sim.params import DriveConfig, TwoMassParams, speed_quantum

COLUMNS: tuple[str, ...] = ("t", "speed", "current", "torque", "torque_ref", "section")
MIN_SAMPLES = 32
#: The longest test run inside SPEC 3.1's envelope has 960 801 rows (six sections each ended by the
#: default 10 s safety timeout, and the 50 ms tail, at the shortest sample time, 62.5 us); a record
#: file may hold about four times as many lines after its header (MAX_ROWS) and MAX_BYTES bytes
#: (128 per row; the toolkit writes 45 to 70 per row of its five columns), its metadata MAX_META_BYTES.
#: Larger files are refused from their size before they are read, or from their lines before
#: they are parsed.
MAX_ROWS = 4_000_000
MAX_BYTES = 512 * 2**20
MAX_META_BYTES = 2**20


@dataclass
class Record:
    """One test run. Arrays are float64 ``N`` (``section`` int64 ``N``, 1..6 and 0 for the tail);
    ``meta`` the metadata as its JSON object, ``info`` the same typed (:class:`RecordMeta`)."""

    t: np.ndarray
    speed: np.ndarray
    meta: dict[str, Any]
    current: np.ndarray | None = None
    torque: np.ndarray | None = None
    torque_ref: np.ndarray | None = None
    section: np.ndarray | None = None
    name: str = "record"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def info(self) -> RecordMeta:
        """The metadata typed (:class:`RecordMeta`) once :func:`validate` has checked it."""
        return RecordMeta.of(self.meta)

    @property
    def T_s(self) -> float:
        """Sample time [s] (metadata; :func:`validate` fills it in from ``t`` when absent)."""
        return float(self.meta["T_s"])

    @property
    def motor_torque(self) -> np.ndarray:
        """Measured motor torque [Nm] ``N``: the ``torque`` column, else ``current * K_M``."""
        if self.torque is not None:
            return np.asarray(self.torque, dtype=np.float64)
        if self.current is None:
            raise RecordError(f"{self.name}: expected a 'current' or 'torque' column, received neither")
        K_M = self.meta.get("K_M")
        if K_M is None:
            raise RecordError(f"{self.name}: metadata 'K_M' is missing (needed to turn current into torque)")
        return np.asarray(self.current, dtype=np.float64) * float(K_M)

    @property
    def encoder_counts(self) -> int | None:
        """Encoder counts per revolution (metadata), or None where the record does not say."""
        counts = self.meta.get("encoder_counts")
        return None if counts is None else int(counts)

    @property
    def q_w(self) -> float | None:
        """Speed quantum ``2 pi / (encoder_counts T_s)`` [rad/s], or None without ``encoder_counts``."""
        counts = self.encoder_counts
        return None if counts is None else speed_quantum(counts, self.T_s)

    @property
    def timed_out(self) -> bool:
        """Whether a section of the run ended by its safety timeout (metadata ``timed_out``)."""
        return any_timed_out(self.meta)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def columns(self) -> dict[str, np.ndarray]:
        return {c: getattr(self, c) for c in COLUMNS if getattr(self, c) is not None}


_err = record_error


#: ``line_of(i)``: the file line of sample ``i`` of a record being read (None: an in-memory record).
LineOf = Callable[[int], int]


def _at(line_of: LineOf | None, i: int) -> str:
    """Where sample ``i`` is: ``line N`` of the file, or ``index i`` of an in-memory record."""
    return f"index {i}" if line_of is None else f"line {line_of(i)}"


def validate(rec: Record, where: Path | str = "record", meta_where: Path | str | None = None, *,
             line_of: LineOf | None = None) -> Record:
    """Check a record (arrays, time grid, metadata); returns a copy of it (the same arrays) with
    its own ``meta`` (plain JSON values: numpy numbers as Python numbers; ``T_s`` filled in);
    ``rec`` stays as it was. Errors name ``where``, those of the metadata ``meta_where`` (default
    ``where``), and a sample by its file line (``line_of``) or else its index."""
    with np.errstate(all="ignore"):  # independent of a caller's np.seterr
        T_s_t = _validate_columns(rec, where, line_of)
        meta = check_meta(rec.meta, T_s_t=T_s_t, n=len(rec.t), has_torque=rec.torque is not None,
                          where=where if meta_where is None else meta_where)
        return dataclasses.replace(rec, meta=meta)


def as_record(record: Any, where: str | None = None) -> Record:
    """A validated copy of an in-memory record (:func:`validate`): its columns as 1-D numpy arrays
    (torch tensors and sequences converted; ``section`` int64, the others float64), its metadata
    checked and ``T_s`` filled in from ``t`` where absent. The caller's record stays as it was.
    Errors name ``where`` (default: the record's name).

    Raises:
        TypeError: ``record`` is no :class:`Record`.
        RecordError: one line, as :func:`read_record` words it.
    """
    if not isinstance(record, Record):
        raise TypeError(f"{'record' if where is None else where}: expected a sim.Record (read_record(path) reads a "
                        f"file), received {type(record).__name__}")
    where = record.name if where is None else where
    cols = {c: _column(where, c, v) for c, v in record.columns().items()}
    return validate(dataclasses.replace(record, **{c: cols.get(c) for c in COLUMNS}), where)


def _column(where: str, name: str, values: Any) -> np.ndarray:
    """Column ``name``'s ``values`` (numpy, torch, a sequence) as float64 (``section``: int64, whole
    numbers only)."""
    if hasattr(values, "detach"):  # a torch tensor, on any device, with or without grad
        values = values.detach().cpu().numpy()
    _refuse_lossy(where, name, values)
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise _err(where, f"column '{name}': expected numbers, received {type(values).__name__}") from None
    return arr if name != "section" else _section(where, arr)


def _refuse_lossy(where: Path | str, name: str, values: Any) -> None:
    """A :class:`RecordError` for a column whose conversion to float64 would lose something: a
    masked array (its mask) or complex numbers (their imaginary part)."""
    if np.ma.isMaskedArray(values):
        raise _err(where, f"column '{name}': a masked array (fill or drop its masked samples first: "
                          "the mask would be lost)")
    if np.iscomplexobj(values):
        raise _err(where, f"column '{name}': expected real numbers, received complex ones (the imaginary part "
                          "would be lost)")


def _section(where: Path | str, values: np.ndarray, line_of: LineOf | None = None) -> np.ndarray:
    """The ``section`` column's float ``values`` as int64, each a whole number 0..6."""
    bad = ~np.isin(values, np.arange(7.0))
    if bad.any():
        i = int(np.argmax(bad))
        raise _err(where, f"column 'section': expected integers 0..6, received {float(values[i])!r} at "
                          f"{_at(line_of, i)}")
    return values.astype(np.int64)


def _validate_columns(rec: Record, where: Path | str, line_of: LineOf | None) -> float:
    """Check the columns and their time grid; returns the sample time of the time column [s]."""
    cols = rec.columns()
    for c in ("t", "speed"):
        if c not in cols:
            raise _err(where, f"missing column '{c}'")
    if rec.current is None and rec.torque is None:
        raise _err(where, "missing column 'current' or 'torque' (one is required)")
    n = len(rec.t)
    for c, v in cols.items():
        if not isinstance(v, np.ndarray) or v.ndim != 1:
            raise _err(where, f"column '{c}': expected a 1-D numpy array")
        _refuse_lossy(where, c, v)
        if v.dtype.kind not in "biuf":
            raise _err(where, f"column '{c}': expected numbers, received an array of {v.dtype}")
        if len(v) != n:
            raise _err(where, f"column '{c}' has {len(v)} samples, 't' has {n}")
        bad = ~np.isfinite(v.astype(np.float64))
        if bad.any():
            raise _err(where, f"column '{c}' has NaN/inf at {_at(line_of, int(np.argmax(bad)))}")
    if n < MIN_SAMPLES:
        raise _err(where, f"too few samples: {n} (expected >= {MIN_SAMPLES})")
    dt = np.diff(rec.t)
    if (dt <= 0).any():
        i = int(np.argmax(dt <= 0))
        raise _err(where, f"time is not increasing at {_at(line_of, i + 1)} (t={float(rec.t[i + 1]):.9g} s after "
                          f"{float(rec.t[i]):.9g} s)")
    T_s_t = float((rec.t[-1] - rec.t[0]) / (n - 1))
    dev = np.abs(rec.t - (rec.t[0] + np.arange(n) * T_s_t))  # against the ideal uniform grid
    if dev.max() > UNIFORM_TOL * T_s_t:
        i = int(np.argmax(dev))
        hint = "" if dev.max() >= 0.5 * T_s_t else " (a time column printed with too few digits?)"
        raise _err(where, f"non-uniform time step near {_at(line_of, i)}: t={float(rec.t[i])!r} s is "
                          f"{float(dev[i]) / T_s_t:.3g} samples off the uniform grid (T_s={T_s_t!r} s){hint}")
    if rec.section is not None:
        _section(where, rec.section.astype(np.float64), line_of)
    return T_s_t


def _paths(path: str | os.PathLike[str]) -> tuple[Path, Path, str]:
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".csv":  # NAME.csv or NAME.CSV as given, its metadata beside it
        return p, p.with_suffix(".json"), p.stem
    if suffix == ".json":
        return p.with_suffix(".csv"), p, p.stem
    return p.with_name(p.name + ".csv"), p.with_name(p.name + ".json"), p.name


def _limit(n_bytes: int) -> str:
    return f"{n_bytes} bytes" if n_bytes < 2**20 else f"{n_bytes / 2**20:g} MiB ({n_bytes} bytes)"


def _read_text(path: Path, limit: int, what: str) -> str:
    """The UTF-8 text of ``path`` (a byte-order mark dropped: spreadsheets' "CSV UTF-8" writes one),
    refused from its size, before it is read, where it is larger than ``limit`` bytes."""
    try:
        size = path.stat().st_size
        if size > limit:
            raise _err(path, f"{size} bytes: larger than the {_limit(limit)} {what} may have")
        with open(path, "rb") as f:
            raw = f.read(limit + 1)  # a device or a file still growing: no more than the limit
    except FileNotFoundError:
        raise _err(path, "file not found") from None
    except OSError as err:
        raise _err(path, f"cannot read ({err.__class__.__name__})") from None
    if len(raw) > limit:
        raise _err(path, f"more than the {_limit(limit)} {what} may have")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        what = "a gzip file (decompress it first)" if raw[:2] == b"\x1f\x8b" else "not UTF-8 text"
        raise _err(path, f"cannot read: {what}") from None


_SEPARATOR_HINT = "export with ',' as separator and '.' as decimal mark"


def _separator_hint(line: str) -> str:
    """A hint where ``line`` looks written with another separator than ``,``: ``;`` (a decimal-comma
    export) or tabs; else ``""``."""
    if ";" in line:
        return f"the file uses ';' as separator (a decimal-comma export?); {_SEPARATOR_HINT}"
    if "\t" in line.strip() and "," not in line:
        return f"the file uses tabs as separator; {_SEPARATOR_HINT}"
    return ""


def _parse_header(header: str, where: Path) -> list[str]:
    hint = _separator_hint(header)
    if hint:
        raise _err(where, f"line 1 (the header): {hint}")
    names = []
    for cell in header.split(","):
        c = cell.strip()
        unit = None
        if c.endswith("]") and "[" in c:
            c, unit = c[: c.index("[")].strip(), c[c.index("[") + 1: -1].strip()
        if c not in UNITS:
            raise _err(where, f"unknown column {shown(c)}; expected some of {list(COLUMNS)}")
        if unit is not None and unit != UNITS[c]:
            raise _err(where, f"unknown unit {shown(unit)} for column '{c}' (expected '{UNITS[c]}')")
        if c in names:
            raise _err(where, f"duplicate column '{c}'")
        names.append(c)
    return names


#: A number as numpy and ``strtod`` read it (decimal, exponent, nan, inf).
_NUMBER = re.compile(r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:e[+-]?\d+)?|nan|inf(?:inity)?)", re.IGNORECASE | re.ASCII)


def _bad_row(rows: Iterator[tuple[int, str]], names: list[str]) -> str:
    """What is wrong with the first of ``rows`` (``(line number, text)``) that is not a number per
    column of ``names``, with its line number; a hint where a separator other than ``,`` shows."""
    for line, text in rows:
        fields = text.split("#", 1)[0].split(",")
        hint = _separator_hint(text)
        if len(fields) != len(names):
            if not hint and len(fields) > len(names) and "." not in text:
                hint = f"a decimal-comma export?; {_SEPARATOR_HINT}"
            return (f"line {line} has {len(fields)} field{'s' * (len(fields) != 1)}, the header has {len(names)}"
                    + (f" ({hint})" if hint else ""))
        for name, field in zip(names, fields):
            if not _NUMBER.fullmatch(field.strip()):
                return (f"line {line}, column '{name}': expected a number, received {shown(field.strip())}"
                        + (f" ({hint})" if hint else ""))
    return "unreadable rows"


def _lines(body: str) -> Iterator[tuple[int, str]]:
    """The rows of ``body`` (the CSV after its header line) with their file line numbers: the lines
    that hold more than blanks or a ``#`` comment."""
    for line, text in enumerate(body.split("\n"), 2):
        if text.split("#", 1)[0].strip(" \t\r"):
            yield line, text


def _line_of_row(body: bytes, row: int) -> int:
    """The file line of row ``row`` (from 0) of ``body`` (the CSV after its header line), whose rows
    are its lines that hold more than blanks (as the number parser reads them)."""
    k, start, line = -1, 0, 2
    while True:
        end = body.find(b"\n", start)
        if body[start: len(body) if end < 0 else end].strip(b" \t\r"):
            k += 1
            if k == row:
                return line
        if end < 0:
            return line
        start, line = end + 1, line + 1


def _rows(body: str, n_lines: int, names: list[str], where: Path) -> tuple[np.ndarray, LineOf]:
    """The numbers of ``body`` (the CSV after its header line, ``n_lines`` lines) as
    ``rows x len(names)`` float64 and the file line of each row. The C parser reads plain rows;
    otherwise numpy reads them (``#`` comments too) and a bad row is named by its line."""
    raw = body.encode()
    data = parse_numbers(raw, len(names))
    if data is not None:  # one row per line unless blank lines lie between them
        return data, (lambda i: i + 2) if data.shape[0] == n_lines else (lambda i: _line_of_row(raw, i))
    del raw
    rows = list(_lines(body))
    try:
        data = np.loadtxt([text for _, text in rows], delimiter=",", dtype=np.float64, ndmin=2) if rows \
            else np.zeros((0, len(names)))
    except ValueError:
        raise _err(where, _bad_row(iter(rows), names)) from None
    if data.shape[1] != len(names):
        raise _err(where, _bad_row(iter(rows), names))
    line_numbers = [line for line, _ in rows]
    return data, line_numbers.__getitem__


def read_record(path: str | os.PathLike[str], meta_defaults: Mapping[str, Any] | None = None) -> Record:
    """Read ``NAME.csv`` + ``NAME.json`` (path with or without suffix), validated. Files larger than
    :data:`MAX_BYTES` (metadata: :data:`MAX_META_BYTES`) or holding more than :data:`MAX_ROWS` lines
    are refused before they are read or parsed. ``meta_defaults``: metadata the JSON may leave out
    (e.g. a drive's own ``K_M`` and ``T_Ei``), taken where it lacks the key, before validation."""
    csv_path, json_path, name = _paths(path)
    text = _read_text(csv_path, MAX_BYTES, "a record file")
    if "\n" not in text:  # classic Mac line ends
        text = text.replace("\r", "\n")
    end = text.find("\n")
    header, body = (text, "") if end < 0 else (text[:end], text[end + 1:])
    del text
    if not header.strip():
        raise _err(csv_path, "empty file (expected a header row)" if not body.strip() else
                   "line 1 is empty (expected the header row: t, speed, current or torque, ...)")
    names = _parse_header(header, csv_path)
    n_lines = body.count("\n") + (bool(body) and not body.endswith("\n"))
    if n_lines > MAX_ROWS:
        raise _err(csv_path, f"{n_lines} lines: more than the {MAX_ROWS} rows a record may have (one test run "
                             "has at most about a million; split the file into its test runs)")
    data, line_of = _rows(body, n_lines, names, csv_path)
    del body
    cols = {c: data[:, i].copy() for i, c in enumerate(names)}
    if not json_path.exists():
        raise _err(json_path, "metadata file not found (expected beside the CSV)")
    meta_text = _read_text(json_path, MAX_META_BYTES, "record metadata")
    try:
        meta = loads(meta_text)
    except ValueError as err:
        raise _err(json_path, str(err)) from None
    if not isinstance(meta, dict):
        raise _err(json_path, f"expected a JSON object, received {shown(meta)}")
    meta = {**(meta_defaults or {}), **meta}
    section = cols.pop("section", None)
    if section is not None:
        section = _section(csv_path, section, line_of)
    rec = Record(t=cols.pop("t", None), speed=cols.pop("speed", None), meta=meta, current=cols.pop("current", None),
                 torque=cols.pop("torque", None), torque_ref=cols.pop("torque_ref", None), section=section, name=name)
    return validate(rec, csv_path, json_path, line_of=line_of)


#: Significant digits written per column (``%.Ng``; 0: an integer, ``%d``).
_DIGITS = {"t": 17, "speed": 12, "current": 7, "torque": 7, "torque_ref": 7, "section": 0}


def write_record(path: str | os.PathLike[str], record: Record, overwrite: bool = False) -> tuple[Path, Path]:
    """Write ``NAME.csv`` and ``NAME.json``; refuses to overwrite unless ``overwrite=True``."""
    csv_path, json_path, _ = _paths(path)
    record = validate(record, csv_path)  # a copy: the caller's record unchanged
    if not overwrite:
        for p in (csv_path, json_path):
            if p.exists():
                raise _err(p, "exists (pass overwrite=True to replace it)")
    cols = record.columns()
    names = list(cols)
    mat = np.column_stack([cols[c].astype(np.float64) for c in names])
    body = format_numbers(mat, [_DIGITS[c] for c in names])
    if body is None:  # no formatter: numpy writes the same text
        buf = io.StringIO()
        np.savetxt(buf, mat, fmt=[f"%.{_DIGITS[c]}g" if _DIGITS[c] else "%d" for c in names], delimiter=",")
        body = buf.getvalue()
    text = ",".join(names) + "\n" + body
    meta = dict(record.meta)
    meta.setdefault("format", FORMAT)
    meta.setdefault("units", {c: UNITS[c] for c in names})
    for p, content in ((csv_path, text), (json_path, json.dumps(meta, indent=1) + "\n")):
        atomic_write(p, lambda f, content=content: f.write(content), text=True)
    return csv_path, json_path


def responses_to_records(response: Any, params: TwoMassParams, drive: DriveConfig, signal: TestSignalConfig,
                         names: list[str] | None = None) -> list[Record]:
    """One :class:`Record` per system of a :class:`sim.plant.Response` (flattened batch order),
    trimmed to its length, with ``meta['truth']`` holding the true parameters and class, and
    ``meta['M_hold']`` where the levels ran around a holding torque that is not 0 (``response.M_hold``)."""
    n = int(response.length.numel())
    L = response.length.reshape(-1).tolist()
    flat = lambda v: v.reshape(n, -1).to(torch.float64).numpy() if v.dtype.is_floating_point else v.reshape(n, -1).numpy()  # noqa: E731
    speed, current, tref, section = (flat(v) for v in (response.speed, response.current, response.torque_ref, response.section))
    t = response.t.numpy()
    truths = params.reshape(-1).truth(drive, signal.M_star)
    tmo = response.timed_out.reshape(n, 6).tolist()
    hold = _holds(getattr(response, "M_hold", None), n)
    base = _base_meta(drive, signal)
    out = []
    for i in range(n):
        m = L[i]
        meta = dict(base)
        _add_hold(meta, hold[i])
        meta["timed_out"] = [bool(b) for b in tmo[i]]
        meta["truth"] = truths[i]
        out.append(Record(t=t[:m].copy(), speed=speed[i, :m].copy(), current=current[i, :m].copy(),
                          torque_ref=tref[i, :m].copy(), section=section[i, :m].astype(np.int64), meta=meta,
                          name=names[i] if names else f"sys{i:05d}"))
    return out


def iter_records(params: TwoMassParams, drive: DriveConfig | None = None, signal: TestSignalConfig | None = None, *,
                 seed: int = 0, group: int = 512, dtype: torch.dtype = torch.float32, substeps: int | None = None,
                 use_kernel: bool = True, around_hold: bool = True, progress: Any = None) -> Iterator[Record]:
    """Simulate the test for every system in duration-sorted groups and yield their records
    (named ``sysNNNNN`` by flattened input index; memory bounded by one group). Current noise
    per record from a generator seeded with ``seed + index``. Real axes (SPEC 1.1): each starts
    held by ``M_hold`` (``M_L0``); with ``around_hold`` the levels run around it and the record's
    metadata says ``M_hold`` (where it is not 0), else they run plain (see :func:`sim.simulate_test`)."""
    from sim._integrate_fast import default_substeps
    from sim._kernel import load_kernel
    from sim.plant import hold_levels, run_test_group, simulate_test

    drive = drive or DriveConfig()
    signal = signal or TestSignalConfig()
    flat = params.reshape(-1)
    S = default_substeps(flat, drive) if substeps is None else substeps
    lib = load_kernel() if use_kernel else None
    order = torch.argsort(signal.expected_duration(flat.J_sigma)).tolist()
    for g0 in range(0, len(order), group):
        idx = order[g0:g0 + group]
        sub = flat[torch.tensor(idx)]
        if lib is None:  # the torch twin; the noise below is drawn alike on both paths
            resp = simulate_test(sub, drive, signal, dtype=dtype, substeps=S, use_kernel=False, around_hold=around_hold)
            buf = {k: getattr(resp, k) for k in ("speed", "torque", "torque_ref", "section")}
            length, timed_out = resp.length, resp.timed_out
        else:
            buf, length, tmo = run_test_group(lib, sub, drive, signal, S, dtype, around_hold=around_hold)
            timed_out = ((tmo.unsqueeze(-1) >> torch.arange(6, dtype=torch.int32)) & 1).bool()
        hold = _holds(hold_levels(sub, around_hold), len(idx))
        truths = sub.truth(drive, signal.M_star)
        L = length.tolist()
        t_all = np.arange(int(length.max()), dtype=np.float64) * drive.T_s
        b = {k: v.numpy() for k, v in buf.items()}
        for j, i in enumerate(idx):
            m = L[j]
            meta = _base_meta(drive, signal)
            _add_hold(meta, hold[j])
            meta["timed_out"] = timed_out[j].tolist()
            meta["truth"] = truths[j]
            noise = np.random.default_rng(seed + i).standard_normal(m, dtype=np.float32)
            current = b["torque"][j, :m].astype(np.float64) / drive.K_M + drive.current_noise_std * noise.astype(np.float64)
            yield Record(t=t_all[:m].copy(), speed=b["speed"][j, :m].astype(np.float64), current=current,
                         torque_ref=b["torque_ref"][j, :m].astype(np.float64),
                         section=b["section"][j, :m].astype(np.int64), meta=meta, name=f"sys{i:05d}")
        if progress is not None:
            progress(len(idx))


def _holds(M_hold: torch.Tensor | None, n: int) -> list[float]:
    """The ``n`` holding torques [Nm] the levels ran around (flat; 0.0 each where None: plain)."""
    return [0.0] * n if M_hold is None else M_hold.reshape(-1).to(torch.float64).tolist()


def _add_hold(meta: dict[str, Any], M_hold: float) -> None:
    """Metadata ``M_hold`` [Nm] where the levels ran around a holding torque that is not 0 (SPEC 1.1)."""
    if M_hold != 0.0:
        meta["M_hold"] = M_hold


def _base_meta(drive: DriveConfig, signal: TestSignalConfig) -> dict[str, Any]:
    return {"K_M": drive.K_M, "T_Ei": drive.T_Ei, "T_s": drive.T_s, "encoder_counts": drive.encoder_counts,
            "M_star": signal.M_star, "w_max": signal.w_max, "M_max": drive.M_max, "M_N": drive.M_N,
            "current_noise_std": drive.current_noise_std}
