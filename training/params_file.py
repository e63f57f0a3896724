"""Plant parameters from JSON (``twomass simulate --params``, ``commission --params``, ``demo --params``).

Accepted shapes: one object (one system), a list of objects (row-wise), or one object of equal-length
lists (column-wise, as ``pandas.DataFrame.to_json(orient="list")`` writes), each with the keys of
``TwoMassParams.from_dicts`` (each a finite number: JSON numbers, not true/false, not beyond a
float's range) and an optional ``name`` (a plain file name: the system's records and pages are
named by it). A UTF-8 byte-order mark is allowed.

:func:`read_plants` (``simulate``, ``commission``) also takes each system's drive: the keys of
``sim.DriveConfig`` (:data:`DRIVE_KEYS`: ``T_s``, ``encoder_counts``, ``T_Ei``, ``K_M``, ``M_N``,
``M_max``, ``current_noise_std``), each defaulting to the reference drive's, so every system of a
file may run on a drive of its own. A drive that gives any of them is checked against the drive
envelope of docs/contract.md, the drives the shipped maps cover (:func:`_check_drive`).
:func:`read_params_file` (``demo``, which runs the reference drive) refuses them.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from training.errors import UserError

#: The drive keys a system may give (``sim.DriveConfig``'s fields, in its order).
DRIVE_KEYS: tuple[str, ...] = ("M_max", "M_N", "K_M", "T_Ei", "T_s", "encoder_counts", "current_noise_std")


@dataclass(frozen=True)
class Plants:
    """The systems of a parameters file: ``params`` (``sim.TwoMassParams``, batch ``(n,)``), their
    ``names`` and each one's drive (``sim.DriveConfig``; the reference drive where none is given)."""

    params: Any
    names: list[str]
    drives: list[Any]


def _rows(data: Any, src: str) -> list[dict[str, Any]]:
    """The systems of ``data`` as a list of row objects."""
    if isinstance(data, dict) and data and all(isinstance(v, list) for v in data.values()):  # column-wise
        lengths = {k: len(v) for k, v in data.items()}
        if len(set(lengths.values())) != 1:
            raise UserError(f"{src}: column-wise parameters need columns of one length, received {lengths}")
        return [{k: v[i] for k, v in data.items()} for i in range(next(iter(lengths.values())))]
    rows = [data] if isinstance(data, dict) else data
    if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
        raise UserError(f"{src}: expected an object, a non-empty list of objects or an object of lists")
    return rows


def _checked(rows: list[dict[str, Any]], src: str,
             name_prefix: str) -> tuple[list[dict[str, Any]], list[dict[str, float]], list[str]]:
    """The parameter rows (without ``name`` and the drive keys; the values of parameter keys as
    Python numbers, other keys left to ``TwoMassParams.from_dicts``, which names them), the drive
    keys each row gives and the system names; a :class:`UserError` naming the system and key for a
    value that is no finite number (a name that is no text)."""
    from sim._values import shown
    from sim.params import _DICT_KEYS, check_real
    from training._checks import record_name

    params, drives, names = [], [], []
    for i, row in enumerate(rows):
        name = row.get("name", f"{name_prefix}{i:05d}")
        if not isinstance(name, str):
            raise UserError(f"{src}: system {i}: 'name': expected a text, received {shown(name)}")
        names.append(record_name(f"{src}: system {i}", name))  # records and pages are named by it
        try:
            params.append({k: check_real(f"system {i}: {shown(k)}", v) if k in _DICT_KEYS else v
                           for k, v in row.items() if k != "name" and k not in DRIVE_KEYS})
            drives.append({k: check_real(f"system {i}: {k}", row[k]) for k in DRIVE_KEYS if k in row})
        except TypeError as err:
            raise UserError(f"{src}: {err}") from None
    return params, drives, names


def _drive(given: dict[str, float], where: str, M_star: float | None) -> Any:
    """The reference drive with the ``given`` keys, checked against the drive envelope (its noise at
    the test torque ``M_star``, or at the drive's rated torque ``M_N``); one-line :class:`UserError`
    naming ``where`` and the key otherwise."""
    from sim import DriveConfig

    try:
        drive = dataclasses.replace(DriveConfig(), **given)
    except (TypeError, ValueError) as err:
        raise UserError(f"{where}: {str(err).removeprefix('DriveConfig.')}") from None
    _check_drive(where, drive, drive.M_N if M_star is None else M_star)
    return drive


def read_params_file(source: str | os.PathLike[str], name_prefix: str = "sys") -> tuple[Any, list[str]]:
    """``(TwoMassParams, names)`` of :func:`read_plants` for a command that runs the reference drive:
    a drive key (:data:`DRIVE_KEYS`) is refused in one line."""
    plants = read_plants(source, name_prefix, drives=False)
    return plants.params, plants.names


