"""The web viewer draws the headset and controllers where the rig puts them (no browser needed)."""

import json
import re

import numpy as np

from egoposevr.model.rig import DEFAULT_OFFSETS_M, TRACKED_JOINTS
from egoposevr.server.app import VIEWER_DIR


def test_the_viewer_draws_each_device_at_the_rigs_offset_from_its_joint():
    source = (VIEWER_DIR / "viewer.js").read_text()
    rows = re.findall(r"\{ joint: (\d+), offset: (\[[^\]]*\])", source)
    assert [int(joint) for joint, _ in rows] == list(TRACKED_JOINTS)
    np.testing.assert_allclose([json.loads(offset) for _, offset in rows], DEFAULT_OFFSETS_M)
