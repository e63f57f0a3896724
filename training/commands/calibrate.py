"""``twomass calibrate``: the confidence calibration of a map folder (SPEC 4.1), written beside the
maps as ``confidence.json`` and listed in their manifest."""

from __future__ import annotations

import argparse
from pathlib import Path

from training.commands import _progress

HELP = "calibrate the answers' 90-percent intervals and probabilities on held-out simulated records (SPEC 4.1)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoints", type=Path, default=None,
                        help="map folder to calibrate (default: the shipped maps); confidence.json is written there")
    parser.add_argument("--per-drive", type=int, default=300, help="systems per matrix drive (default 300)")
    parser.add_argument("--envelope-drives", type=int, default=40,
                        help="drives drawn over the envelope, 25 systems each (default 40)")
    parser.add_argument("--reference", type=int, default=1000,
                        help="systems of the default population on the reference drive (default 1000)")
    parser.add_argument("--samples", type=Path, default=None,
                        help="JSON Lines file of the identified calibration records: read where it exists, else "
                             "written (a refit then needs no simulation)")
    parser.add_argument("--overwrite", action="store_true", help="replace a confidence.json already in the folder")
    parser.add_argument("--workers", type=int, default=None, help="processes, >= 1 (default: CPU count)")
    _progress.add_option(parser)


def run(args: argparse.Namespace) -> int:
    import os
    from functools import partial

    import som_torch as st
    from training._json import dumps
    from training._pool import worker_pool
    from training.config import checkpoints_folder
    from training.errors import OutputExistsError
    from training.identification import CHECKPOINT_FILES, maps_digests
    from training.identification import CONFIDENCE_FILE as FILE_NAME
    from training.learning import (CALIBRATION_SEEDS, calibration_tasks, fit_calibration, load_samples, save_samples,
                                   task_samples)

    folder = args.checkpoints if args.checkpoints is not None else checkpoints_folder()
    target = folder / FILE_NAME
    if target.exists() and not args.overwrite:
        raise OutputExistsError(f"{target} exists: pass --overwrite to replace it")
    for name in ("per_drive", "envelope_drives", "reference"):
        if getattr(args, name) < 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected >= 0, received {getattr(args, name)}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers: expected >= 1, received {args.workers}")
    digests = st.verify_manifest(folder, required=CHECKPOINT_FILES)
    if args.samples is not None and args.samples.exists():
        samples = load_samples(args.samples)
    else:
        tasks = calibration_tasks(args.per_drive, args.envelope_drives, 25, args.reference)
        workers = args.workers or os.cpu_count() or 1
        samples = []
        total = sum(int(t[3].J_sigma.shape[0]) for t in tasks)
        with _progress.bar(args, show=_progress.wanted(args), total=total, unit="sys", desc="calibrate") as bar, \
                worker_pool(workers) as pool:
            for task, done in zip(tasks, pool.map(partial(task_samples, checkpoints=str(folder)), tasks)):
                samples += done
                bar.update(int(task[3].J_sigma.shape[0]))
        if args.samples is not None:
            save_samples(samples, args.samples)
    provenance = {"seeds": CALIBRATION_SEEDS, "per_drive": args.per_drive, "envelope_drives": args.envelope_drives,
                  "reference": args.reference, "maps_sha256": maps_digests(digests)}
    calibration = fit_calibration(samples, provenance)
    st.atomic_write(target, lambda f: f.write(dumps(calibration.to_dict())), text=True)
    st.write_manifest(folder, files=[*CHECKPOINT_FILES, FILE_NAME])
    p = calibration.provenance
    print(f"{target}: {p['n']} calibration answers ({p['classes']}), {100 * p['right']:.1f} % right; "
          f"likely_wrong below P = {calibration.warn_below:.3f} (right answers warned, out of fold: "
          f"{100 * p['right_warned_out_of_fold']:.1f} %)")
    return 0
