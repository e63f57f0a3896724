"""som_torch: the local linear read-out (fit_local_linear, recall through it, checkpoints)."""

from __future__ import annotations

import pytest
import torch

import som_torch as st
from som_torch._checkpoint import FORMAT, _digest


def _plane(n: int, seed: int = 0) -> torch.Tensor:
    """``n x 3`` rows ``(x0, x1, y)`` with ``y = 3 x0 - 2 x1 + 1`` exactly."""
    x = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 4.0
    return torch.cat([x, 3.0 * x[:, :1] - 2.0 * x[:, 1:] + 1.0], 1)


def _trained(data: torch.Tensor, grid: st.Grid = st.Grid(4, 4), maps: int = 2) -> st.SOM:
    som = st.SOM(grid, ["x0", "x1", "y"], [True, True, False], batch_shape=(maps,), dtype=torch.float64)
    st.fit(som, data, normalization="standard", seed=list(range(maps)), epochs=3, sigma=1.5)
    return som


@pytest.mark.parametrize("interpolate", [1, 3])
@pytest.mark.parametrize("topology", ["rectangular", "hexagonal"])
def test_a_plane_is_read_out_exactly_where_the_weights_alone_are_off(interpolate, topology):
    data = _plane(400)
    som = _trained(data, st.Grid(4, 5, topology))
    local = st.fit_local_linear(som, data, ridge=1e-12)
    q = _plane(9, seed=1)
    exact = q[:, 2]
    assert (st.recall(som, q[:, :2], interpolate=interpolate)["y"] - exact).abs().max() > 0.1
    torch.testing.assert_close(st.recall(local, q[:, :2], interpolate=interpolate)["y"],
                               exact.expand(2, -1), atol=1e-8, rtol=0)
    assert som.local is None and local.local is not None  # a copy: the trained maps are unchanged
    torch.testing.assert_close(st.recall(local, q[:, :2], interpolate=interpolate, local=False).values,
                               st.recall(som, q[:, :2], interpolate=interpolate).values, atol=0, rtol=0)


def _reference_fit(som: st.SOM, data: torch.Tensor, radius: float,
                   ridge: tuple[float, float]) -> tuple[torch.Tensor, ...]:
    """Unit by unit, map by map: least squares of y on [1, x - w] over the rows whose best match lies
    within ``radius`` (``ridge`` per slope), and their least and greatest y (the slow, obvious way)."""
    units, _ = st.best_matching_units(som, data)  # B x N
    x = som.normalize(data)[..., :2]  # B x N x 2
    d2 = som.grid.distances2
    b = torch.empty(2, som.n_units, 1, dtype=torch.float64)
    a = torch.zeros(2, som.n_units, 1, 2, dtype=torch.float64)
    lo, hi = b.clone(), b.clone()
    for m in range(2):
        for u in range(som.n_units):
            rows = (d2[u, units[m]] <= radius ** 2 + 1e-9).nonzero().squeeze(-1)
            if len(rows) == 0:
                b[m, u] = lo[m, u] = hi[m, u] = som.raw_weights[m, u, 2]
                continue
            lo[m, u], hi[m, u] = data[rows, 2].min(), data[rows, 2].max()
            z = torch.cat([torch.ones(len(rows), 1, dtype=torch.float64), x[m, rows] - som.weights[m, u, :2]], 1)
            gram = z.T @ z + len(rows) * torch.diag(torch.tensor([0.0, *ridge], dtype=torch.float64))
            sol = torch.linalg.solve(gram, z.T @ data[rows, 2:])
            b[m, u], a[m, u, 0] = sol[0], sol[1:, 0]
    return b, a, lo, hi


@pytest.mark.parametrize(("radius", "ridge"), [(0.0, 0.01), (1.0, 0.01), (1.5, 0.01), (2.5, 0.01), (1.5, (0.01, 3.0)),
                                             (1.0, torch.tensor([2.0, 1e-4]))])
def test_the_vectorized_fit_equals_a_unit_by_unit_least_squares(radius, ridge):
    data = _plane(300)
    data[:, 2] += torch.sin(3.0 * data[:, 0]) * data[:, 1]  # not a plane: the fits differ per unit
    som = _trained(data, st.Grid(5, 5))
    som.weights = som.weights.clone()
    som.weights[:, 0] = 50.0  # a unit far from every row: no data in its neighbourhood
    local = st.fit_local_linear(som, data, radius=radius, ridge=ridge).local
    per_slope = (ridge, ridge) if isinstance(ridge, float) else tuple(map(float, ridge))
    b, a, lo, hi = _reference_fit(som, data, radius, per_slope)
    torch.testing.assert_close(local.intercepts, b)
    torch.testing.assert_close(local.slopes, a)
    torch.testing.assert_close(local.lower, lo)
    torch.testing.assert_close(local.upper, hi)
    if radius == 0.0:  # unit 0 alone holds no row: its weights kept, flat
        assert torch.equal(local.slopes[:, 0], torch.zeros(2, 1, 2, dtype=torch.float64))
        torch.testing.assert_close(local.intercepts[:, 0, 0], som.raw_weights[:, 0, 2])


