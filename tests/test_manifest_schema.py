"""The model package manifest schema (contracts/manifest_schema.py) on the shipped manifest and on copies
with one field wrong: one error naming the file and the field."""
import copy
import json

import pytest
from tensortouch.contracts.errors import ModelPackageError
from tensortouch.contracts.fields import CHANNELS
from tensortouch.contracts.manifest_schema import check_manifest
from tensortouch.contracts.paths import ROOT

SHIPPED = json.loads((ROOT / "exported_models" / "hiera-qup-128" / "manifest.json").read_text())


def _with(fn):
    m = copy.deepcopy(SHIPPED)
    fn(m)
    return m


def test_the_shipped_manifest_passes():
    check_manifest(SHIPPED, "manifest.json")
    assert SHIPPED["input"]["size"] == [128, 128]


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.update(schema_version=0), "schema_version is 0"),
    (lambda m: m["input"].update(size=[128]), "input.size is [128], expected [H, W] positive integers"),
    (lambda m: m["input"].update(size=[4, 128]), "input.size[0] is 4"),
    (lambda m: m["input"].update(channels=list(reversed(m["input"]["channels"]))), "input.channels is"),
    (lambda m: m["input"].update(range=[1.0, 0.0]), "input.range is [1.0, 0.0], expected lo < hi"),
    (lambda m: m["output"].update(size=[64, 64]), "output.size is [64, 64], expected the input size [128, 128]"),
    (lambda m: m["output"]["bounds"].update({CHANNELS[0]: [2.0, 1.0]}), f"output.bounds.{CHANNELS[0]} is [2.0, 1.0]"),
    (lambda m: m["output"]["bounds"].pop(CHANNELS[-1]), f"output.bounds.{CHANNELS[-1]} is None"),
    (lambda m: m["output"]["bounds"].update({CHANNELS[1]: [0.0, float("nan")]}), "is nan, expected a finite number"),
])
def test_one_wrong_field_is_named(edit, message):
    with pytest.raises(ModelPackageError) as info:
        check_manifest(_with(edit), "pkg/manifest.json")
    assert str(info.value).startswith("pkg/manifest.json: ") and message in str(info.value), str(info.value)
