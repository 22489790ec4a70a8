"""A fine-tune on data normalized with other output bounds starts at the init's physical output
(tools/train/model/train.py remap_heads; the heads' last convolutions are rescaled exactly)."""
import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tensortouch.contracts.fields import CHANNELS  # noqa: E402
from tensortouch.tools.train.fields import denormalize, read_bounds, write_bounds  # noqa: E402
from tensortouch.tools.train.model.train import DatasetError, head_remap, load_any_bounds  # noqa: E402


def _bounds(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    lo = -rng.uniform(0.01, 2.0, len(CHANNELS))
    hi = rng.uniform(0.01, 2.0, len(CHANNELS))
    return {c: [float(lo[i]), float(hi[i])] for i, c in enumerate(CHANNELS)}


def test_head_remap_keeps_the_physical_value():
    old, new = _bounds(0), _bounds(1)
    scale, offset = head_remap(old, new)
    y_old = np.random.default_rng(2).uniform(-0.2, 1.2, (15, 4, 4))
    y_new = scale[:, None, None] * y_old + offset[:, None, None]
    np.testing.assert_allclose(denormalize(y_new, new), denormalize(y_old, old), atol=1e-12)
    s, o = head_remap(old, old)
    np.testing.assert_allclose(s, 1.0)
    np.testing.assert_allclose(o, 0.0, atol=1e-15)


@pytest.mark.parametrize("arch", ["unet", "hiera_qup"])
def test_remapped_heads_give_the_same_fields(arch):
    from tensortouch.tools.train.model import build_model

    torch.manual_seed(0)
    model = build_model(arch, 64).eval()
    x = torch.rand(2, 6, 64, 64)
    old, new = _bounds(3), _bounds(4)
    with torch.no_grad():
        before = denormalize(model(x).numpy(), old)
        scale, offset = head_remap(old, new)
        model.heads.remap_output(torch.from_numpy(scale).float(), torch.from_numpy(offset).float())
        after = denormalize(model(x).numpy(), new)
    np.testing.assert_allclose(after, before, rtol=1e-4, atol=1e-4 * np.abs(before).max())


def test_fine_tune_on_wider_bounds_starts_at_the_init_output(tmp_path):
    from tensortouch.tools.train.model import build_model
    from tensortouch.tools.train.model.data import write_synthetic_dataset
    from tensortouch.tools.train.model.train import FitConfig, fit

    data = tmp_path / "ds"
    write_synthetic_dataset(data, 12, size=64, seed=3)
    fit(data, tmp_path / "base", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0))
    assert read_bounds(tmp_path / "base" / "bounds.json") == read_bounds(data / "bounds.json")
    wide = tmp_path / "wide"                       # the same samples under bounds twice as wide
    shutil.copytree(data, wide)
    old = read_bounds(data / "bounds.json")
    write_bounds(wide / "bounds.json", {c: [2 * lo - 0.1, 2 * hi + 0.1] for c, (lo, hi) in old.items()})
    x = torch.rand(1, 6, 64, 64)

    def physical(run, bounds):
        m = build_model("unet", 64).eval()
        m.load_state_dict(torch.load(run / "best.pt", weights_only=True))
        with torch.no_grad():
            return denormalize(m(x).numpy(), bounds)

    ref = physical(tmp_path / "base", old)
    for name, init_bounds in (("auto", ""), ("manifest", "pkg")):
        if init_bounds:                            # the init's bounds from a model package manifest
            (tmp_path / "pkg").mkdir()
            (tmp_path / "pkg" / "manifest.json").write_text(json.dumps({"output": {"bounds": old}}))
            init_bounds = str(tmp_path / "pkg" / "manifest.json")
        fit(wide, tmp_path / name, FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0, lr=0.0,
                                             init_from=str(tmp_path / "base" / "best.pt"), init_bounds=init_bounds))
        got = physical(tmp_path / name, read_bounds(wide / "bounds.json"))
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    # without the remap (no bounds beside the init) the same weights mean other physical values
    (tmp_path / "bare").mkdir()
    shutil.copy(tmp_path / "base" / "best.pt", tmp_path / "bare" / "best.pt")
    fit(wide, tmp_path / "plain", FitConfig(arch="unet", epochs=1, batch_size=4, threads=1, fg_weight=5.0, lr=0.0,
                                            init_from=str(tmp_path / "bare" / "best.pt")))
    assert np.abs(physical(tmp_path / "plain", read_bounds(wide / "bounds.json")) - ref).max() > 1e-2


def test_init_bounds_errors_name_the_file(tmp_path):
    bad = tmp_path / "manifest.json"
    bad.write_text(json.dumps({"output": {}}))
    with pytest.raises(DatasetError, match="manifest.json: no output.bounds"):
        load_any_bounds(bad)
    part = tmp_path / "p" / "manifest.json"
    part.parent.mkdir()
    part.write_text(json.dumps({"output": {"bounds": {"disp_x": [0, 1]}}}))
    with pytest.raises(DatasetError, match="lacks channels"):
        load_any_bounds(part.parent)
