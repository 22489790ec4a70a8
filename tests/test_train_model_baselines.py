"""Baseline networks (tools/train/model/baselines.py): a U-Net for any size divisible by 2^depth and a
dense ViT for its own image size; both map the 6 input channels to the 15 field channels at full
resolution."""
import pytest

torch = pytest.importorskip("torch")

from tensortouch.tools.train.model.baselines import UNet, UNetConfig, ViTConfig, ViTDense  # noqa: E402


def test_unet_is_fully_convolutional():
    torch.manual_seed(0)
    net = UNet(UNetConfig(widths=(4, 8), head_channels=4)).eval()
    with torch.no_grad():
        assert net(torch.rand(1, 6, 32, 48)).shape == (1, 15, 32, 48)
        assert net(torch.rand(2, 6, 16, 16)).shape == (2, 15, 16, 16)
    with pytest.raises(RuntimeError):
        net(torch.rand(1, 6, 18, 18))               # not divisible by 2²: the skips do not line up


def test_vit_dense_is_full_resolution_at_its_own_size_only():
    torch.manual_seed(0)
    cfg = ViTConfig(image_size=32, patch=8, dim=16, depth=1, heads=2, head_channels=4)
    net = ViTDense(cfg).eval()
    with torch.no_grad():
        assert net(torch.rand(2, 6, 32, 32)).shape == (2, 15, 32, 32)
        with pytest.raises(RuntimeError):
            net(torch.rand(1, 6, 40, 40))            # 25 patches, but positions were made for 16
