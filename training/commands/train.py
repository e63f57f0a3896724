"""``twomass train``: train every identification map, log to TensorBoard, write checkpoints."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from training.commands import _progress

HELP = "train the identification maps on a dataset; TensorBoard logs; checkpoints + manifest"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options. Their defaults are ``TrainConfig``'s (``None`` here: no torch import for
    ``--help``); the numbers in the help texts are checked against it by the tests."""
    parser.add_argument("--data", type=Path, required=True, help="dataset folder made by `twomass generate`")
    parser.add_argument("--out", type=Path, required=True,
                        help="checkpoint folder (maps + manifest.json); an interrupted run resumes here")
    parser.add_argument("--logdir", type=Path, default=Path("runs"), help="TensorBoard folder (default runs/)")
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                        help="units of each map, rows x columns (default 40 40, the paper's)")
    parser.add_argument("--ensemble", type=int, default=None,
                        help="maps per ensemble, trained with seeds SEED, SEED+1, ... (default 4)")
    parser.add_argument("--epochs", type=int, default=None, help="passes over the training data (default 10)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the first ensemble member (default 0)")
    parser.add_argument("--mode", default=None, metavar="{online,batch}",
                        help="online rule (the paper's) or batch SOM (default online); under torchrun online "
                             "deals the ensemble members out to the processes, batch splits the data")
    parser.add_argument("--device", default="cpu", help="torch device of the training, e.g. cuda (default cpu; "
                        "the C kernel of the online rule is CPU only, on a GPU the torch path runs)")
    parser.add_argument("--overwrite", action="store_true", help="replace maps already in --out")
    _progress.add_option(parser)


def _config(args: argparse.Namespace) -> Any:
    """``TrainConfig`` with the options given (the others keep its defaults)."""
    from training.learning import TrainConfig

    given = {"ensemble": args.ensemble, "epochs": args.epochs, "seed": args.seed, "mode": args.mode,
             **(dict(zip(("rows", "cols"), args.size)) if args.size is not None else {})}
    return TrainConfig(**{k: v for k, v in given.items() if v is not None})


def run(args: argparse.Namespace) -> int:
    from training._distributed import process_group
    from training._json import dumps
    from training.figures import PLOT_HINT, plots_available
    from training.identification import MAP_SPECS
    from training.learning import load_dataset, train_maps

    from training._checks import seed

    if args.seed is not None:
        seed("--seed", args.seed)
    config = _config(args)
    device = _device(args.device)
    group = process_group()  # under torchrun: the processes share the work, rank 0 writes and prints
    ds = load_dataset(args.data)
    if group.main and not plots_available():
        print(f"twomass train: TensorBoard gets grey arrays instead of figures; {PLOT_HINT}", file=sys.stderr)
    show = _progress.wanted(args) and group.main
    with _progress.bar(args, show=show, total=len(MAP_SPECS), desc="train maps", unit="map") as bar:
        trained = train_maps(ds, args.out, config, logdir=args.logdir, overwrite=args.overwrite, progress=bar.update,
                             device=device, epoch_progress=show)
    if not group.main:
        return 0
    summary = {name: {"systems": t.metadata["dataset"]["n_used"],
                      "seconds": round(t.metadata["train_seconds"], 1) if "train_seconds" in t.metadata else "resumed",
                      "quantization_error": t.metadata["quality"].get("quantization_error"),
                      "topographic_error": t.metadata["quality"].get("topographic_error")}
               for name, t in trained.items()}
    print(dumps(summary))
    print(f"maps written to {args.out} (manifest.json), TensorBoard logs in {args.logdir}")
    return 0


def _device(name: str) -> Any:
    """``--device`` as a torch device; one that is not here is a :class:`UserError`."""
    import torch

    from training.errors import UserError

    try:
        device = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device: expected a torch device such as cpu or cuda, received {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {name}: no CUDA device here")
    if device.type not in ("cpu", "cuda"):
        raise UserError(f"--device: expected cpu or cuda, received {name!r}")
    return device
