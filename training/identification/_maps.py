"""The identification maps: which features each map sees, which parameters it stores, recall.

Each map is a :class:`som_torch.SOM` whose active components are named features
(:data:`training.identification._analysis.FEATURE_NAMES`) and whose inactive components are *targets*:
transformed physical parameters (paper section 3.4). A map is trained as an ensemble of
``E`` maps with different seeds in one batch (``batch_shape = (E,)``); recall takes the median
of the members' interpolated read-outs, which is smoother than one map's quantized answer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

import som_torch as st
from sim import STRUCTURE_CLASSES
from sim._values import shown
from training.identification._analysis import FEATURE_INDEX, FEATURE_NAMES, FEATURE_VERSION, GAP_NAMES
from training.identification._envelope import FILE_NAME as ENVELOPE_FILE

_HARM = tuple(n for n in FEATURE_NAMES if n.startswith("harm_"))


def _log10(x: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    return np.log10(np.maximum(x, floor))


def _feature(f: np.ndarray, name: str) -> np.ndarray:
    return f[:, FEATURE_INDEX[name]]


#: The parameters stored as corrections to the eq.-1 oscillation fit: parameter -> (its fit feature,
#: the correction component); see :func:`from_correction`.
CORRECTIONS: dict[str, tuple[str, str]] = {"f_e": ("log10_f_fit", "dlog10_f_e"), "V_J": ("log10_V_J_fit", "dlog10_V_J")}


def from_correction(param: str, value: Callable[[str], Any]) -> Any:
    """The parameter ``param`` (a key of :data:`CORRECTIONS`) from its eq.-1 fit and its stored
    correction, each read by ``value(component name)``: ``10^(log10 fit + correction)`` (the inverse
    of its :data:`TARGETS` entry; floats or arrays alike)."""
    fit, correction = CORRECTIONS[param]
    return 10.0 ** (value(fit) + value(correction))


#: Inactive components: name -> transform of (truth columns, feature matrix ``N x F``). Every
#: target the identification reads is dimensionless, so that the record's own scales turn it
#: back into SI units on any drive: ``dlog10_*`` are corrections to the eq.-1 oscillation fit (~0
#: for a linear elastic mechanic, so the fit's precision survives recall, while the map learns
#: how backlash shifts the fit); ``log10_s_star`` is the gap's torque over the test's torque,
#: ``s* = s C_F / M*`` (the record's ``M*`` and ``M_N`` give ``s_N = s* M* / M_N``).
#: ``log10_backlash`` (the width in rad) is stored for the maps' figures only.
TARGETS: dict[str, Callable[[dict[str, np.ndarray], np.ndarray], np.ndarray]] = {
    "log10_f_e": lambda t, f: _log10(t["f_e"]),
    "log10_V_J": lambda t, f: _log10(t["V_J"]),
    **{corr: (lambda t, f, p=p, fit=fit: _log10(t[p]) - _feature(f, fit)) for p, (fit, corr) in CORRECTIONS.items()},
    "d": lambda t, f: t["d"],
    "log10_s_star": lambda t, f: _log10(t["s_N"] * t["M_N"] / t["M_star"], 1e-4),
    "log10_w_e_T_Ei": lambda t, f: _log10(t["w_e_T_Ei"]),
    "log10_r_osc": lambda t, f: _log10(t["r_osc"], 1e-3),
    "log10_backlash": lambda t, f: _log10(t["backlash"], 1e-7),
    **{f"p_{c}": (lambda t, f, i=i: (t["structure"] == i).astype(float)) for i, c in enumerate(STRUCTURE_CLASSES)},
}

#: Training subsets: name -> mask over the dataset's systems (``ok`` is always required).
SUBSETS: dict[str, Callable[[dict[str, np.ndarray]], np.ndarray]] = {
    "all": lambda t: np.ones_like(t["f_e"], dtype=bool),
    "visible": lambda t: t["r_osc"] >= 1.0,  # the elastic mode shows in the measured speed
    "backlash": lambda t: t["s_N"] >= 0.1,
}


@dataclass(frozen=True)
class MapSpec:
    """One map: its active ``features``, inactive ``targets`` and training ``subset``;
    ``local_linear``: trained with a local linear read-out (:func:`som_torch.fit_local_linear`:
    each unit reads its targets as a linear function of the features around its own weights)."""

    name: str
    features: tuple[str, ...]
    targets: tuple[str, ...]
    subset: str = "all"
    local_linear: bool = False

    def __post_init__(self) -> None:
        unknown = [f for f in self.features if f not in FEATURE_NAMES]
        if unknown:
            raise ValueError(f"MapSpec {self.name}: unknown features {unknown}; valid: {list(FEATURE_NAMES)}")
        unknown = [t for t in self.targets if t not in TARGETS]
        if unknown:
            raise ValueError(f"MapSpec {self.name}: unknown targets {unknown}; valid: {sorted(TARGETS)}")
        if self.subset not in SUBSETS:
            raise ValueError(f"MapSpec {self.name}: subset {self.subset!r}; valid: {sorted(SUBSETS)}")

    @property
    def components(self) -> tuple[str, ...]:
        return self.features + self.targets


_FIT = ("log10_f_fit", "log10_V_J_fit", "d_fit", "r2_fit")
_SHAPE = _HARM + ("thd", "log2_f_ratio_zero", "log2_f_ratio_07")
_DRIVE = ("log10_f_T_s", "log10_w_T_Ei", "log10_f_tau", "log10_noise")  # the drive, seen from the oscillation
#: The eigenfrequency histogram's bins (:data:`._features.EIG_NAMES`): many correlated features, each weakly
#: informative and noisy at coarse sampling; a local linear read-out holds their slopes closer to zero.
EIG_BINS = tuple(n for n in FEATURE_NAMES if n.startswith("eig_bin_"))
MAP_SPECS: dict[str, MapSpec] = {
    s.name: s for s in (
        MapSpec("structure", _SHAPE + _FIT + ("log10_osc_quanta",) + _DRIVE + GAP_NAMES,
                ("log10_s_star", "log10_w_e_T_Ei", "log10_r_osc") + tuple(f"p_{c}" for c in STRUCTURE_CLASSES)),
        MapSpec("f_e", _FIT + ("log10_f_peak", "log10_f_zc", "thd", "log2_f_ratio_zero", "log2_f_ratio_07") + _DRIVE
                + EIG_BINS, ("dlog10_f_e", "d"), "visible", local_linear=True),
        MapSpec("V_J", _FIT + ("log10_V_J_amp", "thd", "log10_osc_quanta") + _DRIVE, ("dlog10_V_J",), "visible",
                local_linear=True),
        MapSpec("backlash", _SHAPE + _FIT + ("log10_V_J_amp", "log10_osc_quanta") + _DRIVE + GAP_NAMES,
                ("log10_backlash", "log10_s_star"), "backlash"),
    )
}


#: Every file of a checkpoint folder that :meth:`training.identification.Identifier.load` reads: the
#: maps, then the drive envelope. Its ``manifest.json`` must list each with its SHA-256 (``twomass
#: train`` writes it so); a folder whose manifest leaves one out is refused.
CHECKPOINT_FILES: tuple[str, ...] = tuple(f"{name}.pt" for name in MAP_SPECS) + (ENVELOPE_FILE,)

#: The quantiles of held-out training rows' recall distances that a map's metadata holds; the last
#: is the unit of the distance ratio that flags a record unlike the training data.
DISTANCE_QUANTILES = ("0.5", "0.95", "0.99")


def _json_kind(value: Any) -> str:
    """``value`` named as JSON names it, for an error line (``string 'x'``, ``null``, ``array [1, 2]``)."""
    if value is None:
        return "null"
    kind = {bool: "boolean", int: "number", float: "number", str: "string", list: "array", dict: "object"}.get(
        type(value), type(value).__name__)
    return f"{kind} {shown(value)}"


def _number(value: Any) -> float:
    """A JSON number as a float; NaN for anything else (a boolean too), inf beyond float's range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    try:
        return float(value)
    except OverflowError:
        return math.inf


