"""The drive envelope (SPEC 3.1) as data, stored with the maps (``envelope.json`` beside the
checkpoints), and the check of a record's drive and test values against it.

Two ranges per quantity: ``envelope``, SPEC 3.1's (the drives one set of shipped maps must
serve), and ``trained``, what the maps' training data covered (a single value where the maps were
trained on one drive). A value outside either gives a coded warning that names the quantity, its
value and the range; the answer is still given.

Quantities (the ones the features and the class rule depend on; a drive's absolute torque scale
is not among them: torque and inertia scaled together give the same speed, so ``M*`` enters only
through the test's time scale and the ratios):

| quantity | meaning |
| --- | --- |
| ``T_s`` [s] | sample time |
| ``encoder_counts`` | counts per revolution |
| ``T_Ei`` [s] | current-loop time constant |
| ``M_N`` [Nm] | rated torque |
| ``M_max_over_M_N`` | maximum over rated torque |
| ``M_star_over_M_max`` | the test's torque over the maximum torque |
| ``time_scale`` [s] | ``J_sigma w_max / M*``: how long the test's torque takes to reach ``w_max`` |
| ``current_noise`` | std of the measured torque's noise over ``M*`` |
| ``f_e`` [Hz], ``V_J``, ``d``, ``s_N``, ``M_FC_over_M_star`` | the identified mechanics |
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sim import EnvelopeRanges, PopulationRanges, time_scale
from sim._values import shown
from som_torch import CheckpointError, atomic_write
from training._settings import POSITIVE, SHARE, check_settings
from training._json import dumps
from training.errors import error_text
from training.identification._result import IdentWarning

FORMAT = "twomass-envelope/1"
FILE_NAME = "envelope.json"

#: Quantity -> unit (for the warning text).
UNITS: dict[str, str] = {"T_s": "s", "encoder_counts": "counts/rev", "T_Ei": "s", "M_N": "Nm", "M_max_over_M_N": "",
                         "M_star_over_M_max": "", "time_scale": "s", "current_noise": "of M*", "f_e": "Hz", "V_J": "",
                         "d": "", "s_N": "", "M_FC_over_M_star": ""}



@dataclass(frozen=True)
class EnvelopeTolerances:
    """How far outside a range a value may lie before it is called outside."""

    #: the record's noise is estimated (:func:`training.identification._drive.torque_noise`, a few %
    #: spread): the trained range reaches this much above the training drive's noise.
    noise_spread: float = 1.25
    #: the relative tolerance of every range (a drive's T_s read from its time column, rounding of metadata).
    relative: float = 0.01
    #: identified values whose own uncertainty is wide lie outside a range only beyond this factor
    #: of its ends. ``d`` is the least certain value (it trades off against ``V_J``): an answer with
    #: ``d`` past 1.2 x the envelope's 0.1 was wrong for 27 of 31 elastic answers on the drive
    #: matrix and 2000 envelope systems (3 of them unwarned); between 0.1 and 0.12, right for 16 of
    #: 17 unwarned.
    d_slack: float = 1.2
    #: ``current_noise`` is an estimate too (a percent or two of spread on a test run): a record
    #: made at the envelope's 5 % read 5.06 % and was called outside.
    current_noise_slack: float = 1.1

    def __post_init__(self) -> None:
        check_settings(self, {"noise_spread": POSITIVE, "relative": SHARE, "d_slack": POSITIVE,
                              "current_noise_slack": POSITIVE})

    def slack(self, quantity: str) -> float:
        """The factor beyond a range's ends from which ``quantity`` lies outside (1: none)."""
        return {"d": self.d_slack, "current_noise": self.current_noise_slack}.get(quantity, 1.0)


#: The envelope checks' tolerances.
TOLERANCES = EnvelopeTolerances()


def _sampled(env: Mapping[str, Any], noise_spread: float = TOLERANCES.noise_spread) -> dict[str, tuple[float, float]]:
    """The drive and test ranges of :class:`sim.EnvelopeRanges` ``env`` (its fields, as stored in a
    dataset): the test's ``M*`` down to 0 (a weaker test only lowers the noise's share), any noise
    up to ``noise_spread`` x the range's."""
    pair = lambda k: (float(env[k][0]), float(env[k][1]))  # noqa: E731
    lo_bits, hi_bits = env["encoder_bits"]
    out = {k: pair(k) for k in ("T_s", "T_Ei", "M_N", "M_max_over_M_N", "time_scale")}
    out["encoder_counts"] = (2.0 ** lo_bits, 2.0 ** hi_bits)
    out["M_star_over_M_max"] = (0.0, float(env["M_star_over_M_max"][1]))
    out["current_noise"] = (0.0, noise_spread * float(env["current_noise"][1]))
    return out


