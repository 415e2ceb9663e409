"""Torch twin of :mod:`egoposevr.model.skeleton` FK and the 6D conversion, for training losses.

Same conventions as the numpy side (a parity test holds them together); 6D = first two matrix columns,
Gram-Schmidt through ``roma.special_gramschmidt``. Shape legend: ``J`` = 22, ``...`` = any batch shape.
"""

from __future__ import annotations

import roma
import torch

from ...skeleton import NUM_JOINTS, PARENTS, rest_offsets


def sixd_to_matrix(sixd: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> (..., 3, 3); columns [b1, b2, b1 x b2] as in the numpy version."""
    if sixd.shape[-1] != 6:
        raise ValueError(f"sixd must be (..., 6), got {tuple(sixd.shape)}")
    two_columns = sixd.unflatten(-1, (2, 3)).transpose(-1, -2)  # (..., 3, 2)
    return roma.special_gramschmidt(two_columns)


def matrix_to_sixd(matrix: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6)."""
    return torch.cat([matrix[..., :, 0], matrix[..., :, 1]], dim=-1)


def default_offsets(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(J, 3) rest offsets as a tensor."""
    return torch.as_tensor(rest_offsets(), dtype=dtype)


def forward_kinematics(
    local_rot: torch.Tensor, root_pos_m: torch.Tensor, offsets_m: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """local_rot (..., J, 3, 3), root_pos_m (..., 3), offsets_m (J, 3) or (..., J, 3)
    -> (pos_m (..., J, 3), global_rot (..., J, 3, 3)). Differentiable; no in-place writes."""
    if local_rot.shape[-3:] != (NUM_JOINTS, 3, 3):
        raise ValueError(f"local_rot must be (..., {NUM_JOINTS}, 3, 3), got {tuple(local_rot.shape)}")
    if offsets_m is None:
        offsets_m = default_offsets(local_rot.dtype).to(local_rot.device)
    offsets_m = offsets_m.expand(*local_rot.shape[:-3], NUM_JOINTS, 3)
    global_rots = [local_rot[..., 0, :, :]]
    positions = [root_pos_m.expand(*local_rot.shape[:-3], 3)]
    for j in range(1, NUM_JOINTS):
        p = int(PARENTS[j])
        positions.append(positions[p] + (global_rots[p] @ offsets_m[..., j, :, None]).squeeze(-1))
        global_rots.append(global_rots[p] @ local_rot[..., j, :, :])
    return torch.stack(positions, dim=-2), torch.stack(global_rots, dim=-3)
