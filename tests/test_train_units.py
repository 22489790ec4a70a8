"""`tensortouch train units` (tools/train/units.py): check agrees with every recipe, bad input is one line
and exit 2."""
from __future__ import annotations

import subprocess
import sys

from tensortouch.tools.train import protocol as P


def _cli(*args, cwd=None):
    r = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300)
    return r.returncode, [ln for ln in r.stdout.splitlines() + r.stderr.splitlines() if ln.strip()]


def test_units_check_cli():
    rc, lines = _cli("train", "units", "check")
    assert rc == 0 and "recipe(s) agree" in lines[-1], lines


def test_units_cli_bad_input_one_line(tmp_path):
    for args, want in ((("record", "sealed", "--first", "2", "--root", str(tmp_path)), "recorded whole"),
                       (("record", "validation", "--pokes", "0", "--root", str(tmp_path)), "--pokes 0"),
                       (("list", "test"), "set 'test'")):
        rc, lines = _cli("train", "units", *args)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (args, lines)
    bad = tmp_path / "p.toml"
    bad.write_text(P.PROTOCOL_FILE.read_text().replace("seeds = [200, 299]", "seeds = [150, 299]"))
    rc, lines = _cli("train", "units", "check", "--protocol", str(bad))
    assert rc == 2 and len(lines) == 1 and str(bad) in lines[0] and "overlap" in lines[0], lines


def test_units_rim_finds_each_units_rim_nearer_than_the_design_radius():
    from tensortouch.tools.train.units import rim_check

    r = rim_check("TWIN-H01")                        # focal −4 %: the design radius is 4.4 px too large
    assert abs(r["rim_px"] - r["true_px"]) < 0.5 < abs(r["design_px"] - r["true_px"])
    rc, lines = _cli("train", "units", "rim", "validation", "--first", "2")
    assert rc == 0 and any(ln.startswith("2 units:") for ln in lines), lines
    rc, lines = _cli("train", "units", "rim")
    assert rc == 2 and len(lines) == 1 and "name the set" in lines[0], lines
