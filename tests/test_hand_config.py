"""Hand config files (runtime/apps/hand_config.py): round trip, errors that name the problem, the
documented example."""
import pytest
from tensortouch.runtime.apps.hand_config import HandConfigError, load_hand_config, parse_hand_config


def test_config_file_round_trip(tmp_path):
    (tmp_path / "hand.toml").write_text("""
[hand]
name = "left"
precision = "fp32"
share_model = true
calibration_store = "cal"

[zenoh]
listen = ["tcp/127.0.0.1:7555"]

[can]
interface = "virtual"
channel = "x"
id_base = 0x200
rate_hz = 50

[[finger]]
name = "thumb"
serial = "TT-0001"

[[finger]]
name = "index"
serial = "TT-0002"
source = "replay:/data/index"
calibration = "TT-0002-b"
can_slot = 3
""")
    cfg = load_hand_config(tmp_path / "hand.toml")
    assert cfg.name == "left" and cfg.precision == "fp32" and cfg.share_model
    assert cfg.calibration_store == str(tmp_path / "cal")
    assert cfg.listen == ("tcp/127.0.0.1:7555",)
    assert cfg.can.id_base == 0x200 and cfg.can.rate_hz == 50
    thumb, index = cfg.fingers
    assert thumb.source_uri == "usb:TT-0001" and thumb.calibration_id == "TT-0001"
    assert index.calibration_id == "TT-0002-b"
    assert cfg.slots() == {"thumb": 0, "index": 3}


@pytest.mark.parametrize("doc, match", [
    ({"finger": []}, "no \\[\\[finger\\]\\]"),
    ({"finger": [{"name": "a", "serial": "S1"}, {"name": "a", "serial": "S2"}]}, "name \\['a'\\]"),
    ({"finger": [{"name": "a", "serial": "S1", "colour": "red"}]}, "unknown key 'colour'"),
    ({"finger": [{"name": "a", "serial": "bad/id"}]}, "sensor id"),
    ({"hand": {"precison": "int8"}, "finger": [{"name": "a", "serial": "S1"}]}, "unknown key 'precison'"),
    ({"can": {"id_base": 0x7FF}, "finger": [{"name": "a", "serial": "S1"}]}, "11-bit"),
    ({"hand": {"opencv_threads": 0}, "finger": [{"name": "a", "serial": "S1"}]}, "opencv_threads"),
    ({"hand": {"fields_every": 0}, "finger": [{"name": "a", "serial": "S1"}]}, "fields_every"),
    ({"finger": [{"name": "a", "serial": "S1", "can_slot": 1}, {"name": "b", "serial": "S2"}]}, "collide"),
])
def test_config_errors_name_the_problem(doc, match):
    with pytest.raises(HandConfigError, match=match):
        parse_hand_config(doc, "hand.toml")


def test_documented_example_config_parses():
    import re
    import tomllib
    from pathlib import Path

    doc = (Path(__file__).parents[1] / "docs" / "hand.md").read_text()
    block = re.search(r"```toml\n(.*?)```", doc, re.S).group(1)
    cfg = parse_hand_config(tomllib.loads(block), "docs/hand.md")
    assert cfg.fingers[0].serial == "TT-0001" and cfg.can.id_base == 0x300 and cfg.can.rate_hz == 100
    assert cfg.camera_options == {"realtime": True, "loop": False}


def test_fields_every_parses_with_default_1():
    cfg = parse_hand_config({"hand": {"fields_every": 3}, "finger": [{"name": "a", "serial": "S1"}]}, "hand.toml")
    assert cfg.fields_every == 3
    assert parse_hand_config({"finger": [{"name": "a", "serial": "S1"}]}, "hand.toml").fields_every == 1
