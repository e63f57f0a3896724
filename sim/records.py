"""Records in the SPEC section 3 format: ``NAME.csv`` (uniform samples) + ``NAME.json`` (metadata).

CSV header: ``t, speed`` and ``current`` or ``torque``; optional ``torque_ref``, ``section``.
A header cell may carry its unit as ``name [unit]``; it must then be the SI unit of the column.
JSON keys: ``K_M`` (required when only ``current`` is given), ``T_Ei`` (required), optional
``T_s`` (else from ``t``; must agree with it), ``encoder_counts``, ``M_star``, ``w_max``,
``M_max``, ``M_N``, ``current_noise_std``, ``timed_out``, ``aborted``, ``units``, ``format``, ``notes``,
``truth`` (simulated records: the true parameters, derived values and the class name).
Every problem raises :class:`RecordError` with a one-line message naming the file.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from som_torch import atomic_write

from sim._csv import format_numbers, parse_numbers
from sim.params import DriveConfig, TwoMassParams, speed_quantum
from sim._signal import TestSignalConfig

FORMAT = "twomass-record/1"
UNITS: dict[str, str] = {"t": "s", "speed": "rad/s", "current": "A", "torque": "Nm", "torque_ref": "Nm", "section": "1"}
COLUMNS: tuple[str, ...] = ("t", "speed", "current", "torque", "torque_ref", "section")
META_KEYS: frozenset[str] = frozenset({"K_M", "T_Ei", "T_s", "encoder_counts", "M_star", "w_max", "M_max", "M_N",
                                       "current_noise_std", "timed_out", "aborted", "units", "format", "notes", "truth"})
_POSITIVE_META = ("K_M", "T_Ei", "T_s", "encoder_counts", "M_star", "w_max", "M_max", "M_N")
MIN_SAMPLES = 32
#: Largest deviation from the uniform time grid [samples]: a missing or repeated row is a whole
#: sample off; a time column printed to 1 us at 62.5 us is up to 0.016 off.
UNIFORM_TOL = 0.05
MAX_ENCODER_COUNTS = 2 ** 53  # counts per revolution a float64 angle still resolves


class RecordError(ValueError):
    """A record that cannot be read or written; the message is one line naming the file."""


@dataclass
class Record:
    """One test run. Arrays are float64 ``N`` (``section`` int64 ``N``, 1..6 and 0 for the tail)."""

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

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def columns(self) -> dict[str, np.ndarray]:
        return {c: getattr(self, c) for c in COLUMNS if getattr(self, c) is not None}


def _err(where: Path | str, msg: str) -> RecordError:
    return RecordError(f"{where}: {msg}")


def validate(rec: Record, where: Path | str = "record", meta_where: Path | str | None = None) -> Record:
    """Check a record (arrays, time grid, metadata); returns a copy of it (the same arrays) with
    its own ``meta``, ``meta['T_s']`` filled in; ``rec`` stays as it was. Errors name ``where``,
    those of the metadata ``meta_where`` (default ``where``)."""
    with np.errstate(all="ignore"):  # independent of a caller's np.seterr
        T_s_t = _validate_columns(rec, where)
        return dataclasses.replace(rec, meta=_validated_meta(rec, T_s_t, where if meta_where is None else meta_where))


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
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise _err(where, f"column '{name}': expected numbers, received {type(values).__name__}") from None
    return arr if name != "section" else _section(where, arr)


def _section(where: Path | str, values: np.ndarray) -> np.ndarray:
    """The ``section`` column's float ``values`` as int64, each a whole number 0..6."""
    bad = ~np.isin(values, np.arange(7.0))
    if bad.any():
        raise _err(where, f"column 'section': expected integers 0..6, received {float(values[np.argmax(bad)])!r} at row "
                          f"{int(np.argmax(bad)) + 2}")
    return values.astype(np.int64)