def test_a_nan_feature_reads_as_at_the_units_weights_and_nan_rows_are_left_out():
    data = _plane(300)
    som = _trained(data)
    with_nan = torch.cat([data, torch.tensor([[torch.nan, 1.0, 1e6]], dtype=torch.float64)])
    local = st.fit_local_linear(som, with_nan, ridge=1e-12)
    torch.testing.assert_close(local.local.intercepts, st.fit_local_linear(som, data, ridge=1e-12).local.intercepts)
    q = torch.tensor([[torch.nan, 1.0]], dtype=torch.float64)
    r = st.recall(local, q)
    u = r.units[:, 0]
    w = local.weights[torch.arange(2), u]  # 2 x C (normalized)
    dx1 = 1.0 - local.denormalize(w.unsqueeze(-2))[:, 0, 1]  # raw
    expected = local.local.intercepts[torch.arange(2), u, 0] + local.local.slopes[torch.arange(2), u, 0, 1] * (
        dx1 / local.scale[:, 1])
    expected = expected.clamp(local.local.lower[torch.arange(2), u, 0], local.local.upper[torch.arange(2), u, 0])
    torch.testing.assert_close(r["y"][:, 0], expected)


def test_training_or_renormalizing_drops_the_read_out():
    data = _plane(200)
    local = st.fit_local_linear(_trained(data), data)
    again = local.clone()
    st.fit(again, data, normalization="standard", seed=[0, 1], epochs=1)
    assert again.local is None
    again = local.clone()
    again.fit_normalization(data, "range")
    assert again.local is None
    assert local[1].local.slopes.shape == (16, 1, 2)  # indexing keeps it, per map


def test_maps_with_different_masks_or_bad_options_are_refused():
    data = _plane(50)
    som = st.SOM(st.Grid(3, 3), ["x0", "x1", "y"], [[True, True, False], [True, False, False]], batch_shape=(2,))
    with pytest.raises(ValueError, match="one active mask"):
        st.fit_local_linear(som, data)
    for ridge in (0.0, (0.1,), (0.1, -1.0), (0.1, float("nan")), "0.1", True):
        with pytest.raises(ValueError, match="ridge: expected a positive number or 2 positive numbers"):
            st.fit_local_linear(_trained(data), data, ridge=ridge)
    with pytest.raises(ValueError, match="radius"):
        st.fit_local_linear(_trained(data), data, radius=-1)


def test_a_checkpoint_keeps_the_read_out_and_its_hash_covers_it(tmp_path):
    data = _plane(200)
    local = st.fit_local_linear(_trained(data), data)
    path = tmp_path / "m.pt"
    st.save_checkpoint(path, local, {"k": 1})
    back, _ = st.load_checkpoint(path)
    torch.testing.assert_close(st.recall(back, data[:, :2]).values, st.recall(local, data[:, :2]).values)
    payload = torch.load(path, weights_only=True)
    payload["tensors"]["local_slopes"] = payload["tensors"]["local_slopes"] * 1.01
    torch.save(payload, path)
    with pytest.raises(st.CheckpointError, match="content hash mismatch"):
        st.load_checkpoint(path)


def test_a_version_1_checkpoint_still_loads_without_a_read_out(tmp_path):
    som = _trained(_plane(100))
    header = {"format": FORMAT, "format_version": 1, "grid": som.grid.to_dict(),
              "component_names": som.component_names, "metadata_json": "{}"}
    tensors = {"weights": som.weights, "active": som.active, "offset": som.offset, "scale": som.scale}
    torch.save({**header, "tensors": tensors, "sha256": _digest(header, tensors)}, tmp_path / "v1.pt")
    back, meta = st.load_checkpoint(tmp_path / "v1.pt")
    assert back.local is None and meta == {} and torch.equal(back.weights, som.weights)


def test_a_sample_far_from_the_data_reads_no_more_than_its_units_data_showed():
    data = _plane(300)
    local = st.fit_local_linear(_trained(data), data, ridge=1e-12)
    r = st.recall(local, torch.tensor([[40.0, -40.0]], dtype=torch.float64))  # the plane: 201; the data: <= 13
    u = r.units[:, 0]
    torch.testing.assert_close(r["y"][:, 0], local.local.upper[torch.arange(2), u, 0])
    assert float(r["y"].max()) <= float(data[:, 2].max())
