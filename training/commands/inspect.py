"""``twomass inspect [CHECKPOINT_DIR] --out DIR``: the figures of trained maps as PNG files.

Without ``CHECKPOINT_DIR``: the maps ``Identifier.load()`` uses (``$TWOMASS_CHECKPOINTS``, else the
shipped ones, in a checkout and in an installed wheel alike). For each map of the folder (checked
against its manifest): the U-matrix, the hit map (with ``--data``: the dataset the maps were trained
on), each stored parameter as a coloured plane and the paper-style contour plot (Figs. 7-8), as
``DIR/<map>/<figure>.png``: the same figures that ``twomass train`` writes to TensorBoard
(``docs/figures.md``). Prints a JSON summary per map
(grid, ensemble, training systems, quality, recall-distance quantiles). The figures need
matplotlib (the ``plot`` extra): without it the command stops before any work with one line that
says how to get it (exit 2).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

HELP = "the figures of trained maps (U-matrix, hits, parameter planes, contour plots) as PNG files"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoints", type=Path, nargs="?", metavar="CHECKPOINT_DIR",
                        help="folder with the maps and manifest.json (default: the shipped maps, or "
                             "$TWOMASS_CHECKPOINTS)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the PNG files")
    parser.add_argument("--data", type=Path, metavar="DIR",
                        help="dataset folder the maps were trained on (`twomass generate`): adds the hit maps")
    parser.add_argument("--overwrite", action="store_true", help="replace PNG files already in --out")


def _summary(trained: Any) -> dict[str, Any]:
    meta, grid = trained.metadata, trained.som.grid
    quality = meta.get("quality", {})
    return {"grid": f"{grid.rows} x {grid.cols} {grid.topology}", "ensemble": trained.som.batch_shape.numel(),
            "features": len(trained.spec.features), "stored": list(trained.spec.targets),
            "systems": meta.get("dataset", {}).get("n_used"),
            "quantization_error": quality.get("quantization_error"),
            "topographic_error": quality.get("topographic_error"),
            "distance_quantiles": meta.get("distance_quantiles")}


def run(args: argparse.Namespace) -> int:
    from training._json import dumps
    from training.commands.identify import load_identifier
    from training.errors import UserError
    from training.figures import map_png_paths, refuse_existing, require_matplotlib, write_map_pngs

    require_matplotlib()  # the figures are the point: none drawable is bad usage, said before any work
    if args.out.exists() and not args.out.is_dir():
        raise UserError(f"--out: expected a folder, received the file {str(args.out)!r}")
    if args.checkpoints is not None and not args.checkpoints.is_dir():
        raise UserError(f"CHECKPOINT_DIR: expected a folder with the trained maps and manifest.json, received "
                        f"{str(args.checkpoints)!r} (not found)")
    maps = load_identifier(args.checkpoints, refine=False).maps
    rows = _training_rows(args.data, maps) if args.data is not None else {}
    refuse_existing([p for name, t in maps.items() for p in map_png_paths(t, args.out, hits=name in rows).values()],
                    args.overwrite)  # before anything is printed or drawn
    print(dumps({name: _summary(t) for name, t in maps.items()}))
    written = [p for name, t in maps.items()
               for p in write_map_pngs(t, args.out, rows.get(name), overwrite=args.overwrite)]
    print(f"twomass inspect: {len(written)} figure(s) of {len(maps)} map(s) written to {args.out}", file=sys.stderr)
    return 0


def _training_rows(folder: Path, maps: dict[str, Any]) -> dict[str, Any]:
    """Per map, its training rows in ``folder`` (raw ``N x C``; the calibration share included)."""
    import torch

    from training.learning import load_dataset, training_matrix

    ds = load_dataset(folder)
    other = [n for n, t in maps.items() if t.metadata.get("dataset", {}).get("sha256") != ds.sha256]
    if other:
        print(f"twomass inspect: --data: the maps {other} were trained on another dataset; their hit maps count "
              f"the records of {folder}", file=sys.stderr)
    return {name: torch.as_tensor(training_matrix(t.spec, ds), dtype=torch.float32) for name, t in maps.items()}
