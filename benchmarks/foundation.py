"""Per-call cost of the foundation's hot-path pieces: the v1 codec and the per-sample numpy stages.

Usage: python benchmarks/foundation.py [--rounds 15] [--number 2000]
Prints two markdown tables, each number the median over `rounds` timings of `number` calls, in µs:
1. per message: encode, decode, encode+decode, and msgpack alone (unpackb without validation);
2. per headset sample: HMD feature push, FK of one pose, One Euro on 22×3 joints, SMPL axis-angle export.
"""

from __future__ import annotations

import argparse
import statistics
import timeit

import msgpack
import numpy as np

from egoposevr.model import skeleton
from egoposevr.model.hmd import HmdFeatureExtractor
from egoposevr.model.rotations import axis_angle_to_matrix
from egoposevr.model.runtime.filters import OneEuroFilter
from egoposevr.protocol import Pose, decode, encode
from egoposevr.protocol.examples import example_messages


def realistic_pose() -> Pose:
    """A pose with full-precision floats, as the server sends them (not the fixtures' round numbers)."""
    rng = np.random.default_rng(0)
    return Pose(
        seq=123456, t_us=987654321, model="egoposevr",
        global_orient=rng.normal(size=3).tolist(), body_pose=(rng.normal(size=63) * 0.3).tolist(),
        transl=rng.normal(size=3).tolist(), joints=rng.normal(size=66).tolist(),
        timing_us={"features": 41, "visual": 2100, "fusion": 900, "fk_filter": 42, "kpo": 260, "total": 3400},
    )  # fmt: skip


def median_us(fn, rounds: int, number: int) -> float:
    return statistics.median(timeit.repeat(fn, number=number, repeat=rounds)) / number * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--number", type=int, default=2000)
    args = parser.parse_args()
    messages = {"pose (realistic)": realistic_pose(), **example_messages()}
    print("| message | bytes | encode µs | decode µs | encode+decode µs | msgpack unpack only µs |")
    print("|---|---|---|---|---|---|")
    for name, msg in messages.items():
        data = encode(msg)
        enc = median_us(lambda m=msg: encode(m), args.rounds, args.number)
        dec = median_us(lambda d=data: decode(d), args.rounds, args.number)
        both = median_us(lambda m=msg: decode(encode(m)), args.rounds, args.number)
        raw = median_us(lambda d=data: msgpack.unpackb(d, raw=False), args.rounds, args.number)
        print(f"| {name} | {len(data)} | {enc:.1f} | {dec:.1f} | {both:.1f} | {raw:.1f} |")
    print()
    print("| per-sample stage | µs |")
    print("|---|---|")
    for name, fn in sample_stages().items():
        print(f"| {name} | {median_us(fn, args.rounds, args.number // 4):.1f} |")


def sample_stages() -> dict[str, object]:
    """name -> zero-argument callable doing one sample's worth of that stage."""
    rng = np.random.default_rng(1)
    extractor, euro = HmdFeatureExtractor(), OneEuroFilter(min_cutoff_hz=1.0, beta=0.5)
    poses = np.tile([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0], (3, 1))
    local_rot = axis_angle_to_matrix(rng.normal(size=(22, 3)) * 0.3)
    joints = rng.normal(size=(22, 3))
    clock = {"t_us": 0}

    def push_hmd():
        clock["t_us"] += 11_111
        poses[:, 0] += 0.001
        extractor.push(clock["t_us"], poses, [True, True, True])

    def filter_joints():
        clock["t_us"] += 11_111
        euro(clock["t_us"], joints)

    return {
        "HMD feature push (72-d)": push_hmd,
        "FK, one pose": lambda: skeleton.forward_kinematics(local_rot, np.zeros(3)),
        "One Euro, 22×3 joints": filter_joints,
        "SMPL axis-angle export": lambda: skeleton.local_rot_to_smpl(local_rot),
    }


if __name__ == "__main__":
    main()
