"""A record's metadata (docs/contract.md, "JSON metadata"): the one check of it (:func:`check_meta`)
and its typed view (:class:`RecordMeta`, ``Record.info``).

``Record.meta`` stays the plain JSON object (what ``write_record`` writes, key order kept; a drive
may still add ``aborted`` to it); :class:`RecordMeta` reads that checked object into typed fields,
one per key of the contract's table.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim._values import plain, printable, shown
from sim.params import check_real

FORMAT = "twomass-record/1"
#: Each column's SI unit: a CSV header cell ``name [unit]`` and metadata ``units`` must name it.
UNITS: dict[str, str] = {"t": "s", "speed": "rad/s", "current": "A", "torque": "Nm", "torque_ref": "Nm", "section": "1"}
MAX_ENCODER_COUNTS = 2 ** 53  # counts per revolution a float64 angle still resolves
MAX_TIMED_OUT = 6  # flags of metadata 'timed_out': one per section
#: Largest deviation from the uniform time grid [samples]: a missing or repeated row is a whole
#: sample off; a time column printed to 1 us at 62.5 us is up to 0.016 off.
UNIFORM_TOL = 0.05
#: Relative disagreement of metadata ``T_s`` with the time column's that is still agreement (a
#: ``T_s`` printed to 7 digits), on top of the time column's own rounding (``UNIFORM_TOL / N``).
T_S_REL_TOL = 1e-6
#: Metadata numbers that must be > 0 (``current_noise_std`` may be 0).
_POSITIVE = ("K_M", "T_Ei", "T_s", "encoder_counts", "M_star", "w_max", "M_max", "M_N")
_NUMBERS = _POSITIVE + ("current_noise_std",)
#: Metadata numbers of any sign: ``M_hold`` [Nm] (SPEC 1.1).
_SIGNED = ("M_hold",)
_MAX_UNKNOWN_SHOWN = 5  # unknown keys an error message names one by one


class RecordError(ValueError):
    """A record that cannot be read or written; the message is one line naming the file."""


def record_error(where: Path | str, msg: str) -> RecordError:
    """A :class:`RecordError` whose one-line message names ``where``."""
    return RecordError(printable(f"{where}: {msg}"))


@dataclass(frozen=True)
class RecordMeta:
    """A record's checked metadata, typed; a key the record leaves out reads as its default."""

    T_Ei: float  # [s] current-loop time constant (required)
    T_s: float  # [s] sample time (the time column's where the JSON leaves it out)
    K_M: float | None = None  # [Nm/A] torque constant (required when only 'current' is given)
    encoder_counts: int | None = None  # counts per revolution
    M_star: float | None = None  # [Nm] the test's torque level
    w_max: float | None = None  # [rad/s] the test's speed level
    M_N: float | None = None  # [Nm] the drive's rated torque
    M_max: float | None = None  # [Nm] the drive's maximum torque
    current_noise_std: float | None = None  # [A] the current sensor's noise (std), where known
    M_hold: float | None = None  # [Nm] SPEC 1.1: the holding torque the test's levels ran around (any sign)
    timed_out: bool | tuple[bool, ...] = False  # one flag for the run, or one per section
    aborted: bool = False  # the drive stopped the run at a limit
    units: Mapping[str, str] = field(default_factory=dict)  # column -> its SI unit
    format: str = FORMAT
    notes: Any = None  # any JSON of the user's
    truth: Mapping[str, Any] | None = None  # simulated records: true parameters, derived values, class

    @property
    def any_timed_out(self) -> bool:
        """Whether a section of the run ended by its safety timeout."""
        return any(self.timed_out) if isinstance(self.timed_out, tuple) else bool(self.timed_out)

    @classmethod
    def of(cls, meta: Mapping[str, Any]) -> RecordMeta:
        """The typed view of checked metadata (``Record.meta`` of a validated record); a
        :class:`RecordError` where ``T_Ei`` or ``T_s`` is missing (a record not validated)."""
        missing = next((key for key in ("T_Ei", "T_s") if key not in meta), None)
        if missing is not None:
            raise RecordError(f"metadata {missing!r} is missing (validate the record first: sim.records.validate)")
        values = {key: meta[key] for key in META_KEYS if key in meta}
        if values.get("encoder_counts") is not None:
            values["encoder_counts"] = int(values["encoder_counts"])
        if isinstance(values.get("timed_out"), list):
            values["timed_out"] = tuple(values["timed_out"])
        return cls(**values)


#: The metadata keys a record may hold: one per field of :class:`RecordMeta`.
META_KEYS: frozenset[str] = frozenset(f.name for f in dataclasses.fields(RecordMeta))


def any_timed_out(meta: Mapping[str, Any]) -> bool:
    """Whether metadata ``timed_out`` (``true``/``false`` or a list of them per section; absent:
    ``false``) says that a section of the run ended by its safety timeout."""
    flags = meta.get("timed_out", False)
    return any(flags) if isinstance(flags, (list, tuple)) else bool(flags)


def check_meta(raw: Any, *, T_s_t: float, n: int, has_torque: bool, where: Path | str) -> dict[str, Any]:
    """The checked metadata ``raw`` of a record of ``n`` samples whose time column's sample time is
    ``T_s_t`` [s]: plain JSON values (numpy numbers as Python numbers), ``T_s`` filled in from
    ``T_s_t`` where absent, the key order kept. ``has_torque``: the record has a ``torque`` column
    (else ``K_M`` is required). Every problem: a :class:`RecordError` naming ``where`` and the key."""
    _check_keys(raw, where)
    meta = _plain_values(raw, where)
    _check_encoder_counts(meta, where)
    _check_flags(meta, where)
    _check_required(meta, has_torque, where)
    _check_sample_time(meta, T_s_t, n, where)
    _check_units(meta, where)
    _check_format_and_truth(meta, where)
    return meta


