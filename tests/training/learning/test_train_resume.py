"""Training resumes after an interrupt, and identical runs write identical files (no timing stored)."""

from __future__ import annotations

import pytest

from training.errors import OutputExistsError
from training.identification import MAP_SPECS
from training.learning import GenerateConfig, TrainConfig, generate, load_dataset, train_maps

CONFIG = TrainConfig(rows=4, cols=4, ensemble=2, epochs=1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    generate(out, GenerateConfig(n=40, seed=11, shard_size=20), workers=1)
    return load_dataset(out)


def test_train_resumes_and_writes_identical_files(dataset, tmp_path):
    ck = tmp_path / "ck"
    train_maps(dataset, ck, CONFIG)
    first = {p.name: p.read_bytes() for p in ck.iterdir()}
    assert sorted(first) == sorted([f"{n}.pt" for n in MAP_SPECS] + ["envelope.json", "manifest.json"])
    # an interrupt after two maps: two maps, no manifest
    names = list(MAP_SPECS)
    for p in [ck / f"{n}.pt" for n in names[2:]] + [ck / "envelope.json", ck / "manifest.json"]:
        p.unlink()
    kept = {n: (ck / f"{n}.pt").stat().st_mtime_ns for n in names[:2]}
    trained = train_maps(dataset, ck, CONFIG)  # resumes: no overwrite needed
    assert {n: (ck / f"{n}.pt").stat().st_mtime_ns for n in names[:2]} == kept  # loaded, not retrained
    assert ["train_seconds" in trained[n].metadata for n in names] == [False, False, True, True]
    assert {p.name: p.read_bytes() for p in ck.iterdir()} == first  # the same bytes as the whole run
    with pytest.raises(OutputExistsError, match="overwrite"):  # a finished run (manifest) is not resumed
        train_maps(dataset, ck, CONFIG)
    (ck / "manifest.json").unlink()
    with pytest.raises(OutputExistsError, match="another config or dataset"):
        train_maps(dataset, ck, TrainConfig(rows=4, cols=4, ensemble=2, epochs=1, seed=5))


def test_the_manifest_lists_only_what_training_wrote(dataset, tmp_path):
    """The user's own files in --out are not vouched for: changing them later breaks nothing."""
    import json

    from training.identification import Identifier

    ck = tmp_path / "ck"
    ck.mkdir()
    (ck / "notes.txt").write_text("my notes\n")
    (ck / "extra_map.pt").write_bytes(b"not ours")
    train_maps(dataset, ck, CONFIG)
    listed = json.loads((ck / "manifest.json").read_text())["files"]
    assert sorted(listed) == sorted([f"{n}.pt" for n in MAP_SPECS] + ["envelope.json"])
    with open(ck / "notes.txt", "a") as f:
        f.write("more\n")
    Identifier.load(ck)  # no SHA-256 mismatch
    with pytest.raises(OutputExistsError, match="finished training run") as err:
        train_maps(dataset, ck, CONFIG)
    assert "another config" not in str(err.value)


def test_the_f_e_and_V_J_maps_read_out_through_local_linear_maps_closer_to_their_rows(dataset, tmp_path):
    import numpy as np

    import som_torch as st
    from training.identification import load_map, recall_targets
    from training.learning import training_matrix

    train_maps(dataset, tmp_path / "ck", CONFIG)
    for name, spec in MAP_SPECS.items():
        trained = load_map(tmp_path / "ck" / f"{name}.pt")
        assert (trained.som.local is not None) == spec.local_linear, name
        if not spec.local_linear:
            continue
        som = trained.som
        flat = st.SOM(som.grid, som.component_names, som.active, weights=som.weights, offset=som.offset, scale=som.scale)
        rows = training_matrix(spec, dataset)
        feats, target = rows[:, : len(spec.features)], rows[:, len(spec.features)]
        local = recall_targets(trained, feats, 1)[spec.targets[0]]
        plain = recall_targets(type(trained)(spec, flat, trained.metadata), feats, 1)[spec.targets[0]]
        assert np.abs(local - target).mean() < 0.8 * np.abs(plain - target).mean(), name


def test_the_eigenfrequency_bins_slopes_are_held_closer_to_zero_than_with_one_ridge(dataset):
    import som_torch as st
    from training.identification import EIG_BINS
    from training.learning import local_ridges, train_map, training_matrix

    spec = MAP_SPECS["f_e"]
    ridges = dict(zip(spec.features, local_ridges(spec, CONFIG)))
    assert sorted(n for n, r in ridges.items() if r == CONFIG.local_ridge_bins) == sorted(EIG_BINS)
    assert {r for n, r in ridges.items() if n not in EIG_BINS} == {CONFIG.local_ridge}
    trained = train_map(spec, dataset, CONFIG)
    one = st.fit_local_linear(trained.som, training_matrix(spec, dataset), radius=CONFIG.local_radius,
                              ridge=CONFIG.local_ridge)
    bins = [i for i, n in enumerate(spec.features) if n in EIG_BINS]
    assert trained.som.local.slopes[..., bins].abs().mean() < 0.5 * one.local.slopes[..., bins].abs().mean()