def read_plants(source: str | os.PathLike[str], name_prefix: str = "sys", *, M_star: float | None = None,
                drives: bool = True) -> Plants:
    """The systems (:class:`Plants`) of a JSON file, or of JSON text (a string starting with ``{`` or
    ``[``). Names default to ``<prefix><index>``. A system that gives drive keys runs on the reference
    drive with them, checked against the drive envelope (its current noise at the test torque
    ``M_star``; ``None``: at the drive's rated torque ``M_N``); ``drives=False`` refuses drive keys.

    Raises :class:`UserError` with one line for a missing file, bad JSON (nested too deeply, too,
    or an integer too long), unknown keys, values that are no finite numbers, names that are no
    plain file names, duplicate names, values outside the physical range (``TwoMassParams``
    checks the ranges) or drive values outside the envelope."""
    from sim import DriveConfig, TwoMassParams
    from sim._values import loads, printable

    text = str(source)
    src = "--params"
    if not (isinstance(source, str) and text.lstrip().startswith(("{", "["))):
        src = printable(f"--params {text}")
        try:
            text = Path(source).read_text(encoding="utf-8-sig")
        except FileNotFoundError:
            raise UserError(f"{src}: file not found") from None
        except OSError as err:
            raise UserError(f"{src}: cannot read ({err.strerror})") from None
        except UnicodeDecodeError:
            raise UserError(f"{src}: cannot read: not UTF-8 text") from None
    try:
        data = loads(text)
    except ValueError as err:
        raise UserError(f"{src}: {err}") from None
    rows, given, names = _checked(_rows(data, src), src, name_prefix)
    if len(set(names)) != len(names):
        raise UserError(f"{src}: duplicate system names")
    if not drives:
        for i, keys in enumerate(given):
            if keys:
                raise UserError(f"{src}: system {i}: {sorted(keys)}: drive values are not taken here (this command "
                                "runs the reference drive; `twomass simulate` and `commission` take them)")
    try:
        params = TwoMassParams.from_dicts(rows)
    except (TypeError, ValueError) as err:
        raise UserError(printable(f"{src}: {err}")) from None
    reference = DriveConfig()
    configs = [_drive(keys, printable(f"{src}: system {i} ({names[i]})"), M_star) if keys else reference
               for i, keys in enumerate(given)]
    return Plants(params, names, configs)


def _check_drive(source: str, drive: Any, M_star: float) -> None:
    """A :class:`UserError` naming the key, its value and the range where ``drive`` (``sim.DriveConfig``)
    lies outside the drive envelope (:data:`training.identification.SPEC_ENVELOPE`: the drives
    the shipped maps cover): ``T_s``, ``encoder_counts``, ``T_Ei``, ``M_N``; ``M_max`` as ``M_max / M_N``;
    ``current_noise_std`` as the measured torque's noise over the test torque ``M_star``
    (``current_noise_std K_M / M_star``). ``K_M`` alone has no range: torque and inertia scaled
    together give the same speed."""
    from training.identification import SPEC_ENVELOPE, inside_envelope  # here: the commands' --help loads no torch

    d = drive
    checks = (  # key, its value and unit; the envelope's quantity, the value checked, what it is where derived
        ("T_s", d.T_s, "s", "T_s", d.T_s, ""),
        ("encoder_counts", d.encoder_counts, "counts/rev", "encoder_counts", d.encoder_counts, ""),
        ("T_Ei", d.T_Ei, "s", "T_Ei", d.T_Ei, ""),
        ("M_N", d.M_N, "Nm", "M_N", d.M_N, ""),
        ("M_max", d.M_max, "Nm", "M_max_over_M_N", d.M_max / d.M_N, f"M_max / M_N (M_N {d.M_N:g} Nm)"),
        ("current_noise_std", d.current_noise_std, "A", "current_noise", d.current_noise(M_star),
         f"current_noise_std * K_M / M* (K_M {d.K_M:g} Nm/A, M* {M_star:g} Nm)"))
    for key, value, unit, quantity, checked, derived in checks:
        lo, hi = SPEC_ENVELOPE[quantity]
        if inside_envelope(quantity, checked):  # the identification's own test of "inside"
            continue
        expected = (f"{derived} within {lo:.8g} .. {hi:.8g}, received {checked:.4g}" if derived
                    else f"{lo:.8g} .. {hi:.8g} {unit}")
        raise UserError(f"{source}: {key} {value:.8g} {unit}: expected {expected} (the drive envelope of "
                        "docs/contract.md, the drives the shipped maps cover)")
