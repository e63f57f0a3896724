"""Find the six sections I..VI of the test run (SPEC 2) from the signals themselves.

The switching speed controller sets ``M_ref`` to ``+M*, 0, -0.7M*, -M*, 0, +0.7M*`` (sections
I..VI), then 0 for a tail. The measured current follows ``M_ref`` through the current loop's lag
(``T_Ei``), so each sample's torque is classified to the nearest of the five levels
``(+1, +0.7, 0, -0.7, -1) * M*`` (``M*`` estimated from the data when unknown), short runs (the
transitions, spikes, ringing) are dropped, and the first occurrence of the level sequence
``+1, 0, -0.7, -1, 0, +0.7`` gives the sections. Each boundary is placed at the step instant:
the interpolated crossing of the mid level minus ``T_Ei*ln 2`` (the first-order lag's delay to
half the step), rounded to the nearest sample; as in ``sim``, the sample that starts a section
is measured at the instant its new ``M_ref`` is applied (its current still shows the old level). When the record carries ``torque_ref`` the classification uses it directly.

A noisy current (its sample-to-sample noise above :attr:`SectionRules.noisy` of ``M*``) cannot be classified
sample by sample; the switching law itself is known, though, so the sections are then found by
replaying it on the measured speed (:func:`_switching_law`: I ends at ``w_max``, II after I's
duration or at ``0.2 w_max``, III at the zero crossing, ...), from the start of section I (where
the heavily smoothed torque first reaches ``M*/2``) and ``w_max`` (metadata, else the speed where
the smoothed torque drops after I). The torque only has to confirm the levels on average over
each section. Records with ``torque_ref`` need none of this: record it where the drive can.

A record is ONE test run: I..VI, then the tail at rest. Only section I holds ``+M*``, and a run
starts from rest, so each stretch at ``+M*`` that follows rest (zero torque, or the record's
start, with the speed near zero; the torque's rise through ``+0.7 M*`` in between) starts a run
of its own: a record with two or more is refused, naming where the runs start
(:func:`_check_one_run`). A record whose levels stop
part-way through the sequence, with the torque still applied or the speed not yet where the
switching law ends that section, is called an incomplete run, naming the sections it lacks
(:func:`incomplete_run`).
"""

from __future__ import annotations

import contextlib

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from sim import SECTION_LEVELS, SECTION_NAMES, SPEED_RETURN, Record
from training._settings import POSITIVE, check_settings
from training._checks import as_signal

__all__ = ["SectionSplit", "SectionRules", "RULES", "SPEC_TAIL",
           "detect_sections", "sections_from_column", "diff_noise", "law_end", "torque_amplitude",
           "incomplete_run"]

#: The distinct torque levels of the test signal over ``M*``, highest first: ``(1, 0.7, 0, -0.7, -1)``.
_CLASS_LEVELS = np.array(sorted(set(SECTION_LEVELS), reverse=True))
_PATTERN = [int(np.flatnonzero(_CLASS_LEVELS == v)[0]) for v in SECTION_LEVELS]  # sections I..VI
_ZERO = int(np.flatnonzero(_CLASS_LEVELS == 0.0)[0])
_TOP = int(np.flatnonzero(_CLASS_LEVELS == 1.0)[0])  # +M*: section I only
_RISE = int(np.flatnonzero(_CLASS_LEVELS == 0.7)[0])  # +0.7 M*: VI, or the torque's rise into I
#: SPEC 2's tail at rest after section VI [s].
SPEC_TAIL = 0.05


@dataclass(frozen=True)
class SectionRules:
    """The thresholds of the section detection (each checked to be a finite number > 0)."""

    #: runs of one torque level shorter than this [s] are transitions (spikes, ringing), not sections.
    min_run: float = 2e-3
    #: torque noise (std over ``M*``) above which the sections come from the switching law on the speed.
    noisy: float = 0.03
    #: a section's mean torque may miss its level by this much of ``M*`` on the speed path ...
    level_tolerance: float = 0.25
    #: ... plus this many standard deviations of the mean's noise.
    level_sigmas: float = 3.0
    #: a sample's torque belongs to the nearest level within this much of ``M*`` (else to none).
    class_tolerance: float = 0.15
    #: the percentile of ``|torque|`` that stands for the largest level in a first estimate of ``M*`` ...
    amplitude_percentile: float = 99.0
    #: ... and the share of it above which samples count as the largest levels (``M*`` their median).
    amplitude_share: float = 0.85
    #: a noisy torque is smoothed until its noise lies this many sigmas ...
    smooth_sigmas: float = 2.5
    #: ... below this share of its amplitude (the levels' spacing is 0.3 of it).
    smooth_share: float = 0.05
    #: a speed held at its extreme for at least this many samples ...
    saturated_samples: int = 20
    #: ... or one in this many samples of the record (whichever is more) ...
    saturated_part: int = 50
    #: ... away from zero by this share of the speed's span ...
    saturated_span: float = 0.05
    #: ... under a mean torque above this share of the largest is saturated.
    saturated_torque: float = 0.3
    #: current-loop lags ``T_Ei`` after which the next torque step shows (an incomplete run's end).
    settle_lags: float = 3.0

    def __post_init__(self) -> None:
        check_settings(self, {
            "min_run": POSITIVE, "noisy": POSITIVE, "level_tolerance": POSITIVE, "level_sigmas": POSITIVE,
            "class_tolerance": POSITIVE, "amplitude_percentile": POSITIVE, "amplitude_share": POSITIVE,
            "smooth_sigmas": POSITIVE, "smooth_share": POSITIVE, "saturated_samples": POSITIVE, "saturated_part": POSITIVE,
            "saturated_span": POSITIVE, "saturated_torque": POSITIVE, "settle_lags": POSITIVE})


