"""som_torch: grids, hand-computed steps, masking, batching, determinism, recall, quality."""

from __future__ import annotations

import math

import pytest
import torch

import som_torch as st
from som_torch import _native

torch.set_default_dtype(torch.float32)
FAST = ["torch", pytest.param("native", marks=pytest.mark.skipif(not _native.available(), reason="no C compiler"))]


def tiny_som(dtype=torch.float64) -> st.SOM:
    """1 x 3 map, component 'a' active, 'p' inactive."""
    som = st.SOM(st.Grid(1, 3), ["a", "p"], [True, False], dtype=dtype)
    som.weights = torch.tensor([[0.0, 10.0], [1.0, 20.0], [2.0, 30.0]], dtype=dtype)
    return som


def smooth_data(n: int, seed: int, batch=()) -> torch.Tensor:
    """Features that are smooth functions of one parameter p (last column)."""
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(*batch, n, 1, generator=g, dtype=torch.float64)
    f = torch.cat([torch.cos(math.pi * p), torch.sin(math.pi * p), p * p], -1)
    return torch.cat([f, p], -1)  # *batch x n x 4


def small_som(batch=(), dtype=torch.float64, topology="rectangular") -> st.SOM:
    return st.SOM(st.Grid(5, 4, topology), ["c", "s", "q", "p"], [True, True, True, False],
                  batch_shape=batch, dtype=dtype)


# --- grid -----------------------------------------------------------------------------------
def test_grid_coords_and_adjacency():
    rect = st.Grid(3, 4)
    assert rect.coords.shape == (12, 2)
    assert rect.distances2[0, 5].item() == 2.0  # (0,0)-(1,1)
    assert int(rect.adjacency[5].sum()) == 8  # interior unit, diagonals included
    hexg = st.Grid(4, 4, "hexagonal")
    inner = 1 * 4 + 1  # row 1 (shifted), col 1
    assert int(hexg.adjacency[inner].sum()) == 6
    d = hexg.distances2[inner][hexg.adjacency[inner]]
    torch.testing.assert_close(d, torch.ones_like(d))
    with pytest.raises(ValueError, match="expected one of"):
        st.Grid(2, 2, "triangular")


def test_hexagonal_positions_by_hand():
    # odd rows shifted by half a unit, rows sqrt(3)/2 apart; the axes are the positions' product form
    g = st.Grid(2, 3, "hexagonal")
    h = math.sqrt(3.0) / 2.0
    expected = [[0, 0], [0, 1], [0, 2], [h, 0.5], [h, 1.5], [h, 2.5]]
    torch.testing.assert_close(g.coords, torch.tensor(expected, dtype=torch.float64), rtol=0, atol=0)
    y, x = g.axes
    assert y.tolist() == [0.0, h] and x.tolist() == [[0.0, 1.0, 2.0], [0.5, 1.5, 2.5]]


# --- hand-computed BMU, neighbourhood, one update ------------------------------------------
def test_bmu_uses_active_components_only():
    som = tiny_som()
    x = torch.tensor([[0.9, 100.0]])
    units, d2 = st.best_matching_units(som, x)
    assert units.tolist() == [1]  # with 'p' in the distance unit 2 would win
    assert d2.item() == pytest.approx(0.01)
    all_active = st.SOM(som.grid, ["a", "p"], [True, True], weights=som.weights.clone())
    assert st.best_matching_units(all_active, x)[0].tolist() == [2]


@pytest.mark.parametrize("with_nan", [False, True])
def test_distances_equal_the_sum_over_active_present_components(with_nan):
    """Both paths of ``distances`` (every sample complete; samples with NaN) against the plain sum."""
    g = torch.Generator().manual_seed(1)
    active = torch.tensor([[True, False, True, True], [True, True, False, True]])
    som = st.SOM(st.Grid(3, 3), ["a", "b", "c", "p"], active, weights=torch.rand(2, 9, 4, generator=g))
    x = torch.rand(2, 11, 4, generator=g, dtype=torch.float64)
    if with_nan:
        x[0, 3, 0] = x[1, 5, 3] = torch.nan
    xn = som.normalize(x)
    use = active[:, None, None, :] & ~torch.isnan(xn)[:, :, None, :]  # 2 x 11 x 1 x 4
    diff = torch.where(use, xn[:, :, None, :] - som.weights.to(torch.float64)[:, None, :, :], 0.0)
    torch.testing.assert_close(st.distances(som, x), (diff * diff).sum(-1), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [1, 3])
