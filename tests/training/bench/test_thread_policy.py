"""The simulator kernel's threads under the ``twomass`` command's thread policy, and its setting."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sim import _config
from sim._integrate_fast import kernel_threads

_UNDER_CLI = """
import os
for var in ("TWOMASS_SIM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.pop(var, None)  # the policy's defaults, not the caller's
from training.config import apply_process_defaults
apply_process_defaults()  # what `twomass` does first
import torch
from sim._integrate_fast import kernel_threads
print(torch.get_num_threads(), kernel_threads(100_000), os.environ["MKL_NUM_THREADS"])
"""


def test_the_cli_policy_keeps_blas_at_one_thread_and_gives_the_kernel_every_cpu() -> None:
    out = subprocess.run([sys.executable, "-c", _UNDER_CLI], capture_output=True, text=True, check=True).stdout.split()
    torch_threads, kernel, mkl = int(out[0]), int(out[1]), out[2]
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert mkl == "1" and torch_threads == 1  # BLAS limited: torch reports one thread
    assert kernel == cpus
    if cpus > 1:
        assert kernel > 1


@pytest.mark.parametrize(("env", "expected"), [
    ({"TWOMASS_SIM_THREADS": "3"}, 3),
    ({"TWOMASS_SIM_THREADS": "3", "OMP_NUM_THREADS": "1"}, 3),  # the simulator's own setting first
    ({"OMP_NUM_THREADS": "1"}, 1),  # the pool workers' limit
    ({"OMP_NUM_THREADS": "5,2"}, 5),  # OpenMP's nested list: the outer level
])
def test_kernel_threads_setting(monkeypatch: pytest.MonkeyPatch, env: dict[str, str], expected: int) -> None:
    for var in ("TWOMASS_SIM_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    for var, value in env.items():
        monkeypatch.setenv(var, value)
    assert _config.kernel_threads() == expected
    assert kernel_threads(32 * expected) == expected  # one block per thread at most
    assert kernel_threads(1) == 1


@pytest.mark.parametrize("value", ["0", "-2", "two", "1.5"])
def test_a_bad_thread_setting_is_an_error(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv("TWOMASS_SIM_THREADS", value)
    with pytest.raises(ValueError, match="TWOMASS_SIM_THREADS: expected a positive integer"):
        _config.kernel_threads()