#: The section detection's thresholds.
RULES = SectionRules()


@dataclass(frozen=True)
class SectionSplit:
    """Sections of one record.

    ``bounds``: ``(6, 2)`` int, half-open ``[start, stop)`` sample indices of sections I..VI.
    ``tail``: ``(start, stop)`` of the zero-torque tail after VI (``start == stop``: none).
    ``M_star`` [Nm]: torque amplitude used (estimated when ``M_star_estimated``).
    ``levels``: ``(6,)`` mean measured torque per section [Nm].
    ``flags``: notes such as ``"II ended by duration"`` or ``"tail shorter than 50 ms"``.
    ``source``: the signal used: ``"torque_ref"``, ``"torque"`` or ``"section"`` (the column).
    ``n``: record length [samples].
    """

    bounds: np.ndarray
    tail: tuple[int, int]
    M_star: float
    M_star_estimated: bool
    levels: np.ndarray
    flags: tuple[str, ...]
    source: str
    n: int

    def labels(self) -> np.ndarray:
        """``(n,)`` int: 1..6 inside sections I..VI, 7 in the tail, 0 elsewhere."""
        lab = np.zeros(self.n, dtype=np.int64)
        for k, (a, b) in enumerate(self.bounds.tolist()):
            lab[a:b] = k + 1
        lab[self.tail[0]:self.tail[1]] = 7
        return lab



def _from_record(record: Record) -> dict[str, Any]:
    """What :func:`detect_sections` reads from a record."""
    return {"t": record.t, "speed": record.speed, "torque": record.motor_torque, "T_s": record.T_s,
            "torque_ref": record.torque_ref, "M_star": record.meta.get("M_star"),
            "T_Ei": record.meta.get("T_Ei"), "section": record.section, "w_max": record.meta.get("w_max"),
            "aborted": record.meta.get("aborted")}


def sections_from_column(section: Any, torque: Any = None, M_star: float | None = None) -> SectionSplit:
    """A :class:`SectionSplit` from a record's ``section`` column (values 1..6, else 0).

    Raises ValueError when a section is missing or not contiguous.
    """
    sec = np.asarray(section)
    if sec.ndim != 1:
        raise ValueError(f"section: expected a 1-D column, received shape {sec.shape}")
    bounds = np.zeros((6, 2), dtype=np.int64)
    for k in range(1, 7):
        idx = np.flatnonzero(sec == k)
        if idx.size == 0:
            raise ValueError(f"section: expected section {SECTION_NAMES[k - 1]} ({k}) in the column, received none")
        if idx[-1] - idx[0] + 1 != idx.size:
            raise ValueError(f"section: expected section {k} to be contiguous, received gaps")
        bounds[k - 1] = idx[0], idx[-1] + 1
    tq = np.zeros(sec.size) if torque is None else np.asarray(torque, dtype=np.float64)
    levels = np.array([tq[a:b].mean() for a, b in bounds])
    Ms = float(M_star) if M_star is not None else float(max(abs(levels[0]), abs(levels[3])))
    tail_stop = int(bounds[5, 1])
    while tail_stop < sec.size and sec[tail_stop] not in range(1, 7):
        tail_stop += 1
    return SectionSplit(bounds, (int(bounds[5, 1]), tail_stop), Ms, M_star is None, levels, (), "section", sec.size)


