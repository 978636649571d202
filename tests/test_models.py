"""Building blocks: the hand-written ResNet18 is a ResNet18, encoders handle each kind, the GMM
head's action is its dominant mode, unknown names give clear errors."""

import pytest
import torch

from nostra.modality import Modality, paper_modalities
from nostra.models.encoders import LightConv, ModalityEncoder, ResNet18
from nostra.models.heads import GMMHead, make_head


def test_resnet18_has_resnet18_parameters():
    # torchvision's resnet18 without its fc layer has 11,176,512 parameters (BatchNorm)
    net = ResNet18(3, norm="batch")
    assert sum(p.numel() for p in net.parameters()) == 11_176_512
    assert net(torch.zeros(2, 3, 84, 84)).shape == (2, 512)
    assert ResNet18(1)(torch.zeros(1, 1, 84, 84)).shape == (1, 512)


def test_encoders_per_kind():
    for m in paper_modalities(84):
        enc = ModalityEncoder(m, "light", 32, [64])
        x = torch.zeros(2, 3, *m.shape, dtype=torch.uint8 if m.kind == "rgb" else torch.float32)
        assert enc(x).shape == (2, 3, 32)
    assert LightConv(3, (84, 84)).out_dim == 64 * 7 * 7


def test_rgb_is_scaled_to_unit_range():
    m = Modality("cam_image", "rgb", (40, 40, 3))
    enc = ModalityEncoder(m, "light", 8, [])
    seen = {}
    enc.trunk.register_forward_hook(lambda mod, inp, out: seen.update(x=inp[0]))
    enc(torch.full((1, 40, 40, 3), 255, dtype=torch.uint8))
    assert seen["x"].shape == (1, 3, 40, 40) and float(seen["x"].max()) == 1.0


def test_gmm_act_is_the_dominant_mode():
    head = GMMHead(4, [], 2, modes=3)
    with torch.no_grad():
        for p in head.net.parameters():
            p.zero_()
        bias = head.net[-1].bias
        bias[:6] = torch.tensor([1.0, 1.0, 5.0, -5.0, -2.0, 3.0])  # three 2-d means
        bias[12:] = torch.tensor([0.0, 4.0, 0.0])  # mode 1 dominates
    torch.testing.assert_close(head.act(torch.zeros(1, 4)), torch.tensor([[5.0, -5.0]]))
    assert torch.isfinite(head.nll(torch.zeros(1, 4), torch.zeros(1, 2))).all()


def test_unknown_names_are_refused():
    with pytest.raises(ValueError, match="unknown action head 'mdn'; valid: gaussian, gmm"):
        make_head("mdn", 4, [], 2)
    with pytest.raises(ValueError, match="unknown image encoder 'vit'; valid: light, spatial, resnet18"):
        ModalityEncoder(Modality("a_image", "rgb", (84, 84, 3)), "vit", 8, [])
    with pytest.raises(ValueError, match="unknown kind 'audio'"):
        Modality("mic", "audio", (3,))
