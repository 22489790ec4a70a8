"""The twin's effect specs (tools/twin/effect_specs.py) are the runtime's definitions."""
import pytest
from tensortouch.runtime.stages.effects import CANONICAL, Registry


def test_twin_specs_are_the_runtime_definitions():
    """One vocabulary: the twin's specs are read from the runtime's effect classes (no second copy),
    and the twin has a truth form for every library effect."""
    specs = pytest.importorskip("tensortouch.tools.twin.effect_specs")
    twin = pytest.importorskip("tensortouch.tools.twin.effects")
    reg = Registry.default(entry_points=False)
    assert tuple(specs.CANONICAL) == tuple(CANONICAL)
    for name in CANONICAL:
        spec, e = specs.SPECS[name], reg.get(name)
        assert name in twin.EFFECTS, name
        assert e.stage == spec.stage and tuple(e.covariates) == spec.covariates, name
        assert all(a is b for a, b in zip(e.params, spec.params)) and len(e.params) == len(spec.params), name
        assert e.resolve(e.off) == spec.resolve(spec.off), name
        assert set(spec.covariates) <= set(specs.COVARIATES), name