def _validate_columns(rec: Record, where: Path | str) -> float:
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
        if len(v) != n:
            raise _err(where, f"column '{c}' has {len(v)} samples, 't' has {n}")
        bad = ~np.isfinite(v.astype(np.float64))
        if bad.any():
            raise _err(where, f"column '{c}' has NaN/inf at row {int(np.argmax(bad)) + 1}")
    if n < MIN_SAMPLES:
        raise _err(where, f"too few samples: {n} (expected >= {MIN_SAMPLES})")
    dt = np.diff(rec.t)
    if (dt <= 0).any():
        i = int(np.argmax(dt <= 0))
        raise _err(where, f"time is not increasing at row {i + 2} (t={float(rec.t[i + 1]):.9g} s after {float(rec.t[i]):.9g} s)")
    T_s_t = float((rec.t[-1] - rec.t[0]) / (n - 1))
    dev = np.abs(rec.t - (rec.t[0] + np.arange(n) * T_s_t))  # against the ideal uniform grid
    if dev.max() > UNIFORM_TOL * T_s_t:
        i = int(np.argmax(dev))
        hint = "" if dev.max() >= 0.5 * T_s_t else " (a time column printed with too few digits?)"
        raise _err(where, f"non-uniform time step near row {i + 2}: t={float(rec.t[i])!r} s is "
                          f"{float(dev[i]) / T_s_t:.3g} samples off the uniform grid (T_s={T_s_t!r} s){hint}")
    if rec.section is not None:
        s = rec.section
        if not np.all(np.isin(s, np.arange(0, 7))):
            raise _err(where, f"column 'section': expected integers 0..6, received {sorted(set(np.unique(s).tolist()) - set(range(7)))[:5]}")
    return T_s_t


