"""Training the identification maps (:data:`training.identification.MAP_SPECS`) on a dataset."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import som_torch as st
from training._distributed import CallRecorder, Group, process_group
from training.errors import OutputExistsError
from training.figures import log_map_figures
from training.identification import (CHECKPOINT_FILES, DISTANCE_QUANTILES, EIG_BINS, ENVELOPE_FILE, FEATURE_NAMES,
                                     FEATURE_VERSION, MAP_SPECS, SUBSETS, TARGETS, MapSpec, TrainedMap, load_map,
                                     recall_targets, trained_envelope)
from training.learning._dataset import Dataset


#: Training rules: the paper's online rule (ensemble members dealt out to the ranks under torchrun)
#: and the batch SOM (data-parallel under torchrun: the ranks' sums all-reduced).
TRAIN_MODES = {"online": "the paper's online rule (eq. 3)", "batch": "batch SOM, neighbourhood-weighted means"}


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
    mode: str = "online"
    local_radius: float = 1.5  # maps with a local linear read-out (MapSpec.local_linear): som_torch.fit_local_linear
    local_ridge: float = 1e-3
    local_ridge_bins: float = 0.1  # on the slopes of the eigenfrequency bins (EIG_BINS): see local_ridges

    def __post_init__(self) -> None:
        if min(self.rows, self.cols) < 2 or self.ensemble < 1 or self.epochs < 1:
            raise ValueError(f"TrainConfig: expected rows, cols >= 2, ensemble >= 1, epochs >= 1, received "
                             f"{self.rows} x {self.cols}, {self.ensemble}, {self.epochs}")
        if self.mode not in TRAIN_MODES:
            raise ValueError(f"TrainConfig: mode: expected one of {list(TRAIN_MODES)}, received {self.mode!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def training_matrix(spec: MapSpec, dataset: Dataset) -> np.ndarray:
    """``N' x C`` rows of the subset: active features then targets (raw units)."""
    mask = dataset.ok & SUBSETS[spec.subset](dataset.truth)
    cols = [dataset.features[:, FEATURE_NAMES.index(f)] for f in spec.features]
    cols += [TARGETS[t](dataset.truth, dataset.features) for t in spec.targets]
    return np.stack(cols, axis=1)[mask]


def _split_rows(spec: MapSpec, dataset: Dataset, config: TrainConfig,
                calibration_share: float) -> tuple[np.ndarray, np.ndarray]:
    """The subset's rows split by a seeded permutation into ``(training, calibration)``."""
    rows = training_matrix(spec, dataset)
    n_cal = max(5, int(round(calibration_share * rows.shape[0])))
    if rows.shape[0] < n_cal + 10:
        raise ValueError(f"map {spec.name}: expected >= {n_cal + 10} training systems, received {rows.shape[0]}")
    perm = np.random.default_rng(config.seed).permutation(rows.shape[0])
    return rows[perm[n_cal:]], rows[perm[:n_cal]]


def _new_som(spec: MapSpec, config: TrainConfig, maps: int, device: str | torch.device) -> st.SOM:
    active = [True] * len(spec.features) + [False] * len(spec.targets)
    return st.SOM(st.Grid(config.rows, config.cols, config.topology), spec.components, active,
                  batch_shape=(maps,)).to(device)


#: Training rows on which TensorBoard's per-epoch quantization and topographic errors are measured
#: (a seeded sample where there are more: their cost stays flat in the data size; the quality in
#: the checkpoint is measured on every row).
MONITOR_ROWS = 4096


def _monitor_rows(data: torch.Tensor, seed: int) -> torch.Tensor:
    """``data`` (``*batch x N x C``), or a seeded sample of :data:`MONITOR_ROWS` of its rows."""
    N = data.shape[-2]
    if N <= MONITOR_ROWS:
        return data
    pick = torch.randperm(N, generator=torch.Generator().manual_seed(seed))[:MONITOR_ROWS].sort().values
    return data[..., pick, :]


