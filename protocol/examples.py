"""One canonical instance of every v1 message.

They are the source of the golden fixtures (``tests/protocol/golden/*.msgpack``), of the hex dump in
PROTOCOL.md, and handy for client tests. Every float is exactly representable in float32, so that
``decode(encode(m)) == m`` holds bit for bit. Regenerate the fixtures (deliberately: they are the contract) with
``python tests/protocol/regenerate_golden.py``.
"""

from __future__ import annotations

import base64

from .messages import (
    Body,
    Calibrate,
    Calibration,
    Error,
    GetBody,
    Hello,
    Hmd,
    ListModels,
    Message,
    ModelInfo,
    Models,
    Ping,
    Pong,
    Pose,
    Ref,
    Rgbd,
    SelectModel,
    SessionStatus,
    SetBody,
    Welcome,
)

# A 4×2 JPEG (left half blue-ish, right half yellow-ish) and a 4×2 16-bit PNG of depths in mm:
# [[1000, 1250, 1500, 0], [2000, 2250, 2500, 65535]] — real images a client can decode in its tests.
EXAMPLE_JPEG = base64.b64decode(
    "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDABALDA4MChAODQ4SERATGCgaGBYWGDEjJR0oOjM9PDkzODdASFxOQERXRTc4UG1RV19i"
    "Z2hnPk1xeXBkeFxlZ2P/2wBDARESEhgVGC8aGi9jQjhCY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2Nj"
    "Y2NjY2NjY2P/wAARCAACAAQDASIAAhEBAxEB/8QAHwAAAQUBAQEBAQEAAAAAAAAAAAECAwQFBgcICQoL/8QAtRAAAgEDAwIEAwUF"
    "BAQAAAF9AQIDAAQRBRIhMUEGE1FhByJxFDKBkaEII0KxwRVS0fAkM2JyggkKFhcYGRolJicoKSo0NTY3ODk6Q0RFRkdISUpTVFVW"
    "V1hZWmNkZWZnaGlqc3R1dnd4eXqDhIWGh4iJipKTlJWWl5iZmqKjpKWmp6ipqrKztLW2t7i5usLDxMXGx8jJytLT1NXW19jZ2uHi"
    "4+Tl5ufo6erx8vP09fb3+Pn6/8QAHwEAAwEBAQEBAQEBAQAAAAAAAAECAwQFBgcICQoL/8QAtREAAgECBAQDBAcFBAQAAQJ3AAEC"
    "AxEEBSExBhJBUQdhcRMiMoEIFEKRobHBCSMzUvAVYnLRChYkNOEl8RcYGRomJygpKjU2Nzg5OkNERUZHSElKU1RVVldYWVpjZGVm"
    "Z2hpanN0dXZ3eHl6goOEhYaHiImKkpOUlZaXmJmaoqOkpaanqKmqsrO0tba3uLm6wsPExcbHyMnK0tPU1dbX2Nna4uPk5ebn6Onq"
    "8vP09fb3+Pn6/9oADAMBAAIRAxEAPwC5pf8AyD4vx/maKKK8nFfx5+r/ADNqfwL0P//Z"
)
EXAMPLE_DEPTH_PNG = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAQAAAACEAAAAAAKU/78AAAAF0lEQVQI12NkfsH4i/HXbxUWFjDj138ARfEI4ZxV9pwAAAAASUVORK5CYII="
)
IDENTITY_QUAT = [0.0, 0.0, 0.0, 1.0]


