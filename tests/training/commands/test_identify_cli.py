"""``twomass identify``: JSON Lines per record, per-record errors, --out, exit codes; README example."""

from __future__ import annotations

import copy
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from sim import Record, write_record
from sim.params import STRUCTURE_CLASSES
from training.cli import main
from training.config import checkpoints_folder
from training.identification import PARAMETER_NAMES

REPO = Path(__file__).resolve().parents[3]
RPM = 60.0 / (2.0 * math.pi)


def _strict_loads(line: str) -> dict:
    def no_constants(name: str):
        raise AssertionError(f"invalid JSON constant {name}")
    return json.loads(line, parse_constant=no_constants)




def _meta(rec: Record, drop: tuple[str, ...] = ()) -> dict:
    return {k: v for k, v in rec.meta.items() if k not in drop}


def _write_raw(folder: Path, name: str, cols: dict[str, np.ndarray], meta: dict | None) -> None:
    """CSV + JSON by hand (no validation): for records that write_record would refuse."""
    names = list(cols)
    rows = np.column_stack([np.asarray(cols[c], dtype=np.float64) for c in names])
    np.savetxt(folder / f"{name}.csv", rows, fmt="%.12g", delimiter=",", header=",".join(names), comments="")
    if meta is not None:
        (folder / f"{name}.json").write_text(json.dumps(meta))


def _variant(rec: Record, **changes) -> Record:
    new = copy.deepcopy(rec)
    for k, v in changes.items():
        setattr(new, k, v)
    return new


