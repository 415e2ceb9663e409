"""The fusion nets' training terms, on tensors with known answers."""

import math

import pytest

torch = pytest.importorskip("torch")
from egoposevr.model.training.plausibility import FEET  # noqa: E402
from egoposevr.model.training.train import skate_term  # noqa: E402


def _yaw(deg: float) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_the_skate_term_counts_only_feet_down_at_both_samples_and_only_their_slide_in_the_world():
    error = torch.zeros(4, 22, 3)  # two pairs: windows 0, 1, then the samples before them (2, 3)
    error[0, FEET[0]] = torch.tensor([0.03, 0.0, 0.0])  # pair 0: the left foot slid 3 cm, the right stayed
    error[1, FEET[1]] = torch.tensor([0.0, 0.0, 0.05])  # pair 1: the right foot slid 5 cm, but lifted
    frames = torch.eye(3).expand(4, 3, 3)
    down = torch.tensor([[1.0, 1.0], [1.0, 0.0], [1.0, 1.0], [1.0, 1.0]])  # pair 1's right foot is up now
    assert skate_term(error, frames, down).item() == pytest.approx(0.03 / 2)

    error[1, FEET[1]] = 0.0  # the same 3 cm error, seen from frames turned 90 degrees apart:
    error[2, FEET[0]] = torch.tensor([0.0, 0.0, 0.03])  # the same place in the world, so no slide
    frames = torch.stack([torch.eye(3), torch.eye(3), _yaw(90.0), torch.eye(3)])
    assert skate_term(error, frames, down).item() == pytest.approx(0.0, abs=1e-7)
    assert skate_term(error, torch.eye(3).expand(4, 3, 3), down).item() == pytest.approx(0.06 / 2)
