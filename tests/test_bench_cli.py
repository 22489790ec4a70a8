"""Every `tensortouch bench` area registers its arguments when chosen; listing the areas imports none."""
import argparse
import subprocess
import sys

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


def test_area_without_run_is_a_clear_error_when_chosen(monkeypatch):
    monkeypatch.setitem(cli.AREAS, "broken", ("argparse", "not a bench module", None))
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="cmd"))
    assert parser.parse_args(["bench", "runtime"]).bench_area == "runtime"      # the others still work
    with pytest.raises(TypeError, match="broken"):
        parser.parse_args(["bench", "broken"])


def test_listing_the_areas_imports_no_area_module():
    probe = ("import argparse, sys\nfrom tensortouch.tools.bench import cli\n"
             "p = argparse.ArgumentParser(); cli.register(p.add_subparsers())\n"
             "print(sorted(m for m, _ in [r[:2] for r in cli.AREAS.values()] if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
