"""The guard between the chain and a user's drive (SPEC 8.1, 8.2): every call bounded in time,
every returned record checked at once, every record held against the user's limits.

* A drive call runs in a daemon thread and is waited for ``timeout`` seconds at most
  (:func:`call_drive`). A Python call cannot be killed: past the timeout the chain stops waiting and
  ends with a fault, while the call may still run in the background until the process exits.
  Whatever the drive raises (``SystemExit`` included; ``KeyboardInterrupt`` passes) becomes one
  :class:`CommissioningError` naming the method.
* A returned record is validated as the identification would (:func:`sim.records.as_record`: columns,
  time grid, metadata) before anything uses it, so a malformed one is a fault of the experiment
  that returned it, not a refusal after the last test run. The drive values the record does not
  state (``K_M``, ``T_Ei``, ``encoder_counts``, ``M_N``, ``M_max``) are the drive's ``config``; one
  it states differently, or a ``T_s`` (stated, or from its time column) other than the config's,
  is a fault naming both values (:func:`check_record`). A closed-loop record must have the
  scenario's length unless the drive flagged a stop.
* The first record that shows one of the user's limits passed (:func:`passed_limits`: speed,
  travel, torque reference above the cap, measured torque above the cap by more than
  :data:`MEASURED_TORQUE_ALLOWANCE`) raises :class:`LimitPassed` with a :class:`LimitBreach`:
  no further experiment runs on that drive. The user's limits, not the guarded ones the chain
  hands the drive for one experiment: a drive that stops at those and coasts on inside the
  user's limits has kept them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

import sim
from sim.records import as_record
from training.errors import CommissioningError, ExperimentPending, LimitPassed, UserError, error_text, one_line

__all__ = ["CONFIG_KEYS", "CONFIG_TOLERANCE", "MEASURED_TORQUE_ALLOWANCE", "LIMIT_NAMES", "PassedLimit", "LimitBreach",
           "record_peaks", "passed_limits", "call_drive", "close_drive", "config_conflict", "check_record", "CheckedDrive"]

#: The drive's own description (SPEC 8.1 ``config``) the chain reads.
CONFIG_KEYS: tuple[str, ...] = ("T_s", "K_M", "T_Ei", "encoder_counts", "M_N", "M_max")
#: Largest relative difference between a record's drive value and the drive's config that is the same value.
CONFIG_TOLERANCE: float = 1e-3
#: How far the measured torque (``torque``, or ``current * K_M``) may pass the torque cap before it
#: counts as passed, as a share of the cap: measurement noise and the current loop's overshoot, not
#: a torque the drive applied. SPEC 3.1's envelope allows a current noise of 5 % of ``M*`` (std),
#: whose largest sample over a long test run (10^5 samples: under 6 std) stays below 30 % of the
#: cap at ``M*`` at the cap; a current loop's step overshoot adds up to about 15 %. The simulated
#: and the independent plants' measured peaks stay within 1 % of the cap. A drive applying
#: several times the torque asked for passes it at once.
MEASURED_TORQUE_ALLOWANCE: float = 0.5
#: How far the torque reference may pass the cap (relative) and still be at it: floating-point rounding.
TORQUE_REF_ROUNDING: float = 1e-9
#: The limits a record can show passed, with the word for the bound in the one-line text and the unit.
LIMIT_NAMES: dict[str, tuple[str, str]] = {
    "speed": ("limit", "rad/s"),
    "travel": ("limit", "rad"),
    "torque reference": ("cap", "Nm"),
    "measured torque": ("cap", "Nm"),
}


@dataclass(frozen=True)
class PassedLimit:
    """One limit a record passed: ``limit`` (a key of :data:`LIMIT_NAMES`), the record's ``value``
    and the user's ``bound`` (the limit itself; the measured torque counts only beyond the
    allowance)."""

    limit: str
    value: float
    bound: float

    def text(self) -> str:
        """``measured torque 16 Nm > cap 5 Nm (x3.2)``; by less than 10 %: ``(+0.44 %)``."""
        word, unit = LIMIT_NAMES[self.limit]
        r = self.value / self.bound
        by = f"x{r:.2g}" if r >= 1.1 else f"+{100 * (r - 1):.2g} %"
        return f"{self.limit} {self.value:.3g} {unit} > {word} {self.bound:.3g} {unit} ({by})"

    def to_dict(self) -> dict[str, Any]:
        return {"limit": self.limit, "value": self.value, "bound": self.bound, "unit": LIMIT_NAMES[self.limit][1],
                "ratio": self.value / self.bound}


@dataclass(frozen=True)
class LimitBreach:
    """The first record that showed a limit passed: ``experiment`` (1-based count of the drive's
    experiments), ``kind`` (``test run``, or the closed-loop run's label), ``M_star`` of a test run,
    whether the drive flagged a stop (``aborted``) and what was ``passed``."""

    experiment: int
    kind: str
    passed: tuple[PassedLimit, ...]
    aborted: bool = False
    M_star: float | None = None

    def text(self) -> str:
        """One line: which limit, by how much, in which experiment, and what followed."""
        what = self.kind if self.M_star is None else f"{self.kind}, M* {self.M_star:.3g} Nm"
        return (f"limit passed in experiment {self.experiment} ({what}): {', '.join(p.text() for p in self.passed)}; "
                f"no further experiment ran, no controller delivered")

    def to_dict(self) -> dict[str, Any]:
        return {"experiment": self.experiment, "kind": self.kind, "M_star": self.M_star, "aborted": self.aborted,
                "passed": [p.to_dict() for p in self.passed], "text": self.text()}


def record_peaks(record: Any, T_s: float, K_M: float) -> dict[str, float]:
    """A record's peaks: ``peak_speed`` (largest ``|speed|``), ``travel`` (largest ``|phi|`` of the
    integrated measured speed, the encoder angle from the start), ``peak_torque_ref`` and
    ``peak_torque`` (the measured ``torque``, or ``current * K_M``) [Nm]; NaN for a missing column."""
    w = np.asarray(record.speed, dtype=np.float64)
    torque = record.torque if record.torque is not None else (
        None if record.current is None else np.asarray(record.current, dtype=np.float64) * K_M)
    return {
        "peak_speed": float(np.abs(w).max()),
        "travel": float(np.abs(np.cumsum(w) * T_s).max()),
        "peak_torque_ref": float(np.abs(record.torque_ref).max()) if record.torque_ref is not None else math.nan,
        "peak_torque": float(np.abs(torque).max()) if torque is not None else math.nan,
    }


def passed_limits(peaks: dict[str, float], limits: sim.DriveLimits, cap: float) -> tuple[PassedLimit, ...]:
    """The user's limits that ``peaks`` (:func:`record_peaks`) passed: speed above ``w_max``, travel
    above ``travel``, the torque reference above ``cap`` (up to rounding), the measured torque above
    ``cap`` by more than :data:`MEASURED_TORQUE_ALLOWANCE`."""
    checks = (("speed", peaks["peak_speed"], limits.w_max, limits.w_max),
              ("travel", peaks["travel"], limits.travel, limits.travel),
              ("torque reference", peaks["peak_torque_ref"], cap, cap * (1 + TORQUE_REF_ROUNDING)),
              ("measured torque", peaks["peak_torque"], cap, cap * (1 + MEASURED_TORQUE_ALLOWANCE)))
    return tuple(PassedLimit(name, value, bound) for name, value, bound, beyond in checks if value > beyond)


def _fault(what: str, err: BaseException) -> BaseException:
    """The error to raise for what drive method ``what`` raised: the file drive's
    :class:`ExperimentPending`, our own errors and ``KeyboardInterrupt`` unchanged, anything else
    (``SystemExit`` included) one :class:`CommissioningError` naming the method and the exception."""
    if isinstance(err, (ExperimentPending, CommissioningError, UserError, KeyboardInterrupt)):
        return err
    return CommissioningError(f"drive.{what} raised {error_text(err)}")


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM that arrive inside the block are delivered after it (POSIX; elsewhere at once)."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def call_drive(method: Callable[..., Any], what: str, args: tuple[Any, ...], timeout: float | None) -> Any:
    """``method(*args)``, waited for ``timeout`` seconds at most (None: called in this thread, no
    bound). The call runs in a daemon thread; past the timeout the drive is a fault
    (:class:`CommissioningError`) and the call is left running: Python cannot stop it."""
    if timeout is None:
        try:
            return method(*args)
        except BaseException as err:  # noqa: B036 - a drive's SystemExit is a drive fault, not ours
            raise _fault(what, err) from None
    box: dict[str, Any] = {}
    done = threading.Event()  # not Thread.join: an interrupted join takes the thread as ended (Python 3.11)

    def target() -> None:
        try:
            box["value"] = method(*args)
        except BaseException as err:  # noqa: B036 - handed to the waiting thread
            box["error"] = err
        finally:
            done.set()

    worker = threading.Thread(target=target, name=f"drive.{what}", daemon=True)
    try:
        with _signals_held():  # an interruption lands before or after the start, never inside it
            worker.start()
        done.wait(timeout)
    except KeyboardInterrupt:  # Ctrl-C, SIGTERM: the call in flight returns first (within the timeout): a
        if worker.ident is not None:  # process that exits under a call running native code (torch) aborts
            done.wait(timeout)
        raise
    if not done.is_set():
        raise CommissioningError(f"drive.{what} did not answer within {timeout:g} s (the drive timeout, --drive-timeout): "
                                 f"the drive is taken as faulty, no further experiment ran, no controller delivered")
    if "error" in box:
        raise _fault(what, box["error"]) from None
    return box["value"]


def _agrees(got: Any, have: float) -> bool:
    return math.isclose(float(got), float(have), rel_tol=CONFIG_TOLERANCE)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(float(v))


def config_conflict(meta: dict[str, Any], config: Any, keys: tuple[str, ...] = CONFIG_KEYS) -> tuple[str, float, float] | None:
    """The first of ``keys`` whose number in a record's ``meta`` differs from the drive's ``config``
    (attributes or a dict) by more than :data:`CONFIG_TOLERANCE`: ``(key, record's, config's)``;
    None when every stated one agrees (a value that is no number is the record check's to name)."""
    get = config.get if isinstance(config, dict) else (lambda k: getattr(config, k, None))
    for key in keys:
        got, have = meta.get(key), get(key)
        if _number(got) and _number(have) and not _agrees(got, have):
            return key, float(got), float(have)
    return None


def check_record(rec: Any, config: sim.DriveConfig, what: str, where: str) -> sim.Record:
    """The validated copy of a record drive method ``what`` returned (:func:`sim.records.as_record`), its
    missing drive values filled in from ``config``; :class:`CommissioningError` (one line naming
    ``what`` and ``where``) for anything else than a valid SPEC 3 record, or one whose ``K_M``,
    ``T_Ei``, ``encoder_counts``, ``M_N``, ``M_max`` or ``T_s`` (stated, or from its time column)
    differs from ``config``'s by more than :data:`CONFIG_TOLERANCE`."""
    if not isinstance(rec, sim.Record):
        raise CommissioningError(f"drive.{what}: expected a sim.Record, received {type(rec).__name__}")
    if not isinstance(rec.meta, dict):
        raise CommissioningError(f"drive.{what}: {where}: expected its metadata as a dict, received {type(rec.meta).__name__}")
    conflict = config_conflict(rec.meta, config, CONFIG_KEYS[1:])
    if conflict is not None:
        key, got, have = conflict
        raise CommissioningError(f"drive.{what}: {where}: its {key} {got:.6g} disagrees with the drive's config {key} {have:.6g}")
    filled = {**rec.meta, **{k: getattr(config, k) for k in CONFIG_KEYS[1:] if rec.meta.get(k) is None}}
    try:
        checked = as_record(dataclasses.replace(rec, meta=filled), where=where)
    except (TypeError, ValueError) as err:
        raise CommissioningError(f"drive.{what}: {one_line(err)}") from None
    if not _agrees(checked.T_s, config.T_s):
        source = "its metadata" if "T_s" in rec.meta else "its time column"
        raise CommissioningError(f"drive.{what}: {where}: its T_s {checked.T_s:.6g} s ({source}) disagrees with the drive's "
                                 f"config T_s {float(config.T_s):.6g} s")
    return checked


class CheckedDrive:
    """The user's drive with every call bounded by ``timeout`` [s] (None: none), each returned record
    checked (:func:`check_record`) and held against the user's ``limits`` (their ``M_max`` the
    torque cap: ``limits`` as :meth:`sim.DriveLimits.for_drive` made them). ``experiments``: ``(kind, record)`` per
    experiment; ``requests``: what each asked for (``M_star``, ``w_max``, ``stop_at``: the speed
    limit handed to the drive); ``breach``: the :class:`LimitBreach` that ended the experiments."""

    def __init__(self, drive: Any, config: sim.DriveConfig, limits: sim.DriveLimits, timeout: float | None) -> None:
        self.drive, self.config, self.timeout = drive, config, timeout
        self.limits = limits  # already the drive's (for_drive): the chain hands them so
        self.experiments: list[tuple[str, sim.Record]] = []
        self.requests: list[dict[str, Any]] = []
        self.breach: LimitBreach | None = None

    def _checked(self, rec: Any, what: str) -> sim.Record:
        return check_record(rec, self.config, what, f"the record of experiment {len(self.experiments) + 1}")

    def _keep(self, kind: str, rec: sim.Record, request: dict[str, Any]) -> sim.Record:
        """Keep the experiment; :class:`LimitPassed` when its record passed a user's limit."""
        self.experiments.append((kind, rec))
        self.requests.append(request)
        peaks = record_peaks(rec, float(self.config.T_s), float(self.config.K_M))
        passed = passed_limits(peaks, self.limits, float(self.limits.M_max))
        if passed:
            self.breach = LimitBreach(len(self.experiments), "test run" if kind == "test" else kind, passed,
                                      aborted=bool(rec.meta.get("aborted", False)), M_star=request.get("M_star"))
            raise LimitPassed(self.breach)
        return rec

    def run_test(self, M_star: float, w_max: float, limits: sim.DriveLimits) -> sim.Record:
        if self.breach is not None:  # the chain never asks again; a caller that does is stopped here
            raise LimitPassed(self.breach)
        rec = call_drive(self.drive.run_test, "run_test", (float(M_star), float(w_max), limits), self.timeout)
        return self._keep("test", self._checked(rec, "run_test"),
                          {"M_star": float(M_star), "w_max": float(w_max), "stop_at": limits.w_max})

    def run_closed_loop(self, law: Any, scenario: sim.Scenario, limits: sim.DriveLimits, kind: str) -> sim.Record:
        if self.breach is not None:
            raise LimitPassed(self.breach)
        rec = self._checked(call_drive(self.drive.run_closed_loop, "run_closed_loop", (law, scenario, limits), self.timeout),
                            "run_closed_loop")
        n, N = len(rec), len(scenario)
        if n > N:
            raise CommissioningError(f"drive.run_closed_loop returned {n} samples for a scenario of {N}: the recording of "
                                     f"another experiment")
        if n < N and not rec.meta.get("aborted", False):
            raise CommissioningError(f"drive.run_closed_loop returned {n} of the scenario's {N} samples "
                                     f"without flagging a stop (metadata 'aborted'): a cut recording, not a stop at a limit")
        return self._keep(kind, rec, {"stop_at": limits.w_max})


def close_drive(drive: Any, timeout: float | None) -> None:
    """The drive's own ``close()`` where it has one, bounded like every drive call (:func:`call_drive`)."""
    close = getattr(drive, "close", None)
    if callable(close):
        call_drive(close, "close", (), timeout)
