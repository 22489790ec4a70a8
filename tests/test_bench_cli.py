"""Every `tensortouch bench` area registers its arguments (one broken area must not hide the others)."""
import argparse

import pytest

from tensortouch.tools.bench import cli


def test_every_bench_area_registers():
    parser = argparse.ArgumentParser(prog="tensortouch")
    sub = parser.add_subparsers(dest="cmd")
    cli.register(sub)
    for area in cli.AREAS:
        args = parser.parse_args(["bench", area])
        assert args.bench_area == area
        assert callable(args.func)


def test_area_without_run_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(cli.AREAS, "broken", ("argparse", "not a bench module"))
    sub = argparse.ArgumentParser().add_subparsers()
    with pytest.raises(TypeError, match="broken"):
        cli.register(sub)
