"""A SPEC 8.1 drive made of files, for any real drive and its scope: the chain writes each
experiment it wants as JSON into a folder and stops; a person runs it on the drive, drops the
recording (SPEC 3 record) beside it, and the chain goes on (``twomass commission --resume DIR``).

The folder::

    drive.json              {"config": {T_s, K_M, T_Ei, encoder_counts, M_N, M_max},
                             "limits": {w_max, travel, M_max (optional)}, "name": optional}
    001_request.json        written by the chain: {"experiment": 1, "kind": "test", "M_star", "w_max",
                            "limits"} or {"kind": "closed_loop", "law": law.params, "scenario":
                            {"T_s", "w_ref": [...], "M_dist": [...]}, "limits"}
    001.csv + 001.json      the recording, dropped by the person (SPEC 3; ``aborted: true`` in the
                            JSON when the drive stopped the run at a limit; ``K_M``, ``T_Ei``,
                            ``encoder_counts``, ``M_N``, ``M_max`` may be left out: drive.json's
                            config holds them)

The chain is deterministic: on ``--resume`` it runs again from the start, each experiment with a
recording is answered from it (its request must be the one written before, else the folder belongs
to another run), and the first one without a recording stops the run again.

A recording must be the one requested (else :class:`CommissioningError` naming the file): a test
recording's ``M_star`` / ``w_max`` where it states them, and its torque level (its peak
``torque_ref``, else its peak measured torque) within :data:`TORQUE_REF_TOLERANCE` (measured:
:data:`MEASURED_TORQUE_ALLOWANCE`) of the requested ``M_star``; a closed-loop recording has the
scenario's length (a stopped one at most that); its drive values and ``T_s`` (stated, or from its
time column) agree with drive.json's config. Whether it kept the limits is the chain's check of
every record (a recording that passed one ends the run: ``CommissioningReport.breach``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

import sim
from sim._values import loads
from som_torch import atomic_write
from training._json import dumps, json_safe
from training.errors import CommissioningError, ExperimentPending, UserError, one_line

from ._guard import CONFIG_KEYS, MEASURED_TORQUE_ALLOWANCE, config_conflict, record_peaks

__all__ = ["FileDrive", "ExperimentPending", "read_recording", "TORQUE_REF_TOLERANCE"]

#: How far a test recording's peak torque reference may be from the requested ``M_star`` (a share):
#: a drive's own torque units rounded. (Its measured torque: :data:`MEASURED_TORQUE_ALLOWANCE`.)
TORQUE_REF_TOLERANCE: float = 0.02
#: How far a test recording's stated ``M_star`` or ``w_max`` may be from the request's (relative): the
#: same number, written and read back.
REQUEST_TOLERANCE: float = 1e-6


def read_recording(path: Path, config: dict[str, Any] | None = None) -> sim.Record:
    """A SPEC 3 record; its metadata's ``aborted`` flag (SPEC 8.1) is a bool, False when absent.
    ``config``: the drive's own values (drive.json's ``config``): the JSON may leave out ``K_M``,
    ``T_Ei``, ``encoder_counts``, ``M_N``, ``M_max``; one it states otherwise (by more than
    ``CONFIG_TOLERANCE`` of ``_guard``), or a ``T_s`` (stated, or from the time column) other than the
    config's, is refused naming the file."""
    config = config or {}
    rec = sim.read_record(path, meta_defaults={k: config[k] for k in CONFIG_KEYS[1:] if config.get(k) is not None})
    conflict = config_conflict(rec.meta, config)
    if conflict is not None:
        key, got, have = conflict
        where = f"{path}.json" if key != "T_s" else f"{path}.csv + .json (its T_s, or its time column's)"
        raise CommissioningError(f"{where}: {key} {got:.6g} disagrees with the drive's config in drive.json ({key} {have:.6g})")
    rec.meta["aborted"] = bool(rec.meta.get("aborted", False))
    return rec