def _check_keys(raw: Any, where: Path | str) -> None:
    """``raw`` is a mapping of text keys, each a key of the contract's table."""
    if not isinstance(raw, Mapping):
        raise record_error(where, f"metadata: expected a dict (the JSON object of SPEC 3), received {shown(raw)}")
    bad_key = next((key for key in raw if not isinstance(key, str)), None)
    if bad_key is not None:
        raise record_error(where, f"metadata: expected text keys, received {shown(bad_key)}")
    unknown = sorted(set(raw) - META_KEYS)
    if unknown:
        more = f" and {len(unknown) - _MAX_UNKNOWN_SHOWN} more" if len(unknown) > _MAX_UNKNOWN_SHOWN else ""
        names = ", ".join(shown(key) for key in unknown[:_MAX_UNKNOWN_SHOWN])
        raise record_error(where, f"unknown metadata key(s) {names}{more}; expected some of {sorted(META_KEYS)}")


def _plain_values(raw: Mapping[str, Any], where: Path | str) -> dict[str, Any]:
    """``raw``'s values as plain JSON values, in its key order; its numbers checked."""
    meta: dict[str, Any] = {}
    for key, value in raw.items():
        if key in _NUMBERS:
            meta[key] = _number(where, key, value, positive=key in _POSITIVE)
        elif key in _SIGNED:
            meta[key] = _signed(where, key, value)
        else:
            try:
                meta[key] = plain(value, f"metadata {shown(key)}")
            except ValueError as err:
                raise record_error(where, str(err)) from None
    return meta


def _number(where: Path | str, key: str, value: Any, positive: bool) -> int | float:
    """Metadata ``key``'s ``value`` as a Python number if finite and > 0 (``positive``) or >= 0."""
    try:
        number = check_real(f"metadata '{key}'", value)
    except TypeError:
        number = None
    if number is None or (number <= 0 if positive else number < 0):
        raise record_error(where, f"metadata '{key}': expected a finite number {'> 0' if positive else '>= 0'}, "
                                  f"received {shown(value)}")
    return number


def _signed(where: Path | str, key: str, value: Any) -> int | float:
    """Metadata ``key``'s ``value`` as a Python number if finite (any sign)."""
    try:
        return check_real(f"metadata '{key}'", value)
    except TypeError:
        raise record_error(where, f"metadata '{key}': expected a finite number, received {shown(value)}") from None


def _check_encoder_counts(meta: Mapping[str, Any], where: Path | str) -> None:
    counts = meta.get("encoder_counts")
    if counts is not None and (counts > MAX_ENCODER_COUNTS or int(counts) != counts):
        raise record_error(where, f"metadata 'encoder_counts': expected an integer up to 2^53, received {shown(counts)}")


def _check_flags(meta: Mapping[str, Any], where: Path | str) -> None:
    """``aborted`` a boolean; ``timed_out`` a boolean or a list of at most one per section."""
    if "aborted" in meta and not isinstance(meta["aborted"], bool):
        raise record_error(where, f"metadata 'aborted': expected true or false, received {shown(meta['aborted'])}")
    flags = meta.get("timed_out", False)
    if not (isinstance(flags, bool) or isinstance(flags, list) and len(flags) <= MAX_TIMED_OUT
            and all(isinstance(flag, bool) for flag in flags)):
        raise record_error(where, f"metadata 'timed_out': expected a list of true/false per section (at most "
                                  f"{MAX_TIMED_OUT}) or one true/false for the run, received {shown(flags)}")


def _check_required(meta: Mapping[str, Any], has_torque: bool, where: Path | str) -> None:
    if "T_Ei" not in meta:
        raise record_error(where, "metadata 'T_Ei' (current-loop time constant) is missing")
    if not has_torque and "K_M" not in meta:
        raise record_error(where, "metadata 'K_M' is missing (needed when only 'current' is given)")


def _check_sample_time(meta: dict[str, Any], T_s_t: float, n: int, where: Path | str) -> None:
    """``T_s`` agrees with the time column's ``T_s_t`` (of ``n`` samples); filled in where absent."""
    if "T_s" not in meta:
        meta["T_s"] = T_s_t
    elif abs(meta["T_s"] - T_s_t) > T_S_REL_TOL * T_s_t + UNIFORM_TOL * T_s_t / n:
        raise record_error(where, f"metadata T_s={meta['T_s']!r} disagrees with the time column ({T_s_t!r} s)")


def _check_units(meta: Mapping[str, Any], where: Path | str) -> None:
    units = meta.get("units", {})
    if not isinstance(units, dict):
        raise record_error(where, f"metadata 'units': expected an object, received {shown(units)}")
    for column, unit in units.items():
        if column not in UNITS:
            raise record_error(where, f"metadata 'units': unknown column {shown(column)}")
        if unit != UNITS[column]:
            raise record_error(where, f"unknown unit {shown(unit)} for column '{column}' (expected '{UNITS[column]}')")


def _check_format_and_truth(meta: Mapping[str, Any], where: Path | str) -> None:
    if meta.get("format", FORMAT) != FORMAT:
        raise record_error(where, f"metadata 'format': expected {FORMAT!r}, received {shown(meta['format'])}")
    if "truth" in meta and not isinstance(meta["truth"], dict):
        raise record_error(where, f"metadata 'truth': expected an object, received {shown(meta['truth'])}")
