"""Training sessions with their own plan ranges (SessionSpec.trajectory) and the twin's with_ranges."""
import pytest
from tensortouch.tools.train.build import BuildConfig, SessionSpec, stage_keys
from tensortouch.tools.twin.trajectory import TrajectoryConfig, with_ranges


def test_with_ranges_replaces_fields_and_names_bad_input():
    cfg = with_ranges(TrajectoryConfig(), {"kinds": ["slide"], "slide": [0.8, 1.6], "p_two": 0.0}, "x")
    assert cfg.kinds == ("slide",) and cfg.slide == (0.8, 1.6) and cfg.p_two == 0.0
    assert with_ranges(TrajectoryConfig(), {}) == TrajectoryConfig()
    with pytest.raises(ValueError, match="recipe.train: unknown trajectory field 'slidez'"):
        with_ranges(TrajectoryConfig(), {"slidez": [1, 2]}, "recipe.train")
    with pytest.raises(ValueError, match=r"r\.slide: expected a list"):
        with_ranges(TrajectoryConfig(), {"slide": [1, 2, 3]}, "r")
    with pytest.raises(ValueError, match=r"r\.kinds"):
        with_ranges(TrajectoryConfig(), {"kinds": ["wiggle"]}, "r")
    with pytest.raises(ValueError, match=r"r\.p_two: expected a number"):
        with_ranges(TrajectoryConfig(), {"p_two": "none"}, "r")


def test_default_specs_keep_their_stage_keys_and_ranges_change_them():
    plain = BuildConfig.from_dict({"train": [{"serial": "TWIN-T01", "seed": 101, "pokes": 5}]})
    assert "trajectory" not in plain.to_dict()["train"][0]          # older builds' stamps stay valid
    slides = BuildConfig.from_dict({"train": [{"serial": "TWIN-T01", "seed": 101, "pokes": 5,
                                               "trajectory": {"kinds": ["slide"]}}]})
    assert stage_keys(plain)["sessions"] != stage_keys(slides)["sessions"]


def test_record_config_carries_the_ranges():
    spec = SessionSpec("TWIN-T99", 7, 3, trajectory={"kinds": ["slide"], "depth_press": [0.6, 1.0]})
    rcfg = spec.record_config("hertz-fallback", 64)
    assert rcfg.trajectory.kinds == ("slide",) and rcfg.trajectory.depth_press == (0.6, 1.0)
    assert rcfg.serial == "TWIN-T99" and rcfg.pokes == 3 and rcfg.model_size == 64
    assert SessionSpec("TWIN-T99", 7, 3).record_config("hertz-fallback", 64).trajectory == TrajectoryConfig()