class FileDrive:
    """The drive of the folder ``folder`` (module docstring): ``config`` and ``limits`` from its
    ``drive.json``; ``run_test`` / ``run_closed_loop`` answer from the recordings or raise
    :class:`ExperimentPending` after writing the request."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        spec = self.folder / "drive.json"
        try:
            d = loads(spec.read_text(encoding="utf-8-sig"))
        except FileNotFoundError:
            raise UserError(f"{spec}: not found (expected {{\"config\": {{...}}, \"limits\": {{...}}}})") from None
        except (OSError, UnicodeDecodeError, ValueError) as err:  # unreadable, not UTF-8, no JSON, nested too deeply
            raise UserError(f"{spec}: {one_line(err)}") from None
        if not isinstance(d, dict) or not isinstance(d.get("config"), dict) or not isinstance(d.get("limits"), dict):
            raise UserError(f"{spec}: expected an object with 'config' and 'limits' objects")
        self.config = d["config"]
        try:
            self.limits = sim.DriveLimits(**d["limits"])
        except (TypeError, ValueError) as err:
            raise UserError(f"{spec}: limits: {err}") from None
        self.name = str(d.get("name", self.folder.name))
        self.count = 0

    def _exchange(self, request: dict[str, Any]) -> sim.Record:
        self.count += 1
        stem = self.folder / f"{self.count:03d}"
        req_path = Path(f"{stem}_request.json")
        text = dumps({"experiment": self.count, **request}, indent=1)
        if req_path.exists():
            if json.loads(req_path.read_text()) != json.loads(text):
                raise CommissioningError(f"{req_path}: the chain now asks for a different experiment (another run's folder, "
                                         f"or changed settings); remove it and the later files to go on from there")
        else:
            atomic_write(req_path, lambda f: f.write(text), text=True)
        if not stem.with_suffix(".csv").exists():
            raise ExperimentPending(f"experiment {self.count} ({request['kind']}) written to {req_path}; run it on the drive, "
                                    f"drop the recording as {stem}.csv + {stem}.json, then: twomass commission --resume "
                                    f"{self.folder}", str(req_path))
        rec = read_recording(stem, self.config)
        for key in ("M_star", "w_max"):  # a test recording names its signal: it must be the one requested
            got = rec.meta.get(key)
            if key in request and got is not None and not math.isclose(float(got), float(request[key]), rel_tol=REQUEST_TOLERANCE):
                raise CommissioningError(f"{stem}.json: {key} {float(got):.6g} is not the requested {float(request[key]):.6g} "
                                         f"({req_path}): a recording of another experiment")
        if request["kind"] == "test":
            _check_torque_level(rec, float(request["M_star"]), float(rec.meta["K_M"]), stem, req_path)
        else:
            n, N = len(rec), len(request["scenario"]["w_ref"])
            if n > N or (n < N and not rec.meta["aborted"]):
                raise CommissioningError(f"{stem}.csv: {n} samples, the requested scenario has {N} ({req_path})"
                                         + ("" if n > N else " and the recording does not say the drive stopped it "
                                                             "(aborted: true in its JSON)"))
        return rec

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        return self._exchange({"kind": "test", "M_star": M_star, "w_max": w_max, "limits": _limits(limits)})

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits) -> sim.Record:
        return self._exchange({"kind": "closed_loop", "law": json_safe(law.params), "limits": _limits(limits),
                               "scenario": {"w_ref": np.round(scenario.w_ref, 12).tolist(),
                                            "M_dist": np.round(scenario.M_dist, 12).tolist()}})


def _limits(limits: sim.DriveLimits) -> dict[str, Any]:
    return dataclasses.asdict(limits)


def _check_torque_level(rec: sim.Record, M_star: float, K_M: float, stem: Path, req_path: Path) -> None:
    """A test recording's torque level (peak ``torque_ref``, else peak measured torque) must be
    the requested ``M_star``, within :data:`TORQUE_REF_TOLERANCE` (measured:
    :data:`MEASURED_TORQUE_ALLOWANCE`), each way."""
    peaks = record_peaks(rec, rec.T_s, K_M)
    if rec.torque_ref is not None:
        level, what, tol = peaks["peak_torque_ref"], "torque_ref", TORQUE_REF_TOLERANCE
    else:
        level, what, tol = peaks["peak_torque"], "measured torque", MEASURED_TORQUE_ALLOWANCE
    if not M_star / (1 + tol) <= level <= M_star * (1 + tol):
        raise CommissioningError(f"{stem}.csv: its {what} reaches {level:.4g} Nm, the request asks for M_star {M_star:.4g} Nm "
                                 f"({req_path}): a recording of another experiment")
