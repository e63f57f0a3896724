"""A record's metadata: one check (``sim._meta.check_meta``) and its typed view (``Record.info``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim import Record, RecordError, RecordMeta
from sim._meta import check_meta
from sim.records import META_KEYS, validate


def _record(meta: dict, n: int = 64) -> Record:
    t = np.arange(n) * 2.5e-4
    return Record(t=t, speed=np.sin(t * 50), current=np.cos(t * 30), meta=meta)


def test_every_metadata_key_is_a_typed_field() -> None:
    assert META_KEYS == {f.name for f in dataclasses.fields(RecordMeta)}
    assert len(META_KEYS) == 16  # SPEC 3 and 3.1, and M_hold (SPEC 1.1)


def test_info_types_the_checked_metadata() -> None:
    meta = {"K_M": np.float32(0.5), "T_Ei": 5e-4, "encoder_counts": 4096.0, "M_star": 10, "aborted": True,
            "timed_out": [False, True], "truth": {"f_e": 30.0}, "notes": ["any", 1]}
    rec = validate(_record(meta))
    info = rec.info
    assert (info.K_M, info.T_Ei, info.T_s, info.M_star) == (0.5, 5e-4, 2.5e-4, 10)
    assert info.encoder_counts == 4096 and type(info.encoder_counts) is int
    assert info.timed_out == (False, True) and info.any_timed_out and info.aborted
    assert info.truth == {"f_e": 30.0} and info.notes == ["any", 1]
    assert (info.w_max, info.M_N, info.M_max, info.current_noise_std) == (None, None, None, None)
    assert info.format == "twomass-record/1" and dict(info.units) == {}
    assert list(rec.meta) == list(meta) + ["T_s"]  # the JSON object keeps its order; T_s from the time column
    with pytest.raises(dataclasses.FrozenInstanceError):
        info.T_Ei = 1.0  # type: ignore[misc]


def test_absent_flags_read_as_false() -> None:
    info = validate(_record({"K_M": 1.0, "T_Ei": 5e-4})).info
    assert info.aborted is False and info.timed_out is False and not info.any_timed_out


def test_info_of_a_record_not_validated_names_the_missing_key() -> None:
    with pytest.raises(RecordError, match="metadata 'T_s' is missing"):
        _ = _record({"K_M": 1.0, "T_Ei": 5e-4}).info


@pytest.mark.parametrize("meta, match", [
    ({"K_M": 1.0}, "metadata 'T_Ei' \\(current-loop time constant\\) is missing"),
    ({"T_Ei": 5e-4}, "metadata 'K_M' is missing"),
    ({"K_M": 1.0, "T_Ei": 0.0}, "metadata 'T_Ei': expected a finite number > 0, received 0.0"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "current_noise_std": -1}, "metadata 'current_noise_std': expected a finite number >= 0"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "encoder_counts": 1.5}, "metadata 'encoder_counts': expected an integer up to 2\\^53"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "aborted": 1}, "metadata 'aborted': expected true or false"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "timed_out": [False] * 7}, "metadata 'timed_out': expected a list"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "T_s": 1e-3}, "metadata T_s=0.001 disagrees with the time column"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "units": {"speed": "rpm"}}, "unknown unit 'rpm' for column 'speed'"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "format": "v2"}, "metadata 'format': expected 'twomass-record/1'"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "truth": [1]}, "metadata 'truth': expected an object"),
    ({"K_M": 1.0, "T_Ei": 5e-4, "colour": 1}, "unknown metadata key\\(s\\) 'colour'"),
])
def test_one_check_names_the_key(meta: dict, match: str) -> None:
    with pytest.raises(RecordError, match=match) as caught:
        check_meta(meta, T_s_t=2.5e-4, n=64, has_torque=False, where="run.json")
    assert str(caught.value).startswith("run.json: ")
