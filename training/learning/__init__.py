"""Map making: population -> simulated test runs -> dataset of features and truths -> trained maps."""

from ._confidence import (CALIBRATION_SEEDS, CalibrationSample, calibration_tasks, fit_calibration, load_samples,
                          save_samples, task_samples)
from ._dataset import ESTIMATE_NAMES, TRUTH_NAMES, Dataset, GenerateConfig, generate, load_dataset, rejection_reasons
from ._maps import TRAIN_MODES, TrainConfig, local_ridges, save_map, train_map, train_maps, training_matrix

__all__ = ["CALIBRATION_SEEDS", "CalibrationSample", "calibration_tasks", "fit_calibration", "load_samples",
           "save_samples", "task_samples","GenerateConfig", "Dataset", "generate", "load_dataset", "rejection_reasons", "TRUTH_NAMES", "ESTIMATE_NAMES", "TrainConfig",
           "TRAIN_MODES", "local_ridges", "train_map", "train_maps", "training_matrix", "save_map"]