@dataclass(frozen=True)
class MapMetadata:
    """What identification reads from a map checkpoint's metadata (``twomass train`` writes it),
    checked in one place when the map is loaded: ``spec`` (``map`` and ``spec``: the map's name,
    features, targets, subset), ``interpolate`` (``train_config``'s: the units averaged at recall,
    1 .. the map's units) and ``distance_quantiles`` (:data:`DISTANCE_QUANTILES`, finite and
    positive); ``feature_version`` must be this toolkit's :data:`FEATURE_VERSION`, ``dataset`` and
    ``quality`` (the training data and the maps' quality, shown by ``twomass inspect`` and
    ``train``) objects. A wrong entry is a :class:`som_torch.CheckpointError` naming the file and
    the entry."""

    spec: MapSpec
    interpolate: int
    distance_quantiles: dict[str, float]

    @property
    def distance_unit(self) -> float:
        """The unit of a recall's distance ratio: the last of :data:`DISTANCE_QUANTILES` (finite, positive)."""
        return self.distance_quantiles[DISTANCE_QUANTILES[-1]]

    @classmethod
    def from_dict(cls, meta: Mapping[str, Any], where: str | Path, n_units: int) -> "MapMetadata":
        """Check ``meta`` (a map checkpoint's metadata; ``where``: its file; ``n_units``: its map's)."""
        def bad(entry: str, expected: str, value: Any) -> st.CheckpointError:
            return st.CheckpointError(f"{where}: metadata {entry}: expected {expected}, received {_json_kind(value)}")

        def get(obj: Mapping[str, Any], key: str, entry: str) -> Any:
            if key not in obj:
                raise st.CheckpointError(f"{where}: metadata {entry}: missing (`twomass train` writes it)")
            return obj[key]

        def obj(value: Any, entry: str) -> Mapping[str, Any]:
            if not isinstance(value, dict):
                raise bad(entry, "an object", value)
            return value

        def names(value: Any, entry: str) -> tuple[str, ...]:
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise bad(entry, "an array of names", value)
            return tuple(value)

        if meta.get("feature_version") != FEATURE_VERSION:
            raise st.CheckpointError(f"{where}: trained on features {meta.get('feature_version')!r}, "
                                     f"this toolkit computes {FEATURE_VERSION!r}; retrain with `twomass train`")
        name = get(meta, "map", "map")
        if not isinstance(name, str):
            raise bad("map", "a map name", name)
        spec = obj(get(meta, "spec", "spec"), "spec")
        features = names(get(spec, "features", "spec.features"), "spec.features")
        targets = names(get(spec, "targets", "spec.targets"), "spec.targets")
        subset = get(spec, "subset", "spec.subset")
        if not isinstance(subset, str):
            raise bad("spec.subset", "a subset name", subset)
        try:
            map_spec = MapSpec(name, features, targets, subset)
        except ValueError as err:  # unknown features, targets or subset
            raise st.CheckpointError(f"{where}: metadata spec: {err}") from None
        train_config = obj(get(meta, "train_config", "train_config"), "train_config")
        k = get(train_config, "interpolate", "train_config.interpolate")
        if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= n_units:
            raise bad("train_config.interpolate", f"a whole number of units 1 .. {n_units}", k)
        quantiles = obj(get(meta, "distance_quantiles", "distance_quantiles"), "distance_quantiles")
        distances = {q: _number(get(quantiles, q, f"distance_quantiles.{q}")) for q in DISTANCE_QUANTILES}
        for q, v in distances.items():
            if not (math.isfinite(v) and v > 0):
                raise bad(f"distance_quantiles.{q}", "a finite positive distance", quantiles[q])
        for entry in ("dataset", "quality"):
            obj(get(meta, entry, entry), entry)
        return cls(map_spec, k, distances)


