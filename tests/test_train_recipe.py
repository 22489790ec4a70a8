"""Recipes (tools/train/recipe.py) take sessions by protocol set; the runner's step configs follow them."""
from __future__ import annotations

from pathlib import Path

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


def test_a_session_takes_world_parameters_and_older_stage_keys_hold():
    """SessionSpec.world_params: WorldConfig fields of a rig-world session (one difference switched off at a
    time, the label budget's recipes in tools/train/recipes/label-budget/). Empty, it stays out of the
    build's dict, so the stage keys of recipes written before it do not change."""
    from tensortouch.tools.train.build import BuildConfig, SessionSpec, stage_keys
    from tensortouch.tools.train.recipe import load_recipe
    from tensortouch.tools.train.runner import step_configs
    from tensortouch.tools.twin.world import WorldConfig, draw_world

    plain = BuildConfig(train=[SessionSpec("TWIN-T01", 141, 2, world="rig")])
    assert "world_params" not in plain.to_dict()["train"][0]
    same = BuildConfig.from_dict({**plain.to_dict(), "train": [{**plain.to_dict()["train"][0], "world_params": {}}]})
    assert stage_keys(same) == stage_keys(plain)
    off = SessionSpec("TWIN-T01", 141, 2, world="rig", world_params={"c10": 0.0, "c20": 0.0, "c30": 0.0})
    assert stage_keys(BuildConfig(train=[off]))["sessions"] != stage_keys(plain)["sessions"]
    rcfg = off.record_config("fe", 128)
    assert rcfg.world_params == {"c10": 0.0, "c20": 0.0, "c30": 0.0} and rcfg.key() != plain.train[0].record_config("fe", 128).key()
    w_off = draw_world("TWIN-T01", WorldConfig.with_overrides(rcfg.world_params))
    w_all = draw_world("TWIN-T01", WorldConfig())
    assert w_off.yeoh == (0.03, 0.002, 0.0002)                       # nominal Yeoh ...
    assert w_off.gel == w_all.gel and w_off.clock_offset_s == w_all.clock_offset_s   # ... the rest as drawn
    import tensortouch.tools.train as train_pkg
    budget = sorted((Path(train_pkg.__file__).parent / "recipes" / "label-budget").glob("*.toml"))
    assert len(budget) == 6
    for f in budget:
        (cfg,) = step_configs(load_recipe(f))                         # the budget's recipes load and agree with the protocol
        assert len(cfg.heldout) == 3 and not cfg.train