def test_best_matches_in_chunks_equal_all_at_once(monkeypatch, k):
    """Samples worked through in chunks (memory flat in their number) give the unchunked answer."""
    from som_torch import _recall

    g = torch.Generator().manual_seed(0)
    som = st.SOM(st.Grid(4, 5), ["a", "b", "p"], [True, True, False],
                 weights=torch.rand(3, 20, 3, generator=g, dtype=torch.float64))
    x = torch.rand(3, 50, 3, generator=g, dtype=torch.float64)
    d2 = st.distances(som, x)  # 3 x 50 x 20, all at once
    expected = d2.min(-1) if k == 1 else torch.topk(d2, k, dim=-1, largest=False, sorted=True)
    monkeypatch.setattr(_recall, "CHUNK_ELEMENTS", 7 * 3 * 20)  # chunks of 7 samples: 8 chunks, the last short
    units, dist = st.best_matching_units(som, x, k=k)
    assert torch.equal(units, expected.indices)
    torch.testing.assert_close(dist, expected.values, rtol=1e-12, atol=1e-15)  # BLAS blocks by chunk size


@pytest.mark.parametrize("method", ["fast", "torch", "reference"])
def test_one_update_step_by_hand(method):
    som = tiny_som()
    x = torch.tensor([[0.9, 100.0]], dtype=torch.float64)
    st.train_online(som, x, epochs=1, learning_rate=0.5, sigma=1.0, schedule="constant", shuffle=False, method=method)
    h = torch.tensor([math.exp(-0.5), 1.0, math.exp(-0.5)], dtype=torch.float64)
    w0 = tiny_som().weights
    expected = w0 + 0.5 * h[:, None] * (x - w0)
    torch.testing.assert_close(som.weights, expected, rtol=0, atol=1e-12)
    # the inactive component moved too
    assert som.weights[1, 1].item() == pytest.approx(20.0 + 0.5 * 80.0)


