"""Weight-space average of a fine-tune and its starting point (tools/train/average.py), on the tiny run of
tests/test_train_export.py."""
import json
import shutil

import pytest

torch = pytest.importorskip("torch")

from tests.test_train_export import package  # noqa: E402,F401  (the tiny run and its dataset)
from tensortouch.runtime.shells.cli import main    # noqa: E402
from tensortouch.tools.train.average import average_run, average_states    # noqa: E402
from tensortouch.tools.train.model.data import DatasetError    # noqa: E402


def _load(p):
    return torch.load(p, weights_only=True, map_location="cpu")


def test_average_is_the_weighted_mean_and_keeps_integer_buffers():
    a = {"w": torch.ones(3), "n": torch.tensor(5)}
    b = {"w": torch.zeros(3), "n": torch.tensor(9)}
    out = average_states(a, b, 0.25)
    assert torch.allclose(out["w"], torch.full((3,), 0.25)) and int(out["n"]) == 5
    with pytest.raises(DatasetError, match="0..1"):
        average_states(a, b, 1.5)
    with pytest.raises(DatasetError, match="same architecture"):
        average_states(a, {"w": torch.zeros(3)}, 0.5)
    with pytest.raises(DatasetError, match="shape"):
        average_states(a, {"w": torch.zeros(4), "n": torch.tensor(1)}, 0.5)


def test_averaged_run_sits_between_the_two_and_exports(package, tmp_path):  # noqa: F811 (fixture)
    _, data, run = package
    base_dir = tmp_path / "base"
    base_dir.mkdir()
    tuned = _load(run / "best.pt")
    base = {k: (v + 1.0 if torch.is_floating_point(v) else v) for k, v in tuned.items()}
    torch.save(base, base_dir / "best.pt")
    shutil.copyfile(run / "bounds.json", base_dir / "bounds.json")      # same bounds: no head rescale
    cfg = average_run(run, base_dir / "best.pt", 0.75, tmp_path / "avg")
    got = _load(tmp_path / "avg" / "best.pt")
    k = next(k for k, v in tuned.items() if torch.is_floating_point(v))
    assert torch.allclose(got[k], tuned[k] + 0.25) and not cfg["heads_rescaled"]
    assert json.loads((tmp_path / "avg" / "config.json").read_text())["weight"] == 0.75
    assert main(["train", "average", "--tuned", str(run), "--base", str(base_dir / "best.pt"), "--weight", "1.0", "--out",
                 str(tmp_path / "same"), "--export", str(data), "--name", "tiny", "--models-dir", str(tmp_path / "m")]) == 0
    same = _load(tmp_path / "same" / "best.pt")
    assert all(torch.equal(same[k], tuned[k]) for k in tuned)
    man = json.loads((tmp_path / "m" / "tiny" / "manifest.json").read_text())
    assert "tensortouch train average" in json.dumps(man)


def test_a_missing_run_or_state_is_a_clear_error(package, tmp_path):  # noqa: F811 (fixture)
    _, _, run = package
    with pytest.raises(DatasetError, match="no best.pt"):
        average_run(tmp_path, run / "best.pt", 0.5, tmp_path / "x")
    with pytest.raises(DatasetError, match="no such state dict"):
        average_run(run, tmp_path / "nope.pt", 0.5, tmp_path / "x")
