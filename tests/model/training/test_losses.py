"""The fusion nets' training terms, on tensors with known answers."""

import dataclasses
import math

import pytest

from egoposevr.model.config import KEEP_JOINTS_CHOICES, TRUNK_FREE_KEEPS

torch = pytest.importorskip("torch")
from egoposevr.model.training.nets.kinematics import default_offsets, matrix_to_sixd  # noqa: E402
from egoposevr.model.training.plausibility import FEET  # noqa: E402
from egoposevr.model.training.train import (  # noqa: E402
    KEPT_JOINTS,
    PRESETS,
    _anchored_joints,
    _check_keeps_a_start,
    _fit_terms,
    kept_contact_term,
    skate_term,
    upper_body_term,
)


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


def _rotation_terms(sixd: torch.Tensor, targets: torch.Tensor, served_weight: float) -> dict[str, float]:
    """The rotation terms of one output sixd (6,) against every target (B, 6), as one joint of B windows."""
    tc = dataclasses.replace(PRESETS["tiny"], served_rotation_weight=served_weight)
    sixd_b = sixd.expand(len(targets), 1, 6)
    zeros = torch.zeros(len(targets), 1, 3)
    terms = _fit_terms(sixd_b, zeros, None, (targets[:, None], zeros, None), torch.ones(len(targets), 1), tc)
    return {k: v.item() / (tc.rotation_weight if k == "rot" else served_weight) for k, v in terms.items()}


def test_the_served_rotation_term_makes_a_column_that_collapsed_between_two_truths_cost_more_than_either():
    # Half the windows' truth is the identity, half a half turn about z: the raw L1 is flat between them,
    # so a first column near zero costs it no more than picking one truth, but Gram-Schmidt serves that
    # column's direction, a rotation far from both.
    targets = torch.tensor([[1.0, 0, 0, 0, 1, 0]] * 4 + [[-1.0, 0, 0, 0, -1, 0]] * 4)
    one_truth = torch.tensor([1.0, 0, 0, 0, 1, 0])
    collapsed = torch.tensor([0.02, 0.04, 0.0, 0.0, 0.0, 0.0])  # a1 near zero, a2 = 0 (the median of both)
    picked, degenerate = _rotation_terms(one_truth, targets, 1.0), _rotation_terms(collapsed, targets, 1.0)
    assert degenerate["rot"] <= picked["rot"] + 0.01  # the raw term cannot tell them apart
    assert degenerate["rot_served"] > picked["rot_served"] + 0.1  # the served one can
    assert picked["rot_served"] == pytest.approx(picked["rot"])  # a served-as-is output costs the same
    assert "rot_served" not in _fit_terms(  # off by default: the bundled recipe
        one_truth.expand(1, 1, 6), torch.zeros(1, 1, 3), None,
        (targets[:1, None], torch.zeros(1, 1, 3), None), torch.ones(1, 1), PRESETS["tiny"],
    )  # fmt: skip


def _pose(turns: dict[int, float]) -> torch.Tensor:
    """One window's 6D (1, 22, 6): every joint unrotated but each joint j of turns turned by its degrees
    about z."""
    rot = torch.eye(3).repeat(22, 1, 1)
    for joint, deg in turns.items():
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        rot[joint] = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return matrix_to_sixd(rot)[None]


def _kept_cost(now: torch.Tensor, start: torch.Tensor, joints: str) -> float:
    """upper_body_term of the output now against the start (each (1, 22, 6)), keeping ``joints``."""
    tc = dataclasses.replace(PRESETS["tiny"], keep_joints=joints)
    offsets, anchor = default_offsets()[None], torch.zeros(1, 3)
    return upper_body_term(now, _anchored_joints(now, anchor, offsets), start, anchor, offsets, tc).item()


def test_keeping_the_arms_leaves_the_trunk_free_to_lean_and_keeping_the_upper_body_does_not():
    start = _pose({})
    leaned = _pose({3: 10.0, 6: 10.0})  # spine1 and spine2 lean 20 degrees, the arms as they were
    raised = _pose({16: 30.0})  # the left shoulder turns 30 degrees, the trunk as it was
    assert _kept_cost(start, start, "arms") == pytest.approx(0.0, abs=1e-6)
    assert _kept_cost(leaned, start, "arms") == pytest.approx(0.0, abs=1e-6)
    assert _kept_cost(leaned, start, "upper") > 0.05  # the head-anchored arms and the spine moved
    assert _kept_cost(raised, start, "arms") > 0.05
    assert _kept_cost(raised, start, "upper") > 0.0
    with pytest.raises(
        ValueError, match="keep_joints"
    ):  # a name that is no joint set is refused, not "upper"
        _check_keeps_a_start(None, dataclasses.replace(PRESETS["tiny"], keep_joints="arm"))


def test_keeping_arms_and_legs_leaves_only_the_trunk_under_the_head_free():
    """A fine-tune that moves the head joint (--reanchor) may lean the trunk; the legs, their facing and
    the feet's contacts are kept as its start served them."""
    start = _pose({})
    leaned = _pose({3: 10.0, 6: 10.0, 9: 5.0})  # the spine leans, arms and legs as they were
    knee = _pose({4: 40.0})  # the left knee bends 40 degrees, the rest as it was
    turned = _pose({0: 20.0})  # the whole body turns about the pelvis: the legs' facing changes
    assert _kept_cost(leaned, start, "arms_legs") == pytest.approx(0.0, abs=1e-6)
    assert _kept_cost(knee, start, "arms") == pytest.approx(0.0, abs=1e-6)  # "arms" lets the legs go
    assert _kept_cost(knee, start, "arms_legs") > 0.05
    assert _kept_cost(turned, start, "arms_legs") > 0.02
    _check_keeps_a_start(  # a fine-tune that moves the head joint may keep the legs
        object(),
        dataclasses.replace(PRESETS["tiny"], keep_joints="arms_legs", keep_upper_weight=1.0, reanchor=True),
    )


def test_every_keep_joints_choice_the_command_line_offers_names_joints_to_keep():
    """The command line offers config's choices before torch loads; training maps each to its joints, and
    the ones --reanchor allows are among them."""
    assert tuple(KEPT_JOINTS) == KEEP_JOINTS_CHOICES
    assert set(TRUNK_FREE_KEEPS) < set(KEEP_JOINTS_CHOICES)


def test_the_kept_contacts_cost_least_where_the_feet_land_as_the_start_had_them():
    start = torch.tensor([[4.0, -4.0], [-3.0, 2.0]])  # logits: a left foot down, a right one up; then swapped
    same, flipped, unsure = start.clone(), -start, torch.zeros(2, 2)
    assert (
        kept_contact_term(same, start) < kept_contact_term(unsure, start) < kept_contact_term(flipped, start)
    )