def _validated_meta(rec: Record, T_s_t: float, where: Path | str) -> dict[str, Any]:
    """The checked metadata of ``rec`` (``T_s`` filled in from the time column's ``T_s_t``)."""
    n = len(rec.t)
    meta = dict(rec.meta)
    unknown = sorted(set(meta) - META_KEYS)
    if unknown:
        raise _err(where, f"unknown metadata key(s) {unknown}; expected some of {sorted(META_KEYS)}")
    for k in _POSITIVE_META:
        if k in meta:
            v = meta[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise _err(where, f"metadata '{k}': expected a finite number > 0, received {v!r}")
    counts = meta.get("encoder_counts")
    if counts is not None and (counts > MAX_ENCODER_COUNTS or int(counts) != counts):
        raise _err(where, f"metadata 'encoder_counts': expected an integer up to 2^53, received {counts!r}")
    if "aborted" in meta and not isinstance(meta["aborted"], bool):
        raise _err(where, f"metadata 'aborted': expected true or false, received {meta['aborted']!r}")
    tmo = meta.get("timed_out", [])
    if not isinstance(tmo, list) or not all(isinstance(x, bool) for x in tmo):
        raise _err(where, f"metadata 'timed_out': expected a list of true/false per section, received {tmo!r}")
    noise = meta.get("current_noise_std", 0.0)
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not math.isfinite(noise) or noise < 0:
        raise _err(where, f"metadata 'current_noise_std': expected a finite number >= 0, received {noise!r}")
    if "T_Ei" not in meta:
        raise _err(where, "metadata 'T_Ei' (current-loop time constant) is missing")
    if rec.torque is None and "K_M" not in meta:
        raise _err(where, "metadata 'K_M' is missing (needed when only 'current' is given)")
    if "T_s" in meta:
        if abs(meta["T_s"] - T_s_t) > 1e-6 * T_s_t + UNIFORM_TOL * T_s_t / n:
            raise _err(where, f"metadata T_s={meta['T_s']!r} disagrees with the time column ({T_s_t!r} s)")
    else:
        meta["T_s"] = T_s_t
    units = meta.get("units", {})
    if not isinstance(units, dict):
        raise _err(where, f"metadata 'units': expected an object, received {type(units).__name__}")
    for c, u in units.items():
        if c not in UNITS:
            raise _err(where, f"metadata 'units': unknown column '{c}'")
        if u != UNITS[c]:
            raise _err(where, f"unknown unit '{u}' for column '{c}' (expected '{UNITS[c]}')")
    if "truth" in meta and not isinstance(meta["truth"], dict):
        raise _err(where, "metadata 'truth': expected an object")
    return meta


def _paths(path: str | os.PathLike[str]) -> tuple[Path, Path, str]:
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".csv":  # NAME.csv or NAME.CSV as given, its metadata beside it
        return p, p.with_suffix(".json"), p.stem
    if suffix == ".json":
        return p.with_suffix(".csv"), p, p.stem
    return p.with_name(p.name + ".csv"), p.with_name(p.name + ".json"), p.name


def _parse_header(cells: list[str], where: Path) -> list[str]:
    names = []
    for cell in cells:
        c = cell.strip()
        unit = None
        if c.endswith("]") and "[" in c:
            c, unit = c[: c.index("[")].strip(), c[c.index("[") + 1: -1].strip()
        if c not in UNITS:
            raise _err(where, f"unknown column '{c}'; expected some of {list(COLUMNS)}")
        if unit is not None and unit != UNITS[c]:
            raise _err(where, f"unknown unit '{unit}' for column '{c}' (expected '{UNITS[c]}')")
        if c in names:
            raise _err(where, f"duplicate column '{c}'")
        names.append(c)
    return names


def read_record(path: str | os.PathLike[str]) -> Record:
    """Read ``NAME.csv`` + ``NAME.json`` (path with or without suffix), validated."""
    csv_path, json_path, name = _paths(path)
    try:
        text = csv_path.read_text(encoding="utf-8-sig")  # a byte-order mark (spreadsheets' "CSV UTF-8") is no column
    except FileNotFoundError:
        raise _err(csv_path, "file not found") from None
    except OSError as err:
        raise _err(csv_path, f"cannot read ({err.__class__.__name__})") from None
    except UnicodeDecodeError:
        with open(csv_path, "rb") as f:
            what = "a gzip file (decompress it first)" if f.read(2) == b"\x1f\x8b" else "not UTF-8 text"
        raise _err(csv_path, f"cannot read: {what}") from None
    # the header row: the first of text.splitlines(), without splitting the whole file
    header = text[: text.find("\n")] if "\n" in text else text
    header = header.splitlines()[0] if header else header
    if not header.strip():
        raise _err(csv_path, "empty file (expected a header row)")
    names = _parse_header(header.split(","), csv_path)
    data = parse_numbers(text[len(header):].lstrip("\r\n").encode(), len(names))
    if data is None:  # no parser, or rows that are not plain numbers: numpy reads them and words the error
        rows = [ln for ln in text.splitlines()[1:] if ln.strip()]
        try:
            data = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", dtype=np.float64, ndmin=2) if rows \
                else np.zeros((0, len(names)))
        except ValueError as err:
            raise _err(csv_path, f"unreadable data ({str(err).splitlines()[0]})") from None
    if data.shape[1] != len(names):
        raise _err(csv_path, f"rows have {data.shape[1]} fields, header has {len(names)}")
    cols = {c: data[:, i].copy() for i, c in enumerate(names)}
    if not json_path.exists():
        raise _err(json_path, "metadata file not found (expected beside the CSV)")
    try:
        meta = json.loads(json_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _err(json_path, f"invalid JSON ({str(err).splitlines()[0]})") from None
    if not isinstance(meta, dict):
        raise _err(json_path, "expected a JSON object")
    section = cols.pop("section", None)
    if section is not None:
        section = _section(csv_path, section)
    rec = Record(t=cols.pop("t", None), speed=cols.pop("speed", None), meta=meta, current=cols.pop("current", None),
                 torque=cols.pop("torque", None), torque_ref=cols.pop("torque_ref", None), section=section, name=name)
    return validate(rec, csv_path, json_path)


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
    trimmed to its length, with ``meta['truth']`` holding the true parameters and class."""
    n = int(response.length.numel())
    L = response.length.reshape(-1).tolist()
    flat = lambda v: v.reshape(n, -1).to(torch.float64).numpy() if v.dtype.is_floating_point else v.reshape(n, -1).numpy()  # noqa: E731
    speed, current, tref, section = (flat(v) for v in (response.speed, response.current, response.torque_ref, response.section))
    t = response.t.numpy()
    truths = params.reshape(-1).truth(drive, signal.M_star)
    tmo = response.timed_out.reshape(n, 6).tolist()
    base = _base_meta(drive, signal)
    out = []
    for i in range(n):
        m = L[i]
        meta = dict(base)
        meta["timed_out"] = [bool(b) for b in tmo[i]]
        meta["truth"] = truths[i]
        out.append(Record(t=t[:m].copy(), speed=speed[i, :m].copy(), current=current[i, :m].copy(),
                          torque_ref=tref[i, :m].copy(), section=section[i, :m].astype(np.int64), meta=meta,
                          name=names[i] if names else f"sys{i:05d}"))
    return out


def iter_records(params: TwoMassParams, drive: DriveConfig | None = None, signal: TestSignalConfig | None = None, *,
                 seed: int = 0, group: int = 512, dtype: torch.dtype = torch.float32, substeps: int | None = None,
                 use_kernel: bool = True, progress: Any = None) -> Iterator[Record]:
    """Simulate the test for every system in duration-sorted groups and yield their records
    (named ``sysNNNNN`` by flattened input index; memory bounded by one group). Current noise
    per record from a generator seeded with ``seed + index``."""
    from sim._integrate_fast import default_substeps
    from sim._kernel import load_kernel
    from sim.plant import run_test_group, simulate_test

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
            resp = simulate_test(sub, drive, signal, dtype=dtype, substeps=S, use_kernel=False)
            buf = {k: getattr(resp, k) for k in ("speed", "torque", "torque_ref", "section")}
            length, timed_out = resp.length, resp.timed_out
        else:
            buf, length, tmo = run_test_group(lib, sub, drive, signal, S, dtype)
            timed_out = ((tmo.unsqueeze(-1) >> torch.arange(6, dtype=torch.int32)) & 1).bool()
        truths = sub.truth(drive, signal.M_star)
        L = length.tolist()
        t_all = np.arange(int(length.max()), dtype=np.float64) * drive.T_s
        b = {k: v.numpy() for k, v in buf.items()}
        for j, i in enumerate(idx):
            m = L[j]
            meta = _base_meta(drive, signal)
            meta["timed_out"] = timed_out[j].tolist()
            meta["truth"] = truths[j]
            noise = np.random.default_rng(seed + i).standard_normal(m, dtype=np.float32)
            current = b["torque"][j, :m].astype(np.float64) / drive.K_M + drive.current_noise_std * noise.astype(np.float64)
            yield Record(t=t_all[:m].copy(), speed=b["speed"][j, :m].astype(np.float64), current=current,
                         torque_ref=b["torque_ref"][j, :m].astype(np.float64),
                         section=b["section"][j, :m].astype(np.int64), meta=meta, name=f"sys{i:05d}")
        if progress is not None:
            progress(len(idx))


def _base_meta(drive: DriveConfig, signal: TestSignalConfig) -> dict[str, Any]:
    return {"K_M": drive.K_M, "T_Ei": drive.T_Ei, "T_s": drive.T_s, "encoder_counts": drive.encoder_counts,
            "M_star": signal.M_star, "w_max": signal.w_max, "M_max": drive.M_max, "M_N": drive.M_N,
            "current_noise_std": drive.current_noise_std}
