"""ResNet-18 / VGG-16 with torchvision's names, local weight loading, and the residual U-Net encoder."""
from __future__ import annotations

import pytest
import torch

from clsplat.models.common.backbones import (
    VGG16,
    ResidualBlock,
    ResidualUNetEncoder,
    ResNet18,
    load_backbone_weights,
)

BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def torchvision_resnet18_keys() -> list[str]:
    """torchvision's resnet18().state_dict() key set, written out from its published layout."""
    keys = ["conv1.weight"] + [f"bn1.{s}" for s in BN]
    for layer in range(1, 5):
        for block in range(2):
            p = f"layer{layer}.{block}."
            keys += [p + "conv1.weight"] + [p + f"bn1.{s}" for s in BN]
            keys += [p + "conv2.weight"] + [p + f"bn2.{s}" for s in BN]
            if layer > 1 and block == 0:
                keys += [p + "downsample.0.weight"] + [p + f"downsample.1.{s}" for s in BN]
    return keys + ["fc.weight", "fc.bias"]


def torchvision_vgg16_keys() -> list[str]:
    convs = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
    keys = [f"features.{i}.{s}" for i in convs for s in ("weight", "bias")]
    return keys + [f"classifier.{i}.{s}" for i in (0, 3, 6) for s in ("weight", "bias")]


def fake_torchvision_file(path, model: torch.nn.Module, keys: list[str], extra=None):
    """A file with exactly torchvision's keys, random tensors of the model's shapes, plus ``extra``."""
    own = model.state_dict()
    g = torch.Generator().manual_seed(0)
    state = {}
    for k in keys:
        if k in own:
            v = own[k]
            if k.endswith("num_batches_tracked"):
                state[k] = v.clone()
            elif k.endswith("running_var"):
                state[k] = torch.rand(v.shape, generator=g) + 0.5
            else:
                state[k] = torch.randn(v.shape, generator=g) * 0.1
    state.update(extra or {})
    torch.save(state, path)
    return path, state


@pytest.fixture(scope="module")
def resnet_file(tmp_path_factory):
    """(path, state): a torchvision-layout resnet18 file with a 1000-class fc, written once."""
    fc = {"fc.weight": torch.randn(1000, 512), "fc.bias": torch.randn(1000)}
    path = tmp_path_factory.mktemp("resnet") / "resnet18.pth"
    return fake_torchvision_file(path, ResNet18(), torchvision_resnet18_keys(), fc)


def test_resnet18_names_match_torchvision():
    keys = torchvision_resnet18_keys()
    headed = ResNet18(num_classes=1000)
    assert set(headed.state_dict()) == set(keys)
    assert set(ResNet18().state_dict()) == set(keys) - {"fc.weight", "fc.bias"}
    # torchvision's resnet18 has 11,689,512 parameters
    assert sum(p.numel() for p in headed.parameters()) == 11_689_512
    assert headed(torch.rand(2, 3, 32, 32)).shape == (2, 1000)


def test_resnet18_loads_torchvision_file_strict(tmp_path, resnet_file):
    path, state = resnet_file
    model = ResNet18()
    msg = load_backbone_weights(model, path)
    assert msg.startswith(f"ResNet18: loaded weights from {path}") and "fc.bias" in msg
    for k, v in model.state_dict().items():
        assert torch.equal(v, state[k]), k
    # with a head, the fc entries load too
    headed = ResNet18(num_classes=1000)
    load_backbone_weights(headed, path)
    assert torch.equal(headed.fc.weight, state["fc.weight"])
    # files without num_batches_tracked (older torchvision) load as well
    old = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    torch.save(old, tmp_path / "old.pth")
    load_backbone_weights(model, tmp_path / "old.pth")


def test_resnet18_six_channel_conv1_duplicated_and_halved(resnet_file):
    path, state = resnet_file
    model = ResNet18(in_channels=6)
    msg = load_backbone_weights(model, path, in_channels=6)
    assert "6 input channels" in msg
    w = state["conv1.weight"]
    assert torch.equal(model.conv1.weight[:, :3], w / 2) and torch.equal(model.conv1.weight[:, 3:], w / 2)
    # a stack of the same image twice responds like the 3-channel network to one image
    three = ResNet18().eval()
    load_backbone_weights(three, path)
    model.eval()
    x = torch.rand(1, 3, 32, 32)
    torch.testing.assert_close(model.forward_features(torch.cat([x, x], 1))[0], three.forward_features(x)[0])
    with pytest.raises(ValueError, match="in_channels"):
        load_backbone_weights(three, path, in_channels=6)
    # levels of the pose network's encoder
    feats = model.forward_features(torch.rand(2, 6, 64, 96))
    assert [tuple(f.shape) for f in feats] == [
        (2, 64, 32, 48), (2, 64, 16, 24), (2, 128, 8, 12), (2, 256, 4, 6), (2, 512, 2, 3)]
    with pytest.raises(ValueError, match="x: expected"):
        three.forward_features(torch.rand(1, 6, 32, 32))


