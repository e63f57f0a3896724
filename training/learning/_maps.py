"""Training the identification maps (:data:`training.identification.MAP_SPECS`) on a dataset."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import som_torch as st
from training.errors import OutputExistsError
from training.identification import (FEATURE_NAMES, FEATURE_VERSION, MAP_SPECS, SUBSETS, TARGETS, MapSpec, TrainedMap,
                                     recall_targets)
from training.learning._dataset import Dataset


@dataclass(frozen=True)
class TrainConfig:
    """How maps are trained (the paper: 40 x 40, online rule, 10 epochs)."""

    rows: int = 40
    cols: int = 40
    topology: str = "rectangular"
    ensemble: int = 4
    epochs: int = 10
    learning_rate: tuple[float, float] = (0.5, 0.01)
    sigma: tuple[float, float] = (8.0, 0.5)
    schedule: str = "asymptotic"
    neighbourhood: str = "gaussian"
    normalization: str = "standard"
    interpolate: int = 4
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.rows, self.cols) < 2 or self.ensemble < 1 or self.epochs < 1:
            raise ValueError(f"TrainConfig: expected rows, cols >= 2, ensemble >= 1, epochs >= 1, received "
                             f"{self.rows} x {self.cols}, {self.ensemble}, {self.epochs}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def training_matrix(spec: MapSpec, dataset: Dataset) -> np.ndarray:
    """``N' x C`` rows of the subset: active features then targets (raw units)."""
    mask = dataset.ok & SUBSETS[spec.subset](dataset.truth)
    cols = [dataset.features[:, FEATURE_NAMES.index(f)] for f in spec.features]
    cols += [TARGETS[t](dataset.truth, dataset.features) for t in spec.targets]
    return np.stack(cols, axis=1)[mask]


def train_map(spec: MapSpec, dataset: Dataset, config: TrainConfig, *, progress: bool = False,
              writer: Any = None, calibration_share: float = 0.1) -> TrainedMap:
    """Train the ensemble of ``spec`` on its subset of ``dataset``; with a TensorBoard ``writer``,
    log QE/TE/learning rate/radius per epoch and U-matrix, hit and parameter maps (tag prefix = map name).

    A seeded ``calibration_share`` of the rows is held out of training: the recall distances of
    those unseen rows give the quantiles against which identification flags records unlike the
    training data (distances of training rows themselves are much smaller: measured 3x)."""
    rows = training_matrix(spec, dataset)
    n_cal = max(5, int(round(calibration_share * rows.shape[0])))
    if rows.shape[0] < n_cal + 10:
        raise ValueError(f"map {spec.name}: expected >= {n_cal + 10} training systems, received {rows.shape[0]}")
    perm = np.random.default_rng(config.seed).permutation(rows.shape[0])
    calibration, rows = rows[perm[:n_cal]], rows[perm[n_cal:]]
    data = torch.as_tensor(rows, dtype=torch.float32).expand(config.ensemble, *rows.shape)  # E x N x C
    active = [True] * len(spec.features) + [False] * len(spec.targets)
    som = st.SOM(st.Grid(config.rows, config.cols, config.topology), spec.components, active,
                 batch_shape=(config.ensemble,))
    hooks = [st.tensorboard_hook(writer, data, prefix=spec.name)] if writer is not None else []
    t0 = time.perf_counter()
    st.fit(som, data, mode="online", init="random", normalization=config.normalization,
           seed=config.seed, epochs=config.epochs, learning_rate=config.learning_rate, sigma=config.sigma,
           schedule=config.schedule, neighbourhood=config.neighbourhood, progress=progress, hooks=hooks)
    seconds = time.perf_counter() - t0
    trained = TrainedMap(spec, som)
    distance = recall_targets(trained, calibration[:, : len(spec.features)], config.interpolate)["distance"]
    trained.metadata = {
        "map": spec.name, "spec": {"features": list(spec.features), "targets": list(spec.targets),
                                   "subset": spec.subset},
        "feature_version": FEATURE_VERSION, "train_config": config.to_dict(),
        "dataset": {"sha256": dataset.sha256, "n": int(dataset.config["n"]), "seed": int(dataset.config["seed"]),
                    "n_used": int(rows.shape[0]), "n_calibration": int(n_cal),
                    "drive": dataset.config["drive"], "signal": dataset.config["signal"]},
        "quality": st.quality_report(som, data), "train_seconds": seconds,
        "distance_quantiles": {q: float(np.quantile(distance, float(q))) for q in ("0.5", "0.95", "0.99")},
    }
    return trained


def save_map(folder: Path, trained: TrainedMap) -> str:
    """Write ``folder/<name>.pt`` atomically; returns its SHA-256."""
    return st.save_checkpoint(folder / f"{trained.spec.name}.pt", trained.som, trained.metadata)


def train_maps(dataset: Dataset, folder: Path, config: TrainConfig, *, logdir: Path | None = None,
               overwrite: bool = False, progress: Callable[[int], None] | None = None) -> dict[str, TrainedMap]:
    """Train every map of :data:`training.identification.MAP_SPECS` on ``dataset``, write each to
    ``folder/<name>.pt`` and then ``folder/manifest.json``; returns the trained maps by name.

    ``logdir``: TensorBoard folder (config and per-map figures); ``progress(1)`` after each map.
    Raises :class:`training.errors.OutputExistsError` where ``folder`` holds maps and not ``overwrite``.
    """
    existing = [n for n in MAP_SPECS if (folder / f"{n}.pt").exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"{folder} already holds maps {existing}; pass --overwrite to replace them")
    folder.mkdir(parents=True, exist_ok=True)
    writer = None
    if logdir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(logdir))
        st.log_config(writer, {"train": config.to_dict(), "dataset": dataset.config, "dataset_sha256": dataset.sha256})
    trained: dict[str, TrainedMap] = {}
    try:
        for name, spec in MAP_SPECS.items():
            trained[name] = train_map(spec, dataset, config, writer=writer)
            save_map(folder, trained[name])
            if progress is not None:
                progress(1)
    finally:
        if writer is not None:
            writer.close()
    st.write_manifest(folder)
    return trained
