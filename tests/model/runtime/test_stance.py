"""A steady stance (runtime/stance.py) and what it changes for planted feet (runtime/contact.py), and legs
held while both feet are down (stance.LegHold): synthetic head, foot and leg streams with known answers, then
the pipeline."""

import numpy as np
import pytest

from egoposevr.model.runtime.contact import ANCHOR_SPEED_M_S, FEET, RELEASE_HEIGHT_M, FootContacts
from egoposevr.model.runtime.stance import (
    HELD_JOINTS,
    HOLD_WINDOW_S,
    LEAN_SPEED_M_S,
    MAX_GAP_S,
    QUIET_SPEED_M_S,
    QUIET_WINDOW_S,
    REBASE_S,
    REBASE_SLACK_M,
    RELEASE_TAU_S,
    RESEAT_SLACK_M,
    RESEAT_TAU_S,
    SETTLE_SPEED_M_S,
    LegHold,
    SteadyStance,
    legs_folded,
)
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


def head_path(
    start_m: np.ndarray, pivot_m: np.ndarray, motion: str, speed_m_s: float, t_s: float
) -> np.ndarray:
    """The head (3,) m t_s after start_m: "lean" turns it about pivot_m (forward, in the x-y plane), "squat"
    lowers it towards the pivot, each at speed_m_s."""
    if motion == "squat":
        return start_m - np.array([0.0, speed_m_s * t_s, 0.0])
    arm_m = start_m - pivot_m
    angle = speed_m_s * t_s / np.linalg.norm(arm_m)
    turn = np.array(
        [[np.cos(angle), np.sin(angle), 0.0], [-np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]]
    )
    return pivot_m + turn @ arm_m


@pytest.mark.parametrize(
    ("motion", "speed_m_s", "with_pivot", "steady"),
    [
        ("lean", 2 * QUIET_SPEED_M_S, True, True),  # a trunk leaning over still hips
        ("lean", 2 * QUIET_SPEED_M_S, False, False),  # the same head by its speed alone: the runtime before
        ("lean", 1.5 * LEAN_SPEED_M_S, True, False),  # too fast for a lean: a weight shift
        ("squat", 2 * QUIET_SPEED_M_S, True, False),  # towards the hips: the legs bend
    ],
)
def test_a_head_that_leans_about_the_pelvis_keeps_the_stance_and_one_that_drops_does_not(
    motion, speed_m_s, with_pivot, steady
):
    stance, pelvis = SteadyStance(), HEAD - np.array([0.0, 0.6, 0.0])
    t_us = settle(stance)
    for i in range(1, 3 * QUIET_SAMPLES):
        head = head_path(HEAD, pelvis, motion, speed_m_s, i * STEP_US * 1e-6)
        stance.observe_head(t_us + i * STEP_US, head, True, pelvis if with_pivot else None)
        stance.observe_feet((True, True))
    assert stance.steady is steady


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


def serve_left_foot(
    shifts_m: list[np.ndarray], steady: bool, reseat: bool = False, rebase_at: int | None = None
) -> tuple[np.ndarray, FootContacts]:
    """The left foot's target (or the network's foot where none) per sample, and the contacts after; with
    ``rebase_at``, the contacts are rebased before that sample."""
    contacts, served = FootContacts(reseat=reseat), []
    for i, shift in enumerate(shifts_m):
        if i == rebase_at:
            contacts.rebase(i * STEP_US)
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


