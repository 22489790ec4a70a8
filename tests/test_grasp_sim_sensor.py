"""One simulated fingertip (tools/grasp/sim_sensor.py) through the real runtime and a real Zenoh session on
loopback: the controller sees the objects where they are."""
import time

import numpy as np
import pytest
from tensortouch.tools.grasp.controller import SelectiveGraspController
from tensortouch.tools.grasp.dome_contact import ObjectContact

from tests.test_grasp_controller import _line_graph


def test_simulated_fingertip_contacts_arrive_over_zenoh_loopback():
    """Twin render → SensorLoop (shipped int8 model, TWIN-DEMO calibration) → Publisher → a real
    Zenoh session on loopback → the controller's subscriber sees two clusters where the objects are."""
    from tensortouch.contracts.store import CalibrationStore
    from tensortouch.runtime.apps.publisher import open_session
    from tensortouch.runtime.pipeline import SensorPipeline
    from tensortouch.runtime.stages.model import FieldModel, find_package
    from tensortouch.tools.grasp.controller import ControllerNode
    from tensortouch.tools.grasp.sim_sensor import SimFingertip
    from tensortouch.tools.grasp.trial import free_endpoint
    from tensortouch.tools.twin.unit import TwinUnit

    unit = TwinUnit("TWIN-DEMO")
    from tensortouch.tools.grasp.trial import TrialConfig

    pipe = SensorPipeline("TWIN-DEMO", FieldModel(find_package(TrialConfig().model), "int8", threads=1),
                          CalibrationStore().load("TWIN-DEMO"))
    ep = free_endpoint()
    pub_s, sub_s = open_session(listen=[ep]), open_session(connect=[ep])
    try:
        deadline = time.monotonic() + 10
        while not list(sub_s.info.peers_zid()) and time.monotonic() < deadline:
            time.sleep(0.05)
        ctrl = SelectiveGraspController(_line_graph(), 4)
        node = ControllerNode(ctrl, sub_s, {"thumb": "test-thumb"})
        sen = SimFingertip("test-thumb", unit, pipe, pub_s)
        try:
            gel = unit.gel
            objs = [ObjectContact(gel.point_at(abs(x) / gel.profile.radius_mm, 0.0 if x > 0 else np.pi), np.array([0, 1.0, 0]),
                                  1.09, 1.2, np.zeros(3)) for x in (-4.0, 4.0)]   # pressed to the 1.2 mm cushion
            for i in range(36):
                sen.show([] if i < 32 else objs, i * 0.04)
            assert ctrl.wait_frames({"thumb": 36}, timeout=30)
            seen = sorted(p[0] for p, *_ in ctrl.latest["thumb"])
            assert len(seen) == 2, ctrl.latest["thumb"]
            assert seen[0] == pytest.approx(-4.0, abs=1.5) and seen[1] == pytest.approx(4.0, abs=1.5)
        finally:
            sen.close()
            node.close()
    finally:
        sub_s.close()
        pub_s.close()
