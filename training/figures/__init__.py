"""Figures a drive engineer and a map trainer read at a glance (``docs/figures.md``).

* the identify page of a record (:func:`identify_figure`, :func:`failure_figure`) and the record
  on the maps (:func:`maps_figure`); :func:`identify_pages` writes both as PNG files;
* a trained map's figures (:func:`map_figures`: U-matrix, hit map, stored components, the
  paper-style contour plot), into TensorBoard (:func:`log_map_figures`) or as PNG files;
* the commissioning page of a drive (:func:`commission_figure`: test runs, the loop before and
  after tuning, motor and load, the delivered loop's Bode plot with its margins) and its measured
  frequency response beside the model's (:func:`frf_figure`);
* the house style for any page (:func:`new_figure`, :func:`save_png`, :func:`draw_plane`, ...).

matplotlib is the optional ``plot`` extra: it is imported only when a figure is drawn;
:func:`plots_available` says whether it is here, :data:`PLOT_HINT` how to get it (``pip install -e``
in a checkout, from the package index otherwise), :func:`require_plots` refuses a command's figure
option without it.
"""

from ._commission import PANELS as COMMISSION_PANELS
from ._commission import FRF_PANELS, commission_figure, frf_figure
from ._identify import (PageWriter, anti_resonance, best_match, failure_figure, identify_figure, identify_pages,
                        maps_figure, model_speed, page_names)
from ._planes import (COMPONENT_LABELS, PARAMETER_PLANES, ParameterPlane, draw_plane, map_figure, map_figure_names,
                      map_figures, map_png_paths, parameter_plane_figure, unit_weights, unit_xy, write_map_pngs)
from ._style import (DPI, MARK, MEASURED, MODEL, PLOT_HINT, figure_image, new_figure, plots_available,
                     refuse_existing, require_matplotlib, require_plots, save_png, with_unit)
from ._tensorboard import log_map_figures

__all__ = [
    "commission_figure", "COMMISSION_PANELS", "frf_figure", "FRF_PANELS",
    "identify_figure", "failure_figure", "maps_figure", "identify_pages", "PageWriter", "page_names", "model_speed",
    "anti_resonance",
    "best_match", "map_figures", "map_figure", "map_figure_names", "map_png_paths", "write_map_pngs",
    "parameter_plane_figure", "PARAMETER_PLANES", "ParameterPlane", "COMPONENT_LABELS", "draw_plane", "unit_weights",
    "unit_xy", "log_map_figures",
    "PLOT_HINT", "plots_available", "require_matplotlib", "require_plots", "new_figure", "save_png", "refuse_existing",
    "figure_image", "with_unit", "DPI", "MEASURED", "MODEL", "MARK",
]
