"""The native kernel over maps on several threads: the same bits as on one; its thread setting."""

from __future__ import annotations

import math

import pytest
import torch

import som_torch as st
from som_torch import _config, _native

native = pytest.mark.skipif(not _native.available(), reason="no C compiler")


def _data(maps: int, n: int = 40) -> torch.Tensor:
    """``maps x n x 4``: three smooth features of one parameter (last column), NaN in a few."""
    p = torch.rand(maps, n, 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = torch.cat([torch.cos(math.pi * p), torch.sin(math.pi * p), p * p, p], -1)
    x[:, ::7, 1] = float("nan")
    return x


def _trained(threads: str, monkeypatch, dtype: torch.dtype, maps: int = 5) -> torch.Tensor:
    monkeypatch.setenv("SOM_TORCH_THREADS", threads)
    data = _data(maps)
    som = st.SOM(st.Grid(6, 5), ["c", "s", "q", "p"], [True, True, True, False], batch_shape=(maps,), dtype=dtype)
    st.fit(som, data, normalization="range", seed=list(range(maps)), epochs=2, sigma=(3.0, 0.5), method="native")
    return som.weights


@native
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_maps_on_two_threads_give_the_bits_of_one(monkeypatch, dtype):
    one = _trained("1", monkeypatch, dtype)
    assert _native.threads(5) == 1
    two = _trained("2", monkeypatch, dtype)
    assert _native.threads(5) == 2 and _native.threads(1) == 1  # one map: one thread
    assert torch.equal(one, two)
    assert torch.equal(one, _trained("4", monkeypatch, dtype))  # more threads than cores


def test_thread_setting(monkeypatch):
    monkeypatch.delenv("SOM_TORCH_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3,1")
    assert _config.kernel_threads() == 3
    monkeypatch.setenv("SOM_TORCH_THREADS", "2")
    assert _config.kernel_threads() == 2
    monkeypatch.delenv("SOM_TORCH_THREADS")
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert _config.kernel_threads() >= 1
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv("SOM_TORCH_THREADS", bad)
        with pytest.raises(ValueError, match=f"SOM_TORCH_THREADS: expected a positive integer, received '{bad}'"):
            _config.kernel_threads()
