"""``twomass train``: train every identification map, log to TensorBoard, write checkpoints."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "train the identification maps on a dataset; TensorBoard logs; checkpoints + manifest"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from training.learning._maps import TrainConfig

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
    import som_torch as st
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    from training.learning._dataset import load_dataset
    from training.errors import UserError
    from training.identification._maps import MAP_SPECS
    from training.learning._maps import TrainConfig, save_map, train_map

    config = TrainConfig(rows=args.size[0], cols=args.size[1], ensemble=args.ensemble, epochs=args.epochs,
                         seed=args.seed)
    if min(args.size) < 2 or args.ensemble < 1 or args.epochs < 1:
        raise UserError(f"--size, --ensemble, --epochs: expected >= 2, >= 1, >= 1, received "
                        f"{args.size}, {args.ensemble}, {args.epochs}")
    existing = [n for n in MAP_SPECS if (args.out / f"{n}.pt").exists()]
    if existing and not args.overwrite:
        raise UserError(f"{args.out} already holds maps {existing}; pass --overwrite to replace them")
    ds = load_dataset(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    writer = SummaryWriter(str(args.logdir))
    st.log_config(writer, {"train": config.to_dict(), "dataset": ds.config, "dataset_sha256": ds.sha256})
    summary = {}
    for name, spec in tqdm(MAP_SPECS.items(), desc="train", unit="map", disable=args.no_progress):
        trained = train_map(spec, ds, config, writer=writer)
        save_map(args.out, trained)
        q = trained.metadata["quality"]
        summary[name] = {"systems": trained.metadata["dataset"]["n_used"],
                         "seconds": round(trained.metadata["train_seconds"], 1),
                         "quantization_error": q.get("quantization_error"), "topographic_error": q.get("topographic_error")}
    writer.close()
    st.write_manifest(args.out)
    print(json.dumps(summary, default=float))
    print(f"maps written to {args.out} (manifest.json), TensorBoard logs in {args.logdir}")
    return 0
