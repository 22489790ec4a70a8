"""Hiera (tools/train/model/hiera.py): shipped shapes and parameter budget, mask-unit locality in stage
one, MAE masking."""
import pytest

torch = pytest.importorskip("torch")

from tensortouch.tools.train.model import build_model  # noqa: E402
from tensortouch.tools.train.model.hiera import Hiera, HieraConfig, HieraMAE  # noqa: E402
from tensortouch.tools.train.model.layers import count_params  # noqa: E402


@pytest.mark.parametrize("size", [128, 96])
def test_shipped_config_shapes_and_parameter_budget(size):
    torch.manual_seed(0)
    m = build_model("hiera_qup", size)
    feats = m.encoder(torch.rand(1, 6, size, size))
    t = size // 4
    assert [tuple(f.shape[1:]) for f in feats] == [(32, t, t), (64, t // 2, t // 2), (128, t // 4, t // 4),
                                                   (256, t // 8, t // 8)]
    assert [len([b for b in range(len(m.encoder.blocks))])] == [7]          # stages 1-2-3-1
    n = count_params(m)
    assert 1_000_000 <= n <= 3_000_000
    assert m(torch.rand(1, 6, size, size)).shape == (1, 15, size, size)
    for arch in ("unet", "vit"):                                          # baselines of a similar size
        assert 0.6 * n <= count_params(build_model(arch, size)) <= 1.4 * n


def test_mask_unit_attention_is_local_in_stage_one():
    """A change deep inside one mask unit moves stage-1 features of that unit only (Hiera's locality)."""
    torch.manual_seed(0)
    enc = Hiera(HieraConfig(image_size=64)).eval()
    x = torch.rand(1, 6, 64, 64)
    x2 = x.clone()
    x2[:, :, 8:24, 8:24] += 1.0           # unit (0, 0) covers pixels 0..31; 8 px margin > conv reach
    with torch.no_grad():
        d = (enc(x)[0] - enc(x2)[0]).abs().sum(1)[0]                      # (16, 16) tokens
    assert d[:8, :8].min() > 0
    outside = d.clone(); outside[:8, :8] = 0
    assert outside.max() == 0
    with torch.no_grad():                 # deeper stages attend globally: everything moves
        assert (enc(x)[3] - enc(x2)[3]).abs().sum(1)[0].min() > 0


def test_mae_masks_75_percent_and_learns():
    torch.manual_seed(0)
    torch.set_num_threads(1)
    mae = HieraMAE(Hiera(HieraConfig(image_size=64)), decoder_dim=32, decoder_depth=1)
    vis = mae.random_mask(3, 16)
    assert vis.shape == (3, 16) and torch.all(vis.sum(1) == 4)
    x = torch.rand(2, 6, 64, 64)
    x[:, :, ::2] *= 0.2                     # structured
    loss, pred, vis = mae(x)
    assert vis.sum(1).tolist() == [1, 1] and pred.shape == (2, 4, 6 * 32 * 32)
    # the loss only looks at masked units: its gradient w.r.t. visible-unit predictions is zero
    pred.retain_grad()
    loss, pred, vis = mae(x, vis)
    pred.retain_grad(); loss.backward()
    assert pred.grad[vis].abs().max() == 0 and pred.grad[~vis].abs().max() > 0
    opt = torch.optim.AdamW(mae.parameters(), lr=1e-3)
    first = None
    for _ in range(10):
        loss = mae(x, vis)[0]
        opt.zero_grad(); loss.backward(); opt.step()
        first = first or loss.item()
    assert loss.item() < 0.8 * first
