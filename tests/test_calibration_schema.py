"""Plausibility of calibration.json (contracts/calibration_schema.py) on the shipped TWIN-DEMO calibration
and on copies with one field wrong: one error naming the file and the field."""
import copy
import json

import pytest
from tensortouch.contracts.calibration_schema import check_calibration
from tensortouch.contracts.errors import CalibrationError
from tensortouch.contracts.paths import ROOT

DEMO = json.loads((ROOT / "calibration_store" / "TWIN-DEMO" / "versions" / "v0001" / "calibration.json").read_text())


def _with(fn):
    m = copy.deepcopy(DEMO)
    fn(m)
    return m


def test_the_shipped_calibration_passes_and_the_camera_frame_is_optional():
    check_calibration(DEMO, "calibration.json")
    check_calibration(_with(lambda m: m.pop("camera")), "calibration.json")
    # without a camera size only the absolute limits hold: a centre at x = 1000 px is then plausible
    check_calibration(_with(lambda m: (m.pop("camera"), m.update(gel_center_px=[1000.0, 120.0]))), "c.json")


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.update(model_size=[4, 128]), "model_size[0] is 4"),
    (lambda m: m.update(gel_center_px=[400.0, 120.0]),
     "gel_center_px is [400, 120], expected the gel centre inside the image of the 320x240 camera image"),
    (lambda m: m.update(gel_radius_px=4.0), "gel_radius_px is 4.0"),
    (lambda m: m.update(gel_radius_px=500.0), "of the 320x240 camera image"),
    (lambda m: m.update(camera={"width": 320}), "camera is {'width': 320}, expected"),
    (lambda m: m["gel"].update(shape="cube"), "gel.shape is 'cube'"),
    (lambda m: m.update(effects=["viscoelastic"]), "effects must be a list of objects"),
    (lambda m: m.update(gel_radius_px=float("inf")), "gel_radius_px is inf, expected a finite number"),
])
def test_one_implausible_field_is_named(edit, message):
    with pytest.raises(CalibrationError) as info:
        check_calibration(_with(edit), "TWIN-DEMO/calibration.json")
    assert str(info.value).startswith("TWIN-DEMO/calibration.json: ") and message in str(info.value), str(info.value)
