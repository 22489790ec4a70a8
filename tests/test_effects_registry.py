"""The effect registry (runtime/stages/effects/registry.py): plugin folders, entry points, bad plugins
refused."""
import sys
import textwrap

import numpy as np
import pytest
from tensortouch.runtime.stages.effects import Registry

PLUGIN = '''
import numpy as np
from tensortouch.runtime.stages.effects import Effect, Param, need, scale_rows

class AzimuthStiffness(Effect):
    name = "azimuth_stiffness"
    summary = "gel stiffer on one side"
    params = (Param("a", "-", 0.1, 0.0, 1.0), Param("phi0", "rad", 0.0, -3.2, 3.2))
    covariates = ("phi",)
    off = {"a": 0.0}

    def forward(self, x, cov, p):
        return scale_rows(x, 1 + p["a"] * np.cos(need(cov, "phi", self.name) - p["phi0"]))
'''


def test_plugin_folder_joins_the_registry(tmp_path, monkeypatch):
    (tmp_path / "azimuth.py").write_text(PLUGIN)
    reg = Registry.default(plugin_dirs=[tmp_path], entry_points=False)
    assert "azimuth_stiffness" in reg.names()
    e = reg.get("azimuth_stiffness")
    y = e.apply(np.ones((2, 3)), {"phi": np.array([0.0, np.pi])}, e.resolve({"a": 0.5}))
    assert np.allclose(y[:, 0], [1.5, 0.5])
    monkeypatch.setenv("TENSORTOUCH_EFFECTS_PATH", str(tmp_path))
    assert "azimuth_stiffness" in Registry.default(entry_points=False).names()


def test_entry_point_plugin_is_discovered(tmp_path, monkeypatch):
    """A real installed distribution (dist-info with entry_points.txt) on sys.path."""
    (tmp_path / "tt_azimuth_plugin.py").write_text(PLUGIN)
    dist = tmp_path / "tt_azimuth_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: tt-azimuth-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[tensortouch.effects]\nazimuth = tt_azimuth_plugin:AzimuthStiffness\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    reg = Registry.default()
    assert "azimuth_stiffness" in reg.names()
    assert reg.origin["azimuth_stiffness"] == "entry point azimuth"
    sys.modules.pop("tt_azimuth_plugin", None)


def test_bad_plugins_are_rejected_with_a_reason(tmp_path):
    (tmp_path / "bad.py").write_text(textwrap.dedent('''
        from tensortouch.runtime.stages.effects import Effect, Param
        class Bad(Effect):
            name = "temperature_softening"
            params = (Param("a", "-", 0.1, 0.0, 1.0),)
            def forward(self, x, cov, p):
                return x
    '''))
    with pytest.raises(ValueError, match="already taken"):
        Registry.default(plugin_dirs=[tmp_path], entry_points=False)
    (tmp_path / "bad.py").write_text(textwrap.dedent('''
        from tensortouch.runtime.stages.effects import Effect, Param
        class Bad(Effect):
            name = "bad"
            params = (Param("a", "-", 0.1, 0.0, 1.0),)
            covariates = ("moon_phase",)
            def forward(self, x, cov, p):
                return x
    '''))
    with pytest.raises(ValueError, match="moon_phase"):
        Registry.default(plugin_dirs=[tmp_path], entry_points=False)
