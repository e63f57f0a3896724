"""The numpy RK4 baseline of ``twomass bench sim`` and the simulator's torch eager fallback do the
kernel's work: same test, same numbers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sim import DriveConfig, TestSignalConfig, sample_population
from sim._integrate_fast import FastParams, default_substeps
from sim._kernel import load_kernel
from training.bench._sim import kernel_test, numpy_test, torch_test


@pytest.mark.skipif(load_kernel() is None, reason="no C compiler: no kernel to compare with")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numpy_baseline_and_torch_fallback_match_the_kernel_bit_for_bit(dtype: torch.dtype) -> None:
    # a short test (w_max 20 rad/s, sections time out after 0.1 s): every section, timeouts and
    # finished systems within 1000 samples
    drive, signal = DriveConfig(), TestSignalConfig(w_max=20.0, timeout=0.1)
    params = sample_population(32, 3)
    fp = FastParams.build(params, drive, default_substeps(params, drive), dtype)
    _, kernel = kernel_test(fp, drive, signal, 1000)
    _, ours = numpy_test(fp, drive, signal, 1000)
    _, fallback = torch_test(params, fp, drive, signal, 1000)
    valid = ours.section >= 0  # -1: finished (the kernel leaves those columns unwritten)
    assert set(np.unique(ours.section)) == {-1, 0, 1, 2, 3, 4, 5, 6}
    in_one = (ours.section == 1).sum(1)
    assert (in_one == signal.n_timeout(drive)).any(), "no system timed out in section I"
    assert 0 < (~valid).any(1).sum() < 32
    np.testing.assert_array_equal(fallback.section.numpy(), ours.section)  # the same records, -1 once finished
    for name in ("speed", "torque", "torque_ref", "section"):
        np.testing.assert_array_equal(getattr(ours, name)[valid], kernel[name].numpy()[valid], err_msg=name)
        np.testing.assert_array_equal(getattr(fallback, name).numpy()[valid], kernel[name].numpy()[valid],
                                      err_msg=f"torch {name}")
    assert ours.speed.dtype == kernel["speed"].numpy().dtype
