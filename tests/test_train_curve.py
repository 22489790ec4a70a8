"""Learning curve (tools/train/curve.py): the points' recipes and the table from crosseval's scorecards."""
from __future__ import annotations

import pytest
from tensortouch.tools.train.curve import curve_rows, format_rows, point_recipe
from tensortouch.tools.train.recipe import Recipe, RecipeError


def recipe(train):
    return Recipe("cand", "/x/cand.toml", {"name": "cand", "sessions": {"train": train, "heldout": []},
                                          "build": {"epochs": 2}})


def test_point_recipe_takes_the_first_n_train_units_and_the_fit_seed():
    base = recipe({"set": "train", "first": 12, "pokes": 8})
    r = point_recipe(base, 3, 1)
    assert r.name == "cand-u3-s1" and r.doc["name"] == "cand-u3-s1"
    assert r.doc["sessions"]["train"] == {"set": "train", "first": 3, "pokes": 8}
    assert r.doc["build"] == {"epochs": 2, "fit_seed": 1}
    assert base.doc["sessions"]["train"]["first"] == 12 and "fit_seed" not in base.doc["build"]   # not changed
    with pytest.raises(RecipeError, match="not a train-set reference"):
        point_recipe(recipe([{"serial": "TWIN-T01", "seed": 101, "pokes": 5}]), 3, 0)
    with pytest.raises(RecipeError, match="not a train-set reference"):
        point_recipe(recipe({"set": "validation", "first": 2}), 3, 0)
    with pytest.raises(RecipeError, match="≥ 1"):
        point_recipe(base, 0, 0)


def card(mae, miss):
    return {"overall": {"force_mae_n": {"mean": mae}, "miss_rate": {"mean": miss}, "phantom_rate": {"mean": 0.0},
                        "direction_error_deg": {"mean": 10.0}, "force_mae_with_misses_n": {"mean": mae}}}


def test_curve_rows_average_the_fit_seeds_of_each_point():
    cards = {"a": card(0.4, 0.10), "b": card(0.3, 0.06), "c": card(0.2, 0.04)}
    rows = curve_rows(cards, [(3, 0, "a"), (3, 1, "b"), (12, 0, "c"), (24, 0, "missing")])
    assert [r["train_units"] for r in rows] == [3, 12]
    assert rows[0]["packages"] == ["a", "b"] and rows[0]["force_mae_n"]["mean"] == pytest.approx(0.35)
    assert rows[0]["force_mae_n"]["sd"] == pytest.approx(0.0707107, rel=1e-5) and rows[1]["force_mae_n"]["n"] == 1
    text = format_rows(rows)
    assert "| 3 | 2 | 0.35 N ± 0.071 | 8 % ± 2.8 |" in text and "| 12 | 1 | 0.2 N | 4 % |" in text


def test_a_point_exported_from_the_same_recipe_is_not_rebuilt(tmp_path):
    import json

    from tensortouch.tools.train.curve import built_from

    r = point_recipe(recipe({"set": "train", "first": 12, "pokes": 8}), 3, 0)
    assert not built_from(tmp_path / "none", r)
    (tmp_path / "manifest.json").write_text("{not json")
    assert not built_from(tmp_path, r)
    (tmp_path / "manifest.json").write_text(json.dumps({"training": {"recipe": {"hash": r.hash}}}))
    assert built_from(tmp_path, r)
    assert not built_from(tmp_path, point_recipe(recipe({"set": "train", "first": 12, "pokes": 8}), 3, 1))
