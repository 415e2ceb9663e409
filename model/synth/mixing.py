"""Motion that no one captured but any body could do: the legs and pelvis of one clip under the trunk, head
and arms of another.

The nets learn what a wearer's legs do from what the headset and controllers do, and a few captured people
teach them a few people's habits (the arms that swing with a walk, the head that bobs with a dance step);
on a new person they serve those habits instead of the legs the camera sees. A mixed clip keeps what is
physical about the legs (the pelvis's path, the feet that stand and step: clip ``legs``, untouched) and puts
on them the upper body of another clip, started at a random time and played at a random speed, so the
upper body says less about the legs than in any one capture and the camera has to say the rest.

Only rotations below the pelvis and above it are exchanged: the spine's first joint turns relative to the
pelvis as it did in ``upper``, so a trunk that leant forward over its own hips leans over the new ones.

Shape legend: ``F`` frames, ``J`` = 22 joints.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from ..skeleton import UPPER_BODY
from .motion import Motion, resample, sample_at

# The upper body is played at a speed drawn from this range: a mixed clip should not keep the captured
# upper body's tempo bound to the captured legs' (people gesture at their own pace).
SPEED_RANGE: Final = (0.8, 1.25)


def mix_halves(
    legs: Motion, upper: Motion, rng: np.random.Generator, seconds: float, name: str | None = None
) -> Motion:
    """``legs``'s pelvis path and lower-body rotations (LOWER_BODY) with ``upper``'s trunk, head and arm
    rotations (UPPER_BODY), at ``legs``'s frame rate and body, at most ``seconds`` long.

    Where each clip starts is drawn (so two mixes of the same pair differ), and ``upper`` is played at a
    speed drawn from SPEED_RANGE, played back and forth if it is shorter than the result (a loop would jump
    from its last pose to its first). ValueError if either clip has fewer than two frames.
    """
    if legs.num_frames < 2 or upper.num_frames < 2:
        raise ValueError(f"mixing needs clips of two frames or more ({legs.name}, {upper.name})")
    frames = min(legs.num_frames, max(2, round(seconds * legs.fps)))
    start = int(rng.integers(0, legs.num_frames - frames + 1))
    body = legs.slice(start, start + frames)
    upper = resample(upper, legs.fps)
    speed = float(rng.uniform(*SPEED_RANGE))
    span_s = upper.duration_s - 1.0 / upper.fps
    t_s = float(rng.uniform(0.0, span_s)) + speed * np.arange(frames) / legs.fps
    upper_rot, _ = sample_at(upper, back_and_forth(t_s, span_s))
    local_rot = body.local_rot.copy()
    local_rot[:, UPPER_BODY] = upper_rot[:, UPPER_BODY]
    return body.replace(
        name=name or f"{legs.name}+{upper.name}",
        local_rot=local_rot,
        source=f"mixed:{legs.source}+{upper.source}",
        licence=legs.licence if legs.licence == upper.licence else f"{legs.licence}; {upper.licence}",
    )


def back_and_forth(t_s: np.ndarray, span_s: float) -> np.ndarray:
    """(N,) times ``t_s`` (N,) folded into [0, span_s]: forwards, then backwards, then forwards again."""
    if span_s <= 0:
        return np.zeros_like(t_s)
    phase = np.mod(t_s, 2.0 * span_s)
    return np.where(phase > span_s, 2.0 * span_s - phase, phase)
