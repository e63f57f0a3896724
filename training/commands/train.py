"""``twomass train``: train every identification map, log to TensorBoard, write checkpoints."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "train the identification maps on a dataset; TensorBoard logs; checkpoints + manifest"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from training.learning import TrainConfig

    d = TrainConfig()
    parser.add_argument("--data", type=Path, required=True, help="dataset folder made by `twomass generate`")
    parser.add_argument("--out", type=Path, required=True, help="checkpoint folder (maps + manifest.json)")
    parser.add_argument("--logdir", type=Path, default=Path("runs"), help="TensorBoard folder (default runs/)")
    parser.add_argument("--size", type=int, nargs=2, default=(d.rows, d.cols), metavar=("ROWS", "COLS"))
    parser.add_argument("--ensemble", type=int, default=d.ensemble, help=f"maps per ensemble (default {d.ensemble})")
    parser.add_argument("--epochs", type=int, default=d.epochs, help=f"default {d.epochs}")
    parser.add_argument("--seed", type=int, default=d.seed, help=f"default {d.seed}")
    parser.add_argument("--overwrite", action="store_true", help="replace maps already in --out")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from training._json import dumps
    from training.learning import TrainConfig, load_dataset, train_maps

    config = TrainConfig(rows=args.size[0], cols=args.size[1], ensemble=args.ensemble, epochs=args.epochs,
                         seed=args.seed)
    ds = load_dataset(args.data)
    with tqdm(desc="train", unit="map", disable=args.no_progress) as bar:
        trained = train_maps(ds, args.out, config, logdir=args.logdir, overwrite=args.overwrite, progress=bar.update)
    summary = {name: {"systems": t.metadata["dataset"]["n_used"], "seconds": round(t.metadata["train_seconds"], 1),
                      "quantization_error": t.metadata["quality"].get("quantization_error"),
                      "topographic_error": t.metadata["quality"].get("topographic_error")}
               for name, t in trained.items()}
    print(dumps(summary))
    print(f"maps written to {args.out} (manifest.json), TensorBoard logs in {args.logdir}")
    return 0
