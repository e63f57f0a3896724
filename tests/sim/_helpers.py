"""Helpers shared by the simulator tests."""

import torch


class Profile:
    """Open-loop torque reference: ``levels[(k // every) % len]``, the same for every system."""

    def __init__(self, levels: list[float], every: int):
        self.levels, self.every = levels, every

    def reset(self, batch_shape):
        self.shape = tuple(batch_shape)

    def step(self, k, w_meas):
        return torch.full(self.shape, float(self.levels[(k // self.every) % len(self.levels)]))
