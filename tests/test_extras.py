"""contracts/extras.py and the `tensortouch` shell around it: a command whose optional extra is missing
prints one line naming the extra, in the install form of this installation, and exits 2.

The base install itself (only `pip install -e .`, and the wheel) is exercised for real by
.ci/base-install; here the missing extra is simulated in this (full) environment."""
import argparse

import pytest
from tensortouch.contracts import extras
from tensortouch.contracts.paths import ROOT
from tensortouch.runtime.shells import cli


def test_extras_come_from_the_package_metadata():
    ex = extras.extras()
    assert {"train", "viewers", "hand", "cluster"} <= set(ex)
    assert "torch" in ex["train"] and "tqdm" in ex["train"] and "gmsh" in ex["train"]
    assert "foxglove-sdk" in ex["viewers"] and "rerun-sdk" in ex["viewers"]


@pytest.mark.parametrize("module, prefer, extra", [
    ("foxglove", None, "viewers"), ("rerun.blueprint", None, "viewers"), ("sklearn.ensemble", None, "train"),
    ("tqdm", None, "train"), ("gmsh", None, "train"), ("distributed", None, "cluster"), ("pinocchio", None, "hand"),
    ("mcap", None, "viewers"), ("mcap", "train", "train"), ("numpy", None, None), ("no_such_module", None, None)])
def test_the_extra_of_a_module(module, prefer, extra):
    assert extras.extra_of_module(module, prefer) == extra


def test_the_install_form_of_this_editable_checkout(monkeypatch, tmp_path):
    monkeypatch.chdir(ROOT)
    assert extras.install_command("train") == "pip install -e '.[train]'"
    monkeypatch.chdir(tmp_path)                        # elsewhere: the checkout's own path
    assert extras.install_command("viewers") == f"pip install -e '{ROOT.resolve()}[viewers]'"


def test_the_install_form_of_a_wheel_simulated(monkeypatch):
    monkeypatch.setattr(extras, "_editable_checkout", lambda: None)
    assert extras.install_command("hand") == "pip install 'tensortouch[hand]'"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_a_command_of_a_missing_extra_says_which_one_simulated_base_install(monkeypatch, capsys):
    monkeypatch.setattr(extras, "missing", lambda extra: ["tqdm", "torch"] if extra == "train" else [])
    monkeypatch.chdir(ROOT)
    for argv in (["train", "all"], ["fe", "solve", "standard", "--out", "x"], ["compare", "S", "--sensor", "X",
                                                                                  "--out", "d"], ["bench", "fe"]):
        assert cli.main(argv) == 2
        line = _one_line(capsys)
        assert line.startswith(f"tensortouch {argv[0]}: needs the train extra (tqdm and 1 more not installed)"), line
        assert line.endswith("pip install -e '.[train]'"), line


def test_a_missing_module_of_an_extra_met_at_run_time_is_one_line(monkeypatch, capsys):
    from tensortouch.runtime.shells import commands

    def needs_rerun(args):
        raise ModuleNotFoundError("No module named 'rerun'", name="rerun")

    monkeypatch.setattr(commands, "cmd_calib_list", needs_rerun)
    assert cli.main(["calib", "list"]) == 2
    assert "needs the viewers extra (rerun not installed): pip install" in _one_line(capsys)


def test_a_missing_module_no_extra_provides_is_a_real_error(monkeypatch):
    from tensortouch.runtime.shells import commands

    def broken(args):
        raise ModuleNotFoundError("No module named 'tensortouch_typo'", name="tensortouch_typo")

    monkeypatch.setattr(commands, "cmd_calib_list", broken)
    with pytest.raises(ModuleNotFoundError):
        cli.main(["calib", "list"])


def test_an_interrupted_build_says_how_to_resume(monkeypatch, capsys):
    from tensortouch.tools.train import cli as train_cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_cli, "cmd_all", interrupted)
    assert cli.main(["train", "all", "--recipe", "hiera-qup-128"]) == 130
    line = _one_line(capsys)
    assert "interrupted; rerun `tensortouch train all --recipe hiera-qup-128` to resume" in line, line


def test_an_interrupt_surfacing_from_compiled_code_is_the_same_line(monkeypatch, capsys):
    """Ctrl-C inside a numba kernel reaches Python as a SystemError whose context is the KeyboardInterrupt."""
    from tensortouch.runtime.shells import commands

    def interrupted_in_a_kernel(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set")  # noqa: B904 - as the C dispatcher raises it

    monkeypatch.setattr(commands, "cmd_calib_list", interrupted_in_a_kernel)
    assert cli.main(["calib", "list"]) == 130
    assert _one_line(capsys) == "tensortouch calib: interrupted"


def test_a_system_error_without_an_interrupt_is_a_real_error(monkeypatch):
    from tensortouch.runtime.shells import commands

    def broken(args):
        try:
            raise ValueError("inner")
        except ValueError:
            raise SystemError("returned a result with an exception set")  # noqa: B904

    monkeypatch.setattr(commands, "cmd_calib_list", broken)
    with pytest.raises(SystemError):
        cli.main(["calib", "list"])


def test_a_missing_input_file_is_one_line(capsys, tmp_path):
    assert cli.main(["bench", "hand", "--from-log", str(tmp_path / "nope.jsonl")]) == 2
    line = _one_line(capsys)
    assert str(tmp_path / "nope.jsonl") in line


def _leaves(parser, path=()):
    for name, child, _ in cli.subcommands(parser):
        for action in child._actions:                      # lazy subcommands: load them to walk them
            if isinstance(action, argparse._SubParsersAction) and hasattr(action, "load"):
                for pending in list(action._pending):
                    action.load(pending)
        kids = list(cli.subcommands(child))
        if kids:
            yield from _leaves(child, path + (name,))
        else:
            yield path + (name,), child


def test_every_leaf_command_has_a_description_and_one_name_per_harness():
    parser, problems = cli.build_parser()
    assert not problems
    leaves = dict(_leaves(parser))
    assert len(leaves) > 50
    bare = [" ".join(p) for p, child in leaves.items() if not (child.description or "").strip()]
    assert bare == []
    names = [p[-1] for p in leaves]
    assert names.count("workbench-generality") == 1
