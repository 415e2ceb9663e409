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
from typing import Any

import cv2
import numpy as np
import pytest
from loopback import RECORDINGS, Client, running_server
from websockets.sync.client import connect

from egoposevr.clients.replay import Recording, Replayer

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
        deadline = time.monotonic() + timeout
        while not predicate(state := self.state()):
            assert time.monotonic() < deadline, f"viewer state never matched: {state}"
            time.sleep(0.1)
        return state

    def screenshot(self) -> np.ndarray:
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.ws.close()
        self.process.terminate()
        self.process.wait(10)


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
            first = browser.screenshot()
            time.sleep(0.8)
            second = browser.screenshot()
            stage = slice(40, first.shape[0] - 30)  # between the header and the HUD line
            moved = np.abs(first[stage].astype(int) - second[stage].astype(int)).sum(-1) > 40
            xs = np.nonzero(moved)[1]
            assert len(xs) > 300, "the avatar did not move between screenshots"
            assert first.shape[1] * 0.2 < np.median(xs) < first.shape[1] * 0.8  # where the avatar stands
            browser.evaluate('(() => { const s = document.getElementById("model"); s.value = "hmd-rgbd";'
                             ' s.dispatchEvent(new Event("change")); })()')  # fmt: skip
            browser.wait_for(lambda s: s.get("model") == "hmd-rgbd")
            # The calibrate button asks for a T-pose; a walking recording is not one, and the page says so.
            browser.evaluate('document.getElementById("calibrate").click()')
            state = browser.wait_for(
                lambda s: (s.get("calibration") or {}).get("status") == "failed", timeout=20
            )
            assert state["calibration"]["message"]  # why, for the operator
            assert "calibration failed" in browser.evaluate('document.getElementById("status").textContent')
        finally:
            browser.close()


def test_the_viewer_is_served_offline_with_its_vendored_libraries():
    with running_server() as server:
        for path in ("/viewer/", "/viewer/viewer.js", "/viewer/vendor/three/three.module.js",
                     "/viewer/vendor/three/three.core.js", "/viewer/vendor/msgpack/msgpack.min.js",
                     "/viewer/vendor/three/LICENSE", "/viewer/vendor/msgpack/LICENSE"):  # fmt: skip
            status, body = server.get(path)
            assert status == 200 and body, path
        assert "http" not in server.get("/viewer/")[1].replace("http-equiv", "")  # no CDN links
        assert server.get("/viewer/../server/app.py")[0] == 404
        assert server.get("/viewer/nope.js")[0] == 404
        with Client(server.url, "listed") as headset:
            headset.hello("input", "listed")
            sessions = json.loads(server.get("/api/sessions")[1])
        assert {"session": "listed", "model": "egoposevr", "input": True, "viewers": 0} in sessions
