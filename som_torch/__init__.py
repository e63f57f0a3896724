"""Tensorized self-organizing maps: many maps in parallel, masked inactive components.

Domain-free: weights ``*batch x U x C``; components are named; an active mask picks those used
for the best match (the others, e.g. physical parameters, are trained and read out).

``CKernel`` / ``CFunction`` / ``CLibrary``: the project's one way to compile, cache and call a
small C kernel with checked tensor arguments (used by the native online rule and by ``sim``).
"""

from ._cbuild import CFunction, CKernel, CLibrary
from ._config import env_threads
from ._checkpoint import (FORMAT_VERSION, CheckpointError, file_sha256, load_checkpoint, save_checkpoint,
                          verify_manifest, write_manifest)
from ._files import atomic_write
from ._grid import TOPOLOGIES, Grid
from ._local import fit_local_linear
from ._init import INITS, init_linear, init_random, initialize, map_seeds
from ._native import available as native_available
from ._options import NEIGHBOURHOODS, SCHEDULES
from ._quality import (degree_of_order, hit_counts, quality_report, quantization_error, topographic_error,
                       u_matrix)
from ._recall import Recall, best_matching_units, distances, recall
from ._som import SOM, LocalLinear
from ._tensorboard import log_config, log_images, log_scalars, tensorboard_hook
from ._train import fit, train_batch, train_online

__all__ = [
    "SOM", "Grid", "TOPOLOGIES",
    "initialize", "init_random", "init_linear", "map_seeds", "INITS",
    "fit", "train_online", "train_batch", "NEIGHBOURHOODS", "SCHEDULES", "native_available",
    "distances", "best_matching_units", "recall", "Recall", "LocalLinear", "fit_local_linear",
    "quantization_error", "topographic_error", "u_matrix", "hit_counts", "degree_of_order", "quality_report",
    "save_checkpoint", "load_checkpoint", "CheckpointError", "FORMAT_VERSION",
    "write_manifest", "verify_manifest", "file_sha256", "atomic_write",
    "log_scalars", "log_images", "log_config", "tensorboard_hook",
    "CKernel", "CFunction", "CLibrary", "env_threads",
]
