"""Map planes: one value per unit drawn on the map's own grid (squares, or hexagons for a
hexagonal grid), with a colorbar in the value's unit, contour lines of constant value (the
paper's Figs. 7-8) and a marked unit.

:data:`PARAMETER_PLANES` names, per identification map, the physical parameter its units store
(``f_e`` of a unit of the ``f_e`` map is its eq.-1 fit frequency times its stored correction,
as the identifier reads it); :func:`map_figures` gives the figures of one trained map: U-matrix,
hit map, each stored component and the paper-style contour plot.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import som_torch as st
from sim import STRUCTURE_CLASSES
from training.figures._style import MARK, new_figure, refuse_existing, save_png, with_unit
from training.identification import TrainedMap, from_correction

#: Label with unit of each stored component (every key of ``training.identification.TARGETS``).
COMPONENT_LABELS: dict[str, str] = {
    "log10_f_e": with_unit("log10 f_e", "log10 Hz"),
    "log10_V_J": with_unit("log10 V_J", "-"),
    "dlog10_f_e": with_unit("correction log10 f_e - log10 f_fit", "decades"),
    "dlog10_V_J": with_unit("correction log10 V_J - log10 V_J,fit", "decades"),
    "d": with_unit("damping d", "-"),
    "log10_s_star": with_unit("log10 s* (backlash torque C_F s over the test's M*)", "-"),
    "log10_w_e_T_Ei": with_unit("log10 w_e T_Ei", "-"),
    "log10_r_osc": with_unit("log10 r_osc (oscillation over speed quantum)", "-"),
    "log10_backlash": with_unit("log10 backlash width 2s", "log10 rad"),
    **{f"p_{c}": with_unit(f"probability of {c}", "-") for c in STRUCTURE_CLASSES},
}


@dataclass(frozen=True)
class ParameterPlane:
    """The physical parameter that the units of one map store: ``label`` with ``unit``, and
    ``log10(units)``: its log10 per unit from the raw weights ``{component: U values}``."""

    map: str
    symbol: str
    label: str
    unit: str
    log10: Callable[[dict[str, np.ndarray]], np.ndarray]

    def values(self, weights: dict[str, np.ndarray]) -> np.ndarray:
        """The parameter per unit (``U``) in :attr:`unit`."""
        return 10.0 ** self.log10(weights)


#: Per map, the parameter its units store (paper Fig. 7: the structure map's ``C_F s``, here
#: normalized as ``s_N``; Fig. 8: ``f_e``). The ``f_e`` and ``V_J`` maps store corrections to the
#: eq.-1 fit (``training.identification.TARGETS``): a unit's value is its fit feature plus its correction.
PARAMETER_PLANES: dict[str, ParameterPlane] = {p.map: p for p in (
    ParameterPlane("structure", "s_N", "normalized backlash s* = C_F s / M* (s_N where M_N = M*)", "-",
                   lambda w: w["log10_s_star"]),
    ParameterPlane("f_e", "f_e", "eigenfrequency f_e", "Hz", lambda w: np.log10(from_correction("f_e", w.__getitem__))),
    ParameterPlane("V_J", "V_J", "inertia ratio V_J = J_L / J_M", "-", lambda w: np.log10(from_correction("V_J", w.__getitem__))),
    ParameterPlane("backlash", "backlash", "backlash width 2s", "rad", lambda w: w["log10_backlash"]),
)}


def unit_weights(trained: TrainedMap, member: int = 0) -> dict[str, np.ndarray]:
    """Raw weights of ensemble member ``member`` by component name (``U`` each)."""
    w = trained.som.raw_weights.reshape(-1, trained.som.n_units, trained.som.n_components)[member]  # U x C
    return {n: w[:, i].numpy() for i, n in enumerate(trained.som.component_names)}


def unit_xy(grid: st.Grid) -> np.ndarray:
    """Unit centres ``U x 2`` in drawing coordinates: ``x`` = column axis, ``y`` = row axis."""
    return grid.coords.numpy()[:, ::-1].copy()


def _cells(grid: st.Grid) -> np.ndarray:
    """Cell outlines ``U x V x 2``: unit squares, or hexagons that tile the hexagonal grid
    (neighbours 1 apart: pointy-top hexagons of circumradius ``1/sqrt(3)``)."""
    if grid.topology == "hexagonal":
        angles = np.radians(30.0 + 60.0 * np.arange(6))
        shape = np.stack([np.cos(angles), np.sin(angles)], axis=1) / math.sqrt(3.0)  # 6 x 2
    else:
        shape = 0.5 * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return unit_xy(grid)[:, None, :] + shape[None]


def _levels_125(lo: float, hi: float, most: int = 9) -> list[float]:
    """Round values (1, 2, 5 x 10^k; decades only where those are more than ``most``) inside ``(lo, hi)``."""
    if not (lo > 0 and hi > lo):
        return []
    decades = range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
    for mantissas in ((1.0, 2.0, 5.0), (1.0,)):
        levels = [m * 10.0 ** k for k in decades for m in mantissas if lo < m * 10.0 ** k < hi]
        if len(levels) <= most:
            return levels
    return levels[:: math.ceil(len(levels) / most)]


def draw_plane(ax: Any, grid: st.Grid, values: np.ndarray, *, label: str, log: bool = False,
               contours: bool = False, mark: int | None = None, mark_label: str = "best match",
               cmap: str = "viridis") -> Any:
    """Draw ``values`` (``U``, one per unit) on ``grid`` in ``ax``: coloured cells, a colorbar
    labelled ``label`` spanning exactly the values' range (log scale with ``log``), contour lines
    of constant value at round values (``contours``), and a star on unit ``mark``. Row 0 is on
    top, as in an image of the map. Returns the colorbar."""
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import LogNorm, Normalize

    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.shape != (grid.n_units,):
        raise ValueError(f"values: expected {grid.n_units} (one per unit), received {values.shape}")
    finite = values[np.isfinite(values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if log:
        lo, hi = (lo, hi) if hi > lo else (lo / 2.0, lo * 2.0)
        norm = LogNorm(lo, hi)
    else:
        norm = Normalize(lo, hi) if hi > lo else Normalize(lo - 0.5, hi + 0.5)
    cells = PolyCollection(_cells(grid), array=values, cmap=cmap, norm=norm, edgecolors="face", linewidths=0.2)
    cells.set_in_layout(False)  # inside the axes limits; its many paths would only slow the layout
    ax.add_collection(cells)
    xy = unit_xy(grid)
    pad = 0.7
    ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
    ax.set_ylim(xy[:, 1].max() + pad, xy[:, 1].min() - pad)  # row 0 on top
    ax.set_aspect("equal")
    step = max(1, math.ceil(grid.rows / 8))  # ticks at the rows' own heights (hexagonal rows lie sqrt(3)/2 apart)
    ax.set_yticks(xy[:: grid.cols * step, 1], [str(r) for r in range(0, grid.rows, step)])
    ax.set_xlabel("map column")
    ax.set_ylabel("map row")
    bar = ax.figure.colorbar(cells, ax=ax, label=label, shrink=0.9)
    if contours and finite.size == values.size and hi > lo:
        levels = _levels_125(lo, hi) if log else list(np.linspace(lo, hi, 7)[1:-1])
        z = np.log10(values) if log else values
        if levels:
            lines = ax.tricontour(xy[:, 0], xy[:, 1], z, levels=np.log10(levels) if log else levels,
                                  colors="white", linewidths=1.0, linestyles="solid")
            lines.set_in_layout(False)
            ax.clabel(lines, fmt=lambda v: f"{10.0 ** v:.3g}" if log else f"{v:.3g}", fontsize=8)
    if mark is not None:
        ax.plot(*xy[mark], marker="*", markersize=18, color=MARK, markeredgecolor="white", linestyle="none",
                label=mark_label)
        ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
    return bar


def _title(trained: TrainedMap, member: int, what: str) -> str:
    n = trained.som.batch_shape.numel()
    grid = trained.som.grid
    return f"{trained.spec.name} map (member {member + 1} of {n}, {grid.rows} x {grid.cols} {grid.topology}): {what}"


def plane_figure(trained: TrainedMap, values: np.ndarray, label: str, what: str, *, member: int = 0,
                 log: bool = False, contours: bool = False, mark: int | None = None) -> Any:
    """One map plane as its own figure (6.4 x 5.4 in)."""
    fig = new_figure(6.4, 5.4)
    ax = fig.add_subplot()
    draw_plane(ax, trained.som.grid, values, label=label, log=log, contours=contours, mark=mark)
    ax.set_title(_title(trained, member, what), fontsize=9)
    return fig


def parameter_plane_figure(trained: TrainedMap, *, member: int = 0, mark: int | None = None) -> Any:
    """The paper-style contour plot of the parameter the map stores (:data:`PARAMETER_PLANES`)."""
    plane = PARAMETER_PLANES[trained.spec.name]
    values = plane.values(unit_weights(trained, member))
    return plane_figure(trained, values, with_unit(plane.label, plane.unit), f"{plane.symbol} with lines of constant "
                        f"{plane.symbol}", member=member, log=True, contours=True, mark=mark)


def map_figure_names(trained: TrainedMap, *, hits: bool) -> list[str]:
    """The names of :func:`map_figures` of ``trained`` (``hits``: with its training rows)."""
    plane = PARAMETER_PLANES.get(trained.spec.name)
    return (["u_matrix"] + (["hits"] if hits else []) + [f"component/{n}" for n in trained.spec.targets]
            + ([f"contour/{plane.symbol}"] if plane is not None else []))


def map_figure(trained: TrainedMap, name: str, data: torch.Tensor | None = None, *, member: int = 0) -> Any:
    """One figure of :func:`map_figures` by its name (``hits`` needs ``data``)."""
    valid = map_figure_names(trained, hits=True)
    if name not in valid:
        raise ValueError(f"map figure: expected one of {valid}, received {name!r}")
    som = trained.som
    one = som[member] if som.batch_shape else som
    if name == "u_matrix":
        return plane_figure(trained, st.u_matrix(one).reshape(-1).numpy(),
                            "mean distance to the neighbours [normalized feature units]", "U-matrix", member=member)
    if name == "hits":
        if data is None:
            raise ValueError("map figure 'hits': expected the training rows (data), received None")
        rows = torch.as_tensor(data)
        if rows.dim() > 2:  # one set of rows per member
            rows = rows.reshape(-1, *rows.shape[-2:])[member]
        hits = st.hit_counts(one, rows).reshape(-1).numpy().astype(np.float64)
        return plane_figure(trained, hits, "training records per unit [-]", "hit map", member=member)
    if name.startswith("component/"):
        component = name.removeprefix("component/")
        label = COMPONENT_LABELS.get(component, component)
        return plane_figure(trained, unit_weights(trained, member)[component], label, component, member=member)
    return parameter_plane_figure(trained, member=member)


def map_figures(trained: TrainedMap, data: torch.Tensor | None = None, *, member: int = 0) -> dict[str, Any]:
    """The figures of one trained map (ensemble member ``member``), by name: ``u_matrix``,
    ``hits`` (with ``data``: its training rows, raw ``N x C`` or ``*batch x N x C``), one
    ``component/<name>`` per stored (inactive) component, and ``contour/<symbol>``: the paper-style
    contour plot of :data:`PARAMETER_PLANES` (where the map has one)."""
    return {n: map_figure(trained, n, data, member=member) for n in map_figure_names(trained, hits=data is not None)}


def map_png_paths(trained: TrainedMap, folder: str | os.PathLike[str], *, hits: bool) -> dict[str, Path]:
    """Where :func:`write_map_pngs` puts each figure: ``folder/<map>/<name>.png`` (``/`` in a name -> ``_``)."""
    return {n: Path(folder) / trained.spec.name / f"{n.replace('/', '_')}.png"
            for n in map_figure_names(trained, hits=hits)}


def write_map_pngs(trained: TrainedMap, folder: str | os.PathLike[str], data: torch.Tensor | None = None, *,
                   member: int = 0, overwrite: bool = False) -> list[Path]:
    """Write :func:`map_figures` of ``trained`` as PNG files (:func:`map_png_paths`), one figure
    at a time; existing files only with ``overwrite`` (checked before the first is written)."""
    paths = map_png_paths(trained, folder, hits=data is not None)
    refuse_existing(list(paths.values()), overwrite)
    return [save_png(map_figure(trained, name, data, member=member), path, overwrite=overwrite)
            for name, path in paths.items()]
