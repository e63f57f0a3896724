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
