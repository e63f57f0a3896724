"""Command-line options a new user meets first: ``inspect`` without a folder, ``--drive MODULE:FACTORY``
from the current folder, figure options without matplotlib, and drive values in ``--params``."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import pytest
import torch

import sim
import som_torch as st
import training.config
from training.cli import build_parser, main
from training.commands.commission import _drives, load_factory
from training.errors import UserError
from training.params_file import DRIVE_KEYS, read_params_file, read_plants

PLANT = {"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03, "backlash": 0.0, "M_FC": 0.2, "mu_F": 0.001}


@pytest.fixture()
def no_matplotlib(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # every `import matplotlib...` now fails


@pytest.fixture(scope="module")
def tiny_maps(tmp_path_factory):
    """The shipped maps' specs and metadata on 3 x 4 grids (the figures draw in a moment)."""
    from training.identification import MAP_SPECS, TrainedMap
    from training.learning import save_map

    folder, shipped = tmp_path_factory.mktemp("maps"), training.config.shipped_checkpoints()
    for name, spec in MAP_SPECS.items():
        _, meta = st.load_checkpoint(shipped / f"{name}.pt")
        som = st.SOM(st.Grid(3, 4, "hexagonal"), spec.components,
                     [True] * len(spec.features) + [False] * len(spec.targets), batch_shape=(1,))
        st.initialize(som, torch.randn(30, len(spec.components), generator=torch.Generator().manual_seed(1)),
                      "random", 0)
        save_map(folder, TrainedMap(spec, som, meta))
    (folder / "envelope.json").write_bytes((shipped / "envelope.json").read_bytes())
    st.write_manifest(folder)
    return folder


# --- inspect: the shipped maps by default ---

def test_inspect_without_a_folder_draws_the_maps_identify_uses(tiny_maps, tmp_path, monkeypatch, capsys):
    pytest.importorskip("matplotlib")
    monkeypatch.delenv("TWOMASS_CHECKPOINTS", raising=False)
    monkeypatch.setattr(training.config, "shipped_checkpoints", lambda: tiny_maps)  # stands in for the shipped
    assert main(["inspect", "--out", str(tmp_path / "figs")]) == 0
    assert json.loads(capsys.readouterr().out)["f_e"]["grid"] == "3 x 4 hexagonal"
    assert {p.name for p in (tmp_path / "figs").iterdir()} == {"structure", "f_e", "V_J", "backlash"}
    assert list((tmp_path / "figs" / "f_e").glob("*.png"))
    monkeypatch.setenv("TWOMASS_CHECKPOINTS", str(tmp_path / "none"))  # the same folder identify would use
    assert main(["inspect", "--out", str(tmp_path / "figs2")]) == 2
    assert "none" in capsys.readouterr().err


# --- --drive MODULE:FACTORY from the current folder ---

def test_drive_module_is_found_in_the_current_folder(tmp_path, monkeypatch):
    (tmp_path / "mydrive_g41.py").write_text("def make():\n    return 'a drive'\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.delitem(sys.modules, "mydrive_g41", raising=False)
    try:
        assert load_factory("mydrive_g41:make")() == "a drive"
    finally:
        sys.modules.pop("mydrive_g41", None)
    assert str(tmp_path) not in sys.path  # only while it imports


def test_drive_module_missing_or_failing_import_is_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match=r"cannot import 'nodrive_g41': no such module in the current folder .* or on "
                                        r"PYTHONPATH; give its file instead: --drive path/to/nodrive_g41\.py:FACTORY$"):
        load_factory("nodrive_g41:make")
    (tmp_path / "brokendrive_g41.py").write_text("import nosuchdependency_g41\n")
    with pytest.raises(UserError, match="importing brokendrive_g41 failed: .*nosuchdependency_g41"):
        load_factory("brokendrive_g41:make")


# --- figure options without matplotlib: refused before any work ---

@pytest.mark.parametrize("argv", [
    ["identify", "no-such-record", "--plot", "{tmp}/pages"],
    ["commission", "--params", "{tmp}/no-such.json", "--plots", "{tmp}/pages"],
    ["inspect", "{tmp}/no-such-maps", "--out", "{tmp}/figs"],
])
def test_figure_options_without_matplotlib_exit_2_before_any_work(argv, tmp_path, capsys, no_matplotlib):
    from training.figures import PLOT_HINT

    assert main([a.format(tmp=tmp_path) for a in argv]) == 2  # not the missing input: nothing was read
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.endswith(PLOT_HINT) and "'plot' extra" in err
    assert not list(tmp_path.iterdir())


