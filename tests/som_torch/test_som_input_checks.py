"""som_torch input checks: bad input gives a one-line ValueError/TypeError naming the argument;
samples without a usable feature give NaN, never a perfect-looking answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import som_torch as st

NAN = float("nan")


def tiny_som() -> st.SOM:
    """1 x 3 map, component 'a' active, 'p' inactive: units at a = 0, 1, 2 with p = 10, 20, 30."""
    som = st.SOM(st.Grid(1, 3), ["a", "p"], [True, False], dtype=torch.float64)
    som.weights = torch.tensor([[0.0, 10.0], [1.0, 20.0], [2.0, 30.0]], dtype=torch.float64)
    return som


def data(n: int = 12) -> torch.Tensor:
    return torch.rand(n, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))


# --- 1. schedule ends -----------------------------------------------------------------------
@pytest.mark.parametrize("method", ["torch", "reference", "fast"])
@pytest.mark.parametrize("kw, name", [(dict(sigma=(2.0, 0.0)), "sigma"), (dict(sigma=(2.0, -1.0)), "sigma"),
                                      (dict(learning_rate=(0.5, -0.1)), "learning_rate")])
def test_exponential_schedule_refuses_end_not_positive(method, kw, name):
    with pytest.raises(ValueError, match=f"^{name}: expected a finite end value > 0"):
        st.train_online(tiny_som(), data(), epochs=1, schedule="exponential", method=method, **kw)


def test_schedule_end_checks_per_schedule():
    # linear may end at 0 (a learning rate decaying to 0); no schedule takes a negative or NaN end
    som = st.train_online(tiny_som(), data(), epochs=1, schedule="linear", learning_rate=(0.5, 0.0),
                          sigma=(1.0, 0.0), method="torch")
    assert bool(torch.isfinite(som.weights).all())
    with pytest.raises(ValueError, match="^learning_rate: expected a finite end value >= 0"):
        st.train_online(tiny_som(), data(), epochs=1, schedule="linear", learning_rate=(0.5, -0.1))
    with pytest.raises(ValueError, match="^sigma: expected a finite end value >= 0"):
        st.train_batch(tiny_som(), data(), epochs=1, sigma=(1.0, NAN))


# --- 2. samples without a usable feature, normalization -------------------------------------
def test_recall_without_active_feature_is_no_match():
    # row 0: the only active feature is NaN -> no match; row 1: a = 0.9 -> unit 1, distance 0.1
    r = st.recall(tiny_som(), torch.tensor([[NAN, 5.0], [0.9, NAN]], dtype=torch.float64))
    assert r.units.tolist() == [-1, 1]
    assert math.isnan(r.distance[0]) and r.distance[1].item() == pytest.approx(0.1)
    assert math.isnan(r["p"][0]) and r["p"][1].item() == 20.0
    r3 = st.recall(tiny_som(), torch.tensor([[NAN]], dtype=torch.float64), interpolate=3)
    assert r3.units.tolist() == [-1] and bool(torch.isnan(r3.values).all())
    units, d2 = st.best_matching_units(tiny_som(), torch.tensor([[NAN, 1.0]]))
    assert units.tolist() == [-1] and math.isnan(d2)


def test_quality_skips_unusable_samples_and_is_nan_without_any():
    som = tiny_som()
    x = torch.tensor([[0.5, 0.0], [2.0, 0.0], [NAN, 0.0]], dtype=torch.float64)
    assert st.quantization_error(som, x).item() == pytest.approx(0.25)  # (0.5 + 0) / 2
    assert st.hit_counts(som, x).tolist() == [[1, 0, 1]]  # unit 0 (tie 0/1: first), unit 2
    for bad in (torch.full((4, 2), NAN, dtype=torch.float64), x[:0]):
        assert math.isnan(st.quantization_error(som, bad))
        assert math.isnan(st.topographic_error(som, bad))


@pytest.mark.parametrize("kw, name", [(dict(scale=[NAN, 1.0]), "scale"), (dict(scale=[math.inf, 1.0]), "scale"),
                                      (dict(scale=[0.0, 1.0]), "scale"), (dict(offset=[NAN, 0.0]), "offset")])
def test_som_refuses_non_finite_normalization(kw, name):
    with pytest.raises(ValueError, match=f"^{name}: expected finite"):
        st.SOM(st.Grid(1, 3), ["a", "p"], [True, False], **kw)


# --- 3. a list is (start, end), never per map ------------------------------------------------
def test_list_range_is_start_end_on_any_batch():
    def final_lr(som, lr):
        info = {}
        st.train_online(som, data(), epochs=1, learning_rate=lr, schedule="linear", method="torch",
                        hooks=[lambda e, s, i: info.update(i)])
        return info["learning_rate"].reshape(-1).tolist()

    batch = st.SOM(st.Grid(1, 3), ["a", "p"], [True, False], batch_shape=(2,), dtype=torch.float64)
    assert final_lr(batch.clone(), [0.5, 0.01]) == final_lr(batch.clone(), (0.5, 0.01))
    assert final_lr(tiny_som(), [0.5, 0.01]) == final_lr(tiny_som(), (0.5, 0.01))
    per_map = final_lr(batch.clone(), (torch.tensor([0.5, 0.2]), 0.0))  # per map: a tensor
    assert per_map[0] > per_map[1] > 0
    with pytest.raises(ValueError, match="^learning_rate: expected start or \\(start, end\\), per-map values as"):
        st.train_online(tiny_som(), data(), epochs=1, learning_rate=[0.5, 0.1, 0.01])


# --- 4. one-line errors naming the argument --------------------------------------------------
def test_errors_name_the_argument():
    som, x, g = tiny_som(), data(), st.Grid(1, 3)
    cases = [
        (lambda: st.fit(st.SOM(g, ["a", "p"], [True, False]), x[:0]), ValueError, "data: expected at least 1"),
        (lambda: som.clone().fit_normalization(x[:0]), ValueError, "data: expected at least 1"),
        (lambda: st.init_linear(som.clone(), x[:0]), ValueError, "data: expected at least 1"),
        (lambda: st.train_batch(som.clone(), x[:0]), ValueError, "data: expected at least 1"),
        (lambda: st.SOM(g, ["a"], [True], dtype=torch.int64), TypeError, "dtype: expected a floating-point"),
        (lambda: st.SOM(g, ["a"], [True], batch_shape=(0,)), ValueError, "batch_shape: expected positive"),
        (lambda: st.SOM(g, ["a"], [True], weights=torch.zeros(0, 3, 1)), ValueError, "weights: expected positive"),
        (lambda: st.recall(som, torch.tensor(0.5)), ValueError, "features: expected"),
        (lambda: st.recall(som, x[:2], interpolate=0), ValueError, "interpolate: expected an int in 1..3"),
        (lambda: st.recall(som, x[:2])["zz"], ValueError, r"Recall\['zz'\]: unknown component"),
        (lambda: st.train_online(som.clone(), x, epochs=1, method="torch", num_threads=0), ValueError,
         "num_threads: expected a positive int"),
        (lambda: st.train_batch(som.clone(), x, epochs=1, num_threads=0), ValueError, "num_threads: expected"),
    ]
    for call, kind, message in cases:
        with pytest.raises(kind, match=f"^{message}"):
            call()


# --- 5. Grid.from_dict refuses non-integers --------------------------------------------------
def test_grid_from_dict_refuses_non_integer():
    assert st.Grid.from_dict({"rows": np.int64(3), "cols": 4, "topology": "hexagonal"}) == st.Grid(3, 4, "hexagonal")
    for rows in (3.7, True, "3"):
        with pytest.raises(ValueError, match="^Grid.rows: expected a positive int"):
            st.Grid.from_dict({"rows": rows, "cols": 4, "topology": "rectangular"})
