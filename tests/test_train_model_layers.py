"""Shared transformer pieces (tools/train/model/layers.py): the mask-unit layout by hand, unit pooling,
attention against its formula (also the ONNX-export form), and parameter counts."""
import pytest

torch = pytest.importorskip("torch")

from tensortouch.tools.train.model.layers import (  # noqa: E402
    Attention,
    Mlp,
    attention,
    count_params,
    from_units,
    to_units,
    unit_pool,
)


def test_mask_units_by_hand_and_back():
    x = torch.arange(16.0).reshape(1, 1, 4, 4)                # pixel value = 4·row + col
    u = to_units(x, (2, 2))
    assert u.shape == (1, 4, 4, 1)
    assert u[0, :, :, 0].tolist() == [[0, 1, 4, 5], [2, 3, 6, 7], [8, 9, 12, 13], [10, 11, 14, 15]]
    assert torch.equal(from_units(u, (2, 2), (2, 2)), x)
    assert unit_pool(u, (2, 2))[0, :, 0, 0].tolist() == [5, 7, 13, 15]   # the max of each 2×2 unit
    y = torch.rand(2, 3, 8, 12)
    assert torch.equal(from_units(to_units(y, (4, 4)), (4, 4), (2, 3)), y)


def test_attention_is_the_formula_in_training_and_export_forms(monkeypatch):
    torch.manual_seed(0)
    q, k, v = torch.rand(2, 3, 5, 8), torch.rand(2, 3, 5, 8), torch.rand(2, 3, 5, 8)
    ref = torch.softmax(q @ k.transpose(-2, -1) / 8 ** 0.5, dim=-1) @ v
    assert torch.allclose(attention(q, k, v), ref, atol=1e-6)
    monkeypatch.setattr(torch.onnx, "is_in_onnx_export", lambda: True)
    assert torch.allclose(attention(q, k, v), ref, atol=1e-6)
    # one key only: every query gets that key's value
    assert torch.allclose(attention(q[..., :1, :], k[..., :1, :], v[..., :1, :]), v[..., :1, :])


def test_attention_stays_within_its_group_and_parameter_counts():
    torch.manual_seed(0)
    a = Attention(8, heads=2).eval()
    x = torch.rand(1, 2, 4, 8)                                  # two groups of 4 tokens
    x2 = x.clone()
    x2[0, 1] += 1.0                                             # change group 1 only
    with torch.no_grad():
        assert torch.equal(a(x)[0, 0], a(x2)[0, 0]) and not torch.equal(a(x)[0, 1], a(x2)[0, 1])
    assert count_params(a) == (8 * 24 + 24) + (8 * 8 + 8)       # qkv and proj: weights + biases
    assert count_params(Mlp(8, ratio=2.0)) == (8 * 16 + 16) + (16 * 8 + 8)
