"""The Unity package's C# core (clients/unity/Runtime/Core), compiled with Mono and run against the golden
fixtures, numbers computed here, and a real server on loopback. Skipped, saying so, where Mono is missing
(Debian: apt-get install mono-devel; .ci/run installs it)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest
from cameraimages import camera_images
from loopback import running_server
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import PARENTS, forward_kinematics, rest_offsets
from egoposevr.protocol.examples import OPENXR_INPUTS
from egoposevr.protocol.openxr import ORIENTATION_VALID, POSITION_VALID

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "clients" / "unity"
GOLDEN = ROOT / "tests" / "protocol" / "golden"
OPENXR = ROOT / "tests" / "protocol" / "openxr"
MCS, MONO = shutil.which("mcs"), shutil.which("mono")
pytestmark = pytest.mark.skipif(
    MCS is None or MONO is None, reason="needs Mono (Debian: apt-get install mono-devel)"
)
MIRROR = np.diag([1.0, 1.0, -1.0])  # protocol <-> Unity (PROTOCOL.md §3.1)


@pytest.fixture(scope="module")
def program(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CoreTests.exe built from the package's core and its test program, warnings as errors. The core builds
    without UnityEngine's assemblies: that it compiles here is the check that it needs none."""
    exe = tmp_path_factory.mktemp("unity") / "CoreTests.exe"
    sources = [*sorted((PACKAGE / "Runtime" / "Core").glob("*.cs")), PACKAGE / "Tests~" / "CoreTests.cs"]
    build = [
        MCS,
        "-langversion:7.2",
        "-warnaserror+",
        "-r:System.Net.Http",
        f"-out:{exe}",
        *map(str, sources),
    ]
    result = subprocess.run(build, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    return exe


def run(program: Path, *args: str, timeout: float = 120) -> str:
    result = subprocess.run([MONO, str(program), *args], capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def test_unity_layer_and_sample_compile_against_unity_signatures(tmp_path: Path) -> None:
    """Runtime/Unity and the sample, built against a stub of the UnityEngine API they call (Tests~): catches a
    typo or a wrong type here; what the calls do in Unity is not tested."""
    sources = [
        *sorted((PACKAGE / "Runtime").rglob("*.cs")),
        *sorted((PACKAGE / "Samples~").rglob("*.cs")),
        PACKAGE / "Tests~" / "UnityEngineStub.cs",
    ]
    build = [MCS, "-langversion:7.2", "-warnaserror+", "-target:library", "-r:System.Net.Http"]
    result = subprocess.run(
        [*build, f"-out:{tmp_path / 'unity.dll'}", *map(str, sources)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_golden_fixtures_round_trip_byte_for_byte(program: Path) -> None:
    assert run(program, "golden", str(GOLDEN), str(OPENXR)).startswith("ok: ")


def test_body_keeper_asks_keeps_forgets_and_stores(program: Path) -> None:
    """BodyKeeper (PROTOCOL.md §4.2): asks while nothing is kept, keeps only a measured estimate, forgets a body the
    server refuses, and its text store reads back exactly or, damaged, as no body."""
    assert run(program, "keeper").startswith("ok: ")


def test_planted_feet_are_pinned_by_a_two_bone_reach(program: Path) -> None:
    """FootPins (PROTOCOL.md §planted-feet): the reach puts a foot on a target within reach, bones kept, and
    straightens the leg towards one beyond; pins follow `planted`, a pause and a hip out of reach."""
    assert run(program, "pins").startswith("ok: ")


def _unity_device(pose: list[float], flags: int) -> dict[str, object]:
    """What Unity's XR input reports for an OpenXR location: the pose mirrored, and InputTrackingState bits."""
    state = (1 if flags & POSITION_VALID else 0) | (2 if flags & ORIENTATION_VALID else 0)
    x, y, z, qx, qy, qz, qw = pose
    return {"position": [x, y, -z], "rotation": [-qx, -qy, qz, qw], "state": state}


def _random_poses(rng: np.random.Generator, n: int) -> list[dict[str, list[float]]]:
    poses = []
    for _ in range(n):
        global_orient = Rotation.from_euler("yx", [rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3)])
        poses.append(
            {
                "global_orient": global_orient.as_rotvec().tolist(),
                "body_pose": rng.uniform(-0.6, 0.6, 63).tolist(),
                "transl": [rng.uniform(-1, 1), rng.uniform(0.8, 1.0), rng.uniform(-1, 1)],
            }
        )
    return poses


@pytest.fixture(scope="module")
def converted(program: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict]:
    """(inputs, outputs) of the C# conversions: OpenXR cases, random SMPL poses, a random avatar T-pose."""
    rng = np.random.default_rng(7)
    inputs = {
        "openxr": {
            name: [_unity_device(pose, flags) for pose, flags in devices]
            for name, devices in OPENXR_INPUTS.items()
        },
        "poses": _random_poses(rng, 8),
        # Every avatar rig rests its bones its own way: random rest rotations stand for any of them.
        "tpose_world": Rotation.random(22, random_state=3).as_quat().ravel().tolist(),
    }
    folder = tmp_path_factory.mktemp("convert")
    (folder / "in.msgpack").write_bytes(msgpack.packb(inputs))
    run(program, "convert", str(folder / "in.msgpack"), str(folder / "out.msgpack"))
    return inputs, msgpack.unpackb((folder / "out.msgpack").read_bytes())


def test_unity_xr_poses_give_the_openxr_walkthroughs_bytes(converted: tuple[dict, dict]) -> None:
    """PROTOCOL.md §3.3's three worked examples, reached from what Unity reports instead of from OpenXR."""
    _, out = converted
    for name in OPENXR_INPUTS:
        assert out["openxr"][name] == (OPENXR / f"{name}.msgpack").read_bytes(), name


def test_world_rotations_match_smpl_chain(converted: tuple[dict, dict]) -> None:
    inputs, out = converted
    for pose, world in zip(inputs["poses"], out["world"], strict=True):
        got = Rotation.from_quat(np.reshape(world, (22, 4)))
        _, expected = forward_kinematics(_smpl_world_local(pose), np.zeros(3))
        assert (got * Rotation.from_matrix(expected).inv()).magnitude().max() < 1e-5


def test_retargeted_avatar_reproduces_the_served_joints(converted: tuple[dict, dict]) -> None:
    """An avatar whose bones rest at arbitrary rotations, posed by the C# world rotations, puts its joints
    where SMPL FK puts the served ones (mirrored into Unity's frame): rest-pose differences are handled."""
    inputs, out = converted
    tpose = Rotation.from_quat(np.reshape(inputs["tpose_world"], (22, 4)))
    # The avatar's T-pose faces Unity's +Z: SMPL's rest (facing the protocol's +Z) mirrored, turned 180°.
    yaw180 = Rotation.from_euler("y", np.pi).as_matrix()
    offsets_unity = (yaw180 @ MIRROR @ rest_offsets().T).T
    parents = np.maximum(PARENTS, 0)
    local_offsets = tpose[parents].inv().apply(offsets_unity)  # each bone's offset in its parent's rest frame
    for pose, avatar, hips in zip(inputs["poses"], out["avatar"], out["hips"], strict=True):
        world = Rotation.from_quat(np.reshape(avatar, (22, 4)))
        joints = np.zeros((22, 3))
        for j in range(1, 22):
            joints[j] = joints[PARENTS[j]] + world[PARENTS[j]].apply(local_offsets[j])
        served, _ = forward_kinematics(_smpl_world_local(pose), np.zeros(3))
        np.testing.assert_allclose(joints, served @ MIRROR, atol=1e-5)
        transl = np.array(pose["transl"])
        np.testing.assert_allclose(hips, [transl[0], 0.9 * transl[1], -transl[2]], atol=1e-6)


def _smpl_world_local(pose: dict[str, list[float]]) -> np.ndarray:
    """(22, 3, 3) local rotations (the pelvis's global) for skeleton.forward_kinematics."""
    rotvecs = np.concatenate([pose["global_orient"], pose["body_pose"]]).reshape(22, 3)
    return Rotation.from_rotvec(rotvecs).as_matrix()


def test_live_session_against_a_real_server(program: Path, tmp_path: Path) -> None:
    rgb, depth = camera_images(tmp_path)
    with running_server() as server:
        out = run(program, "live", server.url, "unity-live", str(rgb), str(depth))
    assert "ok: " in out, out


def test_reconnects_and_resumes_the_model(program: Path) -> None:
    command = [MONO, str(program), "reconnect"]
    with running_server() as server:
        port = server.server.port
        with subprocess.Popen(
            [*command, server.url, "unity-resume"], stdout=subprocess.PIPE, text=True
        ) as child:
            assert child.stdout is not None
            try:
                assert child.stdout.readline().strip() == "up"
                server.stop()
                assert child.stdout.readline().strip() == "down"
                with running_server(port=port):
                    out = child.stdout.read()
                    assert child.wait(60) == 0, out
            finally:
                if child.poll() is None:
                    child.kill()
    assert "ok: " in out, out
