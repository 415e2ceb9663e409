"""A steady stance (runtime/stance.py) and what it changes for planted feet (runtime/contact.py): synthetic
head and foot streams with known answers."""

import numpy as np
import pytest

from egoposevr.model.runtime.contact import ANCHOR_SPEED_M_S, FEET, RELEASE_HEIGHT_M, FootContacts
from egoposevr.model.runtime.stance import MAX_GAP_S, QUIET_SPEED_M_S, QUIET_WINDOW_S, SteadyStance
from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M, REST_JOINTS_M

STEP_US = 11_111  # 90 Hz
HEAD = np.array([0.0, 1.6, 0.0])
LEFT_ANKLE, LEFT_FOOT = FEET[0]
QUIET_SAMPLES = int(QUIET_WINDOW_S * 1e6 / STEP_US) + 2


def settle(stance: SteadyStance, samples: int = QUIET_SAMPLES, t0_us: int = 0) -> int:
    """Both feet down and a still head for ``samples`` samples -> the next sample's time."""
    for i in range(samples):
        stance.observe_head(t0_us + i * STEP_US, HEAD, True)
        stance.observe_feet((True, True))
    return t0_us + samples * STEP_US


def test_two_planted_feet_and_a_still_head_make_a_steady_stance():
    stance = SteadyStance()
    settle(stance, 5)
    assert not stance.steady  # not yet a quiet window of headset
    settle(stance, QUIET_SAMPLES, 5 * STEP_US)
    assert stance.steady


def test_a_head_moving_fast_never_makes_one():
    stance = SteadyStance()
    for i in range(3 * QUIET_SAMPLES):
        stance.observe_head(i * STEP_US, HEAD + np.array([0.005 * i, 0.0, 0.0]), True)  # 0.45 m/s
        stance.observe_feet((True, True))
    assert not stance.steady


@pytest.mark.parametrize("speed_m_s", [0.5 * QUIET_SPEED_M_S, 2 * QUIET_SPEED_M_S])
def test_a_stance_stays_steady_while_the_head_moves_slowly(speed_m_s):
    """A reach, a lean, a slow squat keep the feet down; a faster head (a weight shift, walking) does not."""
    stance = SteadyStance()
    t_us = settle(stance)
    assert stance.steady
    for i in range(1, 3 * QUIET_SAMPLES):
        stance.observe_head(
            t_us + i * STEP_US, HEAD + np.array([0.0, -speed_m_s * i * STEP_US * 1e-6, 0.0]), True
        )
        stance.observe_feet((True, True))
    assert stance.steady is (speed_m_s < QUIET_SPEED_M_S)


def test_a_step_a_lost_headset_or_a_pause_ends_it():
    for end in ("step", "lost", "pause"):
        stance = SteadyStance()
        t_us = settle(stance)
        if end == "step":
            stance.observe_feet((True, False))
        elif end == "lost":
            stance.observe_head(t_us, HEAD, False)
        else:
            stance.observe_head(t_us + int(2 * MAX_GAP_S * 1e6), HEAD, True)
        assert not stance.steady, end


def standing_joints(foot_shift_m: np.ndarray | None = None) -> np.ndarray:
    """(J, 3) the rest skeleton on the floor; the left foot and ankle moved by foot_shift_m (3,)."""
    joints = REST_JOINTS_M - np.array([0.0, REST_JOINTS_M[[10, 11], 1].min() - FOOT_JOINT_HEIGHT_M, 0.0])
    if foot_shift_m is not None:
        joints[[LEFT_ANKLE, LEFT_FOOT]] += foot_shift_m
    return joints


def serve_left_foot(shifts_m: list[np.ndarray], steady: bool) -> tuple[np.ndarray, FootContacts]:
    """The left foot's target (or the network's foot where none) per sample, and the contacts after."""
    contacts, served = FootContacts(), []
    for i, shift in enumerate(shifts_m):
        targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
        joints = standing_joints(shift)
        contacts.targets(i * STEP_US, joints, 1.0, targets, observed, np.ones(2), steady)
        served.append(targets[LEFT_FOOT] if observed[LEFT_FOOT] else joints[LEFT_FOOT])
    return np.array(served), contacts


def test_in_a_steady_stance_a_wandering_network_foot_does_not_step_but_a_lifted_one_does():
    wander = [np.array([0.25 * np.sin(i / 30), 0.0, 0.0]) for i in range(180)]  # 25 cm over the floor
    served, contacts = serve_left_foot(wander, steady=True)
    assert contacts.planted == (True, True)
    speed_m_s = np.linalg.norm(np.diff(served, axis=0), axis=1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= ANCHOR_SPEED_M_S * 1.01  # no skating beyond the anchor's slow settling
    unsteady, _ = serve_left_foot(wander, steady=False)
    unsteady_speed_m_s = np.linalg.norm(np.diff(unsteady, axis=0), axis=1) / (STEP_US * 1e-6)
    assert unsteady_speed_m_s.max() > 0.1  # outside a steady stance the same wander steps (and re-plants)

    lift = [np.zeros(3)] * 30 + [np.array([0.0, min(0.01 * i, 0.2), 0.0]) for i in range(40)]
    _, lifted = serve_left_foot(lift, steady=True)
    assert lifted.planted[0] is False and RELEASE_HEIGHT_M < 0.2


def test_a_steady_foot_settles_at_the_mean_of_the_networks_placements():
    """The plant takes the first guess; while the stance is steady the anchor goes to the mean of the guesses
    (a still foot's best estimate), at most ANCHOR_SPEED_M_S."""
    rng = np.random.default_rng(0)
    first = np.array([0.06, 0.0, 0.0])  # an early guess 6 cm off; the later ones scatter around zero
    samples = int((0.06 / ANCHOR_SPEED_M_S + 6.0) / (STEP_US * 1e-6))  # long enough to get there
    shifts = [first] + [np.array([rng.normal(0.0, 0.02), 0.0, rng.normal(0.0, 0.02)]) for _ in range(samples)]
    served, contacts = serve_left_foot(shifts, steady=True)
    assert contacts.planted[0]
    truth = standing_joints()[LEFT_FOOT]
    assert abs(served[0, 0] - truth[0]) == pytest.approx(0.06)
    assert np.linalg.norm(served[-1, [0, 2]] - truth[[0, 2]]) < 0.01  # settled
    speed_m_s = np.linalg.norm(np.diff(served, axis=0), axis=1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= ANCHOR_SPEED_M_S * 1.01
