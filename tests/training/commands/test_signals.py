"""SIGTERM and SIGINT during the long commands: exit code 143 (130), one line on stderr and no
traceback, no temporary or half-written file, and no process left behind (pool workers, the
multiprocessing resource tracker).

Each command runs as its own process (``python -m training.cli``) in a session of its own, is
signalled once it is at work (its first output file, or its worker processes, are there: no fixed
sleeps), and every process it started is followed through ``/proc``. SIGINT goes to the whole
process group, as Ctrl-C in a terminal sends it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from sim import write_record
from training import cli
from training.cli import main

TWOMASS = [sys.executable, "-m", "training.cli"]
SIGNALS = [signal.SIGTERM, signal.SIGINT]
#: Seconds a command may take to get to work, and to end once signalled (a busy machine).
START_TIMEOUT, END_TIMEOUT = 240.0, 180.0  # generous: a loaded CI machine is slow, a hang is not


# --- in this process: the handlers of training.cli ---------------------------------------------------


class _Unhandled(Exception):
    """What a signal raises here when ``main`` did not take it over."""


@pytest.fixture
def guarded():
    """SIGTERM and SIGINT raise :class:`_Unhandled` around the test (so that a signal ``main`` does
    not handle fails the test instead of ending pytest), and get their handlers back after it."""
    def unhandled(signum, frame):
        raise _Unhandled(signal.Signals(signum).name)

    before = {s: signal.signal(s, unhandled) for s in SIGNALS}
    yield unhandled
    for s, handler in before.items():
        signal.signal(s, handler)


def _command(monkeypatch, run) -> None:
    """Offer one command, ``boom``, that runs ``run(args)``."""
    import types

    module = types.ModuleType("fake_boom_command")
    module.HELP = "runs a test's function"
    module.add_arguments = lambda parser: None
    module.run = run
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(cli, "COMMANDS", {"boom": module.__name__})


def _signalled(signum: int) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(5)  # the handler raises before this ends


def test_sigterm_in_a_command_exits_143_with_one_line(monkeypatch, capsys, guarded):
    _command(monkeypatch, lambda args: _signalled(signal.SIGTERM))
    assert main(["boom"]) == 143
    assert capsys.readouterr().err.splitlines() == ["twomass boom: terminated (SIGTERM)"]
    assert signal.getsignal(signal.SIGTERM) is guarded  # the handlers of before come back


def test_a_second_signal_does_not_cut_the_cleanup_short(monkeypatch, capsys, guarded):
    cleaned = []

    def run(args):
        try:
            _signalled(signal.SIGINT)
        finally:  # the cleanup of the first interruption, hit by a second signal (SIGTERM after Ctrl-C)
            os.kill(os.getpid(), signal.SIGTERM)
            cleaned.append(True)

    _command(monkeypatch, run)
    assert main(["boom"]) == 130
    assert cleaned == [True]
    assert capsys.readouterr().err.splitlines() == ["twomass boom: interrupted"]


def test_a_signal_ignored_at_the_start_stays_ignored(monkeypatch, guarded):
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # nohup, a background job of a script
    _command(monkeypatch, lambda args: os.kill(os.getpid(), signal.SIGTERM) or 0)
    assert main(["boom"]) == 0
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN


@pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX fork")
def test_a_process_forked_by_a_command_leaves_the_signals_to_it(monkeypatch, guarded):
    """A pool worker forked while a command runs ignores Ctrl-C and ends at SIGTERM by its default
    action (at once, without a Python traceback)."""
    dispositions = []

    def run(args):
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: report its handlers and leave without pytest's cleanup
            os.write(write, repr((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))).encode())
            os._exit(0)
        os.close(write)
        dispositions.append(os.read(read, 200).decode())
        os.close(read)
        os.waitpid(pid, 0)
        return 0

    _command(monkeypatch, run)
    assert main(["boom"]) == 0
    assert dispositions == [repr((signal.SIG_IGN, signal.SIG_DFL))]


# --- each long command as its own process ---------------------------------------------------------------

proc_only = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="follows processes through /proc (Linux)")


def _parents() -> dict[int, int]:
    """Every process's parent, from ``/proc/<pid>/stat``."""
    out = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:  # ended meanwhile
                continue
            out[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    return out


def _descendants(pid: int) -> set[int]:
    parents = _parents()
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = {c for c, pp in parents.items() if pp == p and c not in found}
        found |= kids
        todo += kids
    return found


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its parent's ``wait`` does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").strip()
    except OSError:
        return ""


@dataclass
class Interrupted:
    rc: int
    stderr: str
    left: list[str]  # the command lines of processes it started that outlived it


def _as_from_a_terminal() -> None:
    """The child's signals as a shell's foreground command has them: a test suite run as a background
    job (``pytest &`` in a script) inherits SIGINT ignored, which the command rightly keeps."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt(argv: list[str], ready: Callable[[set[int]], bool], sig: int, tmp_path: Path) -> Interrupted:
    """Run ``twomass argv``, send ``sig`` once ``ready(its live descendants)`` (SIGINT to its process
    group), and wait for it and every process it started to end."""
    err_path = tmp_path / "stderr.txt"
    seen: set[int] = set()
    with open(err_path, "w") as err:
        proc = subprocess.Popen(TWOMASS + argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True, preexec_fn=_as_from_a_terminal)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            live = {p for p in _descendants(proc.pid) if _alive(p)}
            seen |= live
            if ready(live):
                break
            if proc.poll() is not None:
                pytest.fail(f"twomass {argv[0]} ended (exit {proc.returncode}) before it was signalled: "
                            f"{err_path.read_text()[-2000:]}")
            if time.monotonic() > deadline:
                pytest.fail(f"twomass {argv[0]} did not get to work in {START_TIMEOUT:g} s")
            time.sleep(0.05)
        seen |= _descendants(proc.pid)
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)  # Ctrl-C: the whole foreground process group
        else:
            proc.send_signal(sig)
        rc = proc.wait(timeout=END_TIMEOUT)
        deadline = time.monotonic() + 15.0
        while any(_alive(p) for p in seen) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = [f"{p}: {_cmdline(p)}" for p in sorted(seen) if _alive(p)]
    finally:
        for p in [proc.pid, *seen]:
            if _alive(p):
                try:
                    os.kill(p, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        proc.wait()
    return Interrupted(rc, err_path.read_text(), left)


def assert_clean(run: Interrupted, command: str, sig: int, folder: Path) -> None:
    """Exit 128 + ``sig``, the one line of it last on stderr, no traceback, no process left, no
    temporary file in ``folder``."""
    said = "terminated (SIGTERM)" if sig == signal.SIGTERM else "interrupted"
    assert run.rc == 128 + sig, run.stderr[-3000:]
    assert run.stderr.strip().splitlines()[-1] == f"twomass {command}: {said}", run.stderr[-3000:]
    assert "Traceback" not in run.stderr, run.stderr[-3000:]
    assert "leaked" not in run.stderr, run.stderr[-3000:]  # the resource tracker's complaint
    assert run.left == []
    assert [p.name for p in folder.rglob("*") if p.name.endswith(".tmp")] == []


def _workers(live: set[int], cpu_s: float = 0.0) -> int:
    """Live pool workers: forked (``identify``) or spawned (``generate``, ``evaluate``) processes
    other than the resource tracker, each with at least ``cpu_s`` seconds of CPU time."""
    return sum("resource_tracker" not in _cmdline(p) and _cpu_seconds(p) >= cpu_s for p in live)


def _cpu_seconds(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


@pytest.fixture(scope="module")
def records(tmp_path_factory, good) -> Path:
    """70 copies of one record: three batches of 32 for two forked workers."""
    folder = tmp_path_factory.mktemp("records")
    write_record(folder / "r000", good)
    for i in range(1, 70):
        for ext in (".csv", ".json"):
            shutil.copy(folder / f"r000{ext}", folder / f"r{i:03d}{ext}")
    return folder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from training.learning import GenerateConfig, generate

    out = tmp_path_factory.mktemp("ds")
    generate(out, GenerateConfig(n=40, seed=11, shard_size=20), workers=1)
    return out


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_identify_leaves_no_temp_file_and_no_worker(records, tmp_path, sig):
    out = tmp_path / "out"
    out.mkdir()
    argv = ["identify", *map(str, sorted(records.glob("*.csv"))), "--jobs", "2", "--out", str(out / "answers.jsonl")]
    run = interrupt(argv, lambda live: _workers(live) >= 2 and any(out.glob(".answers.jsonl.*.tmp")), sig, tmp_path)
    assert_clean(run, "identify", sig, out)
    assert list(out.iterdir()) == []


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_simulate_leaves_whole_records_only(tmp_path, sig):
    out = tmp_path / "sim"
    argv = ["simulate", "--population", "40", "--w-max", "20", "--out", str(out)]
    run = interrupt(argv, lambda live: any(out.glob("*.csv")), sig, tmp_path)
    assert_clean(run, "simulate", sig, out)
    assert sorted(p.stem for p in out.glob("*.csv")) == sorted(p.stem for p in out.glob("*.json"))


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_generate_ends_its_workers(tmp_path, sig):
    out = tmp_path / "ds"
    argv = ["generate", "--n", "400", "--shard-size", "20", "--workers", "2", "--out", str(out)]
    run = interrupt(argv, lambda live: (out / "shard_00000.npz").exists() and _workers(live) >= 2, sig, tmp_path)
    assert_clean(run, "generate", sig, out)


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_evaluate_ends_its_workers(tmp_path, sig):
    out = tmp_path / "report"
    argv = ["evaluate", "--per-cell", "0", "--population", "40", "--workers", "2", "--no-iv4", "--no-plots",
            "--no-cache", "--out", str(out)]
    # at work: both workers past their start-up (importing torch and loading the maps take seconds)
    run = interrupt(argv, lambda live: _workers(live, cpu_s=4.0) >= 2, sig, tmp_path)
    assert_clean(run, "evaluate", sig, tmp_path)
    assert not out.exists() or list(out.iterdir()) == []


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_train_leaves_no_temp_file(dataset, tmp_path, sig):
    out = tmp_path / "maps"
    argv = ["train", "--data", str(dataset), "--out", str(out), "--logdir", str(tmp_path / "runs"), "--size", "10",
            "10", "--ensemble", "1", "--epochs", "300"]
    run = interrupt(argv, lambda live: any(out.glob("*.pt")), sig, tmp_path)
    assert_clean(run, "train", sig, tmp_path)
    assert not (out / "manifest.json").exists()


@proc_only
@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_commission_leaves_no_temp_file(tmp_path, sig):
    logs = tmp_path / "logs"
    argv = ["commission", "--population", "2", "--logdir", str(logs), "--json", str(tmp_path / "reports.json")]
    # the logs appear as the first experiment starts: the signal often lands while a drive call runs in its
    # thread, which must return before the process exits (exiting under it aborts: exit -6, no 143)
    run = interrupt(argv, lambda live: logs.exists(), sig, tmp_path)
    assert_clean(run, "commission", sig, tmp_path)
    assert not (tmp_path / "reports.json").exists()
