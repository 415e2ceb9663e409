"""The VMC bridge: Unity-frame conversion, bundle sizes, and a live session forwarded to a real python-osc
receiver that decodes every bundle."""

from __future__ import annotations

import threading

import numpy as np
from loopback import Client, recorded_messages, replay, running_server
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_server import ThreadingOSCUDPServer
from scipy.spatial.transform import Rotation

from egoposevr.cli.main import main
from egoposevr.clients.vmc import MAX_DATAGRAM_BYTES, UNITY_BONES, unity_bones, vmc_bundles


def test_facing_openxr_forward_is_facing_unity_forward():
    yaw_pi = Rotation.from_euler("y", np.pi).as_rotvec()  # SMPL faces +z; this turns it to OpenXR's -z
    bones = dict(
        (name, (pos, quat)) for name, pos, quat in unity_bones(yaw_pi, np.zeros(63), [0.5, 0.9, -2.0])
    )
    hips_pos, hips_quat = bones["Hips"]
    assert np.allclose(
        Rotation.from_quat(hips_quat).as_matrix(), np.eye(3), atol=1e-9
    )  # Unity avatars face +z
    assert np.allclose(hips_pos, [0.5, 0.9, 2.0])  # z mirrored into Unity's world


def test_local_rotations_mirror_across_the_bodys_x_axis():
    body_pose = np.zeros(63)
    body_pose[3 * 17 : 3 * 18] = [0.0, 0.3, 0.0]  # left elbow (joint 18): 0.3 rad about SMPL's y
    body_pose[3 * 3 : 3 * 4] = [0.4, 0.0, 0.0]  # left knee (joint 4): 0.4 rad about x (the hinge)
    bones = {name: quat for name, _, quat in unity_bones(np.zeros(3), body_pose, np.zeros(3))}
    assert np.allclose(Rotation.from_quat(bones["LeftLowerArm"]).as_rotvec(), [0, -0.3, 0])  # y flips
    assert np.allclose(Rotation.from_quat(bones["LeftLowerLeg"]).as_rotvec(), [0.4, 0, 0])  # x stays
    assert np.allclose(Rotation.from_quat(bones["Spine"]).as_rotvec(), 0)


def test_every_bundle_fits_one_datagram_and_decodes():
    rng = np.random.default_rng(0)
    bundles = vmc_bundles(rng.normal(size=3), rng.normal(0, 0.3, 63), [0, 1, 0], t_s=12.5)
    assert all(len(b) <= MAX_DATAGRAM_BYTES for b in bundles)
    messages = [m for b in bundles for m in OscBundle(b)]
    bones = [m.params[0] for m in messages if m.address == "/VMC/Ext/Bone/Pos"]
    assert bones == list(UNITY_BONES)
    assert {m.address for m in messages} >= {"/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos"}
    assert all(len(m.params) == 8 for m in messages if m.address.endswith("/Pos"))


class RecordingOSCServer(ThreadingOSCUDPServer):
    """python-osc's own UDP server, which also remembers each datagram's size."""

    sizes: list[int]

    def verify_request(self, request, client_address):
        self.sizes.append(len(request[0]))
        return super().verify_request(request, client_address)


def test_a_live_session_reaches_a_real_osc_receiver(capsys):
    received: list[tuple[str, tuple]] = []
    dispatcher = Dispatcher()
    dispatcher.set_default_handler(lambda address, *args: received.append((address, args)))
    receiver = RecordingOSCServer(("127.0.0.1", 0), dispatcher)
    receiver.sizes = []
    threading.Thread(target=receiver.serve_forever, daemon=True).start()
    port = receiver.server_address[1]
    try:
        with running_server() as server, Client(server.url, "vmc") as headset:
            headset.hello("input", "vmc", model="hmd")
            headset.collect()
            streamer = threading.Thread(
                target=replay, args=(headset, recorded_messages("walk-0000", limit=300))
            )
            streamer.start()
            code = main(
                [
                    "bridge",
                    "vmc",
                    "--url",
                    server.url,
                    "--session",
                    "vmc",
                    "--to",
                    f"127.0.0.1:{port}",
                    "--seconds",
                    "2",
                ]
            )
            streamer.join()
    finally:
        receiver.shutdown()
        receiver.server_close()
    assert code == 0 and "poses as" in capsys.readouterr().out
    bones = [args for address, args in received if address == "/VMC/Ext/Bone/Pos"]
    assert len(bones) >= 22 * 50  # at least 50 poses arrived whole
    assert {b[0] for b in bones} == set(UNITY_BONES)
    quats = np.array([b[4:8] for b in bones])
    assert np.allclose(np.linalg.norm(quats, axis=1), 1, atol=1e-4)
    assert receiver.sizes and max(receiver.sizes) <= MAX_DATAGRAM_BYTES


def test_bridge_refuses_a_bad_destination(capsys):
    assert main(["bridge", "vmc", "--session", "x", "--to", "nowhere"]) == 2
    assert "HOST:PORT" in capsys.readouterr().err
