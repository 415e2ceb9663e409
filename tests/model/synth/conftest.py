"""Small synthetic inputs the synthesis tests share (nothing from ../shared)."""

import numpy as np
import pytest

from egoposevr.model.synth.headset import CameraModel
from egoposevr.model.synth.pipeline import SynthConfig, synthesize_sequence
from egoposevr.model.synth.procedural import generate
from egoposevr.model.synth.render import Renderer

SMALL_CAMERA = CameraModel(width=96, height=80)


@pytest.fixture(scope="session")
def small_config() -> SynthConfig:
    return SynthConfig(hmd_rate_hz=72.0, camera=SMALL_CAMERA)


@pytest.fixture(scope="session")
def small_renderer() -> Renderer:
    return Renderer(SMALL_CAMERA)


@pytest.fixture(scope="session")
def walk_sequence(small_config, small_renderer):
    rng = np.random.default_rng(7)
    motion = generate("walk", 2.0, 60.0, rng)
    return synthesize_sequence(motion, small_config, rng, small_renderer)
