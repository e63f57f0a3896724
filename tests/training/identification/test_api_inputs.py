"""What an app hands the identification in memory: records built by hand (no ``T_s``, torch
columns), the wrong type, a single path where a list is due. The caller's objects stay unchanged."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from test_sections import simulate_switching

from sim import Record, write_record
from training.errors import IdentificationError
from training.identification import Identifier, analyze


@pytest.fixture(scope="module")
def run() -> Record:
    return simulate_switching(seed=5)


def test_a_record_built_in_memory_without_T_s_or_with_torch_columns_is_analysed_alike(run):
    ref = analyze(run)
    bare = copy.deepcopy(run)
    del bare.meta["T_s"]  # SPEC 3: optional, else from t
    for c in ("speed", "current", "torque_ref"):
        setattr(bare, c, torch.as_tensor(getattr(bare, c), dtype=torch.float64))
    a = analyze(bare)
    assert np.array_equal(a.features, ref.features) and a.fit.J_sigma == ref.fit.J_sigma
    assert "T_s" not in bare.meta and isinstance(bare.speed, torch.Tensor)  # the caller's record as it was


def test_a_two_dimensional_column_is_named(run):
    bad = copy.deepcopy(run)
    bad.speed = bad.speed[:, None]
    with pytest.raises(IdentificationError, match=r"column 'speed': expected a 1-D"):
        analyze(bad)


def test_the_wrong_type_is_a_type_error():
    ident = Identifier.load()
    with pytest.raises(TypeError, match="expected a sim.Record"):
        ident.identify({"speed": [0.0]})
    with pytest.raises(TypeError, match=r"expected a list of record paths, received one str .*identify_file"):
        ident.identify_files("run.csv")


def test_writing_a_record_leaves_the_callers_record_unchanged(run, tmp_path):
    rec = copy.deepcopy(run)
    del rec.meta["T_s"]
    meta = rec.meta
    write_record(tmp_path / "r", rec)
    assert rec.meta is meta and "T_s" not in rec.meta