def test_load_errors_name_the_file(tmp_path, resnet_file):
    model = ResNet18()
    assert load_backbone_weights(model, None) == "ResNet18: random initialisation (no weights file given)"
    with pytest.raises(ValueError, match="does not exist"):
        load_backbone_weights(model, tmp_path / "nope.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="junk.pth"):
        load_backbone_weights(model, tmp_path / "junk.pth")
    torch.save([torch.zeros(1)], tmp_path / "list.pth")
    with pytest.raises(ValueError, match="not a state dict"):
        load_backbone_weights(model, tmp_path / "list.pth")
    state = {k: v for k, v in resnet_file[1].items() if not k.startswith("fc.")}
    renamed = {("module." + k if k.startswith("layer4") else k): v for k, v in state.items()}
    torch.save(renamed, tmp_path / "renamed.pth")
    with pytest.raises(ValueError, match=r"renamed.pth.*missing keys: layer4.*unexpected keys: module.layer4"):
        load_backbone_weights(model, tmp_path / "renamed.pth")
    state["layer1.0.conv1.weight"] = torch.zeros(64, 64, 5, 5)
    torch.save(state, tmp_path / "shape.pth")
    with pytest.raises(ValueError, match=r"shape.pth.*layer1.0.conv1.weight of shape \[64, 64, 5, 5\]"):
        load_backbone_weights(model, tmp_path / "shape.pth")


def test_vgg16_names_slices_and_load(tmp_path):
    vgg = VGG16()
    keys = torchvision_vgg16_keys()
    assert set(vgg.state_dict()) == {k for k in keys if k.startswith("features.")}
    assert sum(p.numel() for p in vgg.parameters()) == 14_714_688  # torchvision vgg16().features
    head = {k: torch.zeros(1) for k in keys if k.startswith("classifier.")}
    path, state = fake_torchvision_file(tmp_path / "vgg16.pth", vgg, keys, head)
    assert load_backbone_weights(vgg, path).startswith("VGG16: loaded weights")
    assert torch.equal(vgg.features[28].weight, state["features.28.weight"])
    x = torch.rand(1, 3, 32, 48)
    taps = vgg.lpips_features(x)
    assert [tuple(t.shape) for t in taps] == [
        (1, 64, 32, 48), (1, 128, 16, 24), (1, 256, 8, 12), (1, 512, 4, 6), (1, 512, 2, 3)]
    torch.testing.assert_close(taps[1], vgg.features[:9](x))  # relu2_2 = features[0:9]
    assert vgg(x).shape == (1, 512, 1, 1)


@pytest.mark.parametrize("norm", ["group", "batch", "instance", None])
def test_residual_block(norm):
    block = ResidualBlock(16, 24, stride=2, norm=norm)
    assert block(torch.rand(2, 16, 9, 10)).shape == (2, 24, 5, 5)
    assert sum(p.numel() for p in block.parameters()) == ResidualBlock.num_params(16, 24, 2, norm)
    same = ResidualBlock(8, 8, norm=norm)
    assert same.downsample is None
    assert sum(p.numel() for p in same.parameters()) == ResidualBlock.num_params(8, 8, 1, norm)
    with pytest.raises(ValueError, match="norm"):
        ResidualBlock(8, 8, norm="layer")


def test_residual_unet_encoder_shapes_and_params():
    enc = ResidualUNetEncoder(1)
    feats = enc(torch.rand(2, 1, 40, 64))
    assert [tuple(f.shape) for f in feats] == [(2, 32, 20, 32), (2, 48, 10, 16), (2, 96, 5, 8)]
    n = sum(p.numel() for p in enc.parameters())
    assert n == ResidualUNetEncoder.num_params(1) == 412_784
    # the formula, written out for the default shape: stem, then 6 blocks (two with a shortcut)
    def block(i, o):
        return 9 * i * o + o + 9 * o * o + o + 4 * o + ((i * o + o + 2 * o) if i != o else 0)
    assert n == 25 * 32 + 32 + 64 + 2 * block(32, 32) + block(32, 48) + block(48, 48) + block(48, 96) + block(96, 96)
    assert enc.stem[1].num_groups == 8 and enc.stage3[0].norm1.num_groups == 12  # GPS-Gaussian's groups
    small = ResidualUNetEncoder(3, (8, 12, 20), norm="batch")
    assert sum(p.numel() for p in small.parameters()) == ResidualUNetEncoder.num_params(3, (8, 12, 20), "batch")
    with pytest.raises(ValueError, match="x: expected"):
        enc(torch.rand(1, 3, 16, 16))
    with pytest.raises(ValueError, match="channels"):
        ResidualUNetEncoder(1, (32, 48))
