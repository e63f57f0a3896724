"""``twomass identify --plot`` and ``twomass inspect``: the pages and figures as PNG files, existing
files refused, and without matplotlib one line that says how to get plots, before any work (exit 2)."""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest
import torch

import som_torch as st
from sim import write_record
from training.cli import main
from training.config import checkpoints_folder
from training.figures import PLOT_HINT, log_map_figures, map_figure_names, plots_available, require_matplotlib
from training.errors import UserError
from training.identification import MAP_SPECS, TrainedMap
from training.learning import save_map

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture()
def no_matplotlib(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # every `import matplotlib...` now fails


@pytest.fixture(scope="module")
def records(good, tmp_path_factory):
    """``good`` and a record that cannot be identified (constant speed) as files."""
    folder = tmp_path_factory.mktemp("records")
    write_record(folder / "good", good)
    flat = type(good)(t=good.t, speed=np.zeros_like(good.speed), meta=dict(good.meta), current=good.current,
                      name="flat")
    write_record(folder / "flat", flat)
    return folder


@pytest.fixture(scope="module")
def tiny_checkpoints(tmp_path_factory):
    """Four 3 x 4 hexagonal maps (2 members) with the shipped maps' metadata, their envelope, and a manifest."""
    folder = tmp_path_factory.mktemp("ck")
    for name, spec in MAP_SPECS.items():
        _, meta = st.load_checkpoint(checkpoints_folder() / f"{name}.pt")
        som = st.SOM(st.Grid(3, 4, "hexagonal"), spec.components,
                     [True] * len(spec.features) + [False] * len(spec.targets), batch_shape=(2,))
        st.initialize(som, torch.randn(30, len(spec.components), generator=torch.Generator().manual_seed(1)),
                      "random", 0)
        save_map(folder, TrainedMap(spec, som, meta))
    (folder / "envelope.json").write_bytes((checkpoints_folder() / "envelope.json").read_bytes())
    st.write_manifest(folder)
    return folder


def test_identify_plot_writes_a_page_per_record(records, tiny_checkpoints, tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    pages = tmp_path / "pages"
    args = ["identify", str(records / "good.csv"), str(records / "flat"), "--plot", str(pages), "--no-progress",
            "--checkpoints", str(tiny_checkpoints)]  # small maps: a small maps page (the shipped: test_figure_pages)
    assert main(args) == 1  # flat is not identified; good is
    lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert "structure" in lines[0] and "constant speed" in lines[1]["error"]
    assert sorted(p.name for p in pages.iterdir()) == ["flat.png", "good.png", "good_maps.png"]
    for p in pages.iterdir():
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 20_000
    # pages there already are refused before any work, unless --overwrite
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "good.png" in err and "--overwrite" in err


def test_identify_without_matplotlib_refuses_plot_before_any_work(records, tmp_path, capsys, no_matplotlib) -> None:
    assert not plots_available()
    with pytest.raises(UserError, match=f"^{re.escape(PLOT_HINT)}$"):
        require_matplotlib()
    pages = tmp_path / "pages"
    assert main(["identify", str(records / "good"), "--plot", str(pages), "--no-progress"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.strip() == f"twomass identify: error: --plot: {PLOT_HINT}"
    assert not pages.exists()


def test_tensorboard_falls_back_to_grey_arrays_without_matplotlib(tiny_checkpoints, no_matplotlib) -> None:
    class Writer:
        images: list = []

        def add_image(self, tag, image, step, dataformats="CHW"):
            self.images.append((tag, tuple(np.asarray(image).shape), dataformats))

        def add_scalar(self, *a): pass

        def flush(self): pass

    trained = TrainedMap(MAP_SPECS["V_J"], st.load_checkpoint(tiny_checkpoints / "V_J.pt")[0])
    writer = Writer()
    assert log_map_figures(writer, trained, None, 3) is False
    assert ("V_J/map_0/u_matrix", (1, 3, 4), "CHW") in writer.images


def test_inspect_writes_the_map_figures(tiny_checkpoints, tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "figs"
    assert main(["inspect", str(tiny_checkpoints), "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["f_e"]["grid"] == "3 x 4 hexagonal" and summary["f_e"]["ensemble"] == 2
    for name, spec in MAP_SPECS.items():
        trained = TrainedMap(spec, st.load_checkpoint(tiny_checkpoints / f"{name}.pt")[0])
        expected = {f"{n.replace('/', '_')}.png" for n in map_figure_names(trained, hits=False)}
        assert {p.name for p in (out / name).iterdir()} == expected
        assert all(p.read_bytes()[:8] == PNG for p in (out / name).iterdir())
    assert main(["inspect", str(tiny_checkpoints), "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_inspect_without_matplotlib_says_how_before_any_work(tiny_checkpoints, tmp_path, capsys,
                                                              no_matplotlib) -> None:
    assert main(["inspect", str(tiny_checkpoints), "--out", str(tmp_path / "figs")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.strip() == f"twomass inspect: error: {PLOT_HINT}"
    assert not (tmp_path / "figs").exists()