def _runs(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run-length encoding: starts, stops (exclusive), values."""
    change = np.flatnonzero(np.diff(codes)) + 1
    starts = np.concatenate([[0], change])
    stops = np.concatenate([change, [codes.size]])
    return starts, stops, codes[starts]


def _check_speed(w: np.ndarray, y: np.ndarray) -> None:
    span = float(np.ptp(w))
    if not span > 1e-12 * max(1.0, float(np.max(np.abs(w)))):
        raise ValueError(f"speed: expected a varying speed, received a constant speed ({w[0]:.6g} rad/s)")
    ymax = float(np.max(np.abs(y))) if y.size else 0.0
    min_run = max(RULES.saturated_samples, w.size // RULES.saturated_part)
    for ext in (float(np.max(w)), float(np.min(w))):
        at = np.abs(w - ext) <= 1e-9 * max(1.0, abs(ext))
        starts, stops, vals = _runs(at.astype(np.int8))
        for a, b, v in zip(starts, stops, vals):
            if (v and b - a >= min_run and abs(ext) > RULES.saturated_span * span
                    and np.mean(np.abs(y[a:b])) > RULES.saturated_torque * ymax):
                raise ValueError(f"speed: expected an unsaturated speed, received {b - a} samples saturated "
                                 f"at {ext:.6g} rad/s under torque")


def detect_sections(
    record: Record | None = None,
    *,
    speed: Any = None,
    torque: Any = None,
    T_s: float | None = None,
    M_star: float | None = None,
    T_Ei: float | None = None,
    torque_ref: Any = None,
    use_column: bool = False,
    min_run: float = RULES.min_run,
    w_max: float | None = None,
) -> SectionSplit:
    """Find sections I..VI of a test run.

    Args:
        record: a ``sim.Record`` (its ``motor_torque``, ``speed``, optional ``torque_ref`` and
            ``section``; metadata ``T_s``, ``T_Ei``, ``M_star``); or ``None`` and the keyword arrays.
        speed: ``(N,)`` measured motor speed [rad/s] (used for consistency checks).
        torque: ``(N,)`` measured torque [Nm] (or current [A]; only the pattern matters).
        T_s: sample time [s].
        M_star: torque amplitude [Nm]; estimated from the data when ``None``.
        T_Ei: current-loop lag [s] for placing boundaries at the step instant (0 when unknown).
        torque_ref: ``(N,)`` ``M_ref`` [Nm]; when given it is classified instead of the torque.
        use_column: take the record's ``section`` column when present (else ignore it).
        min_run: runs of one level shorter than this [s] are transitions and dropped (in
            ``torque_ref`` only where the sections do not show without them).
        w_max: the test's speed limit [rad/s] (the switching law on a noisy torque; estimated when ``None``).
        (A keyword given overrides the record's value.)

    Returns:
        :class:`SectionSplit`.

    Raises:
        ValueError: one line, e.g. constant or saturated speed, no recognisable sections.
    """
    info: dict[str, Any] = {"section": None} if record is None else _from_record(record)
    for key, val in (("speed", speed), ("torque", torque), ("T_s", T_s), ("M_star", M_star), ("T_Ei", T_Ei),
                     ("torque_ref", torque_ref), ("w_max", w_max)):
        if val is not None:
            info[key] = val
    w, y, Ts = _checked_signals(info)
    if use_column and info.get("section") is not None:
        return sections_from_column(info["section"], y, info.get("M_star"))
    _check_speed(w, y)
    ys, source, lag = _classified_signal(y, info, Ts)
    Ms, estimated = _amplitude(ys, info.get("M_star"))
    noise = diff_noise(y) if source == "torque" else 0.0  # the reference is noiseless
    if noise > RULES.noisy * Ms:
        return _switching_law(w, y, info, Ts, noise)
    keep = max(3, int(round(min_run / Ts)))
    runs = _level_runs(ys, Ms, keep)
    _check_one_run(runs, w, info, Ts)
    try:
        hit = _test_start(runs, Ms, w, info, Ts, keep)
    except ValueError:
        if source == "torque":  # the switching law may still find it; else the levels' error stands
            with contextlib.suppress(ValueError):
                return _switching_law(w, y, info, Ts, noise)
        if source != "torque_ref":
            raise
        runs = _level_runs(ys, Ms, 1)  # the reference is exact: a section shorter than min_run is one too
        hit = _test_start(runs, Ms, w, info, Ts, 1)
    step = _StepLocator(y, Ms, lag, exact=source == "torque_ref")
    bounds, tail, flags = _boundaries(runs, hit, step, Ts)
    _check_speed_follows(w, bounds)
    flags += _duration_flags(bounds)
    levels = np.array([y[a:b].mean() for a, b in bounds])
    return SectionSplit(bounds, tail, Ms, estimated, levels, tuple(flags), source, w.size)


def _checked_signals(info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, float]:
    """Speed ``(N,)``, torque ``(N,)`` and ``T_s`` of ``info``, checked."""
    if info.get("speed") is None or info.get("torque") is None:
        raise ValueError("detect_sections: expected speed and torque (or a record), received "
                         f"speed={'set' if info.get('speed') is not None else 'None'}, "
                         f"torque={'set' if info.get('torque') is not None else 'None'}")
    w = as_signal("speed", info["speed"])
    y = as_signal("torque", info["torque"])
    if w.size != y.size:
        raise ValueError(f"speed and torque: expected the same length, received {w.size} and {y.size}")
    Ts = info.get("T_s")
    if Ts is None or not np.isfinite(Ts) or Ts <= 0:
        raise ValueError(f"T_s: expected a positive sample time [s], received {Ts!r}")
    if w.size < 16:
        raise ValueError(f"detect_sections: expected at least 16 samples, received {w.size}")
    return w, y, float(Ts)


def _classified_signal(y: np.ndarray, info: dict[str, Any], Ts: float) -> tuple[np.ndarray, str, float]:
    """The signal whose levels are classified (``torque_ref`` where given, else the median-filtered
    torque), its name, and the lag [samples] of the torque behind its reference."""
    ref = info.get("torque_ref")
    if ref is not None:
        ref = as_signal("torque_ref", ref)
        if ref.size != y.size:
            raise ValueError(f"torque_ref: expected {y.size} samples, received {ref.size}")
        return ref, "torque_ref", 0.0
    return _despiked(y), "torque", float(info.get("T_Ei") or 0.0) * math.log(2.0) / Ts


def diff_noise(*parts: np.ndarray) -> float:
    """Std of the white noise on signals ``parts`` that are otherwise piecewise smooth: the median
    absolute sample-to-sample difference over ``0.6745 sqrt 2`` (the few steps of the test signal
    do not move the median)."""
    d = np.concatenate([np.diff(p) for p in parts]) if parts else np.zeros(0)
    return float(np.median(np.abs(d)) / (0.6745 * math.sqrt(2.0))) if d.size else 0.0


def _duration_flags(bounds: np.ndarray) -> list[str]:
    """Sections II and V that ended by their duration (as long as I, IV) rather than by the speed."""
    lens = bounds[:, 1] - bounds[:, 0]
    return ((["II ended by duration"] if lens[1] >= lens[0] - 2 else [])
            + (["V ended by duration"] if lens[4] >= lens[3] - 2 else []))


def _first(mask: np.ndarray, start: int) -> int:
    """The first index ``>= start`` where ``mask`` holds; raises ValueError when there is none."""
    hit = np.flatnonzero(mask[start:])
    if hit.size == 0:
        raise ValueError("none")
    return start + int(hit[0])


def _crossing(ys: np.ndarray, level: float, start: int, up: bool) -> float:
    """The interpolated instant [samples] at which ``ys`` first crosses ``level`` from ``start`` on."""
    j = _first(ys >= level if up else ys < level, start)
    if j == 0:
        return 0.0
    y0, y1 = ys[j - 1], ys[j]
    return j - 1 + (float(np.clip((level - y0) / (y1 - y0), 0.0, 1.0)) if y1 != y0 else 1.0)


def law_end(w: np.ndarray, k: int, start: int, before: int, w_max: float) -> int:
    """Where SPEC 2's switching law ends section ``k`` (0..5 for I..VI) that starts at sample
    ``start`` (:class:`sim.SwitchingController`): the sample after the first whose speed ``w``
    meets the section's condition (the new ``M_ref`` applies from the next sample); II and V also
    end once they have lasted ``before`` samples, the length of the section before (I, IV; the
    other sections ignore it). Raises ValueError when the condition is never met."""
    if k in (1, 4):
        w_low = SPEED_RETURN * w_max
        j = np.arange(start, w.size)
        hit = (j - start + 1 >= before) | ((w[start:] <= w_low) if k == 1 else (w[start:] >= -w_low))
        return start + _first(hit, 0) + 1
    rising, level = {0: (True, w_max), 2: (False, 0.0), 3: (False, -w_max), 5: (True, 0.0)}[k]
    return _first(w >= level if rising else w <= level, start) + 1


def _replay(w: np.ndarray, k0: int, w_max: float) -> np.ndarray:
    """``(6, 2)`` bounds of the switching law (:func:`law_end`) replayed on the measured speed
    ``w`` from section I's first sample ``k0``; the record may end in VI. Raises ValueError when
    a condition is never met."""
    bounds = np.zeros((6, 2), dtype=np.int64)
    start, before = k0, 0
    for k in range(6):
        end = law_end(w, k, start, before, w_max)
        bounds[k] = start, min(end, w.size)
        before, start = end - start, end
    return bounds


def _level_fit(y: np.ndarray, bounds: np.ndarray, M_star: float | None) -> tuple[float, float]:
    """``M*`` (given, else least squares of the section torques on the levels) and the squared error
    of the torque against the levels over the sections."""
    sums = np.array([y[a:b].sum() for a, b in bounds.tolist()])
    L, nk = np.asarray(SECTION_LEVELS), bounds[:, 1] - bounds[:, 0]
    Ms = float(np.sum(L * sums) / np.sum(L * L * nk)) if M_star is None else float(M_star)
    ref = np.concatenate([np.full(b - a, lv * Ms) for (a, b), lv in zip(bounds.tolist(), SECTION_LEVELS)])
    got = np.concatenate([y[a:b] for a, b in bounds.tolist()])
    return Ms, float(np.sum((got - ref) ** 2))


def _switching_law(w: np.ndarray, y: np.ndarray, info: dict[str, Any], Ts: float, noise: float) -> SectionSplit:
    """Sections I..VI of a record whose torque is too noisy to classify sample by sample: the
    switching law replayed on the measured speed (module docstring, :func:`_replay`). Without
    ``w_max``, each speed near the fall of the smoothed torque after I is tried and the one whose
    sections best fit the torque levels wins."""
    n = y.size
    ys, smooth_len = _smoothed(y, noise)
    M_rough = float(np.percentile(np.abs(ys), RULES.amplitude_percentile))
    keep = max(3, int(round(RULES.min_run / Ts)))
    runs = _level_runs(ys, _amplitude(ys, None)[0], keep) if M_rough > 0 else []
    _check_one_run(runs, w, info, Ts)
    lag = float(info.get("T_Ei") or 0.0) * math.log(2.0) / Ts  # [samples] of the torque behind its reference
    fail = (f"no recognisable test-signal sections: expected torque levels {_EXPECTED_LEVELS} x M* and the speed to "
            "follow the switching law (w_max, 0.2 w_max, 0), received a noisy torque "
            f"({noise / max(M_rough, 1e-300):.2g} of M*) and a speed that does not")
    try:
        rise = _crossing(ys, 0.5 * M_rough, 0, True)
        fall = _crossing(ys, 0.5 * M_rough, int(rise) + 1, False)
    except ValueError:
        raise ValueError(_incomplete(runs, w, info, Ts, keep) or fail) from None
    k0 = int(round(rise - lag))
    k0 = 0 if k0 < keep else k0  # no run before I: the record starts in I
    best = _best_replay(w, y, k0, _w_max_candidates(w, info, fall - lag, smooth_len, k0), info.get("M_star"))
    if best is None:
        raise ValueError(_incomplete(runs, w, info, Ts, keep) or fail)
    bounds, Ms = best
    levels = np.array([y[a:b].mean() for a, b in bounds.tolist()])
    _check_law_levels(levels, bounds, Ms, noise)
    _check_speed_follows(w, bounds)
    flags = ([f"sections from the switching law on the speed (torque noise {noise / Ms:.2g} of M*)"]
             + _law_flags(bounds, n, k0, Ts) + _duration_flags(bounds))
    b6 = int(bounds[5, 1])
    return SectionSplit(bounds, (b6, int(n)), Ms, info.get("M_star") is None, levels, tuple(flags), "speed", n)


def _w_max_candidates(w: np.ndarray, info: dict[str, Any], fall: float, smooth_len: int, k0: int) -> list[float]:
    """The ``w_max`` values to replay the law with: the record's, else each speed near the smoothed
    torque's ``fall`` after I [samples, at the step instant]: the controller saw ``w_max`` one
    sample before it, and the smoothed fall is a few samples unsure."""
    if info.get("w_max") is not None:
        return [float(info["w_max"])]
    j = int(round(fall)) - 1
    h = smooth_len // 2 + 3
    return sorted(set(w[max(j - h, k0):min(j + h + 1, w.size)].tolist()))


def _best_replay(w: np.ndarray, y: np.ndarray, k0: int, candidates: list[float],
                 M_star: float | None) -> tuple[np.ndarray, float] | None:
    """The bounds and ``M*`` of the law replayed from ``k0`` with the candidate ``w_max`` whose
    sections (all non-empty) best fit the torque levels (:func:`_level_fit`); None when none does."""
    best = None
    for w_max in candidates:
        try:
            bounds = _replay(w, k0, w_max)
        except ValueError:
            continue
        if np.all(bounds[:, 1] > bounds[:, 0]):
            Ms, cost = _level_fit(y, bounds, M_star)
            if best is None or cost < best[2]:
                best = (bounds, Ms, cost)
    return None if best is None else (best[0], best[1])


def _check_law_levels(levels: np.ndarray, bounds: np.ndarray, Ms: float, noise: float) -> None:
    """Each section's mean torque ``levels`` must lie within :attr:`SectionRules.level_tolerance`
    of ``M*`` (plus :attr:`SectionRules.level_sigmas` of its mean's noise) of its level; else
    ValueError (one line)."""
    miss = np.abs(levels - np.asarray(SECTION_LEVELS) * Ms)
    if not Ms > 0 or np.any(miss > RULES.level_tolerance * Ms
                            + RULES.level_sigmas * noise / np.sqrt(bounds[:, 1] - bounds[:, 0])):
        raise ValueError(f"no recognisable test-signal sections: expected torque levels {_EXPECTED_LEVELS} x M* "
                         f"(M*={Ms:.4g}) in order, received section means "
                         f"{','.join(f'{v / max(abs(Ms), 1e-300):+.2f}' for v in levels)} x M*")


def _law_flags(bounds: np.ndarray, n: int, k0: int, Ts: float) -> list[str]:
    """The notes on the law's sections: the tail missing or short, samples before section I."""
    b6 = int(bounds[5, 1])
    flags = []
    if b6 >= n:
        flags.append("record ends in section VI (no tail)")
    elif n - b6 < int(round(SPEC_TAIL / Ts)) - 2:
        flags.append("tail shorter than 50 ms")
    if k0 > 0:
        flags.append(f"{k0} samples before section I")
    return flags


def _smoothed(y: np.ndarray, noise: float) -> tuple[np.ndarray, int]:
    """A noisy torque ``y`` through a median filter long enough to bring its ``noise`` [Nm] well
    below the levels' spacing, and the filter's length [samples]."""
    n = y.size
    a_rough = float(np.percentile(np.abs(y), RULES.amplitude_percentile))
    smooth_len = max(5, 2 * int(math.ceil((RULES.smooth_sigmas * noise / max(RULES.smooth_share * a_rough, 1e-300)) ** 2
                                          / 2)) + 1)
    return median_filter(y, size=min(smooth_len, max(5, n // 20) | 1), mode="nearest"), smooth_len


def _time_at(info: dict[str, Any], Ts: float, k: int) -> float:
    """The instant [s] of sample ``k``: the record's ``t`` where known, else ``k T_s``."""
    t = info.get("t")
    return float(t[min(k, len(t) - 1)]) if t is not None and len(t) else k * Ts


def _run_starts(runs: list[list[int]], w: np.ndarray) -> list[int]:
    """The first samples of the runs of ``+M*`` that start a test run: section I, the only section
    at that level, from rest: after a zero run (or the record's start; runs of ``+0.7 M*`` between
    are the torque's rise through that level, or the VI of a run without a tail) with the speed
    ``w`` within ``0.2`` of its peak of zero (SPEC 2: a run starts from rest and ends there). A dip
    inside section I does not count (the speed is moving, or the run before the dip is at ``+M*``)."""
    at_rest = SPEED_RETURN * float(np.max(np.abs(w))) if w.size else 0.0
    starts = []
    for i, (a, _, level) in enumerate(runs):
        j = i - 1
        while j >= 0 and runs[j][2] == _RISE:
            j -= 1
        if level == _TOP and (j < 0 or runs[j][2] == _ZERO) and abs(w[a]) <= at_rest:
            starts.append(int(a))
    return starts


def _check_one_run(runs: list[list[int]], w: np.ndarray, info: dict[str, Any], Ts: float) -> None:
    """Raise ValueError (one line) when the level ``runs`` hold more than one test run (SPEC 2:
    one run is I..VI, then the 50 ms tail at rest; :func:`_run_starts` on the speed ``w``)."""
    starts = _run_starts(runs, w)
    if len(starts) < 2:
        return
    again = ", ".join(f"{_time_at(info, Ts, k):.6g}" for k in starts[1:4]) + (", ..." if len(starts) > 4 else "")
    raise ValueError(f"the record holds {len(starts)} test runs (section I starts again from rest at t = {again} s); "
                     "expected one run (sections I-VI, then a 50 ms tail): cut the record to one run")


def _incomplete(runs: list[list[int]], w: np.ndarray, info: dict[str, Any], Ts: float, keep: int,
                upto: int = 6) -> str | None:
    """Why the sections do not show where the record stops part-way through one test run: its
    level ``runs`` from section I on are the start of I..VI, it ends in the last of them (within
    ``keep`` samples), and its speed ``w`` meets that section's end of SPEC 2's switching law (I:
    ``w_max``, II: ``0.2 w_max``, III: 0, IV: ``-w_max``, V: ``-0.2 w_max``, VI: 0; ``w_max`` from the
    metadata, else the speed at the end of I) late or never: too close to the record's end for the
    next torque step to show; else None (a complete run whose short section hides, a record of
    one torque level whose ``w_max`` is unknown; a record that ends after section ``upto``)."""
    codes = [r[2] for r in runs]
    if _TOP not in codes:
        return None
    first = codes.index(_TOP)
    got = codes[first:]
    n = w.size
    if not 0 < len(got) <= upto or got != _PATTERN[:len(got)] or runs[-1][1] < n - keep:
        return None
    k = len(got) - 1  # the section the record ends in (0..5 for I..VI)
    w_max = info.get("w_max")
    if w_max is None and k == 0:
        return None
    w_max = float(w_max) if w_max is not None else abs(float(w[max(runs[first][1] - 1, 0)]))
    rising, level = {0: (True, w_max), 1: (False, SPEED_RETURN * w_max), 2: (False, 0.0), 3: (False, -w_max),
                     4: (True, -SPEED_RETURN * w_max), 5: (True, 0.0)}[k]
    tail = w[runs[-1][0]:]
    ended = np.flatnonzero(tail >= level if rising else tail <= level)
    # the samples before the next step shows
    settle = keep + int(math.ceil(RULES.settle_lags * float(info.get("T_Ei") or 0.0) / Ts)) + 2
    if ended.size and runs[-1][0] + int(ended[0]) < n - settle:
        return None  # the law ended that section well before the record ends: not simply cut short
    return _incomplete_text(k, got[-1] != _ZERO, info, Ts, n)


def _incomplete_text(k: int, torque_applied: bool, info: dict[str, Any], Ts: float, n: int) -> str:
    """The error line of a record of ``n`` samples that ends in section ``k`` (0..5 for I..VI)."""
    missing = f"sections {', '.join(SECTION_NAMES[k + 1:])} and the 50 ms tail are" if k < 5 else "the 50 ms tail is"
    why = ("the drive aborted it at a limit (metadata aborted: true)" if info.get("aborted")
           else "was the recording cut short? record the whole test run")
    state = "the torque still applied" if torque_applied else "the speed still moving"
    return (f"incomplete test run: the record ends in section {SECTION_NAMES[k]} at "
            f"t = {_time_at(info, Ts, n - 1):.6g} s ({state}); {missing} missing: {why}")


def incomplete_run(record: Record, upto: int = 6) -> str | None:
    """Why ``record`` is no whole test run where it stops part-way through one, in one of the
    sections 1..``upto`` (:func:`_incomplete`), classified as :func:`detect_sections` classifies
    it; else None (also where its signals cannot be classified at all: the section detection
    reports those)."""
    try:
        info = _from_record(record)
        w, y, Ts = _checked_signals(info)
        ys, source, _ = _classified_signal(y, info, Ts)
        Ms = _amplitude(ys, info.get("M_star"))[0]
        noise = diff_noise(y) if source == "torque" else 0.0
        if noise > RULES.noisy * Ms:  # as the switching law classifies it
            ys = _smoothed(y, noise)[0]
            Ms = _amplitude(ys, None)[0]
    except ValueError:
        return None
    keep = max(3, int(round(RULES.min_run / Ts)))
    return _incomplete(_level_runs(ys, Ms, keep), w, info, Ts, keep, upto)


def torque_amplitude(torque: np.ndarray) -> float:
    """The largest level [Nm] of a measured ``torque``: ``M*`` as the section detection estimates it."""
    return _amplitude(_despiked(torque), None)[0]


def _despiked(y: np.ndarray) -> np.ndarray:
    """The measured torque through a 5-sample median filter (spikes, noise), as it is classified."""
    return median_filter(y, size=5, mode="nearest") if y.size >= 5 else y


def _amplitude(ys: np.ndarray, M_star: float | None) -> tuple[float, bool]:
    """``M*`` [Nm] (estimated from the largest levels of ``ys`` when ``None``) and whether estimated."""
    estimated = M_star is None
    if estimated:
        a = float(np.percentile(np.abs(ys), RULES.amplitude_percentile))
        if not math.isfinite(a):
            raise ValueError("torque: expected finite values, received inf or NaN (current * K_M beyond the float "
                             "range?)")
        if not a > 0:
            raise ValueError("torque: expected steps between +-M*, +-0.7M* and 0, received a zero torque")
        M_star = float(np.median(np.abs(ys)[np.abs(ys) > RULES.amplitude_share * a]))
    Ms = float(M_star)
    if not Ms > 0:
        raise ValueError(f"M_star: expected a positive torque amplitude [Nm], received {Ms!r}")
    return Ms, estimated


def _level_runs(ys: np.ndarray, Ms: float, keep_len: int) -> list[list[int]]:
    """Runs ``[start, stop, level index]`` of ``ys`` classified to :data:`_CLASS_LEVELS` (within
    :attr:`SectionRules.class_tolerance` of ``M*``), runs shorter than ``keep_len`` samples dropped and equal
    neighbours merged."""
    dist = np.abs(ys[:, None] / Ms - _CLASS_LEVELS[None, :])
    codes = np.argmin(dist, axis=1)
    codes = np.where(np.min(dist, axis=1) <= RULES.class_tolerance, codes, -1)
    starts, stops, vals = _runs(codes)
    merged: list[list[int]] = []
    for a, b, v in zip(starts, stops, vals):
        if v < 0 or b - a < keep_len:
            continue
        if merged and merged[-1][2] == v:
            merged[-1][1] = b
        else:
            merged.append([a, b, v])
    return merged


def _level_text(level: float) -> str:
    return f"{level:+.1f}".rstrip("0").rstrip(".") if level else "0"


#: SPEC 2's torque levels of sections I..VI over ``M*``, as an error line names them.
_EXPECTED_LEVELS = ",".join(_level_text(v) for v in SECTION_LEVELS)


def _test_start(runs: list[list[int]], Ms: float, w: np.ndarray, info: dict[str, Any], Ts: float, keep: int) -> int:
    """:func:`_pattern_start`, its error worded as an incomplete run where the record stops
    part-way through one (:func:`_incomplete`)."""
    try:
        return _pattern_start(runs, Ms)
    except ValueError as err:
        why = _incomplete(runs, w, info, Ts, keep)
        if why is None:
            raise
        raise ValueError(why) from err


def _pattern_start(runs: list[list[int]], Ms: float) -> int:
    """Index of the first run of the level sequence of sections I..VI."""
    seq = [r[2] for r in runs]
    for i in range(len(seq) - 5):
        if seq[i:i + 6] == _PATTERN:
            return i
    found = ",".join(f"{_CLASS_LEVELS[v]:+.1f}" for v in seq[:12]) or "none"
    raise ValueError("no recognisable test-signal sections: expected torque levels "
                     f"{_EXPECTED_LEVELS} x M* (M*={Ms:.4g}) in order, received {found}")


@dataclass(frozen=True)
class _StepLocator:
    """Places the boundary between two runs at the step instant: the interpolated crossing of the
    mid level in the raw torque ``y`` (the median filter would delay small steps) minus ``lag``
    samples; with ``exact`` (a torque reference) the next run's first sample."""

    y: np.ndarray
    M_star: float
    lag: float
    exact: bool

    def __call__(self, prev: list[int], nxt: list[int]) -> int:
        lo, hi = prev[1] - 1, nxt[0]
        if self.exact:
            return int(hi)
        mid = 0.5 * (_CLASS_LEVELS[prev[2]] + _CLASS_LEVELS[nxt[2]]) * self.M_star
        up = _CLASS_LEVELS[nxt[2]] > _CLASS_LEVELS[prev[2]]
        seg = self.y[lo:hi + 1]
        past = seg >= mid if up else seg <= mid
        j = int(np.argmax(past)) if past.any() else seg.size - 1
        if j == 0:
            tau = float(lo)
        else:
            y0, y1 = seg[j - 1], seg[j]
            frac = (mid - y0) / (y1 - y0) if y1 != y0 else 1.0
            tau = lo + j - 1 + float(np.clip(frac, 0.0, 1.0))
        return int(min(max(math.floor(tau - self.lag + 0.5), prev[0] + 1), hi))


def _boundaries(runs: list[list[int]], hit: int, step: _StepLocator,
                Ts: float) -> tuple[np.ndarray, tuple[int, int], list[str]]:
    """``(6, 2)`` section bounds, the tail and the flags, from the runs of the pattern at ``hit``."""
    runs6 = runs[hit:hit + 6]
    bounds = np.zeros((6, 2), dtype=np.int64)
    # I starts where the torque leaves its last zero run before I; without one the record starts in
    # I (runs of other levels before it are the torque's rise through them, a slow current loop's)
    zero = next((r for r in reversed(runs[:hit]) if r[2] == _ZERO), None)
    bounds[0, 0] = step(zero, runs6[0]) if zero is not None else 0
    for k in range(5):
        b = step(runs6[k], runs6[k + 1])
        bounds[k, 1] = b
        bounds[k + 1, 0] = b
    flags: list[str] = []
    if hit + 6 < len(runs):
        tail_run = runs[hit + 6]
        b6 = step(runs6[5], tail_run)
        tail = (b6, int(tail_run[1]) if tail_run[2] == _ZERO else b6)
        if tail_run[2] != _ZERO:
            flags.append("no zero-torque tail after VI")
        if hit + 7 < len(runs):
            flags.append("further torque steps after the tail")
    else:
        b6 = int(runs6[5][1])
        tail = (b6, b6)
        flags.append("record ends in section VI (no tail)")
    bounds[5, 1] = b6
    if tail[1] - tail[0] < int(round(SPEC_TAIL / Ts)) - 2 and tail[1] > tail[0]:
        flags.append("tail shorter than 50 ms")
    if bounds[0, 0] > 0:
        flags.append(f"{bounds[0, 0]} samples before section I")
    return bounds, (int(tail[0]), int(tail[1])), flags


def _check_speed_follows(w: np.ndarray, bounds: np.ndarray) -> None:
    """Each section must move the speed in its torque's direction, by its last sample or the one
    after it (the torque of sample ``k`` acts until sample ``k + 1``: a one-sample section shows there)."""
    for (a, b), level, name in zip(bounds.tolist(), SECTION_LEVELS, SECTION_NAMES):
        dirn = int(np.sign(level))
        dw = max(w[b - 1] - w[a], w[min(b, w.size - 1)] - w[a], key=lambda d: d * dirn)
        if dirn and dw * dirn <= 0:
            raise ValueError(f"speed does not follow the torque: expected the speed to "
                             f"{'rise' if dirn > 0 else 'fall'} in section {name}, received a change of {dw:.4g} rad/s")
