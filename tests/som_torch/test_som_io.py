"""som_torch: checkpoints (SPEC 6), manifest, TensorBoard helpers, docs example, bench CLI."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
import torch

import som_torch as st

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture()
def trained() -> tuple[st.SOM, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    data = torch.rand(2, 40, 4, generator=g, dtype=torch.float64)
    som = st.SOM(st.Grid(4, 3, "hexagonal"), ["f0", "f1", "f2", "param"], [True, True, True, False], batch_shape=(2,))
    st.fit(som, data, normalization="range", seed=[1, 2], epochs=2, sigma=1.5)
    return som, data


def test_checkpoint_round_trip(tmp_path, trained):
    som, data = trained
    meta = {"features": {"name": "toy", "version": 2}, "seed": [1, 2], "quality": st.quality_report(som, data)}
    path = tmp_path / "maps" / "toy.pt"
    digest = st.save_checkpoint(path, som, meta)
    assert not [p for p in path.parent.iterdir() if p.name != "toy.pt"]  # no temp file left
    back, meta2 = st.load_checkpoint(path, expected_sha256=digest)
    assert meta2 == meta
    assert back.grid == som.grid and back.component_names == som.component_names
    for name in ("weights", "active", "offset", "scale"):
        assert torch.equal(getattr(back, name), getattr(som, name)), name
    torch.testing.assert_close(st.recall(back, data).values, st.recall(som, data).values)


def _payload(path: Path) -> dict:
    return torch.load(path, weights_only=True)


@pytest.mark.parametrize(
    "damage, message",
    [
        ("truncate", "corrupt or truncated"),
        ("garbage", "corrupt or truncated"),
        ("pickle", "not a plain-tensor checkpoint"),
        ("tamper", "content hash mismatch"),
        ("version", "format version 99 is not supported"),
        ("foreign", "not a som_torch.checkpoint file"),
        ("missing", "missing entry"),
    ],
)
def test_corrupt_checkpoints_rejected(tmp_path, trained, damage, message):
    som, _ = trained
    path = tmp_path / "m.pt"
    st.save_checkpoint(path, som, {"a": 1})
    raw = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(raw[: len(raw) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00not a checkpoint" * 10)
    elif damage == "pickle":  # a file that would run code on an unsafe load
        torch.save({"format": "som_torch.checkpoint", "evil": argparse.Namespace(a=1)}, path)
    else:
        p = _payload(path)
        if damage == "tamper":
            p["tensors"]["weights"][0, 0, 0] += 1.0
        elif damage == "version":
            p["format_version"] = 99
        elif damage == "foreign":
            p["format"] = "something.else"
        elif damage == "missing":
            del p["tensors"]["scale"]
        torch.save(p, path)
    with pytest.raises(st.CheckpointError, match=message) as info:
        st.load_checkpoint(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_unsafe_pickle_refusal_names_what_it_refused(tmp_path):
    """The refusal names the class the file would import and never passes on torch's advice to load
    it with weights_only=False (which runs code from the file)."""
    path = tmp_path / "evil.pt"
    torch.save({"format": "som_torch.checkpoint", "evil": argparse.Namespace(a=1)}, path)
    with pytest.raises(st.CheckpointError) as info:
        st.load_checkpoint(path)
    text = str(info.value)
    assert "\n" not in text and "GLOBAL argparse.Namespace" in text
    assert "weights_only" not in text and not re.search(r"trust", text)


def test_checkpoint_other_errors(tmp_path, trained):
    som, _ = trained
    with pytest.raises(FileNotFoundError):
        st.load_checkpoint(tmp_path / "absent.pt")
    with pytest.raises(TypeError, match="JSON"):
        st.save_checkpoint(tmp_path / "x.pt", som, {"bad": object()})
    assert not (tmp_path / "x.pt").exists()
    st.save_checkpoint(tmp_path / "y.pt", som)
    with pytest.raises(st.CheckpointError, match="differs from the expected"):
        st.load_checkpoint(tmp_path / "y.pt", expected_sha256="0" * 64)


def test_manifest(tmp_path, trained):
    som, _ = trained
    st.save_checkpoint(tmp_path / "a.pt", som)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "notes.txt").write_text("hello")
    st.write_manifest(tmp_path)
    listing = st.verify_manifest(tmp_path)
    assert set(listing) == {"a.pt", "sub/notes.txt"}
    assert listing["a.pt"] == st.file_sha256(tmp_path / "a.pt")
    (tmp_path / "sub" / "notes.txt").write_text("changed")
    (tmp_path / "a.pt").unlink()
    with pytest.raises(st.CheckpointError, match=r"a\.pt: missing; sub/notes\.txt: SHA-256 mismatch"):
        st.verify_manifest(tmp_path)
    st.save_checkpoint(tmp_path / "a.pt", som)
    st.write_manifest(tmp_path, files=["a.pt"])  # only these: the notes may change
    assert set(st.verify_manifest(tmp_path)) == {"a.pt"}


def test_tensorboard_tags(tmp_path, trained):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    som, data = trained
    with SummaryWriter(tmp_path) as writer:
        st.log_config(writer, {"epochs": 2, "sigma": 1.5})
        st.train_online(som, data, epochs=2, sigma=1.5, hooks=[st.tensorboard_hook(writer, data)])
    acc = EventAccumulator(str(tmp_path), size_guidance={"images": 0, "scalars": 0, "tensors": 0}).Reload()
    tags = acc.Tags()
    for b in (0, 1):
        for name in ("quantization_error", "topographic_error", "learning_rate", "sigma"):
            assert f"som/map_{b}/{name}" in tags["scalars"]
            assert [e.step for e in acc.Scalars(f"som/map_{b}/{name}")] == [1, 2]
        for name in ("u_matrix", "hits", "component/param"):
            assert f"som/map_{b}/{name}" in tags["images"]
    assert any(t.startswith("config") for t in tags["tensors"])


def test_docs_example_runs():
    text = (REPO / "docs" / "som_torch.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "docs/som_torch.md has no python example"
    exec(compile(blocks[0], "docs/som_torch.md", "exec"), {})


def test_twomass_bench_som_cli(capsys):
    pytest.importorskip("training.commands.bench")
    from training.cli import main

    code = main(["bench", "som", "--maps", "1", "--rows", "4", "--cols", "4", "--samples", "20", "--epochs", "1",
                 "--active", "2", "--inactive", "1", "--sigma", "1.5", "--minisom-maps", "0"])
    assert code == 0 and "som_torch online" in capsys.readouterr().out
    assert main(["bench", "som", "--maps", "0"]) == 2
    assert "--maps: expected a positive integer" in capsys.readouterr().err
