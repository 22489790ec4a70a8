"""The FE scenario contract (tools/fe/scenario.py): JSON/TOML round trip, bad scenarios and indenters name
the field."""
import json

import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe import (  # noqa: E402
    ScenarioError,
    load_scenario,
    save_scenario,
    standard_dome,
)
from tensortouch.tools.fe.scenario import scenario_from_dict  # noqa: E402

# ---------------------------------------------------------------- scenario contract


def test_scenario_json_toml_roundtrip(tmp_path):
    s = standard_dome()
    path = save_scenario(s, tmp_path / "s.json")
    s2 = load_scenario(path)
    assert s2.hash() == s.hash()
    toml = """schema = "tensortouch.fe_scenario"
schema_version = 1
friction = 0.5
[gel]
kind = "flat_pad"
thickness = 10.0
[material]
model = "mooney_rivlin"
C10 = 0.02
C01 = 0.005
[[indenters]]
name = "a"
shape = "torus"
params = { major_radius = 4.0, minor_radius = 1.0 }
position = [0.0, 0.0, 10.5]
[[indenters.keypoints]]
translation = [0.0, 0.0, -1.0]
"""
    (tmp_path / "t.toml").write_text(toml)
    t = load_scenario(tmp_path / "t.toml")
    assert t.material.model == "mooney_rivlin" and t.indenters[0].keypoints[0].rotation == [0, 0, 0]
    assert t.hash() != s.hash()


@pytest.mark.parametrize("patch, field", [
    ({"material": {"C10": -0.1}}, "material.C10"),
    ({"material": {"D1": 0.0}}, "material.D1"),
    ({"material": {"C10": 0.03, "C30": -1.0}}, "material.C30"),
    ({"material": {"model": "ogden"}}, "material.model"),
    ({"gel": {"kind": "cube"}}, "gel.kind"),
    ({"gel": {"radius": 5.0, "cap_height": 9.0}}, "gel.cap_height"),
    ({"mesh": {"size_top": 3.0, "size_inside": 2.0}}, "mesh.size_top"),
    ({"friction": -1.0}, "friction"),
    ({"gel": {"colour": "red"}}, "unknown field"),
])
def test_bad_scenarios_name_the_field(patch, field):
    data = json.loads(standard_dome().to_json())
    for key, value in patch.items():
        if isinstance(value, dict):
            data[key].update(value)
        else:
            data[key] = value
    with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
        scenario_from_dict(data)


def test_bad_indenters_rejected():
    data = json.loads(standard_dome().to_json())
    data["indenters"][0]["params"] = {}
    with pytest.raises(ScenarioError, match="missing 'radius'"):
        scenario_from_dict(data)
    data = json.loads(standard_dome().to_json())
    second = dict(data["indenters"][0], name="b", keypoints=data["indenters"][0]["keypoints"][:2])
    data["indenters"].append(second)
    with pytest.raises(ScenarioError, match="same number"):
        scenario_from_dict(data)
    data = json.loads(standard_dome().to_json())
    data["indenters"][0].update(shape="mesh", mesh_path="nope.stl")
    with pytest.raises(ScenarioError, match="file not found"):
        scenario_from_dict(data)


def test_docs_toml_example_is_a_valid_scenario():
    import re
    import tomllib
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "fe.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    s = scenario_from_dict(tomllib.loads(block))
    assert s.n_keypoints == 2 and s.indenters[0].keypoints[1].rotation == [0.0, 0.0, 0.1]
