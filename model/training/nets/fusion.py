"""The fusion net (paper §3.3, Eqs. 3-6): one spatiotemporal encoder per stream, cross-attention, two heads.

    M_t = T_j(F([T_f(E_l(X))]_t) + e_j)          HMD stream, X (T, 72)
    N_t = T_j'(F'([T_f'(E_l'(Z~))]_t) + e_j')     visual stream, Z~ (Tv, 90): keypoints + confidence per frame
    M~_t = CrossAttn(M_t, N_t)                   HMD queries, visual keys and values
    pelvis 6D = T_g(M~_t[pelvis]),  local 6D = T_l(M~_t[1:])
    contact = σ(T_c(M~_t[feet]))                 with ``contact_head`` (not in the paper): each foot on the floor

``fusion = "none"`` is the HMD-only model, ``"concat"`` the ablation that concatenates per-joint features
instead of attending. Inputs are normalised by statistics stored in the net (buffers set from the training
data), so the exported graph takes raw features. Attention is torch's scaled dot-product attention, which
exports to one ONNX ``Attention`` operator (opset 23). Only the newest frame's token leaves T_f, so its last
block computes that token alone (its keys and values still see the whole window): the same numbers as the
full block, a quarter fewer operations in the stream.

Shape legend: ``B`` batch, ``T`` HMD window, ``Tv`` visual window, ``J`` = 22 joints, ``S`` per-joint width.
"""

from __future__ import annotations

import torch
from torch import nn

from ...config import FusionConfig
from ...hmd import hmd_input_dim
from ...inputs import (
    HMD_MIRROR_ORDER,
    HMD_MIRROR_SIGNS,
    SIXD_MIRROR_SIGNS,
    VISUAL_MIRROR_ORDER,
    VISUAL_MIRROR_SIGNS,
    VISUAL_TOKEN_DIM,
)
from ...skeleton import MIRROR_JOINTS
from ..plausibility import FEET  # left, right foot joints: the contact head reads their tokens


class Attention(nn.Module):
    """Multi-head attention: queries (B, Lq, D), keys/values (B, Lk, D) -> (B, Lq, D)."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.q, self.k, self.v, self.out = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        B, Lq, D = x.shape
        Lk, hs = context.shape[1], D // self.heads
        q = self.q(x).view(B, Lq, self.heads, hs).transpose(1, 2)  # (B, nh, Lq, hs)
        k = self.k(context).view(B, Lk, self.heads, hs).transpose(1, 2)
        v = self.v(context).view(B, Lk, self.heads, hs).transpose(1, 2)
        # softmax(q kᵀ / √hs) v, (B, nh, Lq, hs)
        att = nn.functional.scaled_dot_product_attention(q, k, v)
        return self.out(att.transpose(1, 2).reshape(B, Lq, D))


class Block(nn.Module):
    """Pre-norm transformer block; with ``context`` its attention is cross-attention. x (B, L, D) -> (B, L, D),
    or with ``newest_only`` (B, 1, D): the last token's output alone, which attends to all of x as the full
    block's does."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.mlp = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))
        self.drop = nn.Dropout(dropout)

    def forward(
        self, x: torch.Tensor, context: torch.Tensor | None = None, newest_only: bool = False
    ) -> torch.Tensor:
        h = self.norm1(x)
        keys = h if context is None else context
        if newest_only:
            x, h = x[:, -1:], h[:, -1:]
        x = x + self.drop(self.attn(h, keys))
        return x + self.drop(self.mlp(self.norm2(x)))


class StreamEncoder(nn.Module):
    """Eq. 3: E_l -> T_f over frames -> last token -> F (MLP to J×S) -> + e_j -> T_j over joints.

    x (B, L, in_dim) -> (B, J, S).
    """

    def __init__(self, in_dim: int, length: int, cfg: FusionConfig) -> None:
        super().__init__()
        self.register_buffer("input_mean", torch.zeros(in_dim))
        self.register_buffer("input_std", torch.ones(in_dim))
        self.embed = nn.Linear(in_dim, cfg.d_model)  # E_l
        self.frame_position = nn.Parameter(torch.zeros(length, cfg.d_model))
        self.frame_encoder = nn.ModuleList(
            Block(cfg.d_model, cfg.heads, cfg.dropout) for _ in range(cfg.frame_layers)
        )  # T_f
        self.frame_norm = nn.LayerNorm(cfg.d_model)
        self.to_joints = nn.Sequential(
            nn.Linear(cfg.d_model, cfg.d_model * 2),
            nn.GELU(),
            nn.Linear(cfg.d_model * 2, cfg.joints * cfg.joint_dim),
        )  # F
        self.joint_embedding = nn.Parameter(torch.randn(cfg.joints, cfg.joint_dim) * 0.02)  # e_j
        self.joint_encoder = nn.ModuleList(
            Block(cfg.joint_dim, cfg.heads, cfg.dropout) for _ in range(cfg.joint_layers)
        )  # T_j
        self.joints, self.joint_dim = cfg.joints, cfg.joint_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.embed((x - self.input_mean) / self.input_std) + self.frame_position  # (B, L, d)
        for i, block in enumerate(self.frame_encoder):
            # Only the current frame's token goes on: the last block computes it alone, (B, 1, d).
            x = block(x, newest_only=i == len(self.frame_encoder) - 1)
        last = self.frame_norm(x[:, -1])  # (B, d): the current frame's token
        j = self.to_joints(last).view(-1, self.joints, self.joint_dim) + self.joint_embedding  # (B, J, S)
        for block in self.joint_encoder:
            j = block(j)
        return j