@dataclass
class TrainedMap:
    """A trained ensemble with the metadata that makes its checkpoint self-contained."""

    spec: MapSpec
    som: st.SOM
    metadata: dict[str, Any] = field(default_factory=dict)


def recall_targets(trained: TrainedMap, features: np.ndarray, interpolate: int,
                   local: bool = True) -> dict[str, np.ndarray]:
    """Median over the ensemble of the interpolated read-out of each target (``M`` per target),
    plus ``"distance"``: the median best-match distance (``M``); ``local=False``: the units' own
    weights, not their local linear read-out (:func:`som_torch.recall`)."""
    feats = torch.as_tensor(np.asarray(features, dtype=np.float64), dtype=torch.float32)  # M x n_active
    r = st.recall(trained.som, feats, interpolate=interpolate, local=local)  # values: E x M x C
    out = {t: r.values[..., trained.spec.components.index(t)].median(0).values.double().numpy()
           for t in trained.spec.targets}
    out["distance"] = r.distance.median(0).values.double().numpy()
    return out


def load_map(path: Path) -> TrainedMap:
    """Load one map checkpoint (safe loading; version, hash, finite weights and :class:`MapMetadata`
    checked). The file ``<name>.pt`` must hold the map ``name`` of :data:`MAP_SPECS` with its
    features and targets, as the map's components: a map saved under another map's name is
    refused here, not at its first recall."""
    som, meta = st.load_checkpoint(path)
    spec = MapMetadata.from_dict(meta, path, som.grid.n_units).spec
    expected = MAP_SPECS.get(Path(path).stem)
    if expected is None or spec.name != expected.name or spec.components != expected.components:
        raise st.CheckpointError(f"{path}: holds the map {spec.name!r} ({len(spec.features)} features, targets "
                                 f"{list(spec.targets)}), expected the map {Path(path).stem!r} of {sorted(MAP_SPECS)} "
                                 "with its own features and targets; retrain with `twomass train`")
    active = [True] * len(spec.features) + [False] * len(spec.targets)
    if tuple(som.component_names) != spec.components or not bool((som.active == torch.tensor(active)).all()):
        raise st.CheckpointError(f"{path}: the map's components {som.component_names} are not its metadata's "
                                 f"features (active) and targets {list(spec.components)}")
    return TrainedMap(spec, som, meta)
