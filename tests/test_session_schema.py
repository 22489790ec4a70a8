"""The numbers of a session (contracts/session_schema.py): row ranges in house units, whole-number ids,
unit quaternions, and session.json values, each refusal naming the file, row and column."""
import numpy as np
import pytest
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.schema import SchemaError
from tensortouch.contracts.session_schema import check_ft_to_indenter, check_manifest_values, check_rows

WRENCH = ["t", "indenter", "fx", "fy", "fz", "tx", "ty", "tz"]
POSES = ["t", "indenter", "x", "y", "z", "qw", "qx", "qy", "qz"]


def test_rows_inside_the_ranges_pass_and_the_first_bad_row_is_named():
    w = np.array([[0.0, 0, 0.1, 0.2, -3.0, 1.0, 2.0, 3.0], [0.01, 0, 0.1, 0.2, -3.5, 1.0, 2.0, 3.0]])
    check_rows("wrench", w, WRENCH, "wrench.csv")
    check_rows("unknown", w, WRENCH, "x.csv")              # streams without a column table are not checked
    bad = w.copy()
    bad[1, 4] = -2e4                                       # 20 kN: beyond the force range (±1e4 N)
    with pytest.raises(SessionError, match=r"^wrench\.csv:3: fz = -20000, expected a value in .*force, house units"):
        check_rows("wrench", bad, WRENCH, "wrench.csv")
    bad = w.copy()
    bad[0, 1] = 1.5
    with pytest.raises(SessionError, match=r"wrench\.csv:2: indenter = 1\.5, expected a whole number"):
        check_rows("wrench", bad, WRENCH, "wrench.csv")


def test_pose_quaternions_must_be_unit():
    p = np.array([[0.0, 0, 1.0, 2.0, 3.0, 1.0, 0, 0, 0], [0.01, 0, 1.0, 2.0, 3.0, 0.6, 0.8, 0, 0]])
    check_rows("poses", p, POSES, "poses.csv")
    p[1, 5:9] = [0.5, 0, 0, 0]
    with pytest.raises(SessionError, match=r"poses\.csv:3: quaternion qw,qx,qy,qz has norm 0\.5"):
        check_rows("poses", p, POSES, "poses.csv")


def test_ft_to_indenter_and_manifest_values():
    check_ft_to_indenter({"rotation_wxyz": [0.6, 0.8, 0, 0], "translation_mm": [0, 0, 44.0]}, "tf")
    with pytest.raises(SchemaError, match=r"tf\.rotation_wxyz has norm 0\.707107, expected a unit quaternion"):
        check_ft_to_indenter({"rotation_wxyz": [0.5, 0.5, 0, 0], "translation_mm": [0, 0, 0]}, "tf")
    with pytest.raises(SchemaError, match=r"tf\.rotation_wxyz\[0\] is 2\.0, expected a number in \[-1\.001, 1\.001\]"):
        check_ft_to_indenter({"rotation_wxyz": [2.0, 0, 0, 0], "translation_mm": [0, 0, 0]}, "tf")
    with pytest.raises(SchemaError, match=r"tf is 'identity', expected"):
        check_ft_to_indenter("identity", "tf")
    ok = {"clock": {"t0": 1.7e9}, "streams": {"wrench": {"ft_to_indenter": {
        "rotation_wxyz": [1.0, 0, 0, 0], "translation_mm": [0, 0, 44.0]}}}}
    check_manifest_values(ok, "s/session.json")
    with pytest.raises(SessionError, match=r"^s/session\.json: clock\.t0 is inf, expected a finite number"):
        check_manifest_values({**ok, "clock": {"t0": float("inf")}}, "s/session.json")
