"""The acceptance harness's unknown-effect plugin (tools/accept/workbench_plugins/azimuth_stiffness.py)."""
from tensortouch.runtime.stages.effects import Registry
from tensortouch.tools.accept.workbench import PLUGINS  # the harness's plugin


def test_the_acceptance_harness_finds_its_plugin():
    """`tensortouch accept workbench` loads its unknown-effect plugin from the installed tools tree."""
    reg = Registry.default(plugin_dirs=[PLUGINS], entry_points=False)
    assert "azimuth_stiffness" in reg.names()
