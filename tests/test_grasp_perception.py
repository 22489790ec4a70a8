"""tools.grasp.perception: two parallel objects on the gel (pure) and the table."""
import numpy as np
import pytest
from tensortouch.tools.grasp.perception import PerceptionConfig, Response, pair_contacts, table
from tensortouch.tools.grasp.sensor_mount import SensorMount


def test_pair_lies_either_side_of_the_apex_at_the_hand_worked_angle():
    m = SensorMount()
    a, b = pair_contacts(m, 2.0, 0.5, 5.0)
    # axes 7 mm apart: each 3.5 mm across, seen from the fingertip centre at atan(3.5 / (12 + 1))
    th = np.arctan2(3.5, 13.0)
    for c, sign in ((a, -1), (b, 1)):
        u = m.R_ts.T @ m.gel_to_direction(c.point)            # back to the sensor axes
        assert np.isclose(np.arctan2(u[0], u[2]), sign * th, atol=1e-6)
        assert abs(u[1]) < 1e-9
        assert c.radius == 1.0 and c.depth == 0.5 and np.allclose(c.axis, [0, 1, 0]) and not c.shear.any()
    assert (a.index, b.index) == (0, 1)
    assert np.isclose(a.point[2], b.point[2]) and np.isclose(a.point[0], -b.point[0])


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="diameter > 0"):
        pair_contacts(SensorMount(), 0.0, 0.5, 5.0)
    with pytest.raises(ValueError, match="depths_mm"):
        PerceptionConfig(depths_mm=(0.5, -1.0))
    with pytest.raises(ValueError, match="diameters_mm"):
        PerceptionConfig(diameters_mm=())


def test_table_lists_each_size_with_its_clusters():
    rows = [Response(1.0, 0.5, [], 0.0), Response(8.0, 1.0, [([0, 1, 2], 1.5), ([0, -1, 2], 1.25)], 2.7)]
    out = table(rows, "m").splitlines()
    assert out[-2] == "| 1 | 0.5 | 0 | 0.00 | — |"
    assert out[-1] == "| 8 | 1 | 2 | 2.70 | 1.50, 1.25 |"


def test_cli_refuses_a_bad_diameter_list(capsys):
    from tensortouch.runtime.shells.cli import main

    assert main(["grasp", "--perception", "--diameters-mm", "1,x"]) == 2
    assert "--diameters-mm" in capsys.readouterr().err
    assert main(["grasp", "--perception", "--depths-mm", "0.5,-1"]) == 2
    assert "depths_mm" in capsys.readouterr().err
