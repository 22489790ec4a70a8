"""Commands with subcommands (tools/command_group.py): a group without a subcommand prints help and
returns 2, table rows become subcommands, and a lazy subcommand imports its module only when chosen."""
import argparse
import sys

import pytest
from tensortouch.tools.command_group import add_commands, arg, command_group, lazy_group


def _parser():
    p = argparse.ArgumentParser(prog="tt")
    return p, p.add_subparsers(dest="command")


def test_group_without_a_subcommand_prints_help_and_returns_2(capsys):
    p, sub = _parser()
    group = command_group(sub, "calib", "Calibration stores.", "calib_command", "{init,show}")
    add_commands(group, [("show", "Show one store.", lambda a: a.depth * 10, [arg("--depth", type=int, default=3)])])
    a = p.parse_args(["calib"])
    assert a.func(a) == 2 and "Calibration stores." in capsys.readouterr().out
    a = p.parse_args(["calib", "show", "--depth", "4"])
    assert a.calib_command == "show" and a.func(a) == 40


def test_lazy_subcommand_imports_its_module_only_when_chosen(tmp_path, monkeypatch):
    (tmp_path / "tt_lazy_cmd.py").write_text(
        "def add_arguments(p):\n    p.add_argument('--n', type=int, default=2)\n\n"
        "def run(a):\n    return a.n + 1\n")
    (tmp_path / "tt_lazy_bad.py").write_text("def run(a):\n    return 0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    p = argparse.ArgumentParser(prog="tt")
    lazy_group(p, "what", "{go,bad}", [("go", "tt_lazy_cmd", "Go."), ("bad", "tt_lazy_bad", "Bad.")])
    assert "tt_lazy_cmd" not in sys.modules
    p.format_help()                                   # listing the subcommands imports nothing
    assert "tt_lazy_cmd" not in sys.modules
    a = p.parse_args(["go", "--n", "5"])
    assert "tt_lazy_cmd" in sys.modules and a.func(a) == 6
    with pytest.raises(TypeError, match=r"subcommand 'bad': tt_lazy_bad must define add_arguments\(parser\)"):
        p.parse_args(["bad"])
    for name in ("tt_lazy_cmd", "tt_lazy_bad"):
        monkeypatch.delitem(sys.modules, name, raising=False)
