"""What the commands need of the machine, checked before they start: free memory and free disk for
``simulate`` and ``generate`` (one line: needed against free, nothing written), and an output that
cannot be written named as the user gave it (never the temporary file beside it)."""

from __future__ import annotations

import collections
import errno
import os
from pathlib import Path

import pytest

import sim
import training.learning
from sim import write_record
from training import _checks
from training.cli import main

DiskUsage = collections.namedtuple("DiskUsage", "total used free")


def _refused(argv: list[str], capsys, *words: str) -> str:
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"twomass {argv[0]}: error: "), lines
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


@pytest.fixture
def no_work(monkeypatch):
    """The simulation and the dataset generation fail the test if they start."""
    def started(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(sim, "iter_records", started)
    monkeypatch.setattr(training.learning, "generate", started)


@pytest.fixture
def available(tmp_path, monkeypatch):
    """``available(kib)``: the machine reports 64 GiB of memory, ``kib`` KiB of it available now."""
    def report(kib: int) -> None:
        meminfo = tmp_path / "meminfo"
        meminfo.write_text(f"MemTotal:       67108864 kB\nMemFree:        {kib} kB\nMemAvailable:   {kib} kB\n")
        monkeypatch.setattr(_checks, "MEMINFO", meminfo, raising=False)
    return report


@pytest.fixture
def free_disk(monkeypatch):
    """``free_disk(n)``: every file system has ``n`` bytes free."""
    def report(n: int) -> None:
        monkeypatch.setattr("shutil.disk_usage", lambda path: DiskUsage(2**40, 2**40 - n, n))
    return report


def test_available_memory_is_what_the_kernel_says_is_available(available):
    available(1024)
    assert _checks.available_memory() == 2**20


def test_without_mem_available_the_physical_memory_bounds(tmp_path, monkeypatch):
    (tmp_path / "meminfo").write_text("MemTotal:       1024 kB\n")  # a kernel before 3.14
    monkeypatch.setattr(_checks, "MEMINFO", tmp_path / "meminfo")
    assert _checks.available_memory() == os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def test_simulate_refuses_more_memory_than_is_available(tmp_path, capsys, available, no_work):
    available(1024)  # 1 MiB of 64 GiB
    _refused(["simulate", "--population", "20", "--out", str(tmp_path / "o")], capsys,
             "20 systems", "of memory", "1 MiB is available")
    assert not (tmp_path / "o").exists()


def test_simulate_refuses_more_than_the_free_disk(tmp_path, capsys, free_disk, no_work):
    free_disk(2**20)
    line = _refused(["simulate", "--population", "20", "--out", str(tmp_path / "o")], capsys,
                    "20 systems", "writes about", "1 MiB is free there", str(tmp_path / "o"))
    need = float(line.split("writes about ")[1].split()[0])
    assert 5 < need < 100  # MiB: 20 records of the default population take about 20 MiB
    assert not (tmp_path / "o").exists()


def test_generate_counts_its_workers_against_the_available_memory(tmp_path, capsys, available, no_work):
    available(512 * 1024)  # 512 MiB: one worker fits, two do not
    _refused(["generate", "--n", "40", "--workers", "2", "--out", str(tmp_path / "g")], capsys,
             "2 worker(s)", "of memory", "512 MiB is available")
    assert not (tmp_path / "g").exists()


def test_generate_refuses_more_than_the_free_disk(tmp_path, capsys, free_disk, no_work):
    free_disk(4096)
    _refused(["generate", "--n", "100", "--workers", "1", "--out", str(tmp_path / "g")], capsys,
             "--n 100", "writes about", "4 KiB is free there")
    assert not (tmp_path / "g").exists()


# --- an output that cannot be written -----------------------------------------------------------------


@pytest.fixture
def read_only(tmp_path, monkeypatch):
    """A folder nobody may write into (as root, who may, creating a file there fails as it would)."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    if os.access(folder, os.W_OK):  # root ignores the permissions
        real_open = os.open

        def refusing(path, flags, *args, **kwargs):
            if Path(path).parent == folder and flags & os.O_CREAT:
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
            return real_open(path, flags, *args, **kwargs)

        monkeypatch.setattr(os, "open", refusing)
    yield folder
    folder.chmod(0o755)


def test_identify_names_a_read_only_out_as_given(tmp_path, capsys, good, read_only):
    write_record(tmp_path / "rec", good)
    out = read_only / "answers.jsonl"
    line = _refused(["identify", str(tmp_path / "rec"), "--out", str(out)], capsys, str(out), "Permission denied")
    assert ".tmp" not in line
    assert list(read_only.iterdir()) == []


def test_simulate_names_the_record_it_cannot_write(tmp_path, capsys, read_only):
    params = tmp_path / "p.json"
    params.write_text('{"J_sigma": 0.05, "V_J": 1, "f_e": 30, "name": "one"}')
    line = _refused(["simulate", "--params", str(params), "--out", str(read_only)], capsys,
                    str(read_only / "one.csv"), "Permission denied")
    assert ".tmp" not in line
