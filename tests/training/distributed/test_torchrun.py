"""The documented user path, ``torchrun --standalone --nproc_per_node=2 --no-python -- twomass ...``
(2 local processes, gloo on CPU), gives what one process gives: the same dataset (every shard's
arrays), the same maps (online rule: members dealt out; batch SOM: sums all-reduced) and the same
``identify`` JSON Lines in the same order."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import som_torch as st
from training.cli import main
from training.identification import MAP_SPECS

TWOMASS = shutil.which("twomass") or str(Path(sys.executable).with_name("twomass"))
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "--no-python", "--",
            TWOMASS]
N_SYSTEMS, SHARD = 400, 100


def torchrun(*args: str) -> subprocess.CompletedProcess:
    """``twomass args`` under torchrun with 2 processes (a clean torchrun environment)."""
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR",
                                                             "MASTER_PORT", "LOCAL_WORLD_SIZE")}
    return subprocess.run([*TORCHRUN, *args], env=env, capture_output=True, text=True, timeout=300)


def ok(res: subprocess.CompletedProcess) -> None:
    assert res.returncode == 0, res.stderr[-3000:]


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("dist")
    args = ["generate", "--n", str(N_SYSTEMS), "--shard-size", str(SHARD), "--seed", "3", "--no-progress"]
    assert main([*args, "--out", str(tmp / "one"), "--workers", "2"]) == 0
    ok(torchrun(*args, "--out", str(tmp / "two"), "--workers", "1"))
    return tmp / "one", tmp / "two"


def test_generate_two_processes_write_the_dataset_of_one(datasets):
    one, two = datasets
    assert (one / "dataset.json").read_text() == (two / "dataset.json").read_text()
    names = sorted(p.name for p in one.glob("shard_*.npz"))
    assert names == sorted(p.name for p in two.glob("shard_*.npz")) and len(names) == N_SYSTEMS // SHARD
    for name in names:
        with np.load(one / name) as a, np.load(two / name) as b:
            assert a.files == b.files
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}:{key}")


@pytest.mark.parametrize("mode", ["online", "batch"])
def test_train_two_processes_make_the_maps_of_one(datasets, tmp_path, mode):
    one, _ = datasets
    args = ["train", "--data", str(one), "--size", "4", "5", "--ensemble", "3", "--epochs", "2", "--mode", mode,
            "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "m1"), "--logdir", str(tmp_path / "r1")]) == 0
    ok(torchrun(*args, "--out", str(tmp_path / "m2"), "--logdir", str(tmp_path / "r2")))
    for name in MAP_SPECS:
        som1, meta1 = st.load_checkpoint(tmp_path / "m1" / f"{name}.pt")
        som2, meta2 = st.load_checkpoint(tmp_path / "m2" / f"{name}.pt")
        torch.testing.assert_close(som2.weights, som1.weights, rtol=0, atol=1e-5)
        torch.testing.assert_close(som2.offset, som1.offset, rtol=0, atol=0)
        assert meta2["dataset"] == meta1["dataset"] and meta2["train_config"] == meta1["train_config"]
    st.verify_manifest(tmp_path / "m2")
    # rank 0 alone wrote the TensorBoard logs, with every member's tags (those of rank 1 sent to it)
    assert len(list((tmp_path / "r2").glob("events.out.tfevents.*"))) == 1


def test_identify_two_processes_answer_in_input_order(tmp_path):
    records = tmp_path / "records"
    assert main(["simulate", "--population", "10", "--seed", "11", "--out", str(records), "--no-progress"]) == 0
    files = [str(p) for p in sorted(records.glob("*.csv"))]
    files.insert(3, str(records / "missing"))  # an error line keeps its place
    assert main(["identify", *files, "--out", str(tmp_path / "one.jsonl"), "--no-progress"]) == 1
    res = torchrun("identify", *files, "--out", str(tmp_path / "two.jsonl"), "--no-progress")
    assert res.returncode != 0  # some records have an error: exit 1 on every rank, torchrun reports a failure
    assert "exitcode  : 1" in res.stderr
    one, two = ((tmp_path / f"{n}.jsonl").read_text() for n in ("one", "two"))
    assert two == one and len(one.splitlines()) == 11