def test_plot_hint_names_the_install_command_of_a_checkout_and_of_a_wheel(tmp_path):
    from training.figures import PLOT_HINT
    from training.figures._style import _install_command

    module = Path("training/figures/_style.py")
    wheel, checkout = tmp_path / "site-packages", tmp_path / "clone"
    for root in (wheel, checkout):
        (root / module).parent.mkdir(parents=True)
        (root / module).touch()
    (checkout / "pyproject.toml").touch()
    assert _install_command(wheel / module) == "pip install 'twomass-som[plot]'"
    assert _install_command(checkout / module) == f'pip install -e ".[plot]" (in {checkout})'
    assert PLOT_HINT.endswith(_install_command())  # this checkout's own


# --- drive values in --params ---

def test_drive_keys_are_those_of_the_drive_config():
    assert DRIVE_KEYS == tuple(f.name for f in dataclasses.fields(sim.DriveConfig))


def test_simulate_takes_a_drive_per_plant_and_the_record_carries_it(tmp_path):
    rows = [{"name": "fast", **PLANT, "T_s": 0.000125, "encoder_counts": 65536}, {"name": "reference", **PLANT}]
    (tmp_path / "p.json").write_text(json.dumps(rows))
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(tmp_path / "rec"),
                 "--no-progress"]) == 0
    fast, ref = sim.read_record(tmp_path / "rec" / "fast"), sim.read_record(tmp_path / "rec" / "reference")
    assert (fast.meta["T_s"], fast.meta["encoder_counts"]) == (0.000125, 65536)
    assert fast.t[1] == pytest.approx(0.000125)
    assert (ref.meta["T_s"], ref.meta["encoder_counts"]) == (sim.DriveConfig().T_s, sim.DriveConfig().encoder_counts)


@pytest.mark.parametrize("key, value, says", [
    ("T_s", 0.002, "T_s 0.002 s: expected 6.25e-05 .. 0.001 s (the drive envelope of docs/contract.md"),
    ("encoder_counts", 1000, "encoder_counts 1000 counts/rev: expected 4096 .. 16777216 counts/rev"),
    ("M_max", 100.0, "M_max 100 Nm: expected M_max / M_N (M_N 10 Nm) within 1.5 .. 4, received 10"),
    ("current_noise_std", 1.0, "current_noise_std 1 A: expected current_noise_std * K_M / M* (K_M 1 Nm/A, M* 10 Nm) "
                               "within 0 .. 0.05, received 0.1"),
    ("T_Ei", -1.0, "T_Ei: expected > 0, received -1"),
])
def test_a_drive_outside_the_envelope_is_refused_in_one_line(key, value, says, tmp_path, capsys):
    (tmp_path / "p.json").write_text(json.dumps({"name": "a", **PLANT, key: value}))
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--out", str(tmp_path / "rec")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "system 0 (a): " + says in err
    assert not (tmp_path / "rec").exists()


def test_a_command_on_the_reference_drive_refuses_drive_keys():
    with pytest.raises(UserError, match=r"system 0: \['T_s'\]: drive values are not taken here"):
        read_params_file(json.dumps({**PLANT, "T_s": 0.000125}))
    assert read_plants(json.dumps(PLANT)).drives == [sim.DriveConfig()]


def test_commission_simulates_each_plant_on_its_drive(tmp_path):
    rows = [{"name": "a", **PLANT, "T_s": 0.000125, "encoder_counts": 65536, "K_M": 2.0, "M_N": 5.0, "M_max": 15.0},
            {"name": "b", **PLANT}]
    (tmp_path / "p.json").write_text(json.dumps(rows))
    args = build_parser().parse_args(["commission", "--params", str(tmp_path / "p.json")])
    drives, _ = _drives(args, sim.DriveLimits(w_max=100.0, travel=100.0))
    built = {name: make() for name, make in drives}
    assert built["a"].config == sim.DriveConfig(T_s=0.000125, encoder_counts=65536, K_M=2.0, M_N=5.0, M_max=15.0)
    assert built["b"].config == sim.DriveConfig()
