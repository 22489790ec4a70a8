"""`tensortouch run --fields-every N` / `--no-fields`: dense fields at a reduced rate (or not at all)
while contacts and status keep the frame rate — real runtime and listener processes on loopback."""
import json

import pytest
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import SENSOR, SIZE, H, W, run_and_listen, write_poke_session


@pytest.mark.parametrize("extra,ratio", [(["--fields-every", "3"], (2.0, 4.5)), (["--no-fields"], None)])
def test_field_rate_options(tmp_path, extra, ratio):
    session = write_poke_session(tmp_path / "session")
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    dome_calibration(tmp_path / "calib", SENSOR, size=SIZE, image=(W, H), radius_px=50.0)
    listener, err = run_and_listen(tmp_path, session, extra,
                                   ["--count", "120", "--json", "--kinds", "fields,contacts"])
    msgs = [json.loads(line) for line in listener.stdout.splitlines() if line.startswith("{")]
    n_fields = sum(m.get("kind") == "fields" for m in msgs)
    n_contacts = sum(m.get("kind") == "contacts" for m in msgs)
    assert n_contacts > 30, (listener.stderr[-1500:], err[-1500:])
    if ratio is None:
        assert n_fields == 0
    else:
        assert n_fields > 0 and ratio[0] <= n_contacts / n_fields <= ratio[1], (n_contacts, n_fields)
