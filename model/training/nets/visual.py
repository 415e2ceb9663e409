"""The RGB-D visual encoder (paper §3.3): ResNet-style backbone + FPN -> per-joint heatmaps and depth maps
-> 2D keypoints (soft-argmax) with a depth each, plus the visibility head ζ.

It runs once per new camera frame, so it is the one convolutional cost per request: the config's default is
small (80×64 input, ~40 M multiply-adds), and the bundled encoders read 160×128 through a strided stem at
about that cost. Outputs stay camera-agnostic — normalised image coordinates and metres — and the
runtime lifts them to 3D with each frame's own intrinsics, so any client resolution works.

Shape legend: ``B`` batch, ``C`` 3 (RGB) or 4 (RGB-D) channels, ``h``×``w`` input, ``J`` joints.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ...config import VisualConfig


class BasicBlock(nn.Module):
    """ResNet basic block: two 3×3 convs with a (strided) shortcut."""

    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = (
            nn.Identity()
            if stride == 1 and c_in == c_out
            else nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.shortcut(x))


class KeypointNet(nn.Module):
    """image (B, C, h, w) -> uv (B, J, 2) in [0, 1], depth_m (B, J), zeta (B, J) in [0, 1], logits (B, J, hh, hw).

    Heatmaps live at stride 2 of the backbone's input (stride 4 of the image with a stem); uv is their
    soft-argmax and depth the heatmap-weighted mean of a per-joint depth map (integral regression:
    differentiable, sub-cell precise).
    """

    def __init__(self, cfg: VisualConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c_in = cfg.channels
        self.stem: nn.Module = nn.Identity()
        if cfg.stem_channels:
            self.stem = nn.Sequential(
                nn.Conv2d(c_in, cfg.stem_channels, 3, 2, 1, bias=False),
                nn.BatchNorm2d(cfg.stem_channels),
                nn.ReLU(),
            )
            c_in = cfg.stem_channels
        stages = []
        for c_out in cfg.widths:
            stages.append(nn.Sequential(BasicBlock(c_in, c_out, 2), BasicBlock(c_out, c_out, 1)))
            c_in = c_out
        self.stages = nn.ModuleList(stages)
        self.lateral = nn.ModuleList(nn.Conv2d(c, cfg.fpn_channels, 1) for c in cfg.widths)
        self.smooth = nn.Sequential(
            nn.Conv2d(cfg.fpn_channels, cfg.fpn_channels, 3, 1, 1, bias=False),
            nn.BatchNorm2d(cfg.fpn_channels),
            nn.ReLU(),
        )
        self.heatmap_head = nn.Conv2d(cfg.fpn_channels, cfg.joints, 1)
        self.depth_head = nn.Conv2d(cfg.fpn_channels, cfg.joints, 1)
        self.visibility_head = nn.Sequential(
            nn.Linear(cfg.widths[-1] + cfg.widths[-2], 128), nn.ReLU(), nn.Linear(128, cfg.joints)
        )
        hw, hh = cfg.heatmap_wh
        # Cell centres in normalised image coordinates, for the soft-argmax.
        self.register_buffer("grid_u", (torch.arange(hw, dtype=torch.float32) + 0.5) / hw, persistent=False)
        self.register_buffer("grid_v", (torch.arange(hh, dtype=torch.float32) + 0.5) / hh, persistent=False)

    frozen_statistics = False  # freeze_statistics(): batch norm keeps its running statistics in training

    def freeze_statistics(self) -> None:
        """Batch norm normalises by its stored statistics in training too (its scale and shift still learn):
        a net fine-tuned from an exported file, whose statistics are folded into the convolutions, keeps
        the function it starts from instead of renormalising every batch."""
        self.frozen_statistics = True
        self.train(self.training)

    def train(self, mode: bool = True) -> KeypointNet:
        super().train(mode)
        if self.frozen_statistics:
            for module in self.modules():
                if isinstance(module, nn.BatchNorm2d):
                    module.eval()
        return self

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        feats, x = [], self.stem(image)
        for stage in self.stages:
            x = stage(x)
            feats.append(x)  # strides 2, 4, 8, 16 of the stem's output
        top = self.lateral[-1](feats[-1])
        for level in range(len(feats) - 2, -1, -1):  # top-down pathway to stride 2
            top = F.interpolate(top, size=feats[level].shape[-2:], mode="nearest") + self.lateral[level](
                feats[level]
            )
        fused = self.smooth(top)  # (B, fpn, hh, hw)
        logits = self.heatmap_head(fused)  # (B, J, hh, hw)
        B, J, hh, hw = logits.shape
        prob = torch.softmax(logits.flatten(2), dim=-1).view(B, J, hh, hw)
        u = (prob.sum(2) * self.grid_u).sum(-1)  # (B, J)
        v = (prob.sum(3) * self.grid_v).sum(-1)
        depth_m = (prob * self.depth_head(fused)).flatten(2).sum(-1) + 1.0  # maps predict depth - 1 m
        pooled = torch.cat([feats[-1].mean((2, 3)), feats[-2].mean((2, 3))], dim=1)
        zeta = torch.sigmoid(self.visibility_head(pooled))
        return torch.stack([u, v], dim=-1), depth_m, zeta, logits
