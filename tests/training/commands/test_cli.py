import sys
import types

import pytest

from training import cli
from training.cli import main
from training.errors import UserError


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: twomass" in capsys.readouterr().out


def test_unknown_command_is_rejected():
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2


def _command(monkeypatch, raises: BaseException) -> None:
    """Offer one command, ``boom``, whose ``run`` raises ``raises``."""
    module = types.ModuleType("fake_boom_command")
    module.HELP = "raises"
    module.add_arguments = lambda parser: None

    def run(args):
        raise raises

    module.run = run
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(cli, "COMMANDS", {"boom": module.__name__})


@pytest.mark.parametrize("err", [ValueError("bad value\nsecond line"), UserError("bad value"),
                                 FileNotFoundError(2, "bad value")])
def test_domain_and_file_errors_are_one_line_and_exit_2(monkeypatch, capsys, err):
    _command(monkeypatch, err)
    assert main(["boom"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("twomass boom: error: ") and "bad value" in lines[0]


def test_a_type_error_is_a_bug_not_bad_input(monkeypatch, capsys):
    _command(monkeypatch, TypeError("unsupported operand"))
    with pytest.raises(TypeError, match="unsupported operand"):
        main(["boom"])
    assert "error:" not in capsys.readouterr().err


def test_ctrl_c_in_a_command_exits_130_with_one_line(monkeypatch, capsys):
    _command(monkeypatch, KeyboardInterrupt())
    assert main(["boom"]) == 130
    assert capsys.readouterr().err.splitlines() == ["twomass boom: interrupted"]


def test_ctrl_c_during_start_up_exits_130_with_one_line(monkeypatch, capsys):
    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["identify", "x.csv"]) == 130
    assert capsys.readouterr().err.splitlines() == ["twomass: interrupted"]


def test_a_command_module_that_fails_to_import_is_an_error(monkeypatch):
    monkeypatch.setattr(cli, "COMMANDS", {**cli.COMMANDS, "ghost": "training.commands.no_such_module"})
    with pytest.raises(ModuleNotFoundError, match="no_such_module"):
        main(["--help"])


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert all(name in out for name in cli.COMMANDS)


def test_the_thread_policy_is_applied_before_the_command(monkeypatch):
    calls = []
    monkeypatch.setattr(cli, "apply_process_defaults", lambda: calls.append("defaults"))
    _command(monkeypatch, ValueError("x"))
    main(["boom"])
    assert calls == ["defaults"]


def _subparsers() -> dict:
    parser = cli.build_parser()
    return parser._subparsers._group_actions[0].choices


def test_help_imports_no_heavy_module():
    """``twomass --help`` and every ``twomass CMD --help`` build their text without torch, numpy,
    scipy or the rooms (they cost seconds of start-up; imports happen in ``run``)."""
    import subprocess

    code = ("import sys; import training.cli as c; p = c.build_parser(); p.format_help(); "
            "[s.format_help() for s in p._subparsers._group_actions[0].choices.values()]; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'numpy', 'scipy', 'sim', 'som_torch'}), "
            "sorted(m for m in sys.modules if m.split('.')[:2] in [['training', r] for r in "
            "('identification', 'learning', 'evaluation', 'commissioning')]))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[] []"


def test_every_option_has_a_help_text():
    for name, sub in _subparsers().items():
        for action in sub._actions:
            if action.dest != "help":
                assert action.help, f"twomass {name} {action.option_strings or action.dest}: no help text"


def _help(name: str) -> str:
    return " ".join(_subparsers()[name].format_help().split())


def test_help_defaults_match_the_library():
    """Where the defaults live in heavy modules, the help texts state them; these checks keep them in step."""
    from training.evaluation import GRID_BACKLASH_DEG, GRID_F_E
    from training.learning import TRAIN_MODES, TrainConfig

    d = TrainConfig()
    train = _help("train")
    for text in (f"(default {d.rows} {d.cols}, the paper's)", f"(default {d.ensemble})", f"(default {d.epochs})",
                 f"(default {d.seed})", f"(default {d.mode})", "{" + ",".join(TRAIN_MODES) + "}"):
        assert text in train, text
    evaluate = _help("evaluate")
    assert "the paper's " + ",".join(f"{v:g}" for v in GRID_F_E) + ")" in evaluate
    assert "the paper's " + ",".join(f"{v:g}" for v in GRID_BACKLASH_DEG) + ")" in evaluate
    assert "DEGREES" in evaluate and "use rad" in evaluate  # unlike the parameter files


def test_train_options_not_given_keep_the_library_defaults():
    from training.commands import train
    from training.learning import TrainConfig

    args = cli.build_parser().parse_args(["train", "--data", "d", "--out", "o", "--epochs", "3"])
    assert train._config(args) == TrainConfig(epochs=3)


@pytest.mark.parametrize("tty, flag, shown", [(True, False, True), (True, True, False), (False, False, False)])
def test_progress_only_on_a_terminal(monkeypatch, tty, flag, shown):
    import argparse

    from training.commands import _progress

    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    assert _progress.wanted(argparse.Namespace(no_progress=flag)) is shown