def _train_online(spec: MapSpec, rows: np.ndarray, config: TrainConfig, members: list[int], *, progress: bool,
                  writer: Any, device: str | torch.device) -> st.SOM:
    """Ensemble members ``members`` of ``spec`` (member ``b`` seeded ``config.seed + b``), online rule."""
    data = torch.as_tensor(rows, dtype=torch.float32)  # N x C
    som = _new_som(spec, config, len(members), device)
    hooks = ([st.tensorboard_hook(writer, _monitor_rows(data, config.seed).to(device), prefix=spec.name,
                                  images_every=0, members=members)] if writer is not None else [])
    st.fit(som, data.expand(len(members), *data.shape), mode="online", init="random",
           normalization=config.normalization, seed=[config.seed + b for b in members], epochs=config.epochs,
           learning_rate=config.learning_rate, sigma=config.sigma, schedule=config.schedule,
           neighbourhood=config.neighbourhood, progress=progress, hooks=hooks)
    return som.to("cpu")


def _train_batch(spec: MapSpec, rows: np.ndarray, config: TrainConfig, group: Group, *, progress: bool,
                 writer: Any, device: str | torch.device) -> st.SOM:
    """The whole ensemble of ``spec`` with the batch SOM; under torchrun data-parallel: each rank
    sums over its block of the rows, the sums are all-reduced (float64)."""
    data = torch.as_tensor(rows, dtype=torch.float32).expand(config.ensemble, *rows.shape)  # E x N x C
    som = _new_som(spec, config, config.ensemble, device)
    som.fit_normalization(data, config.normalization)
    st.initialize(som, data, "random", config.seed)
    share = group.block(rows.shape[0])
    hooks = ([st.tensorboard_hook(writer, _monitor_rows(data, config.seed).to(device), prefix=spec.name,
                                 images_every=0)]
             if writer is not None and group.main else [])
    st.train_batch(som, data[:, share.start:share.stop], epochs=config.epochs, sigma=config.sigma,
                   schedule=config.schedule, neighbourhood=config.neighbourhood, progress=progress, hooks=hooks,
                   reduce=group.all_reduce_sum if group.distributed else None)
    return som.to("cpu")


def _assemble(parts: list[tuple[list[int], st.SOM | None, float]], ensemble: int) -> tuple[st.SOM, float]:
    """The ensemble from the ranks' ``(members, maps, seconds)``; the seconds summed."""
    som = next(m for _, m, _ in parts if m is not None)
    weights = torch.empty(ensemble, som.n_units, som.n_components, dtype=som.weights.dtype)  # E x U x C
    offset, scale = (torch.empty(ensemble, som.n_components, dtype=torch.float64) for _ in range(2))  # E x C
    for members, part, _ in parts:
        if part is not None:
            weights[members], offset[members], scale[members] = part.weights, part.offset, part.scale
    whole = st.SOM(som.grid, som.component_names, som.active[:1].expand(ensemble, -1), weights=weights,
                   offset=offset, scale=scale, dtype=weights.dtype)
    return whole, sum(t for _, _, t in parts)


def local_ridges(spec: MapSpec, config: TrainConfig) -> list[float]:
    """The local linear read-out's ridge per feature of ``spec``: ``local_ridge_bins`` on the 25
    eigenfrequency bins, ``local_ridge`` on the rest. Held-out training rows alone prefer the small
    ridge everywhere, but with it on the bins the ``f_e`` map reads one in eight elastic records of a
    corner of the envelope (1 ms, 2^13 counts: each bin noisier, 25 correlated slopes adding up)
    1.3-2.5x too high (docs/results.md, "The bins' own ridge")."""
    return [config.local_ridge_bins if name in EIG_BINS else config.local_ridge for name in spec.features]


