"""`tensortouch listen --save out.rrd`: a Rerun recording that rerun's own loader (rerun.chunk.RrdReader
and `rerun rrd verify`) opens, with the dome, fields tensor, contacts, arrows and time series."""
import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("rerun")

from rerun.chunk import RrdReader

from tests import test_listen
from tests.viewers_util import listen_save

sensor_fixture = test_listen.running_sensor          # a publisher on loopback (its endpoint)


def entities(path):
    store = RrdReader(path).store()
    out = {}
    for chunk in store.stream().to_chunks() if hasattr(store, "stream") else store.chunks():
        out.setdefault(chunk.entity_path, []).append(chunk)
    return out


def test_listen_save_rrd_opens_with_rerun(sensor_fixture, tmp_path):
    out = tmp_path / "out.rrd"
    r = listen_save(sensor_fixture, out, tmp_path / "site")
    assert r.returncode == 0, r.stderr[-2000:]
    assert out.is_file() and not (tmp_path / "out.rrd.partial").exists()
    rerun_cli = shutil.which("rerun")
    if rerun_cli:
        r = subprocess.run([rerun_cli, "rrd", "verify", str(out)], capture_output=True, text=True, timeout=60,
                           check=False)
        assert r.returncode == 0, r.stderr[-2000:]
    ents = entities(out)
    for e in ("/dome01/fields", "/dome01/fields/channels", "/dome01/gel/contacts", "/dome01/gel/forces",
              "/dome01/wrench/force_n/z", "/dome01/status"):
        assert e in ents, sorted(ents)
    batch = ents["/dome01/wrench/force_n/z"][0].to_record_batch()
    cols = [c for c in batch.schema.names if "Scalars:scalars" in c or c.endswith("scalars")]
    assert cols, batch.schema.names
    vals = np.concatenate([np.asarray(v, float).ravel() for v in batch.column(cols[0]).to_pylist() if v])
    np.testing.assert_allclose(vals, -1.0)                              # the fixture's force z, N