def _random_torque(rec: Record) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    n = 8000
    levels = rng.uniform(-10.0, 10.0, size=n // 80 + 1)
    current = np.repeat(levels, 80)[:n]  # a new random level every 20 ms
    speed = np.cumsum(current) * 2.5e-4 / 0.02
    return {"t": np.arange(n) * 2.5e-4, "speed": speed, "current": current}


#: name -> expected one-line error (regex); "good" must be answered.
CASES: dict[str, str] = {
    "missing_column": r"missing column 'speed'",
    "nan": r"column 'speed' has NaN/inf at line 11",  # sample 9: the header is line 1
    "non_uniform": r"non-uniform time step near line",
    "random_torque": r"no recognisable test-signal sections",
    "ramp": r"incomplete test run: the record ends in section I at t = .*sections II, III, IV, V, VI",
    "saturated": r"saturated at 60 rad/s",
    "constant": r"constant speed",
    "current_in_mA": r"current looks like wrong units \(.*M_star",
    "speed_in_rpm": r"speed looks like wrong units \(.*w_max.*rpm",
    "t_in_ms": r"metadata T_s=0\.00025 disagrees with the time column",
    "t_in_ms_no_T_s": r"time looks like wrong units \(sample time T_s = 0\.25 s",
    "no_metadata": r"metadata file not found",
    "no_such_file": r"file not found",
}


@pytest.fixture(scope="module")
def records(good, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("records")
    write_record(d / "good", good)
    n = len(good)
    cols = good.columns()
    _write_raw(d, "missing_column", {"t": good.t, "current": good.current}, _meta(good))
    nan_speed = good.speed.copy()
    nan_speed[9] = np.nan
    _write_raw(d, "nan", {**cols, "speed": nan_speed}, _meta(good))
    t_bad = good.t.copy()
    t_bad[n // 2:] += 0.3 * good.T_s
    _write_raw(d, "non_uniform", {**cols, "t": t_bad}, _meta(good))
    basic = {"K_M": 1.0, "T_Ei": 5e-4}
    _write_raw(d, "random_torque", _random_torque(good), basic)
    _write_raw(d, "ramp", {"t": good.t, "speed": np.linspace(0.0, 100.0, n), "current": np.full(n, 10.0)},
               {**basic, "M_star": 10.0, "w_max": 100.0})
    write_record(d / "saturated", _variant(good, speed=np.clip(good.speed, -60.0, 60.0)))
    write_record(d / "constant", _variant(good, speed=np.zeros(n)))
    write_record(d / "current_in_mA", _variant(good, current=good.current * 1000.0))
    write_record(d / "speed_in_rpm", _variant(good, speed=good.speed * RPM))
    no_ts = {k: v for k, v in cols.items() if k != "section"}
    _write_raw(d, "t_in_ms", {**no_ts, "t": good.t * 1000.0}, _meta(good))
    _write_raw(d, "t_in_ms_no_T_s", {**no_ts, "t": good.t * 1000.0}, _meta(good, drop=("T_s",)))
    _write_raw(d, "no_metadata", cols, None)
    return d


@pytest.fixture(scope="module")
def batch(records) -> tuple[int, list[dict], list[str]]:
    """One ``twomass identify`` over all cases, the good record in the middle."""
    names = list(CASES)
    names.insert(len(names) // 2, "good")
    paths = [str(records / f"{n}.csv") for n in names]
    out = records / "out.jsonl"
    rc = main(["identify", *paths, "--out", str(out), "--no-progress"])
    lines = out.read_text().splitlines()
    return rc, [_strict_loads(x) for x in lines], paths


def test_batch_exit_code_and_order(batch):
    rc, results, paths = batch
    assert rc == 1  # some records have errors
    assert [r["record"] for r in results] == paths


def test_good_record_is_answered_among_bad_ones(batch):
    _, results, paths = batch
    res = next(r for r in results if r["record"].endswith("good.csv"))
    assert "error" not in res
    assert res["structure"] in STRUCTURE_CLASSES
    assert list(res["parameters"]) == list(PARAMETER_NAMES)
    assert isinstance(res["quality"], dict) and isinstance(res["warnings"], list)
    assert res["parameters"]["J_sigma"] == pytest.approx(0.02, rel=0.2)  # the one-mass fit, not a map


@pytest.mark.parametrize("name", list(CASES))
def test_bad_record_gets_a_clear_one_line_error(batch, name):
    _, results, _ = batch
    res = next(r for r in results if Path(r["record"]).stem == name)
    assert set(res) == {"record", "error"}
    assert "\n" not in res["error"]
    assert re.search(CASES[name], res["error"]), res["error"]


def test_stdout_and_name_forms(records, tmp_path, capsys):
    for name in ("a", "b", "c"):
        for ext in (".csv", ".json"):
            shutil.copy(records / f"good{ext}", tmp_path / f"{name}{ext}")
    args = [str(tmp_path / "a.csv"), str(tmp_path / "b.json"), str(tmp_path / "c"), str(tmp_path / "a.json")]
    assert main(["identify", *args, "--no-progress"]) == 0
    cap = capsys.readouterr()
    lines = [_strict_loads(x) for x in cap.out.splitlines()]
    assert [r["record"] for r in lines] == args[:3]  # a.json names a record already given: answered once
    assert all("structure" in r for r in lines)
    for r in lines[1:]:  # same record: same answer (to rounding: the recall is batched)
        values = {k: v for k, v in lines[0]["parameters"].items() if v is not None}
        assert {k: v for k, v in r["parameters"].items() if v is not None} == pytest.approx(values, rel=1e-9)
    assert "3 of 3 record(s) identified" in cap.err


def test_jobs_give_the_same_answers(records, capsys):
    paths = [str(records / "good.csv"), str(records / "constant.csv"), str(records / "speed_in_rpm")]
    assert main(["identify", *paths, "--jobs", "1", "--no-progress"]) == 1
    one = capsys.readouterr().out
    assert main(["identify", *paths, "--jobs", "2", "--no-progress"]) == 1
    assert capsys.readouterr().out == one


def test_worker_processes_give_the_same_outcomes(records):
    """Whole batches of records in forked workers (3 batches here) answer as one process does."""
    from training.identification import CHUNK, Identifier

    ident = Identifier.load()
    paths = [str(records / n) for n in ("good.csv", "constant.csv", "speed_in_rpm")] * CHUNK
    one = [r.to_dict() for r in ident.identify_files(paths, jobs=1)]
    assert [r.to_dict() for r in ident.identify_files(paths, jobs=2)] == one


def test_out_is_atomic_and_not_overwritten(records, tmp_path, capsys):
    out = tmp_path / "res.jsonl"
    good = str(records / "good.csv")
    assert main(["identify", good, "--out", str(out), "--no-progress"]) == 0
    first = out.read_text()
    assert len(first.splitlines()) == 1 and capsys.readouterr().out == ""
    assert main(["identify", good, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert out.read_text() == first
    assert main(["identify", str(records / "constant.csv"), "--out", str(out), "--overwrite", "--no-progress"]) == 1
    assert "constant speed" in out.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res.jsonl"]  # no temporary files left


def test_bad_usage_exits_2(records, tmp_path, capsys):
    assert main(["identify"]) == 2
    assert "expected at least one record FILE" in capsys.readouterr().err
    good = str(records / "good.csv")
    assert main(["identify", good, "--checkpoints", str(tmp_path / "none")]) == 2
    assert "--checkpoints" in capsys.readouterr().err
    assert main(["identify", good, "--out", str(tmp_path / "no" / "dir.jsonl")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["identify", good, "--jobs", "0"]) == 2
    capsys.readouterr()


def test_changed_checkpoint_is_refused(records, tmp_path, capsys):
    ck = tmp_path / "ck"
    shutil.copytree(checkpoints_folder(), ck)
    with open(ck / "f_e.pt", "ab") as f:
        f.write(b"\0")
    assert main(["identify", str(records / "good.csv"), "--checkpoints", str(ck)]) == 2
    err = capsys.readouterr().err
    assert "SHA-256" in err and len(err.strip().splitlines()) == 1


def test_help_documents_exit_codes(capsys):
    with pytest.raises(SystemExit) as e:
        main(["identify", "--help"])
    assert e.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "0 all records identified, 1 some records have an 'error'" in out


def test_jobs_help_states_the_batching_the_code_uses(capsys):
    # the help is written without importing the identification (start-up time): its figures are checked here
    from training.identification import CHUNK
    from training.identification._batch import default_jobs

    with pytest.raises(SystemExit):
        main(["identify", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert f"batches of {CHUNK} records (default: 1 for fewer than {2 * CHUNK} records" in out
    assert default_jobs(2 * CHUNK - 1) == 1


def test_readme_python_example_runs(records, tmp_path, monkeypatch):
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## Identify your own record"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    for ext in (".csv", ".json"):
        shutil.copy(records / f"good{ext}", tmp_path / f"run{ext}")
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)  # noqa: S102 - our own README
    result = ns["result"].to_dict()
    assert result["structure"] in STRUCTURE_CLASSES and set(result["parameters"]) == set(PARAMETER_NAMES)


def test_readme_sample_line_has_the_output_keys():
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## Identify your own record"):]
    line = next(x for x in section.splitlines() if x.startswith('{"record"'))
    res = _strict_loads(line)
    assert {"record", "structure", "parameters", "quality", "warnings"} <= set(res)
    assert list(res["parameters"]) == list(PARAMETER_NAMES)


def test_out_exists_is_one_line_and_exit_2(records, tmp_path, capsys):
    out = tmp_path / "taken.jsonl"
    out.write_text("keep me\n")
    assert main(["identify", str(records / "good.csv"), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"twomass identify: error: --out: {str(out)!r} exists (pass --overwrite to replace it)"
    assert out.read_text() == "keep me\n"


def test_existing_out_raises_output_exists_error(records, tmp_path):
    import argparse

    from training.commands import identify
    from training.errors import OutputExistsError

    out = tmp_path / "taken.jsonl"
    out.write_text("")
    args = argparse.Namespace(files=[str(records / "good.csv")], out=out, overwrite=False, checkpoints=None,
                              jobs=None, no_refine=True, no_progress=True, plot=None)
    with pytest.raises(OutputExistsError, match="exists"):
        identify.run(args)


def test_bench_identify_small(tmp_path, capsys):
    """``twomass bench identify`` times real ``twomass identify`` processes and writes its figures."""
    out = tmp_path / "bench.json"
    assert main(["bench", "identify", "--n", "2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "twomass identify, 2 records" in text and "per record" in text
    figures = json.loads(out.read_text())
    assert figures["n"] == 2 and figures["many"]["wall"] > 0 and figures["many"]["peak_rss_mib"] > 0
    assert main(["bench", "identify", "--n", "1"]) == 2


def test_every_error_names_its_file(batch):
    """Unit, section and analysis errors start with the record's path, as reading errors do."""
    _, results, _ = batch
    for res in results:
        if "error" in res:
            assert str(Path(res["record"]).with_suffix("")) in res["error"], res["error"]


def test_time_error_prints_plain_numbers(good, tmp_path, capsys):
    t = good.t.copy()
    t[100:] -= 0.01  # time runs backwards after sample 100
    _write_raw(tmp_path, "backwards", {**good.columns(), "t": t}, _meta(good))
    assert main(["identify", str(tmp_path / "backwards.csv"), "--no-progress"]) == 1
    err = _strict_loads(capsys.readouterr().out)["error"]
    assert "time is not increasing at line 102 (t=0.015 s after 0.02475 s)" in err and "np." not in err  # sample 100


def test_map_saved_under_another_name_is_refused(records, tmp_path, capsys):
    """A valid map copied over another (manifest updated): refused at load, one line, exit 2."""
    from som_torch import write_manifest

    ck = tmp_path / "ck"
    shutil.copytree(checkpoints_folder(), ck)
    shutil.copy(ck / "f_e.pt", ck / "structure.pt")
    write_manifest(ck)
    assert main(["identify", str(records / "good.csv"), "--checkpoints", str(ck), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "structure.pt: holds the map 'f_e'" in err and "KeyError" not in err


def test_help_states_output_units(capsys):
    with pytest.raises(SystemExit):
        main(["identify", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "SI units" in out and "f_e [Hz]" in out and "backlash [rad, total width 2s]" in out


def test_missing_maps_say_how_to_point_at_them(records, tmp_path, capsys):
    assert main(["identify", str(records / "good.csv"), "--checkpoints", str(tmp_path / "none")]) == 2
    assert "TWOMASS_CHECKPOINTS" in capsys.readouterr().err