def train_map(spec: MapSpec, dataset: Dataset, config: TrainConfig, *, progress: bool = False,
              writer: Any = None, calibration_share: float = 0.1, device: str | torch.device = "cpu") -> TrainedMap:
    """Train the ensemble of ``spec`` on its subset of ``dataset``; with a TensorBoard ``writer``,
    log QE/TE/learning rate/radius per epoch and, after the last, the figures of
    :func:`training.figures.map_figures`: U-matrix, hit map, parameter maps, contour plot (tag prefix = map name).

    A seeded ``calibration_share`` of the rows is held out of training: the recall distances of
    those unseen rows give the quantiles against which identification flags records unlike the
    training data (distances of training rows themselves are much smaller: measured 3x).

    ``device``: where the maps train (``"cuda"``: the torch path on the GPU; the C kernel is CPU only).
    Under torchrun every rank calls it and gets the same map: the online rule deals the ensemble
    members out to the ranks (member ``b`` to rank ``b mod world``; each is trained exactly as in
    one process) and gathers them; the batch SOM all-reduces its sums over the ranks' rows. Only
    rank 0 writes to ``writer`` (the other ranks' log calls are sent to it)."""
    group = process_group()
    rows, calibration = _split_rows(spec, dataset, config, calibration_share)
    if not group.main and writer is not None:
        writer = CallRecorder()
    t0 = time.perf_counter()
    if config.mode == "batch":
        som = _train_batch(spec, rows, config, group, progress=progress, writer=writer, device=device)
        seconds = time.perf_counter() - t0
    else:
        members = group.strided(list(range(config.ensemble)))
        part = (_train_online(spec, rows, config, members, progress=progress, writer=writer, device=device)
                if members else None)
        calls = writer.take() if isinstance(writer, CallRecorder) else []
        parts = group.all_gather((members, part, time.perf_counter() - t0, calls))
        if group.main and writer is not None:
            for *_, recorded in parts:
                CallRecorder.replay(recorded, writer)
        som, seconds = _assemble([p[:3] for p in parts], config.ensemble)
    if spec.local_linear:
        som = st.fit_local_linear(som, torch.as_tensor(rows), radius=config.local_radius,
                                  ridge=local_ridges(spec, config))
    data = torch.as_tensor(rows, dtype=torch.float32).expand(config.ensemble, *rows.shape)  # E x N x C
    trained = TrainedMap(spec, som)
    distance = recall_targets(trained, calibration[:, : len(spec.features)], config.interpolate)["distance"]
    trained.metadata = {
        "map": spec.name, "spec": {"features": list(spec.features), "targets": list(spec.targets),
                                   "subset": spec.subset},
        "feature_version": FEATURE_VERSION, "train_config": config.to_dict(),
        "dataset": {"sha256": dataset.sha256, "n": int(dataset.config["n"]), "seed": int(dataset.config["seed"]),
                    "n_used": int(rows.shape[0]), "n_calibration": int(calibration.shape[0]),
                    "drive": dataset.config["drive"], "signal": dataset.config["signal"],
                    "ranges": dataset.config["ranges"], "envelope": dataset.config.get("envelope")},
        "quality": st.quality_report(som, data), "train_seconds": seconds,
        "distance_quantiles": {q: float(np.quantile(distance, float(q))) for q in DISTANCE_QUANTILES},
    }
    if writer is not None and group.main:  # the finished map's figures (the epochs log scalars only)
        log_map_figures(writer, trained, data, config.epochs)
    return trained


#: Metadata that differs between identical runs: kept in memory, not written (identical runs, identical files).
_VOLATILE = ("train_seconds",)


def save_map(folder: Path, trained: TrainedMap) -> str:
    """Write ``folder/<name>.pt`` atomically (without the :data:`_VOLATILE` metadata); returns its SHA-256."""
    metadata = {k: v for k, v in trained.metadata.items() if k not in _VOLATILE}
    return st.save_checkpoint(folder / f"{trained.spec.name}.pt", trained.som, metadata)