def example_messages() -> dict[str, Message]:
    """{type: message} for every v1 message type."""
    # Quarter-steps keep every float exact in float32.
    joints = [round(0.25 * (i % 8) - 1.0, 2) for i in range(66)]
    body_pose = [0.0] * 63
    body_pose[3 * 3 + 0] = 0.5  # left knee (SMPL joint 4 -> body_pose index 3) bent 0.5 rad about x
    # joints 1..21, each from its parent: near the mean body's, in 1/16 m steps
    bone_lengths_m = [0.125] * 3 + [0.375] * 2 + [0.125] + [0.4375] * 2 + [0.0625] + [0.125] * 2 + [0.1875]
    bone_lengths_m += [0.125] * 5 + [0.25] * 4
    return {
        "hello": Hello(role="input", session="room-1", model="egoposevr", token="s3cret", client="unity/1.0"),
        "hmd": Hmd(
            seq=42,
            t_us=1_000_000,
            head=[0.0, 1.625, 0.0, *IDENTITY_QUAT],
            left=[-0.25, 1.0, -0.25, 0.0, 0.0, 0.0, 1.0],
            right=[0.25, 1.0, -0.25, 0.0, 0.7071067690849304, 0.0, 0.7071067690849304],
            valid=[True, True, False],
        ),
        "rgbd": Rgbd(
            seq=7,
            t_us=1_000_500,
            width=4,
            height=2,
            intrinsics=[2.0, 2.0, 2.0, 1.0],
            rgb=EXAMPLE_JPEG,
            depth=EXAMPLE_DEPTH_PNG,
            # Camera 6.25 cm below and 12.5 cm ahead of the head device, optical axis straight down, image top
            # towards the face's forward direction (OpenCV camera axes: x right, y down, z along the view).
            cam_from_head=[
                1.0,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                1.0,
                0.125,
                0.0,
                -1.0,
                0.0,
                -0.0625,
                0.0,
                0.0,
                0.0,
                1.0,
            ],
        ),
        "select_model": SelectModel(model="hmd"),
        "list_models": ListModels(),
        "ping": Ping(nonce=3, t_us=1_000_900),
        "welcome": Welcome(
            session="room-1",
            role="input",
            server="egoposevr/0.1.0",
            model="egoposevr",
            models=["egoposevr", "hmd"],
        ),
        "pose": Pose(
            seq=42,
            t_us=1_000_000,
            model="egoposevr",
            global_orient=[0.0, 3.125, 0.0],
            body_pose=body_pose,
            transl=[0.0, 0.875, 0.0],
            joints=joints,
            timing_us={"features": 40, "fusion": 900, "fk_filter": 30, "kpo": 250, "total": 1300},
            planted=[True, False],
            floor_y_m=0.0,
        ),
        "models": Models(
            active="egoposevr",
            models=[
                ModelInfo(
                    name="egoposevr",
                    inputs=["hmd", "rgb", "depth"],
                    description="HMD + RGB-D fusion with KPO",
                    sha256="0123456789abcdef" * 4,
                    encoder_sha256="fedcba9876543210" * 4,
                    head_joint_m=[0.0, -0.0234375, 0.0830078125],  # float32-exact, near the bundled value
                ),
                ModelInfo(name="hmd", inputs=["hmd"], description="HMD-only baseline"),
            ],
        ),
        "error": Error(
            code="wrong_length",
            message="hmd.head: expected exactly 7 items, got 6",
            fatal=False,
            seq=43,
            ref=Ref(type="hmd", seq=43),
        ),
        "session": SessionStatus(
            session="room-1", event="input_joined", input=True, model="egoposevr", renders=2
        ),
        "pong": Pong(nonce=3, t_us=1_000_900, server_t_us=5_000_000_123),
        "calibrate": Calibrate(pose="tpose", seconds=2.0),
        "calibration": Calibration(
            status="done",
            pose="tpose",
            message="calibrated: head 1.5 m above the floor, arm span 1.5 m",
            head_height_m=1.5,
            arm_span_m=1.5,
            corrections=[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.25, 0.96875, 0.0, 0.0, -0.25, 0.96875],
        ),
        "set_body": SetBody(bone_lengths_m=bone_lengths_m),
        "get_body": GetBody(),
        "body": Body(bone_lengths_m=bone_lengths_m, given=True, measured=False),
    }


# OpenXR walk-through of PROTOCOL.md §3.3: (VIEW pose, flags), (left grip pose, flags), (right grip pose, flags).
_ALL_FLAGS = 0xF  # ORIENTATION/POSITION, VALID and TRACKED
OPENXR_INPUTS: dict[str, tuple[tuple[list[float], int], ...]] = {
    "openxr-tracked": (
        ([0.0, 1.625, 0.0, 0.0, 0.0, 0.0, 1.0], _ALL_FLAGS),
        ([-0.25, 1.0, -0.25, 0.0, 0.0, 0.0, 1.0], _ALL_FLAGS),
        ([0.25, 1.0, -0.25, 0.0, 0.7071067690849304, 0.0, 0.7071067690849304], 0x3),  # valid, not tracked
    ),
    "openxr-lost-right": (
        ([0.0, 1.625, 0.0, 0.0, 0.0, 0.0, 1.0], _ALL_FLAGS),
        ([-0.25, 1.0, -0.25, 0.0, 0.0, 0.0, 1.0], _ALL_FLAGS),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0x0),  # the runtime lost the controller
    ),
    "openxr-orientation-only": (
        ([0.0, 1.625, 0.0, 0.0, 0.0, 0.0, 1.0], _ALL_FLAGS),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], 0x5),  # 3-DoF: orientation valid and tracked, no position
        ([0.25, 1.0, -0.25, 0.0, 0.7071067690849304, 0.0, 0.7071067690849304], _ALL_FLAGS),
    ),
}


def openxr_examples() -> dict[str, Hmd]:
    """{name: hmd message} for the OpenXR walk-through (``tests/protocol/openxr/<name>.msgpack``)."""
    from .openxr import hmd_from_openxr

    return {
        name: hmd_from_openxr(7, 2_000_000, *inputs)  # type: ignore[arg-type]
        for name, inputs in OPENXR_INPUTS.items()
    }
