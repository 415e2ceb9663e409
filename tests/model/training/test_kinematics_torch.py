"""The torch FK and 6D twins used in training match the numpy versions used in serving."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from egoposevr.model import rotations as r  # noqa: E402
from egoposevr.model import skeleton as sk  # noqa: E402
from egoposevr.model.training.nets import kinematics as tk  # noqa: E402

RNG = np.random.default_rng(11)


def test_fk_parity_float64_and_float32():
    local = r.axis_angle_to_matrix(RNG.normal(size=(8, 22, 3)))
    root = RNG.normal(size=(8, 3))
    offsets = sk.rest_offsets(RNG.uniform(0.9, 1.1, size=(8, 22)))
    pos, rot = sk.forward_kinematics(local, root, offsets)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        t_pos, t_rot = tk.forward_kinematics(
            torch.tensor(local, dtype=dtype),
            torch.tensor(root, dtype=dtype),
            torch.tensor(offsets, dtype=dtype),
        )
        np.testing.assert_allclose(t_pos.numpy(), pos, atol=tol)
        np.testing.assert_allclose(t_rot.numpy(), rot, atol=tol)


def test_fk_default_offsets_reproduce_rest_joints():
    pos, _ = tk.forward_kinematics(torch.eye(3).expand(22, 3, 3), torch.zeros(3))
    np.testing.assert_allclose(pos.numpy(), sk.REST_JOINTS_M, atol=1e-6)


def test_sixd_parity_including_unnormalised_input():
    sixd = RNG.normal(size=(50, 6)) * 3
    np.testing.assert_allclose(
        tk.sixd_to_matrix(torch.tensor(sixd)).numpy(), r.sixd_to_matrix(sixd), atol=1e-12
    )
    m = r.sixd_to_matrix(sixd)
    np.testing.assert_allclose(tk.matrix_to_sixd(torch.tensor(m)).numpy(), r.matrix_to_sixd(m), atol=1e-15)


def test_fk_is_differentiable():
    sixd = torch.tensor(RNG.normal(size=(22, 6)), requires_grad=True)
    pos, _ = tk.forward_kinematics(tk.sixd_to_matrix(sixd), torch.zeros(3, dtype=torch.float64),
                                   tk.default_offsets(torch.float64))  # fmt: skip
    pos[sk.LEFT_WRIST].sum().backward()
    assert torch.isfinite(sixd.grad).all() and sixd.grad.abs().sum() > 0
