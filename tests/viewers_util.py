"""Helpers for the viewer tests: register the `tensortouch.savers` entry points of this worktree the way
an install of the `viewers` extra does (a dist-info folder with entry_points.txt on the PYTHONPATH of
a `tensortouch listen` process), so it finds them through importlib.metadata, with no mock."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def site_with_savers(folder: Path) -> Path:
    """A folder holding the dist-info; put it on a process's PYTHONPATH."""
    dist = folder / "tensortouch_viewers_test-0.0.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: tensortouch-viewers-test\nVersion: 0.0.0\n")
    (dist / "entry_points.txt").write_text("[tensortouch.savers]\nmcap = tensortouch.tools.viewers.mcap_saver:McapSaver\n"
                                           "rrd = tensortouch.tools.viewers.rerun_saver:RerunSaver\n")
    return folder



def listen_save(endpoint: str, out: Path, site: Path) -> subprocess.CompletedProcess:
    """`tensortouch listen dome01 --count 40 --save out` in its own process, connected to `endpoint`,
    finding the savers through the dist-info made in `site`."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site_with_savers(site)), str(ROOT)]))
    return subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "listen", "dome01", "--connect", endpoint,
                           "--count", "40", "--save", str(out)], env=env, capture_output=True, text=True, timeout=60,
                          check=False)