def test_a_steady_foot_planted_on_a_wrong_guess_reseats_at_the_mean_and_one_near_it_settles_as_before():
    """With ``reseat``, an anchor 15 cm from the network's mean closes the gap past RESEAT_SLACK_M within a
    few RESEAT_TAU_S; a wander within the slack settles at ANCHOR_SPEED_M_S as without it."""
    first = np.array([0.15, 0.0, 0.0])
    samples = int(5 * RESEAT_TAU_S / (STEP_US * 1e-6))
    shifts = [first] + [np.zeros(3)] * samples
    truth = standing_joints()[LEFT_FOOT]
    reseated, _ = serve_left_foot(shifts, steady=True, reseat=True)
    assert abs(reseated[-1, 0] - truth[0]) < RESEAT_SLACK_M + 0.01
    kept, _ = serve_left_foot(shifts, steady=True)
    assert abs(kept[-1, 0] - truth[0]) > 0.13  # without it, the wrong guess is nearly all still there
    wander = [np.array([0.03 * np.sin(i / 30), 0.0, 0.0]) for i in range(samples)]
    near, _ = serve_left_foot(wander, steady=True, reseat=True)
    speed_m_s = np.linalg.norm(np.diff(near, axis=0), axis=1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= ANCHOR_SPEED_M_S * 1.01


def test_a_foot_planted_on_a_cold_guess_reseats_at_the_networks_answers_after_a_rebase():
    """A foot planted 10 cm off (the session's cold first guess, not far enough to be let go), the network
    then placing it right: after a rebase in a steady stance its anchor reaches the slack (REBASE_SLACK_M) of
    the network's answers within REBASE_S, and then settles at ANCHOR_SPEED_M_S again; without one, or outside
    a steady stance (a crouch's planted feet would be dragged with a moving guess), it stays where it was
    planted."""
    cold = int(0.4 / (STEP_US * 1e-6))
    after = int(2 * REBASE_S / (STEP_US * 1e-6))
    shifts = [np.array([0.10, 0.0, 0.0])] * cold + [np.zeros(3)] * after
    truth = standing_joints()[LEFT_FOOT]
    rebased, contacts = serve_left_foot(shifts, steady=True, rebase_at=cold)
    assert contacts.planted[0]
    gap_m = np.linalg.norm(rebased[cold + int(REBASE_S / (STEP_US * 1e-6))] - truth)
    assert REBASE_SLACK_M - 0.01 < gap_m < REBASE_SLACK_M + 0.01
    for steady, rebase_at in ((True, None), (False, cold), (False, None)):
        kept, contacts = serve_left_foot(shifts, steady=steady, rebase_at=rebase_at)
        assert contacts.planted[0] and abs(kept[-1, 0] - truth[0]) > 0.09, (steady, rebase_at)
    wander = [np.array([0.03 * np.sin(i / 30), 0.0, 0.0]) for i in range(3 * after)]  # after the rebase
    settled, _ = serve_left_foot(shifts + wander, steady=True, rebase_at=cold)
    speed_m_s = np.linalg.norm(np.diff(settled[cold + after :], axis=0), axis=1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= ANCHOR_SPEED_M_S * 1.01


HELD = list(HELD_JOINTS)


def hold_legs(
    hold: LegHold,
    network: list[np.ndarray],
    heads_m: list[np.ndarray],
    planted: list[tuple[bool, bool]],
    pull_m: np.ndarray | None = None,
    t0: int = 0,
) -> list[np.ndarray | None]:
    """Each sample's held targets (5, 3), or None where the legs are served without the hold. What is served
    is the target where there is one, else the network's joints moved by ``pull_m`` (3,): what KPO does to
    them for the planted feet (None: nothing). The first sample is sample ``t0`` of the stream."""
    out = []
    for i, joints in enumerate(network):
        unheld = joints + (0.0 if pull_m is None else pull_m)
        targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
        t_us, head_m = (t0 + i) * STEP_US, heads_m[i]
        hold.targets(t_us, joints, head_m, True, planted[i], targets, observed, unheld=lambda u=unheld: u)
        assert observed[HELD].all() or not observed[HELD].any()
        out.append(targets[HELD].copy() if observed[HELD].any() else None)
        served = unheld.copy()
        if observed[HELD].any():
            served[HELD] = targets[HELD]
        hold.served(served)
    return out


def wandering_legs(samples: int) -> list[np.ndarray]:
    """A network that moves the pelvis, hips and knees 6 cm back and forth over 3 s while the feet stay."""
    return [standing_joints() + np.array([0.06 * np.sin(i / 45), 0.0, 0.0]) * np.isin(range(22), HELD)[:, None]
            for i in range(samples)]  # fmt: skip


def test_legs_stay_where_they_were_served_while_both_feet_are_down_and_the_head_is_quiet():
    network = wandering_legs(360)
    held = hold_legs(LegHold(), network, [HEAD] * 360, [(True, True)] * 360)
    assert held[0] is None  # nothing served yet to hold
    assert np.allclose(held[1], network[0][HELD])  # begun where they were served, not at the new guess
    path = np.array(held[1:])
    speed_m_s = np.linalg.norm(np.diff(path, axis=0), axis=-1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= SETTLE_SPEED_M_S * 1.01  # settling, never wandering
    assert np.abs(np.array(network)[:, HELD, 0]).max() > 0.05  # while the network's moved 6 cm


def test_legs_held_on_a_wrong_guess_reseat_at_the_networks_mean_and_wandering_ones_stay_held():
    """A hold begun where the legs were served 15 cm off, the network then placing them right: with
    ``reseat`` the held joints reach the slack of the mean in a few RESEAT_TAU_S; without it they barely move.
    A network that wanders within the slack is held as without it."""
    samples = int(5 * RESEAT_TAU_S / (STEP_US * 1e-6))
    legs = np.isin(range(22), HELD)[:, None]
    network = [standing_joints() + np.array([0.15, 0.0, 0.0]) * legs] + [standing_joints()] * samples
    truth = standing_joints()[HELD]
    gap_m = {}
    for reseat in (True, False):
        held = hold_legs(
            LegHold(reseat=reseat), network, [HEAD] * len(network), [(True, True)] * len(network)
        )
        gap_m[reseat] = np.abs(held[-1][:, 0] - truth[:, 0]).max()
    assert gap_m[True] < RESEAT_SLACK_M + 0.01
    assert gap_m[False] > 0.13  # without it, the wrong guess is nearly all still there
    wander = wandering_legs(samples)  # 6 cm back and forth about its start: a mean within the slack
    held = np.array(hold_legs(LegHold(reseat=True), wander, [HEAD] * samples, [(True, True)] * samples)[1:])
    speed_m_s = np.linalg.norm(np.diff(held, axis=0), axis=-1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= SETTLE_SPEED_M_S * 1.01


def test_legs_held_on_a_cold_guess_reseat_at_the_networks_answers_after_a_rebase():
    """A hold begun where the legs were served 15 cm off, the network placing them right from the next
    sample: a rebase 0.4 s in (the windows filled) brings the held joints to the slack (REBASE_SLACK_M) of the
    network's answers within REBASE_S, and after it a wandering network moves them at SETTLE_SPEED_M_S again;
    without it they barely move."""
    cold = int(0.4 / (STEP_US * 1e-6))
    after = int(REBASE_S / (STEP_US * 1e-6))
    legs = np.isin(range(22), HELD)[:, None]
    network = [standing_joints() + np.array([0.15, 0.0, 0.0]) * legs] + [standing_joints()] * (cold + after)
    network += wandering_legs(3 * after)
    truth = standing_joints()[HELD]
    heads, planted = [HEAD] * len(network), [(True, True)] * len(network)
    held = {}
    for rebase in (True, False):
        hold = LegHold()
        held[rebase] = hold_legs(hold, network[:cold], heads[:cold], planted[:cold])
        if rebase:
            hold.rebase(cold * STEP_US)
        rest = len(network) - cold
        held[rebase] += hold_legs(hold, network[cold:], heads[:rest], planted[:rest], t0=cold)
    assert np.abs(held[True][cold + after][:, 0] - truth[:, 0]).max() < REBASE_SLACK_M + 0.01
    assert np.abs(held[False][cold + after][:, 0] - truth[:, 0]).max() > 0.13
    path = np.array(held[True][cold + after + 1 :])
    speed_m_s = np.linalg.norm(np.diff(path, axis=0), axis=-1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= SETTLE_SPEED_M_S * 1.01


def test_legs_held_on_a_cold_guess_within_the_slack_only_settle_after_a_rebase(monkeypatch):
    """A cold guess nearer the network's warm answers than a REBASE_SLACK_M (5 cm here) is kept: after the
    rebase the held joints move at SETTLE_SPEED_M_S at most."""
    from egoposevr.model.runtime import stance

    slack_m = 0.05
    monkeypatch.setattr(stance, "REBASE_SLACK_M", slack_m)
    cold = int(0.4 / (STEP_US * 1e-6))
    legs = np.isin(range(22), HELD)[:, None]
    off = np.array([0.8 * slack_m, 0.0, 0.0])
    network = [standing_joints() + off * legs] + [standing_joints()] * (
        cold + int(2 * REBASE_S / (STEP_US * 1e-6))
    )
    heads, planted = [HEAD] * len(network), [(True, True)] * len(network)
    hold = LegHold()
    held = hold_legs(hold, network[:cold], heads[:cold], planted[:cold])
    hold.rebase(cold * STEP_US)
    rest = len(network) - cold
    held += hold_legs(hold, network[cold:], heads[:rest], planted[:rest], t0=cold)
    path = np.array(held[1:])
    speed_m_s = np.linalg.norm(np.diff(path, axis=0), axis=-1) / (STEP_US * 1e-6)
    assert speed_m_s.max() <= SETTLE_SPEED_M_S * 1.01
    truth = standing_joints()[HELD]
    assert np.abs(path[-1][:, 0] - truth[:, 0]).max() > 0.7 * slack_m  # nearly where the cold guess was


@pytest.mark.parametrize("lean", [False, True])
def test_a_head_that_moves_or_a_foot_let_go_ends_the_hold_and_the_legs_glide_back(lean):
    quiet = int(2 * HOLD_WINDOW_S * 1e6 / STEP_US)
    for end in ("head", "foot"):
        network = wandering_legs(quiet + 120)
        heads = [HEAD] * quiet + [HEAD + np.array([0.5 * i * STEP_US * 1e-6, 0.0, 0.0]) for i in range(120)]
        planted = [(True, True)] * quiet + [(True, False)] * 120
        if end == "head":
            planted = [(True, True)] * len(network)
        else:
            heads = [HEAD] * len(network)
        held = hold_legs(LegHold(lean=lean), network, heads, planted)
        served = np.array([h if h is not None else n[HELD] for h, n in zip(held, network, strict=True)])
        assert np.linalg.norm(served[quiet - 1] - network[quiet - 1][HELD], axis=-1).max() > 0.02, end
        # the hold had kept the legs 2+ cm from the network's, and the gap grows until the hold ends: within
        # HOLD_WINDOW_S for a head (its speed is measured over that; a head that sets off over the pelvis
        # moves round it at first, as a lean would), at once for a foot
        window = int(HOLD_WINDOW_S * 1e6 / STEP_US) + 1
        gap_m = max(
            np.linalg.norm(served[i] - network[i][HELD], axis=-1).max()
            for i in range(quiet - 1, quiet + window)
        )
        step_m = np.linalg.norm(np.diff(served, axis=0), axis=-1).max()
        # No jump when the hold ends: a sample takes 1 - exp(-dt / tau) of the gap (17 % at 90 Hz), plus the
        # network's own move (at most 1.3 mm a sample here).
        assert step_m < (1.0 - np.exp(-STEP_US * 1e-6 / RELEASE_TAU_S)) * gap_m + 0.0015, end
        gone = int(8 * RELEASE_TAU_S * 1e6 / STEP_US)
        if end == "foot":
            assert held[quiet + gone] is None, end  # the legs are the network's again
        else:  # the head's speed is measured over HOLD_WINDOW_S: it ends the hold within that
            assert held[quiet + int(HOLD_WINDOW_S * 1e6 / STEP_US) + gone] is None, end


@pytest.mark.parametrize("lean", [True, False])
def test_legs_stay_held_while_the_head_leans_about_the_pelvis(lean):
    """A head that leans forward over the held pelvis at twice the quiet speed (a reach, a bow): the hold
    lasts through it with the lean gate, and without it ends as for any head that fast."""
    quiet, leaning = int(2 * HOLD_WINDOW_S * 1e6 / STEP_US), 90
    network = wandering_legs(quiet + leaning)
    start, pelvis = standing_joints()[15], standing_joints()[0]
    heads = [start] * quiet + [
        head_path(start, pelvis, "lean", 2 * QUIET_SPEED_M_S, i * STEP_US * 1e-6) for i in range(leaning)
    ]
    hold = LegHold(lean=lean)
    held = hold_legs(hold, network, heads, [(True, True)] * len(network))
    assert held[quiet - 1] is not None
    assert hold.holding is lean
    if lean:
        path = np.array(held[quiet:])
        assert (
            np.linalg.norm(path - path[0], axis=-1).max() < SETTLE_SPEED_M_S * leaning * STEP_US * 1e-6 + 1e-9
        )


def test_the_legs_glide_to_where_kpo_would_serve_them_without_the_hold_and_do_not_jump_there():
    """Without the hold, KPO serves the legs away from the network's guess (the planted feet pull them): the
    fade ends there, not at the network's joints."""
    quiet, pull_m = 90, np.array([0.0, -0.02, 0.015])
    network = wandering_legs(quiet + 90)
    planted = [(True, True)] * quiet + [(True, False)] * 90
    held = hold_legs(LegHold(), network, [HEAD] * len(network), planted, pull_m)
    served = np.array([h if h is not None else n[HELD] + pull_m for h, n in zip(held, network, strict=True)])
    assert held[-1] is None and np.allclose(served[-1], network[-1][HELD] + pull_m)
    end = quiet + next(i for i, h in enumerate(held[quiet:]) if h is None)  # the first sample without targets
    assert end > quiet + 5  # it faded
    step_m = np.linalg.norm(served[end] - served[end - 1], axis=-1).max()
    assert step_m < 0.0025  # at most the network's own move (1.3 mm) and the last millimetre of the fade


def test_a_long_pause_forgets_the_hold():
    hold = LegHold()
    network = wandering_legs(60)
    hold_legs(hold, network[:30], [HEAD] * 30, [(True, True)] * 30)
    assert hold.holding
    targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
    hold.targets(
        int(30 * STEP_US + 2 * MAX_GAP_S * 1e6), network[30], HEAD, True, (True, True), targets, observed
    )
    assert not observed.any() and not hold.holding  # nothing served since the pause to hold


@pytest.mark.parametrize(
    ("family", "stage", "most"),
    [("still_stand", "leg_hold", 0.7), ("lean_stand", "lean_gate", 0.5), ("still_sit", "seated_yaw", 0.5)],
)
def test_the_served_legs_of_a_user_who_only_moves_the_upper_body_wander_less_with_the_stage(
    family, stage, most
):
    """The whole pipeline (bundled egoposevr) on a procedural user who stands still and moves only the upper
    body (``lean_stand``: leaning and swaying over the still hips too; ``still_sit``: seated and turning, no
    camera frame ever sent): the leg leakage with the hold (with the lean gate, with the seated yaw) is well
    under the runtime's without it, and the served joints are still FK of the rotations."""
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.skeleton import forward_kinematics, rest_offsets
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.training.plausibility import plausibility, summarize_plausibility
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(1)
    track = simulate_headset(generate(family, 8.0, 60.0, rng), 90.0, rng)
    model = LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx")
    leakage = {}
    for hold in (True, False):
        pipeline = Pipeline(model, **{stage: hold})
        results = [
            pipeline.push_hmd(int(t), track.poses[i], track.valid[i]) for i, t in enumerate(track.t_us)
        ]
        joints = np.array([r.joints for r in results])
        after = slice(90, None)  # once the height estimate has settled
        measured = plausibility(joints[after], track.joints_m[after], track.t_us[after])
        leakage[hold] = summarize_plausibility([measured])["leg_leakage_cm"]
        last = results[-1]
        fk, _ = forward_kinematics(last.local_rot, last.transl, rest_offsets(pipeline.served_scale.scale))
        assert np.allclose(fk, last.joints, atol=1e-6)
    assert leakage[True] < most * leakage[False], leakage


def test_the_stillness_gates_watch_one_point_of_the_headset_whatever_head_offset_a_model_has():
    from scipy.spatial.transform import Rotation

    from egoposevr.model.rig import (
        DEFAULT_OFFSETS_M,
        STILLNESS_OFFSET_M,
        joints_from_devices,
        stillness_point,
    )

    rng = np.random.default_rng(3)
    poses = np.zeros((3, 7))
    poses[:, :3] = rng.normal(0.0, 1.0, (3, 3))
    poses[:, 3:] = Rotation.random(3, random_state=4).as_quat()
    other = DEFAULT_OFFSETS_M.copy()
    other[0] = (0.01, 0.09, 0.05)
    points = []
    for offsets in (DEFAULT_OFFSETS_M, other):
        head_m, head_rot = joints_from_devices(poses, offsets)
        points.append(stillness_point(head_m[0], head_rot[0], offsets[0]))
    np.testing.assert_allclose(points[0], points[1], atol=1e-12)
    # a model whose head offset is the stillness one (those trained before 2026-11-27) watches its head joint
    still_offsets = DEFAULT_OFFSETS_M.copy()
    still_offsets[0] = STILLNESS_OFFSET_M
    head_m, head_rot = joints_from_devices(poses, still_offsets)
    np.testing.assert_allclose(stillness_point(head_m[0], head_rot[0], still_offsets[0]), head_m[0])


def rebases_of_a_still_stander(
    model, warm_reseat: bool, frame_every: int | None = None
) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """A still standing person's 1.5 s headset stream (90 Hz) served by a Pipeline of ``model``, with a camera
    frame every ``frame_every`` samples (None: none): the stream's t_us (N,) and each rebase the pipeline
    asked for, (``legs`` or ``feet``, t_us), in order."""
    from egoposevr.model.runtime.frames import EncodedFrame
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate

    rng = np.random.default_rng(5)
    track = simulate_headset(generate("still_stand", 1.5, 60.0, rng), 90.0, rng)
    pipeline = Pipeline(model, warm_reseat=warm_reseat)
    rebased: list[tuple[str, int]] = []
    pipeline.legs.rebase = lambda t: rebased.append(("legs", t))
    pipeline.feet.rebase = lambda t: rebased.append(("feet", t))
    for i, t_us in enumerate(track.t_us):
        if frame_every and i % frame_every == 0:
            pipeline.add_frame(EncodedFrame(
                int(t_us), (160, 128), np.array([100.0, 100.0, 80.0, 64.0]), np.eye(4),
                np.tile([0.0, 0.5, 1.0], (22, 1)), np.zeros(22), model.info.visual_path, 0,
            ))  # fmt: skip
        pipeline.push_hmd(int(t_us), track.poses[i], track.valid[i])
    return track.t_us, rebased


@pytest.mark.parametrize(("name", "frame_every", "filled_at"), [
    ("egoposevr", 1, "window"),  # frames faster than the headset window fills
    ("egoposevr", None, "twice the window"),  # a camera net whose camera does not send
    ("egoposevr", 6, "the eighth frame"),  # frames slower than the headset window fills
])  # fmt: skip
def test_warm_reseat_rebases_the_hold_and_the_feet_once_when_the_nets_windows_fill(
    name, frame_every, filled_at, monkeypatch
):
    """With ``warm_reseat`` the leg hold and the planted feet are rebased once, at the first sample whose
    windows hold no padding: ``window`` headset samples and, for a net that reads the camera, its
    ``visual_window`` frames (or twice ``window`` samples without any); never with it off."""
    from egoposevr.model.runtime import stance
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.weights import WEIGHTS_DIR

    monkeypatch.setattr(stance, "REBASE_FOLDED_SHARE", None)  # a standing stream: rebased whatever its legs
    model = LoadedModel.load(WEIGHTS_DIR / f"{name}.onnx")
    window, visual_window = model.info.config.window, model.info.config.visual_window
    expected = {"window": window, "twice the window": 2 * window,
                "the eighth frame": (visual_window - 1) * (frame_every or 1) + 1}[filled_at]  # fmt: skip
    assert expected > window or filled_at != "the eighth frame"
    for warm_reseat in (True, False):
        t_us, rebased = rebases_of_a_still_stander(model, warm_reseat, frame_every)
        at = int(t_us[expected - 1])
        assert rebased == ([("feet", at), ("legs", at)] if warm_reseat else []), (filled_at, expected)


def test_legs_are_folded_when_the_pelvis_is_low_over_the_ankles():
    """A standing body's pelvis is about its legs' length above the ankles; a seated one's, thighs level,
    about a shin's."""
    standing = standing_joints()
    assert not legs_folded(standing, 0.7)
    seated = standing.copy()
    thigh_m = np.linalg.norm(standing[4] - standing[1])
    seated[[0, 1, 2, 3]] -= [0.0, thigh_m, 0.0]  # pelvis and hips down to the knees' height
    seated[[1, 2], 2] -= thigh_m  # thighs level, pointing forward to the knees
    assert legs_folded(seated, 0.7)


def test_warm_reseat_with_a_folded_share_rebases_only_where_the_nets_legs_fold(monkeypatch):
    """With stance.REBASE_FOLDED_SHARE, a still standing person's stream is not rebased when the windows fill
    (the net serves straight legs), and is with a share every pose is under."""
    from egoposevr.model.runtime import stance
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.weights import WEIGHTS_DIR

    model = LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx")  # no frames: its windows fill at 2 x window
    for share, expected in ((0.7, 0), (5.0, 2)):
        monkeypatch.setattr(stance, "REBASE_FOLDED_SHARE", share)
        _, rebased = rebases_of_a_still_stander(model, warm_reseat=True)
        assert len(rebased) == expected, share