_SPEC = EnvelopeRanges()  # SPEC 3.1's numbers, once (the training population draws from them)
_SPEC_RANGES = {**_sampled(asdict(_SPEC), noise_spread=1.0), "f_e": _SPEC.f_e, "V_J": _SPEC.V_J, "d": _SPEC.d,
                "s_N": (0.0, 10.0), "M_FC_over_M_star": _SPEC.M_FC}
#: SPEC 3.1's envelope: what a record may come from (the test's M* down to 0, any noise below the
#: envelope's, any normalized backlash up to 10), in the order of :data:`UNITS`.
SPEC_ENVELOPE: dict[str, tuple[float, float]] = {k: _SPEC_RANGES[k] for k in UNITS}

#: The quantities every ``trained`` part holds: the drive and test values that fix the features
#: (:func:`trained_envelope` gives them for any training data; data drawn over the envelope adds
#: ``M_N``, ``M_max_over_M_N``, ``M_star_over_M_max``, which the ``envelope`` part checks too).
#: The ``envelope`` part holds every quantity of :data:`UNITS`. A file without one is refused: a
#: quantity left out would be a check silently off.
TRAINED_QUANTITIES = ("T_s", "encoder_counts", "T_Ei", "time_scale", "current_noise")



@dataclass(frozen=True)
class Finding:
    """One quantity outside a range: its ``value``, the ``trained`` and ``envelope`` ranges, and
    which of them it leaves (``outside``: ``"trained"``, ``"envelope"`` or both)."""

    quantity: str
    value: float
    trained: tuple[float, float] | None
    envelope: tuple[float, float] | None
    outside: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "trained": None if self.trained is None else list(self.trained),
                "envelope": None if self.envelope is None else list(self.envelope), "outside": list(self.outside)}




def _inside(value: float, rng: tuple[float, float], slack: float = 1.0) -> bool:
    lo, hi = rng
    return (lo * (1.0 - TOLERANCES.relative) / slack - 1e-300 <= value
            <= hi * (1.0 + TOLERANCES.relative) * slack + 1e-300)


def inside_envelope(quantity: str, value: float) -> bool:
    """Whether ``value`` lies in the drive envelope's range of ``quantity`` (:data:`SPEC_ENVELOPE`),
    with the tolerance the identification's own check allows (:attr:`EnvelopeTolerances.relative`)."""
    return _inside(value, SPEC_ENVELOPE[quantity])


def _fmt(v: float) -> str:
    return f"2^{math.log2(v):.4g}" if v >= 1024 and float(math.log2(v)).is_integer() else f"{v:.4g}"


