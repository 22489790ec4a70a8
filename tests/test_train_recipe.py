"""Recipes (tools/train/recipe.py) take sessions by protocol set; the runner's step configs follow them."""
from __future__ import annotations

import pytest
from tensortouch.tools.train import protocol as P


def test_a_recipe_takes_sessions_by_set(tmp_path):
    from tensortouch.tools.train.recipe import RecipeError, load_recipe
    from tensortouch.tools.train.runner import step_configs

    h = P.load_protocol().hash
    r = tmp_path / "r.toml"
    r.write_text('name = "n"\n[sessions]\ntrain = { set = "train", first = 2, pokes = 3 }\n'
                 f'heldout = {{ set = "validation", first = 1, protocol = "{h}" }}\n[build]\nepochs = 2\n')
    (cfg,) = step_configs(load_recipe(r))
    assert [s.name for s in cfg.train] == ["TWIN-T01-s141", "TWIN-T02-s142"] and cfg.train[0].pokes == 3
    assert cfg.train[1].trajectory["indenters"] == ["sphere5", "flat4"] and cfg.train[1].world == "rig"
    assert [(s.serial, s.pokes) for s in cfg.heldout] == [("TWIN-H01", 8)]
    for text, want in (('heldout = { set = "sealed" }', "sessions.heldout takes the validation set"),
                       ('train = { set = "validation" }', "sessions.train takes the train set"),
                       ('train = { set = "train", first = 0 }', "sessions.train.first: expected a positive integer"),
                       ('train = { set = "train", protocol = "0000" }', "the unit sets changed"),
                       ('train = { units = "train" }', "takes set")):
        r.write_text(f'name = "n"\n[sessions]\n{text}\n')
        with pytest.raises(RecipeError, match=want):
            step_configs(load_recipe(r))
