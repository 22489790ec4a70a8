"""The exported graph's rewrites (tools/train/export_graph.py): conv + pixel shuffle as one transposed
conv, fused heads."""
import pytest

torch = pytest.importorskip("torch")


@pytest.mark.parametrize("k,groups,s", [(1, 5, 2), (3, 1, 2), (3, 2, 3)])
def test_conv_shuffle_as_one_conv_transpose_is_exact(k, groups, s):
    from tensortouch.tools.train.export_graph import ConvShuffle

    torch.manual_seed(k + groups + s)
    conv = torch.nn.Conv2d(4 * groups, 3 * groups * s * s, k, padding=k // 2, groups=groups)
    ref = torch.nn.Sequential(conv, torch.nn.PixelShuffle(s))
    x = torch.randn(2, 4 * groups, 7, 5)
    with torch.no_grad():
        assert torch.allclose(ConvShuffle(conv, s)(x), ref(x), atol=1e-5)
    with pytest.raises(ValueError, match="ConvShuffle"):
        ConvShuffle(torch.nn.Conv2d(4, 12, 3, padding=0), 2)             # not a 'same' conv


def test_rewritten_network_equals_the_trained_one():
    """The exported graph's rewrites (fused heads, shuffle as deconvolution) keep the function."""
    from tensortouch.tools.train.export_graph import FusedHeads, reparametrize
    from tensortouch.tools.train.model.hiera import HieraConfig
    from tensortouch.tools.train.model.qupsample import HieraQUpsample

    torch.manual_seed(0)
    net = HieraQUpsample(HieraConfig(image_size=64)).eval()
    for p in net.heads.parameters():                       # distinct per-head / per-sub-position weights
        p.data.normal_(0, 0.3)
    x = torch.rand(3, 6, 64, 64)
    with torch.no_grad():
        ref = net(x)
        out, done = reparametrize(net, 64)
        assert done == ["heads"] and isinstance(out.heads, FusedHeads)
        assert torch.allclose(out(x), ref, atol=1e-5)
