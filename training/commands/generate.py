"""``twomass generate``: simulate a population, analyse each record, store features + truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from training.commands import _progress

HELP = "make training data: population responses and their features, sharded to disk (resumable)"

#: Default sharding: at least this many shards where N allows, of at most this many systems.
MIN_SHARDS, MAX_SHARD_SIZE = 10, 500

#: Bytes of a shard file besides its numbers (the .npz's headers: about 1000 measured), for the disk check.
SHARD_OVERHEAD = 2048

#: Rejected systems whose reason the summary prints (the rest: in the shards' .rejected.json files).
SHOWN_REASONS = 3

def default_shard_size(n: int) -> int:
    """Systems per shard for ``n`` systems when ``--shard-size`` is not given."""
    return max(1, min(MAX_SHARD_SIZE, -(-n // MIN_SHARDS)))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="dataset folder (an interrupted run resumes here)")
    parser.add_argument("--n", type=int, default=20000, help="number of systems (default 20000)")
    parser.add_argument("--seed", type=int, default=1, help="population and noise seed (default 1)")
    parser.add_argument("--shard-size", type=int, default=None,
                        help=f"systems per shard file, the unit of resuming (default: N/{MIN_SHARDS} rounded up, "
                             f"at most {MAX_SHARD_SIZE}: an interrupt loses at most one shard's work)")
    parser.add_argument("--envelope", action="store_true",
                        help="draw drives, test runs and mechanics over the drive envelope of docs/contract.md (the shipped "
                             "maps' data) instead of the default population on the reference drive")
    parser.add_argument("--workers", type=int, default=None,
                        help="analysis processes, >= 1 (default: CPU count; under torchrun: each process's share)")
    _progress.add_option(parser)


def run(args: argparse.Namespace) -> int:
    from training._distributed import process_group
    from sim import EnvelopeRanges
    from training.learning import ESTIMATE_NAMES, TRUTH_NAMES, GenerateConfig, generate

    from training._checks import BYTES_PER_SYSTEM, check_disk, check_memory, seed
    from training._pool import WORKER_MEMORY
    from training.identification import FEATURE_NAMES

    shard_size = default_shard_size(args.n) if args.shard_size is None else args.shard_size
    if args.n < 1 or shard_size < 1:
        raise ValueError(f"--n and --shard-size: expected >= 1, received {args.n}, {shard_size}")
    seed("--seed", args.seed)
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers: expected >= 1, received {args.workers}")
    columns = len(FEATURE_NAMES) + len(TRUTH_NAMES) + len(ESTIMATE_NAMES) + 1
    group = process_group()  # under torchrun: the ranks share the shards, rank 0 writes and prints
    workers = args.workers or group.cpus()
    check_memory(f"--n {args.n} with {workers} worker(s)",  # drawn, shards, loaded; each worker
                 args.n * (BYTES_PER_SYSTEM + 3 * 8 * columns) + workers * WORKER_MEMORY)
    n_shards = -(-args.n // shard_size)
    check_disk(f"--n {args.n}", args.out, args.n * 8 * columns + n_shards * SHARD_OVERHEAD)
    config = GenerateConfig(n=args.n, seed=args.seed, shard_size=shard_size,
                            envelope=EnvelopeRanges() if args.envelope else None)
    with _progress.bar(args, show=_progress.wanted(args) and group.main, total=args.n, unit="sys",
                       desc="generate") as bar:
        generate(args.out, config, workers=workers, progress=bar.update)
    if not group.main:
        return 0
    print("\n".join(summary(args.out)))
    return 0


def summary(out: Path) -> list[str]:
    """What the dataset in ``out`` holds, and why the analysis rejected the first few systems it did."""
    from training.learning import load_dataset, rejection_reasons

    ds = load_dataset(out)
    lines = [f"{out}: {len(ds)} systems, {int(ds.ok.sum())} analysed, {len(ds) - int(ds.ok.sum())} rejected "
             f"by the analysis, sha256 {ds.sha256[:16]}"]
    reasons = rejection_reasons(out)
    lines += [f"  rejected system {system}: {reason}" for system, reason in list(reasons.items())[:SHOWN_REASONS]]
    if len(reasons) > SHOWN_REASONS:
        lines.append(f"  ... {len(reasons) - SHOWN_REASONS} more in {out}/shard_*.rejected.json")
    return lines
