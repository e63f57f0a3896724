"""Map making: population -> simulated test runs -> dataset of features and truths -> trained maps."""

from ._dataset import Dataset, GenerateConfig, generate, load_dataset
from ._maps import TrainConfig, save_map, train_map, training_matrix

__all__ = ["GenerateConfig", "Dataset", "generate", "load_dataset", "TrainConfig", "train_map", "training_matrix",
           "save_map"]