def test_neighbourhood_functions_by_hand():
    d2 = torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64)
    s = torch.tensor(1.5, dtype=torch.float64)
    nb = st.NEIGHBOURHOODS
    torch.testing.assert_close(nb["gaussian"](d2, s), torch.exp(-d2 / 4.5))
    assert nb["bubble"](d2, s).tolist() == [1.0, 1.0, 0.0]
    torch.testing.assert_close(nb["cut_gaussian"](d2, s), torch.tensor([1.0, math.exp(-1 / 4.5), 0.0], dtype=torch.float64))
    torch.testing.assert_close(nb["epanechnikov"](d2, s), torch.tensor([1.0, 1 - 1 / 2.25, 0.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="bubble"):
        st.train_online(tiny_som(), torch.zeros(1, 2), neighbourhood="mexican")


def test_schedules():
    t = torch.arange(4.0, dtype=torch.float64)[:, None]
    one, end = torch.ones(1, dtype=torch.float64), torch.full((1,), 0.25, dtype=torch.float64)
    torch.testing.assert_close(st.SCHEDULES["asymptotic"](one, end, t, 4)[:, 0], 1 / (1 + t[:, 0] / 2))
    torch.testing.assert_close(st.SCHEDULES["linear"](one, end, t, 4)[:, 0], 1 - 0.75 * t[:, 0] / 4)
    torch.testing.assert_close(st.SCHEDULES["exponential"](one, end, t, 4)[:, 0], 0.25 ** (t[:, 0] / 4))


# --- masking --------------------------------------------------------------------------------
def test_inactive_components_never_change_the_best_match():
    data = smooth_data(40, 1)
    som = small_som()
    st.init_random(som, data, 3)
    before = st.best_matching_units(som, data)[0]
    scrambled = data.clone()
    scrambled[:, 3] = torch.randn(40, dtype=torch.float64) * 1e3
    assert torch.equal(st.best_matching_units(som, scrambled)[0], before)
    # training with scrambled inactive values: same BMU sequence -> same active weights
    a, b = som.clone(), som.clone()
    st.train_online(a, data, epochs=2, sigma=2.0, seed=5)
    st.train_online(b, scrambled, epochs=2, sigma=2.0, seed=5)
    torch.testing.assert_close(a.weights[:, :3], b.weights[:, :3], rtol=0, atol=1e-12)
    assert not torch.allclose(a.weights[:, 3], b.weights[:, 3])  # but the inactive one was moved


# --- batching and determinism ---------------------------------------------------------------
@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
@pytest.mark.parametrize("mode", ["online", "batch"])
def test_batch_equals_each_map_alone(batch, mode):
    data = smooth_data(30, 2, batch)
    seeds = torch.arange(int(torch.Size(batch).numel())).reshape(batch) + 10
    som = small_som(batch)
    st.fit(som, data, mode=mode, seed=seeds, epochs=2, sigma=2.0)
    for idx in ([()] if not batch else list(torch.cartesian_prod(*[torch.arange(n) for n in batch]).reshape(-1, len(batch)))):
        idx = tuple(int(i) for i in idx)
        alone = small_som()
        st.fit(alone, data[idx], mode=mode, seed=[int(seeds[idx])], epochs=2, sigma=2.0)
        torch.testing.assert_close(som.weights[idx], alone.weights, rtol=0, atol=1e-10)


def test_maps_with_different_feature_counts_share_a_batch():
    data = smooth_data(30, 4, (2,))
    active = torch.tensor([[True, True, True, False], [True, True, False, False]])
    padded = data.clone()
    padded[1, :, 2] = 0.0  # map 1 has only two features: pad column 'q' with 0 and mark it inactive
    som = st.SOM(st.Grid(5, 4), ["c", "s", "q", "p"], active, batch_shape=(2,), dtype=torch.float64)
    st.init_random(som, padded, [1, 2])
    alone = st.SOM(st.Grid(5, 4), ["c", "s", "p"], [True, True, False], dtype=torch.float64)
    alone.weights = som.weights[1][:, [0, 1, 3]].clone()  # same start (random draws depend on C)
    st.train_online(som, padded, seed=[1, 2], epochs=2, sigma=2.0)
    st.train_online(alone, data[1][:, [0, 1, 3]], seed=[2], epochs=2, sigma=2.0)
    assert torch.equal(som.weights[1][:, 2], torch.zeros(20, dtype=torch.float64))  # padding stays 0
    torch.testing.assert_close(som.weights[1][:, [0, 1, 3]], alone.weights, rtol=0, atol=1e-10)


def test_same_seed_same_weights_and_different_seed_differs():
    data = smooth_data(50, 3)
    runs = []
    for seed in (7, 7, 8):
        som = st.SOM(st.Grid(6, 6), ["c", "s", "q", "p"], [True, True, True, False])
        st.fit(som, data, seed=seed, epochs=2)
        runs.append(som.weights)
    assert torch.equal(runs[0], runs[1])
    assert not torch.equal(runs[0], runs[2])


@pytest.mark.parametrize("method", FAST)
@pytest.mark.parametrize("neighbourhood", sorted(st.NEIGHBOURHOODS))
@pytest.mark.parametrize("schedule", sorted(st.SCHEDULES))
def test_fast_path_equals_reference(neighbourhood, schedule, method):
    data = smooth_data(25, 6, (2,))
    som = small_som((2,), topology="hexagonal" if schedule == "linear" else "rectangular")
    st.init_random(som, data, [1, 2])
    fast, ref = som.clone(), som.clone()
    opts = dict(epochs=2, learning_rate=(0.5, 0.05), sigma=(2.5, 1.0), schedule=schedule,
                neighbourhood=neighbourhood, seed=[3, 4], refresh_every=7)
    st.train_online(fast, data, method=method, **opts)
    st.train_online(ref, data, method="reference", **opts)
    torch.testing.assert_close(fast.weights, ref.weights, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", FAST)
def test_float32_fast_path_close_to_reference(method):
    data = smooth_data(40, 6)
    som = small_som(dtype=torch.float32)
    st.init_random(som, data, 1)
    ref = small_som()
    ref.weights = som.weights.to(torch.float64)
    st.train_online(som, data, epochs=2, sigma=2.0, seed=1, method=method)
    st.train_online(ref, data, epochs=2, sigma=2.0, seed=1, method="reference")
    torch.testing.assert_close(som.weights.double(), ref.weights, rtol=0, atol=1e-4)


# --- training quality and recall ------------------------------------------------------------
def test_quantization_error_falls_with_training():
    data = smooth_data(200, 8)
    som = st.SOM(st.Grid(8, 8), ["c", "s", "q", "p"], [True, True, True, False])
    st.init_random(som, data, 0)
    qes = [float(st.quantization_error(som, data))]
    for _ in range(3):
        st.train_online(som, data, epochs=1, learning_rate=(0.3, 0.05), sigma=(2.0, 0.7), seed=len(qes))
        qes.append(float(st.quantization_error(som, data)))
    assert qes[1] < 0.5 * qes[0] and qes[-1] < qes[1], qes


@pytest.mark.parametrize("mode", ["online", "batch"])
def test_recall_of_a_smooth_parameter(mode):
    """Features are smooth functions of p: recall p within 0.03 median, 0.1 max abs error (p in 0..1)."""
    som = st.SOM(st.Grid(10, 10), ["c", "s", "q", "p"], [True, True, True, False])
    opts = dict(learning_rate=(0.5, 0.02), schedule="linear") if mode == "online" else dict(schedule="linear")
    st.fit(som, smooth_data(500, 9), mode=mode, normalization="range", seed=0, epochs=10, sigma=(5.0, 0.5), **opts)
    test = smooth_data(200, 10)
    for k in (1, 4):
        got = st.recall(som, test[:, :3], interpolate=k)["p"]  # features only (n_active columns)
        err = (got - test[:, 3]).abs()
        assert err.median() < 0.03 and err.max() < 0.1, (k, err.median(), err.max())
    order = st.degree_of_order(som)
    assert order[3] > 0.85  # the parameter map is smooth ...
    shuffled = som.clone()
    shuffled.weights = som.weights[torch.randperm(100, generator=torch.Generator().manual_seed(0))]
    assert st.degree_of_order(shuffled)[3] < 0.3  # ... and a shuffled one is not


def test_nan_features_skipped():
    som = tiny_som()
    units, d2 = st.best_matching_units(som, torch.tensor([[float("nan"), 100.0], [1.9, float("nan")]]))
    assert units.tolist() == [-1, 2] and math.isnan(d2[0])  # no active value: no match (unit -1, NaN)
    som2 = st.SOM(st.Grid(1, 3), ["a", "b", "p"], [True, True, False], dtype=torch.float64)
    som2.weights = torch.tensor([[0.0, 5.0, 1.0], [1.0, 0.0, 2.0], [2.0, 9.0, 3.0]], dtype=torch.float64)
    r = st.recall(som2, torch.tensor([[float("nan"), 0.2, 0.0], [2.1, float("nan"), 0.0]]))
    assert r.units.tolist() == [1, 2] and r["p"].tolist() == [2.0, 3.0]
    # training with NaN: NaN components stay put, the rest learns, no NaN leaks in
    data = smooth_data(60, 11)
    data[::3, 0] = float("nan")
    data[1::7, 3] = float("nan")
    s = small_som()
    st.init_random(s, data, 0)
    ref = s.clone()
    st.train_online(ref, data, epochs=2, sigma=2.0, seed=2, method="reference")
    for method in ("torch", "native") if _native.available() else ("torch",):
        fast = s.clone()
        st.train_online(fast, data, epochs=2, sigma=2.0, seed=2, method=method)
        assert not torch.isnan(fast.weights).any()
        torch.testing.assert_close(fast.weights, ref.weights, rtol=0, atol=1e-9)
    st.train_batch(s, data, epochs=2, sigma=2.0)
    assert not torch.isnan(s.weights).any()
    assert torch.isfinite(st.quantization_error(s, data)).all()


def test_quality_measures_by_hand():
    som = tiny_som()
    data = torch.tensor([[0.0, 0.0], [1.5, 0.0], [2.0, 5.0]], dtype=torch.float64)
    assert st.quantization_error(som, data).item() == pytest.approx((0 + 0.5 + 0) / 3)
    assert st.topographic_error(som, data).item() == 0.0  # neighbours on a 1x3 line
    assert st.hit_counts(som, data).tolist() == [[1, 1, 1]]
    torch.testing.assert_close(st.u_matrix(som), torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64))
    far = st.SOM(st.Grid(1, 3), ["a", "p"], [True, False], weights=torch.tensor([[0.0, 0], [5.0, 0], [0.1, 0]]))
    assert st.topographic_error(far, torch.tensor([[0.0, 0.0]])).item() == 1.0  # best 0, second 2: not adjacent
    order = st.degree_of_order(som)
    assert order[0].item() == pytest.approx(1 - 1 / (2 * 2 / 3))  # msd 1, var 2/3


def test_linear_init_spans_the_principal_plane():
    data = smooth_data(100, 12)
    som = small_som()
    st.initialize(som, data, "linear")
    assert st.quantization_error(som, data) < 0.3
    with pytest.raises(ValueError, match="linear"):
        st.initialize(som, data, "pca2")


def test_input_errors_name_the_shapes():
    som = small_som((2,))
    with pytest.raises(ValueError, match=r"\(7, 3\)"):
        st.train_online(som, torch.zeros(7, 3))
    with pytest.raises(ValueError, match="active"):
        st.SOM(st.Grid(2, 2), ["a", "b"], [False, False])
    with pytest.raises(ValueError, match="seed"):
        st.init_random(som, smooth_data(5, 0), [1, 2, 3])
    with pytest.raises(ValueError, match="reference"):
        st.train_online(som, smooth_data(5, 0), method="slow")
    with pytest.raises(ValueError, match="learning_rate"):
        st.train_online(som, smooth_data(5, 0), learning_rate=torch.ones(3))


@pytest.mark.parametrize("method", ["reference", *FAST])
def test_all_nan_rows_are_no_op_steps(method):
    """Maps with fewer samples share a batch by padding with all-NaN rows: they move nothing."""
    som = small_som()
    st.init_random(som, smooth_data(20, 1), 0)
    before = som.weights.clone()
    st.train_online(som, torch.full((6, 4), float("nan"), dtype=torch.float64), epochs=2, sigma=2.0, method=method)
    assert torch.equal(som.weights, before)
    st.train_batch(som, torch.full((6, 4), float("nan"), dtype=torch.float64), epochs=1, sigma=2.0)
    assert torch.equal(som.weights, before)


def test_progress_and_hooks(capsys):
    seen = []
    som = small_som()
    st.fit(som, smooth_data(20, 1), epochs=3, sigma=2.0, progress=True,
           hooks=[lambda epoch, s, info: seen.append((epoch, info["step"], float(info["sigma"])))])
    assert [e for e, _, _ in seen] == [0, 1, 2] and [s for _, s, _ in seen] == [20, 40, 60]
    assert seen[0][2] > seen[-1][2]


def test_loading_the_native_kernel_keeps_subnormals():
    """A library linked with -ffast-math would flush subnormals for the whole process on load."""
    import numpy as np

    import som_torch as st

    st.native_available()  # builds/loads the kernel when a compiler is present
    tiny = np.float64(5e-324)
    assert tiny > 0 and tiny / 2 == 0 and np.nextafter(0.0, 1.0) > 0