@dataclass(frozen=True)
class Envelope:
    """``envelope`` (SPEC 3.1) and ``trained`` (the maps' training data) ranges per quantity."""

    trained: dict[str, tuple[float, float]]
    envelope: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(SPEC_ENVELOPE))

    def check(self, values: Mapping[str, float | None]) -> list[Finding]:
        """The quantities of ``values`` (``None``: unknown, not checked) outside a range."""
        out = []
        for name, value in values.items():
            if value is None or not math.isfinite(value):
                continue
            tr, env = self.trained.get(name), self.envelope.get(name)
            outside = tuple(k for k, rng in (("trained", tr), ("envelope", env)) if rng is not None
                            and not _inside(value, rng, TOLERANCES.slack(name)))
            if outside:
                out.append(Finding(name, float(value), tr, env, outside))
        return out

    def to_dict(self) -> dict[str, Any]:
        """The ``envelope.json`` form (:meth:`from_dict` reads it back)."""
        return {"format": FORMAT, **{part: {k: list(v) for k, v in getattr(self, part).items()}
                                     for part in ("envelope", "trained")}}

    def write(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`to_dict` to ``path`` (atomically)."""
        text = dumps(self.to_dict(), indent=1)
        atomic_write(Path(path), lambda f: f.write(text), text=True)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = FILE_NAME) -> "Envelope":
        """The envelope of :meth:`to_dict`'s form. Each part must hold its quantities
        (``envelope``: every one of :data:`UNITS`; ``trained``: at least :data:`TRAINED_QUANTITIES`),
        each as ``[low, high]``, two finite numbers with ``low <= high``. Raises
        :class:`som_torch.CheckpointError` (a ``ValueError``) naming ``where`` and the quantity."""
        if not isinstance(data, Mapping) or data.get("format") != FORMAT:
            raise CheckpointError(f"{where}: expected format {FORMAT!r}, received "
                                  f"{data.get('format') if isinstance(data, Mapping) else type(data).__name__!r}")
        parts = {}
        for part, required in (("envelope", tuple(UNITS)), ("trained", TRAINED_QUANTITIES)):
            ranges = data.get(part)
            if not isinstance(ranges, Mapping):
                raise CheckpointError(f"{where}: expected an object {part!r} of quantity -> [low, high]")
            unknown = sorted(set(ranges) - set(UNITS))
            if unknown:
                raise CheckpointError(f"{where}: unknown quantities {unknown} in {part!r}; valid: {sorted(UNITS)}")
            missing = [k for k in required if k not in ranges]
            if missing:
                raise CheckpointError(f"{where}: {part!r} lacks {missing}; every one is required (a quantity left "
                                      "out would not be checked)")
            parts[part] = {k: _range(v, f"{where}: {part}.{k}") for k, v in ranges.items()}
        return cls(trained=parts["trained"], envelope=parts["envelope"])

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> "Envelope":
        """``folder/envelope.json`` (:meth:`from_dict`), which a checkpoint folder must hold:
        without it no record's drive would be checked against what the maps were trained on."""
        path = Path(folder) / FILE_NAME
        try:
            data = json.loads(path.read_bytes())
        except FileNotFoundError:
            raise CheckpointError(f"{path}: not found; `twomass train` writes it beside the maps") from None
        except (OSError, ValueError, RecursionError) as err:  # unreadable, not UTF-8, not JSON, nested too deep
            raise CheckpointError(f"{path}: unreadable ({error_text(err)})") from None
        return cls.from_dict(data, str(path))


def _range(value: Any, entry: str) -> tuple[float, float]:
    """``value`` (``[low, high]``, two finite numbers, ``low <= high``) as a pair of floats;
    :class:`som_torch.CheckpointError` naming ``entry`` otherwise."""
    pair = value if isinstance(value, list) and len(value) == 2 else None
    numbers = pair is not None and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair)
    try:
        lo, hi = (float(pair[0]), float(pair[1])) if numbers else (math.nan, math.nan)
    except OverflowError:  # an integer beyond float's range
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise CheckpointError(f"{entry}: expected [low, high], two finite numbers with low <= high, received "
                              f"{shown(value)}")
    return lo, hi


def trained_envelope(metadata: Mapping[str, Any]) -> Envelope:
    """The ranges one map's ``metadata`` (its ``dataset``: drive, test signal, population) covers:
    for a dataset drawn over the envelope (``dataset.envelope``, :class:`sim.EnvelopeRanges`) its
    drive and test ranges; for one drive and one test single values, the population's ``J_sigma``
    range as the time scale, noise from none up to the training drive's."""
    ds = metadata["dataset"]
    if ds.get("envelope"):
        return Envelope(trained=_sampled(ds["envelope"]))
    drive, signal = ds["drive"], ds["signal"]
    ranges = ds.get("ranges") or {}
    J = tuple(ranges.get("J_sigma", PopulationRanges().J_sigma))
    M_star, w_max = float(signal["M_star"]), float(signal["w_max"])
    point = lambda v: (float(v), float(v))  # noqa: E731
    # M_N, M_max and M* themselves do not enter the features (torque and inertia scale together)
    trained = {"T_s": point(drive["T_s"]), "encoder_counts": point(drive["encoder_counts"]), "T_Ei": point(drive["T_Ei"]),
               "time_scale": (time_scale(J[0], M_star, w_max), time_scale(J[1], M_star, w_max)),
               # up to the training drive's noise, with room for the estimate's own spread
               "current_noise": (0.0, TOLERANCES.noise_spread * drive["current_noise_std"] * drive["K_M"] / M_star)}
    return Envelope(trained=trained)


def envelope_warnings(findings: list[Finding], *, answer: bool = False) -> list[IdentWarning]:
    """One coded warning per finding: ``drive_outside_training`` when only the training range is
    left, ``outside_envelope`` when SPEC 3.1's is; ``answer_outside_envelope`` for either where the
    findings are on identified values (``answer``)."""
    out = []
    for f in findings:
        unit = UNITS[f.quantity]
        rng = f.envelope if "envelope" in f.outside else f.trained
        what = "the drive envelope (docs/contract.md)" if "envelope" in f.outside else "what the maps were trained on"
        code = ("answer_outside_envelope" if answer else "outside_envelope" if "envelope" in f.outside
                else "drive_outside_training")
        out.append(IdentWarning(code, f"{f.quantity} = {_fmt(f.value)} {unit} is outside {what} "
                                      f"({_fmt(rng[0])} .. {_fmt(rng[1])} {unit}): the answer is less certain".replace(
                                          "  ", " ")))
    return out
