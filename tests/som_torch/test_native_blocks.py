"""The native kernel's blocks of units (each block's weights contiguous; weights, neighbourhood weights and
distances in registers), the last one padded: against the torch reference, at unit counts around a block's
size; the layout check."""

from __future__ import annotations

import math
import shutil

import pytest
import torch

import som_torch as st
from som_torch import _config, _native
from som_torch._cbuild import CKernel

native = pytest.mark.skipif(not _native.available(), reason="no C compiler")

# Units per block: 8, 16, 32 or 64 (float64 / float32, SSE, AVX or AVX-512): counts below, at and above each.
GRIDS = [(1, 7), (3, 3), (4, 4), (1, 17), (3, 11), (7, 9), (8, 8), (5, 13), (3, 11, "hexagonal"),
         (7, 9, "hexagonal")]


def _data(n: int, seed: int) -> torch.Tensor:
    """``n x 5``: four smooth features of one parameter (last column), NaN in some features."""
    p = torch.rand(n, 1, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    x = torch.cat([torch.cos(math.pi * p), torch.sin(math.pi * p), p * p, torch.cos(3 * p), p], -1)
    x[::5, 1] = float("nan")  # a step without component 1: its weights stay, its distance is left out
    x[2::7, 3] = float("nan")
    return x


def _som(grid: tuple[int, int], dtype: torch.dtype) -> st.SOM:
    return st.SOM(st.Grid(*grid), ["c", "s", "q", "k", "p"], [True, True, True, True, False], dtype=dtype)  # grid: rows, cols[, topology]


@native
@pytest.mark.parametrize("grid", GRIDS)
@pytest.mark.parametrize("neighbourhood", sorted(st.NEIGHBOURHOODS))
def test_blocks_and_remaining_units_equal_the_reference(grid, neighbourhood):
    data = _data(30, sum(grid[:2]))
    som = _som(grid, torch.float64)
    st.init_random(som, data, 1)
    fast, ref = som.clone(), som.clone()
    opts = dict(epochs=2, learning_rate=(0.5, 0.05), sigma=(2.0, 0.5), neighbourhood=neighbourhood, seed=4)
    st.train_online(fast, data, method="native", **opts)
    st.train_online(ref, data, method="reference", **opts)
    torch.testing.assert_close(fast.weights, ref.weights, rtol=0, atol=1e-9)


@native
@pytest.mark.parametrize("grid", GRIDS)
def test_float32_blocks_close_to_the_reference(grid):
    data = _data(30, sum(grid[:2]))
    som = _som(grid, torch.float32)
    st.init_random(som, data, 1)
    ref = _som(grid, torch.float64)
    ref.weights = som.weights.to(torch.float64)
    st.train_online(som, data, epochs=2, sigma=2.0, seed=4, method="native")
    st.train_online(ref, data, epochs=2, sigma=2.0, seed=4, method="reference")
    torch.testing.assert_close(som.weights.double(), ref.weights, rtol=0, atol=1e-4)


@native
@pytest.mark.parametrize("topology", ["rectangular", "hexagonal"])
def test_one_gaussian_step_by_hand(topology):
    # 2 x 3 units, one sample next to unit 4: each unit moves by lr exp(-d^2 / (2 sigma^2)) of its
    # distance to the sample, d the grid distance to unit 4 from positions written out here
    h = math.sqrt(3.0) / 2.0 if topology == "hexagonal" else 1.0
    shift = 0.5 if topology == "hexagonal" else 0.0
    pos = [(0, 0), (0, 1), (0, 2), (h, shift), (h, 1 + shift), (h, 2 + shift)]
    som = st.SOM(st.Grid(2, 3, topology), ["a", "b"], [True, True], dtype=torch.float64)
    w0 = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0], [1.0, 1.0], [2.0, 1.0]], dtype=torch.float64)
    som.weights = w0.clone()
    x = torch.tensor([[1.1, 0.9]], dtype=torch.float64)
    lr, sigma = 0.5, 0.8
    st.train_online(som, x, epochs=1, learning_rate=(lr, lr), sigma=(sigma, sigma), schedule="constant",
                    method="native")
    b = pos[4]
    g = torch.tensor([lr * math.exp(-((p[0] - b[0]) ** 2 + (p[1] - b[1]) ** 2) / (2 * sigma ** 2)) for p in pos],
                     dtype=torch.float64)
    torch.testing.assert_close(som.weights, w0 + g[:, None] * (x - w0), rtol=0, atol=1e-15)


@native
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_layout_that_does_not_fit_the_build_is_refused(dtype):
    L = _native.lanes(dtype)
    assert L in (8, 16, 32, 64)
    fn = _native.kernel(dtype)
    U, C, N = 6, 2, 1
    z = lambda *shape: torch.zeros(*shape, dtype=dtype)  # noqa: E731
    for NB, lanes in ((1, L), (1, 2 * L), (2, L)):
        args = (1, U, C, N, NB, lanes, z(1, NB, C, lanes), z(N, 1, C), None, torch.ones(1, C, dtype=dtype), 2, 3,
                z(2), z(2, 3), None, z(N, 1) + 0.1, z(N, 1) + 1.0, 0, 1, z(1, NB, lanes), z(1, NB, lanes),
                torch.zeros(N, 1, dtype=torch.long))
        assert fn(*args) == (0 if (NB, lanes) == (1, L) else -1)


@native
@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
def test_the_scalar_build_equals_the_reference(tmp_path, monkeypatch):
    # compilers without vector extensions (-DSOM_TORCH_SCALAR here): blocks of one unit, loops over units
    k = _native.KERNEL
    scalar = CKernel("som_torch_epoch_scalar", k.source, k.functions, flags=(*k.flags, "-DSOM_TORCH_SCALAR"),
                     link_flags=k.link_flags).load(tmp_path, _config.compiler())
    monkeypatch.setattr(_native, "_library", lambda: scalar)
    assert _native.lanes(torch.float64) == 1
    data = _data(30, 3)
    som = _som((3, 11, "hexagonal"), torch.float64)
    st.init_random(som, data, 1)
    fast, ref = som.clone(), som.clone()
    opts = dict(epochs=2, learning_rate=(0.5, 0.05), sigma=(2.0, 0.5), seed=4)
    st.train_online(fast, data, method="native", **opts)
    st.train_online(ref, data, method="reference", **opts)
    torch.testing.assert_close(fast.weights, ref.weights, rtol=0, atol=1e-9)
