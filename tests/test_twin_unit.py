"""A twin unit (tools/twin/unit.py): a rig unit's calibration names the gel design, not its own gel."""
import numpy as np
from tensortouch.tools.twin.world import draw_world


def test_a_rig_units_calibration_names_the_gel_design_not_its_own_gel():
    """The label FE reads the gel from the calibration's meta: it must stay the design (no truth leak)."""
    from tensortouch.tools.twin.unit import TwinUnit, calibration_meta, true_tables

    w = draw_world("TWIN-W1")
    rig, label = TwinUnit("TWIN-W1", world=w), TwinUnit("TWIN-W1")
    m = calibration_meta(rig, 32)
    assert m["gel"] == calibration_meta(label, 32)["gel"] and m["gel"]["base_radius_mm"] == 12.0
    assert m["provenance"]["unit_gel"]["base_radius_mm"] == w.gel.radius
    assert not np.array_equal(true_tables(rig, 32)["theta"], true_tables(label, 32)["theta"])   # the images differ