def _resumable(folder: Path, name: str, config: TrainConfig, dataset: Dataset) -> bool:
    """Whether ``folder/<name>.pt`` is a map an interrupted run of ``config`` on ``dataset`` finished."""
    try:
        meta = load_map(folder / f"{name}.pt").metadata
    except (ValueError, OSError):
        return False
    return (meta.get("map") == name and meta.get("train_config") == json.loads(json.dumps(config.to_dict()))
            and meta.get("dataset", {}).get("sha256") == dataset.sha256)


def _check_folder(folder: Path, overwrite: bool, config: TrainConfig, dataset: Dataset) -> list[str]:
    """The maps already finished in ``folder`` by an interrupted run (no manifest yet) of the same
    config on the same dataset (resumed, not retrained); other maps there are refused unless ``overwrite``."""
    existing = [n for n in MAP_SPECS if (folder / f"{n}.pt").exists()]
    manifest = (folder / "manifest.json").exists()  # a finished run wrote its manifest
    interrupted = not overwrite and not manifest
    finished = [n for n in existing if _resumable(folder, n, config, dataset)] if interrupted else []
    foreign = [n for n in existing if n not in finished]
    if foreign and not overwrite:
        why = "of a finished training run (manifest.json)" if manifest else "from another config or dataset"
        raise OutputExistsError(f"{folder} already holds maps {foreign} ({why}); pass --overwrite to replace them")
    folder.mkdir(parents=True, exist_ok=True)
    return finished


def train_maps(dataset: Dataset, folder: Path, config: TrainConfig, *, logdir: Path | None = None,
               overwrite: bool = False, progress: Callable[[int], None] | None = None,
               device: str | torch.device = "cpu", epoch_progress: bool = False) -> dict[str, TrainedMap]:
    """Train every map of :data:`training.identification.MAP_SPECS` on ``dataset``, write each to
    ``folder/<name>.pt``, then ``folder/envelope.json`` (SPEC 3.1's envelope and the drive and test
    ranges the dataset covered) and ``folder/manifest.json``; returns the trained maps by name.

    ``logdir``: TensorBoard folder (config and per-map figures); ``progress(1)`` after each map;
    ``epoch_progress``: a progress bar per map over its epochs (on stderr, rank 0).
    Resumable: maps that an interrupted run of the same ``config`` on the same dataset left in
    ``folder`` are loaded, not retrained. Raises :class:`training.errors.OutputExistsError` where
    ``folder`` holds other maps and not ``overwrite``.
    Under torchrun every rank trains its share (see :func:`train_map`) and returns the same maps;
    rank 0 alone checks the folder, writes the checkpoints and the TensorBoard logs and calls ``progress``.
    """
    group = process_group()
    finished = group.on_main(lambda: _check_folder(folder, overwrite, config, dataset))
    writer = None
    if logdir is not None and group.main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(logdir))
        st.log_config(writer, {"train": config.to_dict(), "dataset": dataset.config, "dataset_sha256": dataset.sha256})
    elif logdir is not None:
        writer = CallRecorder()
    trained: dict[str, TrainedMap] = {}
    try:
        for name, spec in MAP_SPECS.items():
            if name in finished:  # resumed: an interrupted run of this config on this dataset made it
                trained[name] = load_map(folder / f"{name}.pt")
            else:
                trained[name] = train_map(spec, dataset, config, writer=writer, device=device,
                                          progress=epoch_progress and group.main)
                if group.main:
                    save_map(folder, trained[name])
            if group.main and progress is not None:
                progress(1)
    finally:
        if writer is not None:
            writer.close()
    if group.main:  # what the maps were trained on, beside them (checked against every record)
        trained_envelope(trained["structure"].metadata).write(folder / ENVELOPE_FILE)
        # every file the maps are loaded from, and only those: files the user keeps in the folder are not the maps'
        st.write_manifest(folder, files=CHECKPOINT_FILES)
    return trained
