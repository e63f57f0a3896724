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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from training._checks import as_signal

__all__ = ["SectionSplit", "detect_sections", "sections_from_column", "SECTION_LEVELS"]

#: ``M_ref / M*`` of sections I..VI.
SECTION_LEVELS = (1.0, 0.0, -0.7, -1.0, 0.0, 0.7)
_CLASS_LEVELS = np.array([1.0, 0.7, 0.0, -0.7, -1.0])
_PATTERN = [0, 2, 3, 4, 2, 1]  # indices into _CLASS_LEVELS for sections I..VI
_NAMES = ("I", "II", "III", "IV", "V", "VI")


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

    def durations(self, T_s: float) -> np.ndarray:
        """``(6,)`` section durations [s]."""
        return (self.bounds[:, 1] - self.bounds[:, 0]) * float(T_s)


def _from_record(record: Any) -> dict[str, Any]:
    meta = dict(getattr(record, "meta", None) or {})
    torque = getattr(record, "torque", None)
    current = getattr(record, "current", None)
    if torque is None:
        if current is None:
            raise ValueError("record: expected a current or torque column, received neither")
        K_M = meta.get("K_M")
        if K_M is None:
            raise ValueError("record: expected K_M in the metadata to convert current to torque, received none")
        torque = np.asarray(current, dtype=np.float64) * float(K_M)
    T_s = meta.get("T_s")
    t = getattr(record, "t", None)
    if T_s is None and t is not None and len(t) > 1:
        T_s = float(np.median(np.diff(np.asarray(t, dtype=np.float64))))
    return {"speed": getattr(record, "speed", None), "torque": torque, "T_s": T_s,
            "torque_ref": getattr(record, "torque_ref", None), "M_star": meta.get("M_star"),
            "T_Ei": meta.get("T_Ei"), "section": getattr(record, "section", None)}


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
            raise ValueError(f"section: expected section {_NAMES[k - 1]} ({k}) in the column, received none")
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
    min_run = max(20, w.size // 50)
    for ext in (float(np.max(w)), float(np.min(w))):
        at = np.abs(w - ext) <= 1e-9 * max(1.0, abs(ext))
        starts, stops, vals = _runs(at.astype(np.int8))
        for a, b, v in zip(starts, stops, vals):
            if v and b - a >= min_run and abs(ext) > 0.05 * span and np.mean(np.abs(y[a:b])) > 0.3 * ymax:
                raise ValueError(f"speed: expected an unsaturated speed, received {b - a} samples saturated "
                                 f"at {ext:.6g} rad/s under torque")


def detect_sections(
    record: Any = None,
    *,
    speed: Any = None,
    torque: Any = None,
    T_s: float | None = None,
    M_star: float | None = None,
    T_Ei: float | None = None,
    torque_ref: Any = None,
    use_column: bool = False,
    min_run: float = 2e-3,
) -> SectionSplit:
    """Find sections I..VI of a test run.

    Args:
        record: an object with ``speed``, ``current`` or ``torque``, optional ``torque_ref``,
            ``section``, ``t`` and a ``meta`` dict (``K_M``, ``T_s``, ``T_Ei``, ``M_star``), such as
            ``sim.Record``; or ``None`` and the keyword arrays.
        speed: ``(N,)`` measured motor speed [rad/s] (used for consistency checks).
        torque: ``(N,)`` measured torque [Nm] (or current [A]; only the pattern matters).
        T_s: sample time [s].
        M_star: torque amplitude [Nm]; estimated from the data when ``None``.
        T_Ei: current-loop lag [s] for placing boundaries at the step instant (0 when unknown).
        torque_ref: ``(N,)`` ``M_ref`` [Nm]; when given it is classified instead of the torque.
        use_column: take the record's ``section`` column when present (else ignore it).
        min_run: runs of one level shorter than this [s] are transitions and dropped.

    Returns:
        :class:`SectionSplit`.

    Raises:
        ValueError: one line, e.g. constant or saturated speed, no recognisable sections.
    """
    info: dict[str, Any] = {"section": None}
    if record is not None:
        info = _from_record(record)
    for key, val in (("speed", speed), ("torque", torque), ("T_s", T_s), ("M_star", M_star), ("T_Ei", T_Ei),
                     ("torque_ref", torque_ref)):
        if val is not None:
            info[key] = val
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
    Ts = float(Ts)
    n = w.size
    if n < 16:
        raise ValueError(f"detect_sections: expected at least 16 samples, received {n}")
    if use_column and info.get("section") is not None:
        return sections_from_column(info["section"], y, info.get("M_star"))
    _check_speed(w, y)

    ref = info.get("torque_ref")
    if ref is not None:
        ref = as_signal("torque_ref", ref)
        if ref.size != n:
            raise ValueError(f"torque_ref: expected {n} samples, received {ref.size}")
        ys, source, lag = ref, "torque_ref", 0.0
    else:
        ys = median_filter(y, size=5, mode="nearest") if n >= 5 else y
        source = "torque"
        lag = float(info.get("T_Ei") or 0.0) * math.log(2.0) / Ts

    Ms = info.get("M_star")
    estimated = Ms is None
    if estimated:
        a = float(np.percentile(np.abs(ys), 99.0))
        if not a > 0:
            raise ValueError("torque: expected steps between +-M*, +-0.7M* and 0, received a zero torque")
        Ms = float(np.median(np.abs(ys)[np.abs(ys) > 0.85 * a]))
    Ms = float(Ms)
    if not Ms > 0:
        raise ValueError(f"M_star: expected a positive torque amplitude [Nm], received {Ms!r}")

    dist = np.abs(ys[:, None] / Ms - _CLASS_LEVELS[None, :])
    codes = np.argmin(dist, axis=1)
    codes = np.where(np.min(dist, axis=1) <= 0.15, codes, -1)
    starts, stops, vals = _runs(codes)
    keep_len = max(3, int(round(min_run / Ts)))
    stable = [(a, b, v) for a, b, v in zip(starts, stops, vals) if v >= 0 and b - a >= keep_len]
    merged: list[list[int]] = []
    for a, b, v in stable:
        if merged and merged[-1][2] == v:
            merged[-1][1] = b
        else:
            merged.append([a, b, v])
    seq = [m[2] for m in merged]
    hit = -1
    for i in range(len(seq) - 5):
        if seq[i:i + 6] == _PATTERN:
            hit = i
            break
    if hit < 0:
        found = ",".join(f"{_CLASS_LEVELS[v]:+.1f}" for v in seq[:12]) or "none"
        raise ValueError("no recognisable test-signal sections: expected torque levels "
                         f"+1,0,-0.7,-1,0,+0.7 x M* (M*={Ms:.4g}) in order, received {found}")

    def step_at(prev: list[int], nxt: list[int]) -> int:
        """Boundary sample between run ``prev`` and run ``nxt`` (step instant)."""
        lo, hi = prev[1] - 1, nxt[0]
        if source == "torque_ref":
            return int(hi)
        mid = 0.5 * (_CLASS_LEVELS[prev[2]] + _CLASS_LEVELS[nxt[2]]) * Ms
        up = _CLASS_LEVELS[nxt[2]] > _CLASS_LEVELS[prev[2]]
        seg = y[lo:hi + 1]  # raw torque: the median filter would delay small steps
        past = seg >= mid if up else seg <= mid
        j = int(np.argmax(past)) if past.any() else seg.size - 1
        if j == 0:
            tau = float(lo)
        else:
            y0, y1 = seg[j - 1], seg[j]
            frac = (mid - y0) / (y1 - y0) if y1 != y0 else 1.0
            tau = lo + j - 1 + float(np.clip(frac, 0.0, 1.0))
        return int(min(max(math.floor(tau - lag + 0.5), prev[0] + 1), hi))

    runs6 = merged[hit:hit + 6]
    bounds = np.zeros((6, 2), dtype=np.int64)
    if hit > 0:
        bounds[0, 0] = step_at(merged[hit - 1], runs6[0])
    else:
        bounds[0, 0] = 0  # the record starts in section I (its first samples are the torque's rise)
    for k in range(5):
        b = step_at(runs6[k], runs6[k + 1])
        bounds[k, 1] = b
        bounds[k + 1, 0] = b
    flags: list[str] = []
    if hit + 6 < len(merged):
        tail_run = merged[hit + 6]
        b6 = step_at(runs6[5], tail_run)
        tail = (b6, int(tail_run[1]) if tail_run[2] == 2 else b6)
        if tail_run[2] != 2:
            flags.append("no zero-torque tail after VI")
        if hit + 7 < len(merged):
            flags.append("further torque steps after the tail")
    else:
        b6 = int(runs6[5][1])
        tail = (b6, b6)
        flags.append("record ends in section VI (no tail)")
    bounds[5, 1] = b6
    if tail[1] - tail[0] < int(round(0.05 / Ts)) - 2 and tail[1] > tail[0]:
        flags.append("tail shorter than 50 ms")
    if hit > 0:
        flags.append(f"{bounds[0, 0]} samples before section I")

    # consistency with the speed: each section must move the speed in the torque's direction
    for k, (dirn, name) in enumerate(zip((1, 0, -1, -1, 0, 1), _NAMES)):
        a, b = bounds[k]
        dw = w[b - 1] - w[a]
        if dirn and dw * dirn <= 0:
            raise ValueError(f"speed does not follow the torque: expected the speed to "
                             f"{'rise' if dirn > 0 else 'fall'} in section {name}, received a change of {dw:.4g} rad/s")
    lens = bounds[:, 1] - bounds[:, 0]
    if lens[1] >= lens[0] - 2:
        flags.append("II ended by duration")
    if lens[4] >= lens[3] - 2:
        flags.append("V ended by duration")
    levels = np.array([y[a:b].mean() for a, b in bounds])
    return SectionSplit(bounds, (int(tail[0]), int(tail[1])), Ms, estimated, levels, tuple(flags), source, n)