class FusionNet(nn.Module):
    """hmd (B, T, 72 or 78 with device_validity) [, visual (B, Tv, 90)] -> 6D rotations (B, J, 6): row 0 the pelvis in the heading
    frame, rows 1.. local rotations."""

    def __init__(self, cfg: FusionConfig) -> None:
        super().__init__()
        self.cfg = cfg
        S = cfg.joint_dim
        self.hmd_stream = StreamEncoder(hmd_input_dim(cfg.device_validity), cfg.window, cfg)
        if cfg.uses_camera:
            self.visual_stream = StreamEncoder(VISUAL_TOKEN_DIM, cfg.visual_window, cfg)
        if cfg.fusion == "cross":
            self.cross = Block(S, cfg.heads, cfg.dropout)
        elif cfg.fusion == "concat":
            self.concat = nn.Sequential(nn.Linear(2 * S, 2 * S), nn.GELU(), nn.Linear(2 * S, S))
        self.pelvis_head = nn.Sequential(
            nn.LayerNorm(S), nn.Linear(S, 64), nn.GELU(), nn.Linear(64, 6)
        )  # T_g
        self.local_head = nn.Sequential(nn.LayerNorm(S), nn.Linear(S, 64), nn.GELU(), nn.Linear(64, 6))  # T_l
        if cfg.contact_head:  # each foot joint's token -> its contact logit
            self.contact_head = nn.Sequential(nn.LayerNorm(S), nn.Linear(S, 32), nn.GELU(), nn.Linear(32, 1))
        if cfg.timing_head:  # each foot joint's token -> its step timing (training only)
            self.timing_head = nn.Sequential(nn.LayerNorm(S), nn.Linear(S, 32), nn.GELU(), nn.Linear(32, 2))
        # Start at the identity rotation: 6D (1, 0, 0, 0, 1, 0).
        for head in (self.pelvis_head, self.local_head):
            nn.init.zeros_(head[-1].weight)
            with torch.no_grad():
                head[-1].bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))

    def forward(self, hmd: torch.Tensor, visual: torch.Tensor | None = None) -> torch.Tensor:
        return self._rotations(self._fused(hmd, visual))

    def forward_with_contact(
        self, hmd: torch.Tensor, visual: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """-> 6D rotations (B, J, 6) and each foot's contact logit (B, 2), left then right (needs
        ``cfg.contact_head``)."""
        m = self._fused(hmd, visual)
        return self._rotations(m), self.contact_head(m[:, list(FEET)])[..., 0]

    def forward_with_timing(
        self, hmd: torch.Tensor, visual: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """-> 6D rotations (B, J, 6), each foot's contact logit (B, 2) (None without ``cfg.contact_head``) and
        its step timing (B, 2, 2) in [0, 1]: time to the next contact change, then since the last, as
        plausibility.contact_timing (needs ``cfg.timing_head``; training only, never exported)."""
        m = self._fused(hmd, visual)
        feet = m[:, list(FEET)]
        logits = self.contact_head(feet)[..., 0] if self.cfg.contact_head else None
        return self._rotations(m), logits, torch.sigmoid(self.timing_head(feet))

    def _fused(self, hmd: torch.Tensor, visual: torch.Tensor | None) -> torch.Tensor:
        m = self.hmd_stream(hmd)  # (B, J, S)
        if self.cfg.fusion == "cross":
            m = self.cross(m, self.visual_stream(visual))
        elif self.cfg.fusion == "concat":
            m = m + self.concat(torch.cat([m, self.visual_stream(visual)], dim=-1))
        return m

    def _rotations(self, m: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.pelvis_head(m[:, :1]), self.local_head(m[:, 1:])], dim=1)


class ContactOutputs(nn.Module):
    """The served outputs of a fusion net with a contact head: rot6d (B, J, 6) and each foot's contact
    probability (B, 2)."""

    def __init__(self, net: FusionNet) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, hmd: torch.Tensor, visual: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        sixd, logits = self.net.forward_with_contact(hmd, visual)
        return sixd, torch.sigmoid(logits)


class SeedEnsemble(nn.Module):
    """Several trainings of one fusion net (same config, other seeds) served as one graph: the mean of
    their rotations, each member's rot6d (B, J, 6) first made orthonormal (Gram-Schmidt, as the runtime
    reads it) so that no member weighs more for a longer raw vector, and the mean of their contact
    probabilities (B, 2) where they have a contact head. The runtime reads the mean like any rot6d."""

    def __init__(self, nets: list[nn.Module]) -> None:
        super().__init__()
        configs = {repr(net.cfg) for net in nets}
        if len(configs) != 1:
            raise ValueError(f"an ensemble's nets must share one config, got {len(configs)}")
        self.cfg = nets[0].cfg
        self.members = nn.ModuleList([ContactOutputs(net) if self.cfg.contact_head else net for net in nets])

    def forward(
        self, hmd: torch.Tensor, visual: torch.Tensor | None = None
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        outputs = [member(hmd) if visual is None else member(hmd, visual) for member in self.members]
        if not self.cfg.contact_head:
            return torch.stack([orthonormal_sixd(o) for o in outputs]).mean(0)
        sixd = torch.stack([orthonormal_sixd(o[0]) for o in outputs]).mean(0)
        return sixd, torch.stack([o[1] for o in outputs]).mean(0)


class MirrorAveraged(nn.Module):
    """A served fusion module (one net or a :class:`SeedEnsemble`) that also reads the mirrored person's
    inputs (inputs.py: the world reflected through the heading frame's x = 0, left and right swapped) and
    serves the mean of its two answers: its own, and the mirrored person's reflected back. Training mirrors
    every sequence, so both are answers the net learnt to give; averaging them cancels the part of each
    guess that is not the person's (as two seeds do). One batch of 2B through the nets; rotations each made
    orthonormal first, as :class:`SeedEnsemble` does, contact probabilities with the feet swapped back."""

    def __init__(self, served: nn.Module, cfg: FusionConfig) -> None:
        super().__init__()
        self.served, self.cfg = served, cfg
        width = hmd_input_dim(cfg.device_validity)
        layouts = {
            "hmd_order": HMD_MIRROR_ORDER[:width], "hmd_signs": HMD_MIRROR_SIGNS[:width],
            "visual_order": VISUAL_MIRROR_ORDER, "visual_signs": VISUAL_MIRROR_SIGNS,
            "joints": MIRROR_JOINTS, "sixd_signs": SIXD_MIRROR_SIGNS,
        }  # fmt: skip
        for name, layout in layouts.items():  # signs in the inputs' float32, orders as indices
            value = torch.as_tensor(layout, dtype=torch.float32 if name.endswith("signs") else torch.long)
            self.register_buffer(name, value, persistent=False)

    def forward(
        self, hmd: torch.Tensor, visual: torch.Tensor | None = None
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        batch = hmd.shape[0]
        hmd = torch.cat([hmd, hmd[..., self.hmd_order] * self.hmd_signs])
        if visual is None:
            out = self.served(hmd)
        else:
            out = self.served(hmd, torch.cat([visual, visual[..., self.visual_order] * self.visual_signs]))
        sixd = out[0] if self.cfg.contact_head else out
        back = sixd[batch:][:, self.joints] * self.sixd_signs
        mean = (orthonormal_sixd(sixd[:batch]) + orthonormal_sixd(back)) / 2
        if not self.cfg.contact_head:
            return mean
        contact = out[1]
        return mean, (contact[:batch] + contact[batch:].flip(-1)) / 2


def orthonormal_sixd(sixd: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> the same two columns after Gram-Schmidt (kernels.sixd_to_matrices), (..., 6)."""
    b1 = nn.functional.normalize(sixd[..., :3], dim=-1, eps=1e-8)
    a2 = sixd[..., 3:]
    b2 = nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1, eps=1e-8)
    return torch.cat([b1, b2], dim=-1)


def set_input_statistics(encoder: StreamEncoder, samples: torch.Tensor) -> None:
    """Normalisation from training samples (N, in_dim): mean and std per feature (std floored)."""
    with torch.no_grad():
        encoder.input_mean.copy_(samples.mean(0))
        encoder.input_std.copy_(samples.std(0).clamp_min(1e-2))
