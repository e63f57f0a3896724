"""``twomass bench identify``: ``twomass identify`` on one record and on N records, each a fresh
process (start-up included): wall time, CPU time (user + system) and peak resident memory, and
the cost per record from the difference of the two."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from training.bench._report import Table, machine_line, ProcessCost, run_process, write_figures
from training.errors import UserError

#: The file in ``--records-dir`` that says which seed its records were simulated with.
MARKER = "bench_records.json"

HELP = "'twomass identify' on 1 and on N population records, fresh processes: wall, CPU, peak memory, per record"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, default=1000, help="population records of the large run (default 1000)")
    parser.add_argument("--seed", type=int, default=7, help="population and noise seed (default 7)")
    parser.add_argument("--records-dir", default=None,
                        help="keep the simulated records in this folder and reuse those already there (writing "
                             "CSV records is slow); default: a temporary folder")
    parser.add_argument("--no-refine", action="store_true", help="time 'twomass identify --no-refine'")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def _records(folder: Path, n: int, seed: int) -> list[str]:
    """Paths of ``n`` population records in ``folder``, simulated and written where missing."""
    import sim

    paths = [folder / f"sys{i:05d}.csv" for i in range(n)]  # iter_records' names
    marker = folder / MARKER
    present = [p.exists() for p in paths]
    if any(present):  # reuse only the records of this seed
        try:
            made = json.loads(marker.read_text()).get("seed")
        except (OSError, ValueError, AttributeError):
            made = None
        if made != seed:
            held = "records this bench did not write" if made is None else f"records of --seed {made}"
            raise UserError(f"--records-dir {folder}: holds {held} ({MARKER}); pass their seed or another folder")
        if all(present):
            return [str(p) for p in paths]
    folder.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"seed": seed}))
    print(f"simulating and writing {n} records to {folder} (not timed)...", flush=True)
    drive, signal = sim.DriveConfig(), sim.TestSignalConfig()
    params = sim.sample_population(n, seed)
    for rec in sim.iter_records(params, drive, signal, seed=seed):
        path = folder / f"{rec.name}.csv"
        if not path.exists():
            sim.write_record(path, rec)
    missing = [p for p in paths if not p.exists()]
    if missing:
        raise UserError(f"records missing after simulation (names differ?): {missing[0]}")
    return [str(p) for p in paths]


def run(args: argparse.Namespace) -> int:
    if args.n < 2:
        raise UserError(f"--n: expected >= 2, received {args.n}")
    with tempfile.TemporaryDirectory(prefix="twomass-bench-") as tmp:
        folder = Path(args.records_dir) if args.records_dir else Path(tmp) / "records"
        paths = _records(folder, args.n, args.seed)
        extra = ["--no-refine"] if args.no_refine else []
        out = str(Path(tmp) / "out.jsonl")
        cmd = [sys.executable, "-m", "training.cli", "identify", "--no-progress", "--out", out, "--overwrite", *extra]
        print(machine_line())
        one = run_process([*cmd, paths[0]])
        many = run_process([*cmd, *paths])
    per_wall, per_cpu = (many.wall - one.wall) / (args.n - 1), (many.cpu - one.cpu) / (args.n - 1)
    table = Table(["run", "wall s", "CPU s", *ProcessCost.MEMORY])
    label = "twomass identify" + (" --no-refine" if args.no_refine else "")
    table.add(f"{label}, 1 record", f"{one.wall:.2f}", f"{one.cpu:.2f}", *one.memory())
    table.add(f"{label}, {args.n} records", f"{many.wall:.2f}", f"{many.cpu:.2f}", *many.memory())
    table.add("per record ((N records - 1 record) / (N - 1))", f"{per_wall:.3f}", f"{per_cpu:.3f}", "-", "-")
    print(table.render())
    if per_cpu <= 0:
        print(f"note: the per-record figures are not meaningful: {args.n} records cost no more than one (the "
              "start-up's spread exceeds their work); use a larger --n")
    print(f"records: population seed {args.seed}, the default drive and test; each run a fresh process "
          "(start-up included)")
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, {"n": args.n, "seed": args.seed, "one": vars(one), "many": vars(many),
                                      "per_record_wall_s": per_wall, "per_record_cpu_s": per_cpu})
    return 0
