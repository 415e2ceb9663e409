"""The web viewer in real headless Chromium: it joins a session, poses arrive, the avatar moves, the model
switcher works. Driven over the DevTools protocol with a plain WebSocket (no extra browser library)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import shutil
import socket
import subprocess
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from loopback import RECORDINGS, Client, running_server
from scipy.spatial.transform import Rotation
from websockets.sync.client import connect

from egoposevr.clients.avatar import VRM_BONES
from egoposevr.clients.replay import Recording, Replayer
from egoposevr.model.provenance import file_digest
from egoposevr.model.runtime.body import bone_lengths_m
from egoposevr.model.skeleton import forward_kinematics, rest_offsets
from egoposevr.model.weights import WEIGHTS_DIR
from egoposevr.server.app import VIEWER_DIR

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (Debian: apt-get install chromium)")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--no-first-run", "--window-size=800,600"]  # fmt: skip


class Browser:
    """One headless Chromium page, driven over the DevTools protocol."""

    def __init__(self, url: str, profile: str) -> None:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        args = [CHROMIUM, *FLAGS, f"--remote-debugging-port={port}", f"--user-data-dir={profile}", url]
        self.process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 30
        while True:
            with contextlib.suppress(OSError, StopIteration, ValueError):
                pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2))
                target = next(p for p in pages if p["type"] == "page")
                break
            assert time.monotonic() < deadline, "Chromium did not start"
            time.sleep(0.1)
        self.ws = connect(target["webSocketDebuggerUrl"], max_size=None, open_timeout=10, legacy=True)
        self._id = 0

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == self._id:
                assert "error" not in reply, reply
                return reply["result"]

    def evaluate(self, expression: str) -> Any:
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def state(self) -> dict[str, Any]:
        return json.loads(self.evaluate("JSON.stringify(window.viewerState || null)") or "null") or {}

    def wait_for(self, predicate: Any, timeout: float = 20.0) -> dict[str, Any]:
        return _poll(self.state, predicate, timeout, "viewer state never matched")

    def wait_for_text(self, element_id: str, text: str, timeout: float = 10.0) -> None:
        """Until the element's text holds ``text``. The page draws its text on the next animation frame after
        the state changes, which a loaded machine can delay past a state read."""

        def shown() -> str:
            return self.evaluate(f'document.getElementById("{element_id}").textContent')

        _poll(shown, lambda now: text in now, timeout, f"#{element_id} never showed {text!r}")

    def screenshot(self) -> np.ndarray:
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.ws.close()
        self.process.terminate()
        self.process.wait(10)


def _poll(read: Any, done: Any, timeout: float, failure: str) -> Any:
    """read() every 0.1 s until done(value) -> that value; fails with ``failure`` and the last value."""
    deadline = time.monotonic() + timeout
    while not done(value := read()):
        assert time.monotonic() < deadline, f"{failure}: {value!r}"
        time.sleep(0.1)
    return value


@contextlib.contextmanager
def streaming_headset(server: Any, session: str) -> Iterator[None]:
    """A headset replaying a recording (with truth) on loop until the block ends."""
    replayer = Replayer(Recording.load(RECORDINGS / "walk-0000.egrec"), server.url, session, "hmd", loop=True)

    def run() -> None:  # the mock headset sends the recorded truth too
        asyncio.run(replayer.run())

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        replayer.stop()
        thread.join(10)


def test_the_viewer_shows_the_avatar_moving_and_switches_models(tmp_path):
    with running_server() as server, streaming_headset(server, "walk"):
        browser = Browser(f"{server.http}/viewer/?session=walk", str(tmp_path / "profile"))
        try:
            state = browser.wait_for(lambda s: s.get("poses", 0) > 30)
            assert state["connected"] and state["session"] == "walk" and state["renderer"] in ("webgl", "2d")
            assert state["truthSeen"] and state["serverMs"] > 0 and state["fps"] > 10
            assert "walk" in state["sessions"] and "egoposevr" in state["models"]
            assert state["headset"] is True  # told by the session status messages
            assert state["planted"] is None  # hmd plants no feet (§planted-feet) ...
            browser.wait_for_text("hud", "feet n/a")  # ... and the HUD says so
            title = browser.evaluate('document.querySelector("#model option[value=egoposevr]").title')
            assert title.endswith(
                f"sha256 {file_digest(WEIGHTS_DIR / 'egoposevr.onnx')[:12]}"
            )  # which weights
            assert np.allclose(state["headJoints"]["egoposevr"], [0.0, -0.024, 0.083])  # §model-head-joint
            first = browser.screenshot()
            time.sleep(0.8)
            second = browser.screenshot()
            stage = slice(40, first.shape[0] - 30)  # between the header and the HUD line
            moved = np.abs(first[stage].astype(int) - second[stage].astype(int)).sum(-1) > 40
            xs = np.nonzero(moved)[1]
            assert len(xs) > 300, "the avatar did not move between screenshots"
            assert first.shape[1] * 0.2 < np.median(xs) < first.shape[1] * 0.8  # where the avatar stands
            browser.evaluate('(() => { const s = document.getElementById("model"); s.value = "egoposevr";'
                             ' s.dispatchEvent(new Event("change")); })()')  # fmt: skip
            state = browser.wait_for(lambda s: s.get("model") == "egoposevr" and s.get("planted") is not None)
            assert len(state["planted"]) == 2  # egoposevr says which feet it holds down
            browser.wait_for_text("hud", "feet L ")
            # The calibrate button asks for a T-pose; a walking recording is not one, and the page says so.
            browser.evaluate('document.getElementById("calibrate").click()')
            state = browser.wait_for(
                lambda s: (s.get("calibration") or {}).get("status") == "failed", timeout=20
            )
            assert state["calibration"]["message"]  # why, for the operator
            browser.wait_for_text("status", "calibration failed")
        finally:
            browser.close()


def _known_pose() -> tuple[dict[str, list[float]], np.ndarray]:
    """A pose served for a body with 10 % longer bones than the mannequin, and its (22, 3, 3) local rotations."""
    rng = np.random.default_rng(5)
    rotvecs = np.vstack([Rotation.from_euler("yx", [2.5, 0.2]).as_rotvec(), rng.uniform(-0.5, 0.5, (21, 3))])
    local = Rotation.from_rotvec(rotvecs).as_matrix()
    transl = np.array([0.3, 0.95, -0.2])
    joints, _ = forward_kinematics(local, transl, rest_offsets(np.full(22, 1.1)))
    pose = {"global_orient": rotvecs[0].tolist(), "body_pose": rotvecs[1:].ravel().tolist(),
            "transl": transl.tolist(), "joints": joints.ravel().tolist()}  # fmt: skip
    return pose, local


DROP_FILE = """(async (name, bytes) => {
  const data = new DataTransfer();
  data.items.add(new File([bytes], name));
  document.getElementById("stage").dispatchEvent(new DragEvent("drop", {dataTransfer: data, bubbles: true, cancelable: true}));
})"""


def test_the_avatar_follows_a_known_pose_and_a_dropped_vrm_replaces_it(tmp_path):
    """The skinned avatar's own bones land where FK of the served rotations on the avatar's skeleton puts them
    (hips height scaled to its legs), read back from the page; a .vrm dropped on the page replaces it, and a
    broken one leaves it and says why."""
    with running_server() as server:
        browser = Browser(f"{server.http}/viewer/", str(tmp_path / "profile"))
        try:
            state = browser.wait_for(lambda s: (s.get("avatar") or {}).get("loaded"))
            assert state["avatar"]["name"] == "mannequin.vrm" and state["renderer"] == "webgl"
            pose, local = _known_pose()
            bones = json.loads(
                browser.evaluate(f"JSON.stringify(window.viewerAvatar.pose({json.dumps(pose)}))")
            )
            served_leg = sum(np.linalg.norm(np.subtract(*np.reshape(pose["joints"], (22, 3))[[a, b]]))
                             for a, b in ((1, 4), (4, 7)))  # fmt: skip
            scale = browser.evaluate("window.viewerAvatar.legM()") / served_leg
            root = np.multiply(pose["transl"], [1.0, scale, 1.0])
            expected, _ = forward_kinematics(
                local, root, rest_offsets()
            )  # the mannequin's skeleton is SMPL's rest
            for j, bone in enumerate(VRM_BONES):
                np.testing.assert_allclose(bones[bone], expected[j], atol=2e-3, err_msg=bone)
            _planted_feet_stay(browser, pose, expected)
            vrm = (Path(VIEWER_DIR) / "avatar" / "mannequin.vrm").read_bytes()
            as_js = f"new Uint8Array({json.dumps(list(vrm))})"
            browser.evaluate(f'{DROP_FILE}("mine.vrm", {as_js})')
            browser.wait_for(lambda s: (s.get("avatar") or {}).get("name") == "mine.vrm")
            browser.evaluate(f'{DROP_FILE}("broken.vrm", new Uint8Array([1, 2, 3]))')
            state = browser.wait_for(lambda s: (s.get("avatar") or {}).get("error"))
            assert state["avatar"]["name"] == "mine.vrm" and state["avatar"]["error"].startswith("broken.vrm")
        finally:
            browser.close()


def _planted_feet_stay(browser: Browser, pose: dict, unpinned: np.ndarray) -> None:
    """The avatar's planted feet (PROTOCOL.md §planted-feet) stay where they landed while the hips move over
    them, whatever the avatar's proportions; a foot let go follows the pose again. ``unpinned``: the avatar's
    joints (J, 3) for ``pose`` as the rotations alone place them."""

    def posed(**change: object) -> dict[str, np.ndarray]:
        bones = browser.evaluate(f"JSON.stringify(window.viewerAvatar.pose({json.dumps(pose | change)}))")
        return {bone: np.array(at) for bone, at in json.loads(bones).items()}

    landed = posed(planted=[True, True])
    np.testing.assert_allclose(landed["leftFoot"], unpinned[7], atol=2e-3)  # pinned where it stood
    moved = np.add(pose["transl"], [0.06, 0.0, -0.04]).tolist()  # the hips move, the rotations stay
    pinned = posed(transl=moved, planted=[True, True])
    np.testing.assert_allclose(pinned["hips"] - landed["hips"], [0.06, 0.0, -0.04], atol=2e-3)
    for foot in ("leftFoot", "rightFoot"):  # the legs bend instead
        np.testing.assert_allclose(pinned[foot], landed[foot], atol=5e-3, err_msg=foot)
    left_free = posed(transl=moved, planted=[False, True])
    np.testing.assert_allclose(left_free["leftFoot"], unpinned[7] + [0.06, 0.0, -0.04], atol=2e-3)
    np.testing.assert_allclose(left_free["rightFoot"], landed["rightFoot"], atol=5e-3)
    posed(planted=None)  # no planted feet: every pin let go

    # Standing straight, the hips come down over planted feet: the knees bend to the body's front (+z here).
    rest, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.array([0.0, 0.95, 0.0]), rest_offsets()
    )
    straight = {"global_orient": [0.0] * 3, "body_pose": [0.0] * 63, "transl": [0.0, 0.95, 0.0],
                "joints": rest.ravel().tolist(), "planted": [True, True]}  # fmt: skip
    stood = posed(**straight)
    crouched = posed(**(straight | {"transl": [0.0, 0.9, 0.0]}))
    for knee, foot in (("leftLowerLeg", "leftFoot"), ("rightLowerLeg", "rightFoot")):
        assert crouched[knee][2] - stood[knee][2] > 0.05, knee  # forward ...
        assert abs(crouched[knee][0] - stood[knee][0]) < 0.03, knee  # ... not out
        np.testing.assert_allclose(crouched[foot], stood[foot], atol=5e-3, err_msg=foot)
    posed(planted=None)


def test_the_viewer_is_served_offline_with_its_vendored_libraries():
    with running_server() as server:
        for path in ("/viewer/", "/viewer/viewer.js", "/viewer/vendor/three/three.module.js",
                     "/viewer/vendor/three/three.core.js", "/viewer/vendor/msgpack/msgpack.min.js",
                     "/viewer/vendor/three/LICENSE", "/viewer/vendor/msgpack/LICENSE", "/viewer/avatar.js",
                     "/viewer/vendor/three/addons/loaders/GLTFLoader.js", "/viewer/vendor/three-vrm/LICENSE",
                     "/viewer/vendor/three-vrm/three-vrm.module.min.js", "/viewer/avatar/README.md"):  # fmt: skip
            status, body = server.get(path)
            assert status == 200 and body, path
        with urllib.request.urlopen(f"{server.http}/viewer/avatar/mannequin.vrm", timeout=5) as reply:
            assert reply.headers["Content-Type"] == "model/gltf-binary" and reply.read(4) == b"glTF"
        assert "http" not in server.get("/viewer/")[1].replace("http-equiv", "")  # no CDN links
        assert server.get("/viewer/../server/app.py")[0] == 404
        assert server.get("/viewer/nope.js")[0] == 404
        with Client(server.url, "listed") as headset:
            headset.hello("input", "listed")
            sessions = json.loads(server.get("/api/sessions")[1])
        assert {"session": "listed", "model": "egoposevr", "input": True, "viewers": 0} in sessions


def test_the_viewer_keeps_a_wearers_body_and_gives_it_back(tmp_path):
    """PROTOCOL.md §4.2 from the operator's viewer: a body is kept under the wearer's name only when it is worth
    keeping, given back to the session (the headset hears it), refused bodies and damaged stores say so, and
    "estimate body" gives the estimate back."""
    known = bone_lengths_m(np.full(22, 0.9))
    with running_server() as server, Client(server.url, "wearer") as headset:
        headset.hello("input", "wearer", model="procedural")
        browser = Browser(f"{server.http}/viewer/?session=wearer", str(tmp_path / "profile"))
        try:
            browser.wait_for(lambda s: s.get("connected"))

            def press(button: str, wearer: str | None = None) -> str:
                if wearer is not None:
                    browser.evaluate(f'document.getElementById("wearer").value = {json.dumps(wearer)}')
                browser.evaluate("window.viewerState.bodyNote = null")
                browser.evaluate(f'document.getElementById("{button}").click()')
                return browser.wait_for(lambda s: s.get("bodyNote"))["bodyNote"]

            def store(wearer: str, text: str) -> None:
                browser.evaluate(
                    f"localStorage.setItem({json.dumps('egoposevr.body.' + wearer)}, {json.dumps(text)})"
                )

            def stored(wearer: str) -> Any:
                return json.loads(
                    browser.evaluate(f"localStorage.getItem({json.dumps('egoposevr.body.' + wearer)})")
                    or "null"
                )

            assert press("keepBody", "") == "name the wearer first"
            assert press("keepBody", "ann").startswith("not kept: the server has not measured ann")
            assert not headset.recv_type("body").given and stored("ann") is None  # an estimate from nothing
            assert press("giveBody") == "no body kept for ann"

            store("ann", json.dumps({"bone_lengths_m": known.tolist()}))
            assert press("giveBody") == "gave ann's body"
            given = headset.recv_type("body")
            assert given.given and np.allclose(given.bone_lengths_m, known, atol=1e-6)
            browser.wait_for(lambda s: (s.get("body") or {}).get("given"))
            browser.wait_for_text("status", "gave ann's body")
            assert press("keepBody", "carol") == "body kept for carol"  # a given body is worth keeping
            assert np.allclose(stored("carol")["bone_lengths_m"], known, atol=1e-9)

            store("bob", '{"bone_lengths_m": [0.2, "x"')  # a damaged store reads as none kept
            assert press("giveBody", "bob") == "no body kept for bob"
            giant = known.copy()
            giant[4] = 1.0  # a 1 m shin: within the wire's range, not a body's
            store("dave", json.dumps({"bone_lengths_m": giant.tolist()}))
            press("giveBody", "dave")  # "gave dave's body", soon replaced by the refusal
            note = browser.wait_for(lambda s: (s.get("bodyNote") or "").startswith("body refused"))[
                "bodyNote"
            ]
            assert "bone 5" in note
            assert press("estimateBody") == "the server estimates the body"
            # the headset heard carol's get_body answered first, then the estimate
            assert [headset.recv_type("body").given for _ in range(2)] == [True, False]
        finally:
            browser.close()
