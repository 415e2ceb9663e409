"""Network shapes and starting points (torch)."""

import pytest
import torch

from egoposevr.model.hmd import FEATURE_DIM
from egoposevr.model.inputs import VISUAL_TOKEN_DIM
from egoposevr.model.training.nets.fusion import FusionConfig, FusionNet
from egoposevr.model.training.nets.visual import KeypointNet, VisualConfig


@pytest.mark.parametrize(
    ("channels", "width", "height", "stem"), [(3, 80, 64, 0), (4, 80, 64, 0), (4, 160, 128, 16)]
)
def test_keypoint_net_shapes_and_ranges(channels, width, height, stem):
    cfg = VisualConfig(channels=channels, width=width, height=height, stem_channels=stem)
    uv, depth_m, zeta, logits = KeypointNet(cfg).eval()(torch.randn(2, channels, height, width))
    assert uv.shape == (2, 22, 2) and depth_m.shape == (2, 22) and zeta.shape == (2, 22)
    assert logits.shape == (2, 22, 32, 40) and cfg.heatmap_wh == (40, 32)
    assert ((uv >= 0) & (uv <= 1)).all() and ((zeta >= 0) & (zeta <= 1)).all()


@pytest.mark.parametrize(
    ("fusion", "visual_window"), [("none", 8), ("cross", 8), ("cross", 1), ("concat", 8)]
)
def test_fusion_net_shapes_and_identity_start(fusion, visual_window):
    cfg = FusionConfig(window=12, visual_window=visual_window, fusion=fusion, d_model=32, joint_dim=16)
    net = FusionNet(cfg).eval()
    visual = torch.randn(3, visual_window, VISUAL_TOKEN_DIM) if cfg.uses_camera else None
    out = net(torch.randn(3, 12, FEATURE_DIM), visual)
    assert out.shape == (3, 22, 6)
    # A fresh net predicts the rest pose (identity rotations), a sane start for training.
    assert torch.allclose(out, torch.tensor([1.0, 0, 0, 0, 1, 0]).expand(3, 22, 6))


def test_unknown_fusion_is_refused():
    with pytest.raises(ValueError, match="fusion"):
        FusionConfig(fusion="sum")


def test_a_fusion_net_with_tracking_state_reads_78_numbers_per_sample():
    from egoposevr.model.hmd import VALIDITY_DIM

    cfg = FusionConfig(window=10, visual_window=4, d_model=16, joint_dim=8, device_validity=True)
    net = FusionNet(cfg).eval()
    out = net(torch.randn(2, 10, FEATURE_DIM + VALIDITY_DIM), torch.randn(2, 4, VISUAL_TOKEN_DIM))
    assert out.shape == (2, 22, 6)
    with pytest.raises(RuntimeError):
        net(torch.randn(2, 10, FEATURE_DIM), torch.randn(2, 4, VISUAL_TOKEN_DIM))


@pytest.mark.parametrize("cross", [False, True])
def test_a_block_asked_for_its_newest_token_alone_gives_that_token_of_the_full_block(cross):
    """The last frame block computes only the token that goes on (fusion.py); with keys and values from the
    whole window it must be the full block's last row, for self- and cross-attention, forward and backward."""
    from egoposevr.model.training.nets.fusion import Block

    torch.manual_seed(0)
    block = Block(dim=16, heads=4, dropout=0.0)
    x = torch.randn(3, 9, 16, requires_grad=True)
    context = torch.randn(3, 5, 16) if cross else None
    full = block(x, context)[:, -1:]
    newest = block(x, context, newest_only=True)
    assert newest.shape == (3, 1, 16)
    torch.testing.assert_close(newest, full, atol=1e-6, rtol=1e-5)
    (grad_full,) = torch.autograd.grad(full.square().sum(), x)
    (grad_newest,) = torch.autograd.grad(newest.square().sum(), x)
    torch.testing.assert_close(grad_newest, grad_full, atol=1e-6, rtol=1e-5)  # earlier tokens still learn


def test_a_mirror_averaged_net_gives_the_mirrored_person_the_mirrored_answer():
    """MirrorAveraged's answer is symmetric whatever the weights: the mirrored person's inputs get this
    person's answer reflected (rotations) and swapped (feet), which a net alone does not give."""
    from egoposevr.model.inputs import (
        HMD_MIRROR_ORDER,
        HMD_MIRROR_SIGNS,
        SIXD_MIRROR_SIGNS,
        VISUAL_MIRROR_ORDER,
        VISUAL_MIRROR_SIGNS,
    )
    from egoposevr.model.skeleton import MIRROR_JOINTS
    from egoposevr.model.training.nets.fusion import ContactOutputs, MirrorAveraged, orthonormal_sixd

    cfg = FusionConfig(
        window=12, visual_window=4, d_model=32, joint_dim=16, contact_head=True, device_validity=True
    )
    torch.manual_seed(0)
    net = FusionNet(cfg).eval()
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.2)  # away from the identity start, whose answers are symmetric already
    single, served = ContactOutputs(net), MirrorAveraged(ContactOutputs(net), cfg).eval()
    hmd, visual = torch.randn(3, 12, 78), torch.randn(3, 4, VISUAL_TOKEN_DIM)
    hmd_m = hmd[..., HMD_MIRROR_ORDER] * torch.as_tensor(HMD_MIRROR_SIGNS, dtype=torch.float32)
    visual_m = visual[..., VISUAL_MIRROR_ORDER] * torch.as_tensor(VISUAL_MIRROR_SIGNS, dtype=torch.float32)
    signs = torch.as_tensor(SIXD_MIRROR_SIGNS, dtype=torch.float32)
    with torch.no_grad():
        (sixd, contact), (sixd_m, contact_m) = served(hmd, visual), served(hmd_m, visual_m)
        alone_sixd, _ = single(hmd, visual)
        alone_m, _ = single(hmd_m, visual_m)
        first, _ = served(hmd[:1], visual[:1])
    torch.testing.assert_close(sixd_m, sixd[:, MIRROR_JOINTS] * signs, atol=1e-5, rtol=0)
    torch.testing.assert_close(contact_m, contact.flip(-1), atol=1e-6, rtol=0)
    torch.testing.assert_close(first, sixd[:1], atol=1e-5, rtol=0)  # each person answered on their own
    reflected = orthonormal_sixd(alone_sixd)[:, MIRROR_JOINTS] * signs
    assert (orthonormal_sixd(alone_m) - reflected).abs().max() > 1e-2  # a net alone is not symmetric
