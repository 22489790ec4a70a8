"""`tensortouch workbench effects` (tools/workbench/effects_cli.py): the library listed with units, and
parameters given with a unit converted by hand."""
import argparse
import json

import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.stages.effects import Registry
from tensortouch.tools.workbench import cli
from tensortouch.tools.workbench.effects_cli import param_value


def run(argv, capsys):
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    code = args.func(args)
    return code, capsys.readouterr().out


def test_effects_list_json_names_parameters_with_units(capsys):
    code, text = run(["effects", "list", "--json"], capsys)
    rows = {r["name"]: r for r in json.loads(text)}
    assert {"temperature_softening", "viscoelastic_relaxation", "mullins_softening", "strain_stiffening",
            "friction_mismatch", "rim_stiffening", "ft_bias_drift", "led_drift"} <= set(rows)
    tau = [p for p in rows["viscoelastic_relaxation"]["params"] if p["name"] == "tau"][0]
    assert tau["unit"] == "s" and tau["lo"] < tau["hi"]


def test_param_values_with_units_by_hand():
    visco = Registry.default(entry_points=False).get("viscoelastic_relaxation")
    assert param_value(visco, "tau=1.9") == ("tau", 1.9)
    assert param_value(visco, "tau = 1500 ms")[1] == pytest.approx(1.5)
    assert param_value(visco, "tau=2.5e5us")[1] == pytest.approx(0.25)
    for bad, words in (("tau", "expected P=V"), ("tau=fast", "expected P=V"), ("spin=1", "has no parameter 'spin'"),
                       ("tau=3N", "tau is in 's'; 'N' does not convert")):
        with pytest.raises(TensorTouchError, match=words):
            param_value(visco, bad)
