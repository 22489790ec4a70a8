"""The Q-Upsample decoder pieces (tools/train/model/qupsample.py): queries at twice the resolution, the
heads' remap to other bounds exact, and their start at the mean target."""
import pytest

torch = pytest.importorskip("torch")

from tensortouch.tools.train.model.qupsample import Heads, QUpsample  # noqa: E402


def test_qupsample_doubles_the_resolution_and_the_residual_is_nearest():
    torch.manual_seed(0)
    up = QUpsample(dim_in=8, dim_out=4, heads=2).eval()
    x = torch.rand(2, 8, 3, 5)
    with torch.no_grad():
        assert up(x).shape == (2, 4, 6, 10)
        y = up._up(torch.arange(4.0).reshape(1, 2, 2, 1), sub_pos=False)[0, :, :, 0]
    assert y.tolist() == [[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 3, 3], [2, 2, 3, 3]]


@pytest.mark.parametrize("shuffle", [1, 2])
def test_heads_remap_is_exact_and_the_bias_starts_at_the_mean(shuffle):
    torch.manual_seed(0)
    h = Heads(6, hidden=4, shuffle=shuffle).eval()
    x = torch.rand(2, 6, 8, 8)
    scale, offset = torch.linspace(0.5, 2.0, 15), torch.linspace(-1.0, 1.0, 15)
    with torch.no_grad():
        before = h(x)
        assert before.shape == (2, 15, 8 * shuffle, 8 * shuffle)
        h.remap_output(scale, offset)
        after = h(x)
    assert torch.allclose(after, scale.view(1, 15, 1, 1) * before + offset.view(1, 15, 1, 1), atol=1e-5)
    h.set_output_bias(torch.full((15,), 0.5))
    for head in h.heads:
        last = head[-2]
        assert torch.equal(last.bias, torch.full_like(last.bias, 0.5))
