"""Map figures on small maps: cells where the units are, hexagons that tile, colorbar range equal to
the component's range, hit counts, the paper-style planes, TensorBoard images; headless (Agg)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import som_torch as st
from training.figures import (COMPONENT_LABELS, PARAMETER_PLANES, log_map_figures, map_figure, map_figure_names,
                              unit_xy)
from training.identification import MAP_SPECS, TARGETS, TrainedMap

pytest.importorskip("matplotlib")


def _tiny_map(name: str, topology: str, rows: int = 4, cols: int = 5, seed: int = 0) -> tuple[TrainedMap, torch.Tensor]:
    spec = MAP_SPECS[name]
    som = st.SOM(st.Grid(rows, cols, topology), spec.components,
                 [True] * len(spec.features) + [False] * len(spec.targets), batch_shape=(2,))
    g = torch.Generator().manual_seed(seed)
    data = torch.randn(60, len(spec.components), generator=g).expand(2, 60, -1)  # 2 x N x C
    st.initialize(som, data, "random", seed)
    st.train_batch(som, data, epochs=2, sigma=(2.0, 0.5))
    return TrainedMap(spec, som), data


def _cells(fig):
    ax = fig.axes[0]
    return ax, ax.collections[0]


def _area(v: np.ndarray) -> float:
    x, y = v[:, 0], v[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def test_every_stored_component_has_a_label_with_a_unit() -> None:
    assert set(COMPONENT_LABELS) == set(TARGETS)
    assert all(label.endswith("]") and "[" in label for label in COMPONENT_LABELS.values())
    assert set(PARAMETER_PLANES) == set(MAP_SPECS)


@pytest.mark.parametrize("topology", ["hexagonal", "rectangular"])
def test_component_plane_cells_and_colorbar_range(topology: str) -> None:
    trained, _ = _tiny_map("f_e", topology)
    fig = map_figure(trained, "component/d")
    ax, cells = _cells(fig)
    w = trained.som.raw_weights[0, :, trained.som.index("d")].numpy()  # member 0, independent of the figure code
    np.testing.assert_allclose(cells.get_array(), w)
    assert cells.norm.vmin == pytest.approx(w.min()) and cells.norm.vmax == pytest.approx(w.max())
    bar = cells.colorbar
    assert bar is not None and bar.ax.get_ylabel() == "damping d [-]"
    assert ax.get_xlabel() == "map column" and ax.get_ylabel() == "map row"
    # each cell is centred on its unit; hexagons (6 corners) and squares (4) of the grid's own area
    corners, area = (6, math.sqrt(3.0) / 2.0) if topology == "hexagonal" else (4, 1.0)
    grid = trained.som.grid
    for u, path in enumerate(cells.get_paths()):
        v = path.vertices[:corners]
        assert len(np.unique(np.round(v, 9), axis=0)) == corners
        assert _area(v) == pytest.approx(area)
        r, c = divmod(u, grid.cols)
        x = c + (0.5 * (r % 2) if topology == "hexagonal" else 0.0)
        y = r * (math.sqrt(3.0) / 2.0 if topology == "hexagonal" else 1.0)
        np.testing.assert_allclose(v.mean(0), [x, y], atol=1e-12)
    # the row ticks name the rows at their own heights
    assert [t.get_text() for t in ax.get_yticklabels()] == [str(r) for r in range(grid.rows)]


def test_hit_map_counts_each_row_once() -> None:
    trained, data = _tiny_map("V_J", "hexagonal")
    fig = map_figure(trained, "hits", data)
    _, cells = _cells(fig)
    hits = cells.get_array()
    assert hits.sum() == data.shape[1]
    units, _ = st.best_matching_units(trained.som[0], data[0])
    np.testing.assert_array_equal(hits, np.bincount(units.numpy(), minlength=trained.som.n_units))
    assert cells.colorbar.ax.get_ylabel() == "training records per unit [-]"


def test_paper_plane_is_fit_plus_correction_on_a_log_colorbar_with_contours() -> None:
    trained, _ = _tiny_map("f_e", "rectangular", rows=6, cols=6)
    w = trained.som.raw_weights[0]
    f_e = 10.0 ** (w[:, trained.som.index("log10_f_fit")] + w[:, trained.som.index("dlog10_f_e")]).numpy()
    fig = map_figure(trained, "contour/f_e")
    ax, cells = _cells(fig)
    np.testing.assert_allclose(cells.get_array(), f_e)
    assert cells.norm.vmin == pytest.approx(f_e.min()) and cells.norm.vmax == pytest.approx(f_e.max())
    assert cells.colorbar.ax.get_ylabel() == "eigenfrequency f_e [Hz]"
    assert "lines of constant f_e" in ax.get_title()
    levels = [float(t.get_text()) for t in ax.texts]  # the contour labels: round values inside the range
    assert levels and all(f_e.min() < v < f_e.max() for v in levels)
    assert all(round(v / 10 ** math.floor(math.log10(v)), 9) in (1.0, 2.0, 5.0) for v in levels)


def test_map_figures_names_and_bad_name() -> None:
    trained, _ = _tiny_map("structure", "rectangular")
    assert map_figure_names(trained, hits=True) == (["u_matrix", "hits"] + [f"component/{t}" for t in
                                                                           MAP_SPECS["structure"].targets]
                                                    + ["contour/s_N"])
    with pytest.raises(ValueError, match="expected one of"):
        map_figure(trained, "component/no_such")
    with pytest.raises(ValueError, match="training rows"):
        map_figure(trained, "hits")


class _Writer:
    def __init__(self) -> None:
        self.images: dict[str, tuple[np.ndarray, int, str]] = {}

    def add_image(self, tag, image, step, dataformats="CHW") -> None:
        self.images[tag] = (np.asarray(image), step, dataformats)

    def flush(self) -> None:
        pass


def test_tensorboard_gets_coloured_figures_at_a_readable_size() -> None:
    trained, data = _tiny_map("backlash", "hexagonal")
    writer = _Writer()
    assert log_map_figures(writer, trained, data, 7)
    assert sorted(writer.images) == sorted(f"backlash/map_0/figure/{n}" for n in map_figure_names(trained, hits=True))
    for image, step, fmt in writer.images.values():
        assert step == 7 and fmt == "HWC" and image.dtype == np.uint8
        assert image.shape[0] >= 400 and image.shape[1] >= 500 and image.shape[2] == 3
        assert (image[..., 0] != image[..., 2]).any()  # coloured, not grey


def test_unit_xy_is_column_then_row() -> None:
    grid = st.Grid(3, 4, "hexagonal")
    xy = unit_xy(grid)
    np.testing.assert_allclose(xy[4 + 2], [2.5, math.sqrt(3.0) / 2.0])  # row 1, column 2 (odd row shifted)
