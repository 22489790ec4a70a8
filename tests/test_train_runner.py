"""The build runner (tools/train/runner.py): export never silently replaces a package made from another
recipe or other data, and the checkout's commit is recorded."""
import json
import re

import pytest
from tensortouch.contracts.paths import ROOT
from tensortouch.tools.train.recipe import RecipeError
from tensortouch.tools.train.runner import check_replace, git_commit


def _package(tmp_path, training):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "manifest.json").write_text(json.dumps({"training": training}))
    return pkg


def test_same_recipe_and_data_or_no_package_is_replaced_quietly(tmp_path):
    check_replace(tmp_path / "none", "r1", "d1", replace=False)          # nothing there yet
    pkg = _package(tmp_path, {"recipe": {"hash": "r1"}, "data_hash": "d1"})
    check_replace(pkg, "r1", "d1", replace=False)


def test_another_recipe_or_other_data_needs_replace(tmp_path):
    pkg = _package(tmp_path, {"recipe": {"hash": "r1"}, "data_hash": "d1234567890abcdef"})
    with pytest.raises(RecipeError, match=r"pkg was built from recipe r1; this build would replace it: give --replace"):
        check_replace(pkg, "r2", "d1234567890abcdef", replace=False)
    with pytest.raises(RecipeError, match=r"pkg was built from data d1234567890a;"):
        check_replace(pkg, "r1", "other", replace=False)
    check_replace(pkg, "r2", "other", replace=True)
    (pkg / "manifest.json").write_text("{not json")                       # unreadable: no recipe recorded
    with pytest.raises(RecipeError, match="built from recipe none recorded"):
        check_replace(pkg, "r1", "d1", replace=False)


def test_the_checkout_commit_is_a_sha_perhaps_dirty():
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    assert re.fullmatch(r"[0-9a-f]{40}(-dirty)?", git_commit() or ""), git_commit()
