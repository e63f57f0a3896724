"""A trained map's figures into TensorBoard: coloured planes with colorbars instead of raw arrays."""

from __future__ import annotations

from typing import Any

import torch

import som_torch as st
from training.figures._planes import map_figure, map_figure_names
from training.figures._style import figure_image, plots_available
from training.identification import TrainedMap


def log_map_figures(writer: Any, trained: TrainedMap, data: torch.Tensor | None, step: int, *,
                    member: int = 0) -> bool:
    """Log :func:`training.figures.map_figures` of ``trained`` (ensemble member ``member``) as
    images ``<map>/map_<member>/figure/<name>`` at ``step``. Without matplotlib, log
    :func:`som_torch.log_images`'s grey arrays instead and return False."""
    if not plots_available():
        st.log_images(writer, trained.som, data, step, prefix=trained.spec.name)
        return False
    for name in map_figure_names(trained, hits=data is not None):  # one figure at a time
        image = figure_image(map_figure(trained, name, data, member=member))
        writer.add_image(f"{trained.spec.name}/map_{member}/figure/{name}", image, step, dataformats="HWC")
    writer.flush()
    return True
