"""The toolkit's domain exceptions and coded warnings, in one module, and the one-line text of an error.

Each subclasses the builtin it refines, so ``except ValueError`` / ``except OSError`` keep working.
The library raises them; only the command line (:mod:`training.cli`) turns them into a one-line
message and an exit code. Errors from :mod:`sim` (``RecordError``) and :mod:`som_torch`
(``CheckpointError``) are ``ValueError`` subclasses too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar


class UserError(ValueError):
    """Bad input from the user: an option, a file, a parameter file. The message is the whole story."""


class IdentificationError(ValueError):
    """A record that cannot be identified (no recognisable test run, implausible units, ...)."""


class CommissioningError(ValueError):
    """A commissioning step that cannot go on (a drive that does not keep the interface, ...)."""


class LimitPassed(CommissioningError):
    """A drive's record shows one of the user's limits passed: no further experiment may run on
    that drive. ``breach``: what was passed, by how much, in which experiment
    (``training.commissioning.LimitBreach``); ``commission`` turns it into its report's ``breach``."""

    def __init__(self, breach: Any) -> None:
        super().__init__(breach.text())
        self.breach = breach


class LimitsTooTight(CommissioningError):
    """The user's limits leave no room for an informative test run, known before any experiment:
    the message names the limit to raise and to what; ``needed``: each limit that must be raised
    (``"w_max"`` [rad/s], ``"travel"`` [rad]) with the smallest value that lets a test fit."""

    def __init__(self, message: str, needed: Mapping[str, float]) -> None:
        super().__init__(message)
        self.needed = dict(needed)


class AxisNotHeld(CommissioningError):
    """The drive does not hold the axis at rest (SPEC 1.1): in the rest check before the first test
    run the axis drifted with the drive's holding torque on and the speed loop off; no test runs.
    ``code``: ``axis_not_held``; ``drift`` [rad] the largest travel, ``duration`` [s] the check's
    length, ``peak_speed`` [rad/s] its largest measured speed."""

    code: ClassVar[str] = "axis_not_held"

    def __init__(self, message: str, drift: float, duration: float, peak_speed: float) -> None:
        super().__init__(message)
        self.drift, self.duration, self.peak_speed = float(drift), float(duration), float(peak_speed)


class ExperimentPending(Exception):
    """Not an error: a file-based drive has written the experiment it wants and waits for its
    recording (``twomass commission --resume DIR`` goes on once it is there). ``request``: the
    request file's path."""

    def __init__(self, message: str, request: str) -> None:
        super().__init__(message)
        self.request = request


class OutputExistsError(UserError, FileExistsError):
    """A file or folder that the work would overwrite; nothing is written unless asked to."""


def one_line(err: BaseException) -> str:
    """The first line of ``err``'s message (its class name when it has none)."""
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__


def error_text(err: BaseException) -> str:
    """``"<type>: <first line>"`` of ``err`` (:func:`one_line` after its class name)."""
    return f"{type(err).__name__}: {one_line(err)}"


@dataclass(frozen=True)
class CodedWarning:
    """A warning: a stable machine-readable ``code`` (a key of the subclass's :attr:`CODES`, which
    says what each means) and a one-line ``text`` for people. Code decides on the code, never on
    the text."""

    CODES: ClassVar[Mapping[str, str]] = {}
    code: str
    text: str

    def __post_init__(self) -> None:
        if self.code not in self.CODES:
            raise ValueError(f"{type(self).__name__}.code: expected one of {sorted(self.CODES)}, received {self.code!r}")
