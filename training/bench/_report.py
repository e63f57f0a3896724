"""What every ``twomass bench`` target prints besides its figures: the machine, a table, the
machine's matmul FLOP rate, and the figures as JSON."""

from __future__ import annotations

import os
import platform
import subprocess
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from training._json import dumps
from training.errors import UserError


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else :func:`platform.processor`)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine_line() -> str:
    """CPU model and count, load, and the thread settings of torch, BLAS and the simulator kernel."""
    import numpy as np
    import torch
    from threadpoolctl import threadpool_info

    from sim._config import kernel_threads

    blas = ", ".join(f"{i['internal_api']} {i['num_threads']}" for i in threadpool_info() if i["user_api"] == "blas")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"machine: {cpu_model()}, {os.cpu_count()} CPUs, 1-min load average {load:.2f} (above 0.5: shared/busy); "
            f"threads: simulator kernel {kernel_threads()}, torch {torch.get_num_threads()}, BLAS ({blas or 'none'}); "
            f"torch {torch.__version__}, numpy {np.__version__}")


def matmul_gflops(dtype, threads: int, n: int = 1024, repeat: int = 5) -> float:
    """The machine's FLOP rate [GFLOP/s] on ``threads`` threads: the best of ``repeat`` ``n x n``
    matmuls (``2 n^3`` FLOP each) in numpy's BLAS and in torch, whichever is faster."""
    import numpy as np
    import torch
    from threadpoolctl import threadpool_limits

    def best(mm, a, b) -> float:
        mm(a, b)
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            mm(a, b)
            times.append(time.perf_counter() - t0)
        return min(times)

    a = torch.rand(n, n, dtype=dtype)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        t_torch = best(torch.mm, a, a.clone())
    finally:
        torch.set_num_threads(before)
    with threadpool_limits(limits=threads, user_api="blas"):
        t_numpy = best(np.matmul, a.numpy(), a.numpy().copy())
    return 2 * n**3 / min(t_torch, t_numpy) / 1e9


@dataclass
class ProcessCost:
    """One child process: wall and CPU time [s] (user + system, its waited-for children included),
    the peak resident memory of its largest process [MiB] (exact, from ``wait4``) and the peak of
    its whole process tree's proportional set size [MiB] (sampled every 0.2 s; Linux only, else NaN)."""

    wall: float
    cpu: float
    peak_rss_mib: float
    peak_tree_mib: float

    MEMORY: ClassVar[tuple[str, str]] = ("peak RSS, largest process MiB", "peak PSS, process tree MiB")

    def memory(self) -> tuple[str, str]:
        return f"{self.peak_rss_mib:.0f}", f"{self.peak_tree_mib:.0f}"


def _tree_pss_mib(root: int) -> float:
    """Proportional set size [MiB] of ``root`` and its descendants now (Linux ``/proc``), NaN elsewhere."""
    parent: dict[int, int] = {}
    for d in Path("/proc").glob("[0-9]*"):
        try:
            parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    if root not in parent:
        return float("nan")
    tree, grew = {root}, True
    while grew:
        more = {p for p, pp in parent.items() if pp in tree} - tree
        tree |= more
        grew = bool(more)
    kib = 0
    for pid in tree:
        try:
            rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
        except OSError:
            continue
        kib += sum(int(line.split()[1]) for line in rollup.splitlines() if line.startswith("Pss:"))
    return kib / 1024


def run_process(cmd: list[str]) -> ProcessCost:
    """Run ``cmd`` (its output discarded, stderr kept for the error); its :class:`ProcessCost`.
    Exit codes 0 and 1 (the toolkit's "done, with warnings") count as success."""
    peak = [float("nan")]
    done = threading.Event()
    t0 = time.perf_counter()
    with subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as proc:
        def sample() -> None:
            while not done.wait(0.2):
                now = _tree_pss_mib(proc.pid)
                peak[0] = now if peak[0] != peak[0] else max(peak[0], now)  # NaN until the first sample

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        err = proc.stderr.read() if proc.stderr else ""  # drained while it runs: no pipe deadlock
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 1):
        raise UserError(f"{' '.join(cmd[:4])} ... failed (exit {proc.returncode}): {err.strip().splitlines()[-1:]}")
    return ProcessCost(wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, peak[0])  # ru_maxrss: KiB


class Table:
    """A markdown table (pasteable into ``docs/``)."""

    def __init__(self, header: Sequence[str]):
        self.header, self.rows = list(header), []

    def add(self, *cells: Any) -> None:
        self.rows.append([str(c) for c in cells])

    def render(self) -> str:
        lines = [self.header, ["---"] * len(self.header), *self.rows]
        return "\n".join("| " + " | ".join(line) + " |" for line in lines)


def write_figures(path: str | Path, figures: Mapping[str, Any]) -> None:
    """A target's figures as JSON at ``path`` (atomically)."""
    from som_torch import atomic_write  # here: `twomass --help` lists the targets without torch

    text = dumps(figures, indent=1)
    atomic_write(path, lambda f: f.write(text), text=True)
