"""End to end on tiny data: generate (resumable, config-checked) -> train tiny maps -> identify."""

import json
import os

import numpy as np
import pytest

from sim import TestSignalConfig, iter_records, sample_population
from training.cli import main
from training._pool import worker_pool
from training.errors import UserError
from training.identification import MAP_SPECS, PARAMETER_NAMES, Identifier
from training.learning import GenerateConfig, TrainConfig, generate, load_dataset


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    generate(out, GenerateConfig(n=40, seed=11, shard_size=20), workers=1)
    return out


def test_dataset_is_complete_and_resumable(dataset_dir, tmp_path):
    ds = load_dataset(dataset_dir)
    assert len(ds) == 40 and ds.ok.mean() > 0.9
    assert np.isfinite(ds.features[ds.ok]).all()
    # the same config in a folder with one shard lost: a rerun completes it to the same data
    copy = tmp_path / "copy"
    copy.mkdir()
    for p in dataset_dir.iterdir():
        if p.name != "shard_00001.npz":
            (copy / p.name).write_bytes(p.read_bytes())
    with pytest.raises(UserError, match="1 of 2 shards missing"):
        load_dataset(copy)
    generate(copy, GenerateConfig(n=40, seed=11, shard_size=20), workers=1)
    assert load_dataset(copy).sha256 == ds.sha256


def test_another_config_is_refused(dataset_dir):
    with pytest.raises(UserError, match="another config"):
        generate(dataset_dir, GenerateConfig(n=40, seed=12, shard_size=20), workers=1)


def test_train_then_identify(dataset_dir, tmp_path, capsys):
    ck = tmp_path / "ck"
    args = ["train", "--data", str(dataset_dir), "--out", str(ck), "--logdir", str(tmp_path / "runs"),
            "--size", "5", "5", "--ensemble", "2", "--epochs", "2", "--no-progress"]
    assert main(args) == 0
    assert sorted(p.name for p in ck.iterdir()) == sorted([f"{n}.pt" for n in MAP_SPECS] + ["envelope.json", "manifest.json"])
    assert main(args) == 2  # refuses to overwrite without --overwrite
    assert "--overwrite" in capsys.readouterr().err

    ident = Identifier.load(ck)
    records = list(iter_records(sample_population(2, seed=5), signal=TestSignalConfig(), seed=3))
    results = ident.identify_records(records)
    for res in results:
        assert res.ok and res.structure in ("stiff", "elastic", "elastic_backlash", "stiff_backlash")
        assert set(res.parameters.to_dict()) == set(PARAMETER_NAMES)
        assert res.parameters.J_sigma > 0
        json.dumps(res.to_dict(), allow_nan=False)  # JSON-able, no NaN

    # a tampered checkpoint is rejected by the manifest check
    with open(ck / "f_e.pt", "r+b") as f:
        f.seek(200)
        f.write(b"\x00\x01\x02")
    with pytest.raises(ValueError, match="f_e.pt"):
        Identifier.load(ck)


def test_train_config_checks_its_sizes():
    with pytest.raises(ValueError, match="rows, cols >= 2"):
        TrainConfig(rows=1)
    with pytest.raises(ValueError, match="epochs >= 1"):
        TrainConfig(epochs=0)


def test_worker_pool_limits_threads_in_the_workers_only(monkeypatch):
    """The workers run with one BLAS/OpenMP thread; this process's environment stays as it was."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")
    before = dict(os.environ)
    with worker_pool(1) as pool:
        seen = pool.submit(os.getenv, "OMP_NUM_THREADS").result(), pool.submit(os.getenv, "OPENBLAS_NUM_THREADS").result()
        assert dict(os.environ) == before
    assert dict(os.environ) == before
    assert seen == ("1", "1")
    with pytest.raises(ValueError, match="workers >= 1"):
        with worker_pool(0):
            pass
