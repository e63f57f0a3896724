"""The house style of every figure: matplotlib imported lazily (an optional extra), one figure
object per page (no pyplot state), PNG files written atomically, figures as image arrays.

matplotlib is the ``plot`` extra. Without it :func:`require_matplotlib` raises one line that says
how to get it (:data:`PLOT_HINT`); :func:`plots_available` lets a command say so and go on.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from training.errors import OutputExistsError, UserError



def _install_command(here: Path = Path(__file__)) -> str:
    """How to get the ``plot`` extra where this module (``here``) lies: into a checkout
    (``pyproject.toml`` beside the ``training`` package; an editable install too) with
    ``pip install -e``, else (an installed wheel) from the package index."""
    root = here.resolve().parents[2]
    if (root / "pyproject.toml").is_file():
        return f'pip install -e ".[plot]" (in {root})'
    return "pip install 'twomass-som[plot]'"


#: The one line a command prints (or the error says) where matplotlib is missing.
PLOT_HINT = f"figures need matplotlib, the 'plot' extra: {_install_command()}"

#: Resolution of every figure [dots per inch]; sizes below are in inches.
DPI = 100

#: Colours: measured signals, the identified model, markers.
MEASURED, MODEL, MARK = "0.15", "tab:orange", "tab:red"


def require_matplotlib() -> Any:
    """The ``matplotlib`` module; raises :class:`training.errors.UserError` (:data:`PLOT_HINT`)
    where it is not installed."""
    try:
        import matplotlib
        from matplotlib.figure import Figure  # noqa: F401 - the part every page uses
    except ImportError:
        raise UserError(PLOT_HINT) from None
    return matplotlib


def require_plots(option: str) -> None:
    """A :class:`training.errors.UserError` naming ``option`` (``--plot``, ...) and saying how to get
    matplotlib (:data:`PLOT_HINT`) where it is not installed: a command checks before any work."""
    if not plots_available():
        raise UserError(f"{option}: {PLOT_HINT}")


def plots_available() -> bool:
    """Whether figures can be drawn here (matplotlib importable)."""
    try:
        require_matplotlib()
    except UserError:
        return False
    return True


def new_figure(width: float, height: float) -> Any:
    """An empty ``matplotlib.figure.Figure`` of ``width x height`` inches, laid out by matplotlib
    (no pyplot: nothing global is touched, no window opens)."""
    require_matplotlib()
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=DPI, layout="constrained")


def refuse_existing(paths: list[Path], overwrite: bool) -> None:
    """:class:`training.errors.OutputExistsError` naming the first of ``paths`` that exists (unless ``overwrite``)."""
    if overwrite:
        return
    existing = [p for p in paths if p.exists()]
    if existing:
        more = f" and {len(existing) - 1} more" if len(existing) > 1 else ""
        raise OutputExistsError(f"{str(existing[0])!r}{more} exist(s) (pass --overwrite to replace)")


def save_png(fig: Any, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically (an existing file only with ``overwrite``)."""
    from som_torch import atomic_write

    path = Path(path)
    refuse_existing([path], overwrite)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=DPI))
    return path


def figure_image(fig: Any) -> np.ndarray:
    """The rendered figure as ``H x W x 3`` uint8 (for ``SummaryWriter.add_image(..., dataformats="HWC")``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def number(x: float | None, digits: int = 4) -> str:
    """``x`` with ``digits`` significant digits; ``-`` for None or non-finite."""
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.{digits}g}"


def with_unit(label: str, unit: str) -> str:
    """``label [unit]`` (``[-]`` for dimensionless)."""
    return f"{label} [{unit}]"
