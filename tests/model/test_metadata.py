"""Typed configs and metadata: what export writes, the runtime reads back exactly, and refuses clearly."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from egoposevr.model.config import (
    CameraInfo,
    EncoderMetadata,
    FusionConfig,
    ModelMetadata,
    VisualConfig,
    from_properties,
    parse,
    to_properties,
)
from egoposevr.model.runtime.loading import LoadedModel
from egoposevr.model.runtime.procedural import ProceduralModel
from egoposevr.model.weights import model_files

PROTOCOL_MD = Path(__file__).resolve().parents[2] / "PROTOCOL.md"
CAMERA = CameraInfo(
    width=160, height=128, intrinsics=(80.0, 80.0, 79.5, 63.5), hfov_deg=90.0, pitch_down_deg=78.0,
    cam_from_head=tuple(float(i == j) for i in range(4) for j in range(4)),
    depth_units="uint16 millimetres, 0 = no reading", min_depth_m=0.1, max_depth_m=6.0,
)  # fmt: skip


def model_metadata(**changes):
    fields = dict(
        format="1", kind="model", name="m", description="a model", inputs=("hmd", "rgb", "depth"),
        config=FusionConfig(window=20), kpo=True, visual_encoder="visual-rgbd.onnx", joint_names=("pelvis",),
        rig_offsets_m=((0.0, 0.06, 0.11), (0.085, -0.015, 0.015), (-0.085, -0.015, 0.015)),
        training={"steps": 4}, units="metres",
    )  # fmt: skip
    return ModelMetadata(**{**fields, **changes})


def test_metadata_round_trips_through_string_properties():
    meta = model_metadata()
    props = to_properties(meta)
    assert all(isinstance(v, str) for v in props.values())
    assert props["name"] == "m" and props["kpo"] == "true" and json.loads(props["config"])["window"] == 20
    assert from_properties(ModelMetadata, props) == meta
    encoder = EncoderMetadata(
        "1", "visual", "visual-rgbd", VisualConfig(widths=(8, 16)), CAMERA, ("pelvis",), {}, ""
    )
    assert from_properties(EncoderMetadata, to_properties(encoder)) == encoder


def test_a_field_from_a_newer_version_is_refused_by_name():
    props = to_properties(model_metadata())
    props["config"] = json.dumps({**json.loads(props["config"]), "validity_inputs": True})
    with pytest.raises(ValueError, match=r"unknown field 'config.validity_inputs'.*newer"):
        from_properties(ModelMetadata, props)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [("config", '{"window": "long"}', r"config.window"), ("kpo", "maybe", r"'kpo' is not JSON"),
     ("rig_offsets_m", "[[0, 0]]", r"rig_offsets_m"), ("kind", "visual", r"'kind'")],
)  # fmt: skip
def test_wrong_values_name_their_field(key, value, message):
    props = {**to_properties(model_metadata()), key: value}
    with pytest.raises(ValueError, match=message):
        from_properties(ModelMetadata, props)


def test_a_missing_field_is_named():
    props = to_properties(model_metadata())
    del props["visual_encoder"]
    with pytest.raises(ValueError, match=r"'visual_encoder' is missing"):
        from_properties(ModelMetadata, props)


def test_parse_builds_nested_tuples_and_keeps_validation_of_the_dataclass():
    assert parse(VisualConfig, {"widths": [8, 16]}).widths == (8, 16)
    with pytest.raises(ValueError, match="fusion"):
        parse(FusionConfig, {"fusion": "sum"})


def test_every_bundled_model_reads_into_the_types():
    from egoposevr.model.runtime.loading import LoadedModel

    for name, path in model_files().items():
        info = LoadedModel.load(path).info
        assert info.name == name and isinstance(info.config, FusionConfig)
        assert (info.visual_config is None) == (info.camera is None) == (info.encoder is None)


def test_every_bundled_model_describes_itself_as_the_zoo_does():
    """Clients list models by the description in their files; the zoo's text is kept true as nets change."""
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.zoo import ZOO

    for name, path in model_files().items():
        assert LoadedModel.load(path).info.description == ZOO[name].description, name


def test_a_model_file_written_before_the_lean_gate_field_reads_as_without_it():
    """Files exported before ModelMetadata.lean_gate existed have no such property: served without the gate."""
    props = to_properties(model_metadata(lean_gate=True))
    assert props["lean_gate"] == "true" and from_properties(ModelMetadata, props).lean_gate
    del props["lean_gate"]
    assert from_properties(ModelMetadata, props).lean_gate is False


def test_a_model_file_written_before_the_quiet_lift_field_reads_as_without_it():
    """Files exported before ModelMetadata.quiet_lift existed: served without the quiet-head lift."""
    props = to_properties(model_metadata(quiet_lift=True))
    assert props["quiet_lift"] == "true" and from_properties(ModelMetadata, props).quiet_lift
    del props["quiet_lift"]
    assert from_properties(ModelMetadata, props).quiet_lift is False


def test_every_bundled_model_hangs_the_body_from_the_head_joint_protocol_md_states():
    """A client places the served body from PROTOCOL.md's `head` row; each bundled file records its own offset
    (`rig_offsets_m`), so a file moved to another head joint must come with the row that says so."""
    row = next(line for line in PROTOCOL_MD.read_text().splitlines() if line.startswith("| `head` |"))
    stated = re.search(r"for every bundled model ([\d.]+) cm behind and ([\d.]+) cm below", row)
    assert stated, "PROTOCOL.md's head row no longer states one offset for every bundled model"
    behind_m, below_m = (float(cm) / 100 for cm in stated.groups())
    files = model_files()
    assert len(files) >= 7
    heads = {name: LoadedModel.load(path).info.rig_offsets_m[0] for name, path in files.items()}
    heads["procedural"] = np.asarray(ProceduralModel().info.rig_offsets_m[0])
    for name, head in heads.items():
        np.testing.assert_allclose(head, (0.0, below_m, behind_m), atol=1e-6, err_msg=name)
