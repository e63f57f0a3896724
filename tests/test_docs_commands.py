"""Every ``twomass`` command that README.md and docs/ show is a command the CLI takes.

Each command line of a ``bash`` block and each inline ```twomass ...``` span is parsed by the
real parsers (``training.cli.build_parser`` and, for ``twomass bench TARGET``, the target's own),
with the placeholders of a synopsis (``DIR``, ``N``, ``FILE...``) filled in. A renamed or removed
option fails here, naming the document and the line. Commands whose work is cheap enough run
end to end below or in the test named in :data:`RUN_BY`; the long ones (the maps' 40-minute
training, the 50-plant studies) are held to parsing.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import shlex
from pathlib import Path

import pytest

from training.bench import TARGETS
from training.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: synopsis placeholders -> a value the parser takes
PLACEHOLDERS = {"DIR": "out", "CHECKPOINT_DIR": "checkpoints", "N": "3", "FILE...": "run.csv", "PATH": "a.json",
                "JSON": "a.json", "TARGET": "sim", "MODULE:FACTORY": "mydrive:make"}
#: a command shown in a document -> the test that runs it (file :: function)
RUN_BY = {
    "twomass demo": "tests/training/commands/test_demo.py",
    "twomass demo --json": "tests/training/commands/test_demo.py",
    "twomass commission --drive mydrive.py:make --w-limit 20 --travel-limit 5 --no-tune --json report.json":
        "tests/test_contract_doc.py",
    "twomass commission --resume rig/": "tests/training/commissioning/test_safety.py",
}


def _commands() -> list[tuple[str, str, bool]]:
    """(document, command, whole) for every twomass command of the documents; ``whole``: a command
    line of a ``bash`` block (run as written), else an inline span (it may name a command or an option)."""
    found: set[tuple[str, str, bool]] = set()
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        blocks = re.findall(r"```(?:bash|sh)\n(.*?)```", text, re.S)
        lines = [(line, True) for block in blocks for line in block.replace("\\\n", " ").splitlines()]
        lines += [(span, False) for span in re.findall(r"`(twomass [^`]*)`", text)]
        for line, whole in lines:
            for part in line.split("#")[0].split("&&"):
                for command in part.split(";"):
                    command = re.sub(r"^.*?--no-python --\s*", "", command.strip()).removeprefix("$T ").strip()
                    if command.startswith("twomass") and "error:" not in command:  # not a message
                        found.add((doc.name, command, whole))
    return sorted(found)


COMMANDS = _commands()
SHOWN = {command for _, command, _ in COMMANDS}


def _parsers(words: list[str]) -> list[argparse.ArgumentParser]:
    """The parsers a command line goes through: the command's, and a bench target's own."""
    root = build_parser()
    if words[0].startswith("-"):  # twomass --help
        return [root]
    commands = next(a for a in root._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert words and words[0] in commands, f"no command {words[:1]}"
    parsers = [commands[words[0]]]
    if words[0] == "bench" and len(words) > 1 and not words[1].startswith("-"):
        assert words[1] in TARGETS, f"no bench target {words[1]!r}"
        target = argparse.ArgumentParser(prog=f"twomass bench {words[1]}")
        importlib.import_module(TARGETS[words[1]]).add_arguments(target)
        parsers.append(target)
    return parsers


def test_the_documents_show_commands():
    assert len(COMMANDS) > 30
    assert ("README.md", "twomass demo", True) in COMMANDS


@pytest.mark.parametrize("where, command, whole", COMMANDS, ids=[f"{w}:{c}" for w, c, _ in COMMANDS])
def test_every_documented_command_is_taken(where, command, whole):
    """Every option a document names exists; a command line of a block parses as written."""
    words = [PLACEHOLDERS.get(word, word) for word in shlex.split(command.replace("\\|", "|"))][1:]
    words = [w for w in words if not set(w) & set("[]<>|")]  # a synopsis' optional parts and alternatives
    parsers = _parsers(words)
    options = {o for p in parsers for a in p._actions for o in a.option_strings}
    unknown = [w for w in words if w.startswith("--") and w.split("=")[0] not in options]
    assert not unknown, f"{where}: {command!r} names options the CLI does not have: {unknown}"
    if whole:
        try:
            build_parser().parse_args(words)
            if len(parsers) == 2:
                parsers[1].parse_args(words[2:])
        except SystemExit as exit_:
            assert exit_.code == 0, f"{where}: the CLI refuses {command!r}"


def test_the_tests_named_for_documented_commands_exist():
    for command, test_file in RUN_BY.items():
        assert command in SHOWN, f"{command!r} is no longer in the documents: update RUN_BY"
        assert command.split()[1] in (ROOT / test_file).read_text(encoding="utf-8")


def test_readme_see_it_commands_run(tmp_path, monkeypatch):
    """README "See it" (and docs/figures.md): simulate the example plant, identify it with --plot."""
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)
    plant = ROOT / "docs" / "figures" / "example_plant.json"
    assert f"twomass simulate --params {plant.relative_to(ROOT)} --out runs/example" in SHOWN
    assert main(["simulate", "--params", str(plant), "--out", "runs/example", "--no-progress"]) == 0
    record = "runs/example/" + json.loads(plant.read_text())["name"]
    assert f"twomass identify {record} --plot docs/figures" in SHOWN
    assert main(["identify", record, "--plot", "pages", "--no-progress", "--out", "answers.jsonl"]) == 0
    assert (tmp_path / "pages" / "plant_with_backlash.png").stat().st_size > 10_000
    assert (tmp_path / "pages" / "plant_with_backlash_maps.png").stat().st_size > 10_000


def test_readme_commission_on_the_simulator_runs(tmp_path, monkeypatch, capsys):
    """README "Commissioning", first line: the simulator with a plant file and the user's limits."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plant.json").write_text(json.dumps({"J_sigma": 0.05, "V_J": 1.0, "f_e": 30.0, "d": 0.03,
                                                     "backlash": 0.0, "M_FC": 0.2, "mu_F": 0.001}))
    assert "twomass commission --params plant.json --w-limit 20 --travel-limit 5" in SHOWN
    code = main(["commission", "--params", "plant.json", "--w-limit", "20", "--travel-limit", "5", "--no-tune",
                 "--json", "report.json"])
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report


def test_scale_out_small_commands_run(tmp_path, monkeypatch):
    """docs/scale-out.md's single-process comparisons, at a tenth of their size."""
    monkeypatch.chdir(tmp_path)
    assert "twomass simulate --population 32 --seed 11 --out recs" in SHOWN
    assert main(["simulate", "--population", "3", "--seed", "11", "--out", "recs", "--no-progress"]) == 0
    records = sorted(str(p) for p in (tmp_path / "recs").glob("*.csv"))
    assert main(["identify", *records, "--out", "i1", "--no-progress"]) == 0
    assert len((tmp_path / "i1").read_text().splitlines()) == 3
