"""TensorBoard helpers: scalars (QE, TE, radius, learning rate), images (U-matrix, hit map,
each parameter map) and the configuration, for any ``SummaryWriter``-like writer."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import torch

from ._quality import hit_counts, quantization_error, topographic_error, u_matrix
from ._som import SOM


def _suffixes(som: SOM, members: Sequence[int] | None = None) -> list[str]:
    """Tag suffix of each map of the batch: ``/map_<b>`` (``b`` from ``members`` where given: the
    maps' numbers in a larger ensemble), none for a single map."""
    B = som.batch_shape.numel()
    if members is not None and len(members) != B:
        raise ValueError(f"members: expected {B} numbers (one per map), received {len(members)}")
    if not som.batch_shape:
        return [""]
    return [f"/map_{b}" for b in (members if members is not None else range(B))]


def _image(x: torch.Tensor) -> torch.Tensor:
    """``rows x cols`` -> ``1 x rows x cols`` scaled to [0, 1] (CHW)."""
    x = x.to(torch.float64)
    x = torch.where(torch.isfinite(x), x, 0.0)
    lo, hi = x.min(), x.max()
    return ((x - lo) / (hi - lo) if hi > lo else torch.zeros_like(x)).unsqueeze(0).float()


def log_config(writer, config: dict[str, Any], tag: str = "config") -> None:
    """The configuration as JSON text (``tag``)."""
    writer.add_text(tag, "```\n" + json.dumps(config, indent=2, sort_keys=True, default=str) + "\n```", 0)


def log_scalars(writer, som: SOM, data: torch.Tensor | None, step: int, *, learning_rate=None, sigma=None,
                prefix: str = "som", members: Sequence[int] | None = None) -> None:
    """Tags ``{prefix}[/map_b]/quantization_error``, ``.../topographic_error`` (if ``data``),
    ``.../learning_rate``, ``.../sigma`` (if given; float or ``*batch``); ``members``: the maps'
    numbers ``b`` (default ``0 .. B-1``)."""
    values: dict[str, torch.Tensor] = {}
    if data is not None:
        values["quantization_error"] = quantization_error(som, data)
        if som.n_units > 1:
            values["topographic_error"] = topographic_error(som, data)
    for name, v in (("learning_rate", learning_rate), ("sigma", sigma)):
        if v is not None:
            values[name] = torch.as_tensor(v, dtype=torch.float64).expand(som.batch_shape)
    for b, sfx in enumerate(_suffixes(som, members)):
        for name, v in values.items():
            writer.add_scalar(f"{prefix}{sfx}/{name}", float(v.reshape(-1)[b]), step)


def log_images(writer, som: SOM, data: torch.Tensor | None, step: int, *, prefix: str = "som",
               components: list[str] | None = None, members: Sequence[int] | None = None) -> None:
    """Grey images ``{prefix}[/map_b]/u_matrix``, ``.../hits`` (if ``data``) and
    ``.../component/<name>`` for ``components`` (default: each inactive component of map 0);
    ``members``: the maps' numbers ``b`` (default ``0 .. B-1``)."""
    B, C = som.batch_shape.numel(), som.n_components
    um = u_matrix(som).reshape(B, som.grid.rows, som.grid.cols)
    hits = hit_counts(som, data).reshape(B, som.grid.rows, som.grid.cols) if data is not None else None
    if components is None:
        components = [n for n, a in zip(som.component_names, som.active.reshape(B, C)[0].tolist()) if not a]
    w = som.raw_weights.reshape(B, som.grid.rows, som.grid.cols, C)
    for b, sfx in enumerate(_suffixes(som, members)):
        writer.add_image(f"{prefix}{sfx}/u_matrix", _image(um[b]), step)
        if hits is not None:
            writer.add_image(f"{prefix}{sfx}/hits", _image(hits[b]), step)
        for name in components:
            writer.add_image(f"{prefix}{sfx}/component/{name}", _image(w[b, ..., som.index(name)]), step)


def tensorboard_hook(writer, data: torch.Tensor | None, *, prefix: str = "som", images_every: int = 1,
                     members: Sequence[int] | None = None):
    """A training hook (``hook(epoch, som, info)``) that logs scalars each epoch and images every
    ``images_every`` epochs and after the last; the step is the epoch number (1-based);
    ``members``: the maps' numbers in the tags (default ``0 .. B-1``)."""

    def hook(epoch: int, som: SOM, info: dict) -> None:
        log_scalars(writer, som, data, epoch + 1, learning_rate=info.get("learning_rate"),
                    sigma=info.get("sigma"), prefix=prefix, members=members)
        if images_every and ((epoch + 1) % images_every == 0 or epoch + 1 == info.get("epochs")):
            log_images(writer, som, data, epoch + 1, prefix=prefix, members=members)
        writer.flush()

    return hook
