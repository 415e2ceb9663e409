"""Export trained checkpoints to the ONNX files the runtime serves (torch + onnx; training side only).

Per zoo entry one **model file** ``<name>.onnx`` (the fusion net over the windows) and, shared by every model
of a modality, one **visual encoder** ``visual-<rgb|rgbd>.onnx`` (per frame, dynamic batch). Each graph
carries what the runtime needs in its metadata (``egoposevr.*`` keys, typed in :mod:`egoposevr.model.config`:
kind, name, config, joint order, units, its visual encoder's file, KPO, training record), so a models folder
is self-describing. Every export is checked against torch on random inputs: the graphs must agree within
``PARITY_TOL``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import shutil
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from google.protobuf.message import DecodeError

from .. import provenance
from ..config import (
    FORMAT_VERSION,
    CameraInfo,
    EncoderMetadata,
    FusionConfig,
    ModelMetadata,
    VisualConfig,
    from_properties,
    parse,
    to_properties,
)
from ..hmd import hmd_input_dim
from ..inputs import VISUAL_TOKEN_DIM
from ..rig import DEFAULT_OFFSETS_M
from ..runtime.body import regressor_path
from ..runtime.loading import ModelError, load_encoder
from ..skeleton import JOINT_NAMES
from ..zoo import ZOO
from .nets.fusion import ContactOutputs, FusionNet, MirrorAveraged, SeedEnsemble
from .nets.visual import KeypointNet
from .train import InitialVisual, InitialWeights, build_net, invocation_record, load_checkpoint

PARITY_TOL = 1e-4
OPSET = 23  # the first with an Attention operator (onnxruntime >= 1.23 runs it)


class _VisualOutputs(torch.nn.Module):
    """The served outputs of the keypoint net: uv (B, J, 2), depth_m (B, J), zeta (B, J)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        uv, depth_m, zeta, _ = self.net(image)
        return uv, depth_m, zeta


def _export(
    module: torch.nn.Module, args: tuple, path: Path, names: tuple[list[str], list[str]], dynamic: dict
) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's own deprecation chatter is not ours to fix
        program = torch.onnx.export(
            module, args, dynamo=True, input_names=names[0], output_names=names[1], dynamic_shapes=dynamic,
            opset_version=OPSET, external_data=False, verbose=False,
        )  # fmt: skip
    program.save(str(path))


def _set_metadata(path: Path, metadata: ModelMetadata | EncoderMetadata) -> None:
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for key, value in to_properties(metadata).items():
        prop = model.metadata_props.add()
        prop.key = f"egoposevr.{key}"
        prop.value = value
    onnx.save(model, str(path))


def _parity(module: torch.nn.Module, path: Path, inputs: dict[str, np.ndarray]) -> float:
    """Largest |torch - onnxruntime| over all outputs."""
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, inputs)
    with torch.no_grad():
        want = module(*(torch.from_numpy(v) for v in inputs.values()))
    want = want if isinstance(want, tuple) else (want,)
    return max(float(np.abs(g - w.numpy()).max()) for g, w in zip(got, want, strict=True))


def _fusion_inputs(cfg: Any, batch: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random fusion-net inputs: hmd (B, T, D) [, visual (B, Tv, 90)] float32."""
    rng = np.random.default_rng(seed)
    dim = hmd_input_dim(cfg.device_validity)
    inputs = {"hmd": rng.normal(size=(batch, cfg.window, dim)).astype(np.float32)}
    if cfg.uses_camera:
        inputs["visual"] = rng.normal(size=(batch, cfg.visual_window, VISUAL_TOKEN_DIM)).astype(np.float32)
    return inputs


def add_batch_axis(path: Path) -> float:
    """Give a fusion graph exported for batch 1 a symbolic batch axis, in place, so that the server can
    run several sessions' windows in one call; metadata and weights are kept. Returns the largest
    difference between a batch of 8 and the same 8 rows run one by one by the original graph.

    The exporter bakes the batch size into each Reshape's target shape; a leading 1 becomes -1 (infer).
    Raises ValueError for a graph where that would be wrong (a Reshape whose target already infers an axis
    or does not start with the batch) or whose batched outputs disagree with the original's.
    """
    original = onnx.load(str(path))
    model = onnx.load(str(path))
    graph = model.graph
    first_dims = [v.type.tensor_type.shape.dim[0] for v in [*graph.input, *graph.output]]
    if all(d.dim_param for d in first_dims):
        return 0.0  # already batched
    initializers = {i.name: i for i in graph.initializer}
    for node in graph.node:
        if node.op_type != "Reshape":
            continue
        shape = (
            onnx.numpy_helper.to_array(initializers[node.input[1]]) if node.input[1] in initializers else None
        )
        if shape is None:
            raise ValueError(f"{path}: Reshape {node.name} has a computed shape; re-export it instead")
        if shape[0] == -1:
            continue
        if shape[0] != 1 or -1 in shape:
            raise ValueError(f"{path}: Reshape {node.name} to {shape.tolist()} does not start with the batch")
        shape = shape.copy()
        shape[0] = -1
        initializers[node.input[1]].CopyFrom(onnx.numpy_helper.from_array(shape, node.input[1]))
    for dim in first_dims:
        dim.ClearField("dim_value")
        dim.dim_param = "batch"
    del graph.value_info[:]  # shapes inferred for batch 1
    onnx.checker.check_model(model)
    worst = _batched_against_single(original, model)
    if worst > PARITY_TOL:
        raise ValueError(f"{path}: batched outputs differ from the original's by {worst:.2e}")
    onnx.save(model, str(path))
    return worst


def _cpu_session(model: onnx.ModelProto) -> ort.InferenceSession:
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])


def _batched_against_single(single: onnx.ModelProto, batched: onnx.ModelProto, batch: int = 8) -> float:
    one, many = _cpu_session(single), _cpu_session(batched)
    rng = np.random.default_rng(0)
    feed = {i.name: rng.normal(size=(batch, *i.shape[1:])).astype(np.float32) for i in one.get_inputs()}
    rows = [one.run(None, {k: v[b : b + 1] for k, v in feed.items()})[0] for b in range(batch)]
    return float(np.abs(many.run(None, feed)[0] - np.concatenate(rows)).max())


_RECORDED_FIELDS = (
    "teachers",
    "teacher_files",
    "init",
    "encoders",
    "keypoints_out_of_fold",
    "blend",
    "runs",
    "ancestors",
)


def training_record(ckpt: dict[str, Any], path: Path | None = None) -> dict[str, Any]:
    """What a model file says of how one net was made: its data (with its digest), steps, seed, time and last
    losses, and where they apply, its teachers, its start (``init``), the encoders its keypoints came from,
    the nets it blends (``blend``, each with its own record), the invocations that ran it (``runs``: the
    provenance module) and the records of the files it started from or read (``ancestors``); with ``path``,
    the checkpoint file and its digest."""
    record = {
        "data": ckpt.get("data"),
        "steps": ckpt["step"],
        "seed": ckpt["train_config"]["seed"],
        "train_seconds": round(ckpt["train_seconds"], 1),
        "final_losses": ckpt["history"][-1] if ckpt["history"] else {},
    } | {key: ckpt[key] for key in _RECORDED_FIELDS if key in ckpt}
    if path is not None:
        record["checkpoint"] = {"from": str(path), "sha256": provenance.file_digest(path)}
    return record


def export_visual(ckpt_path: Path, out_path: Path, invocation: dict[str, Any] | None = None) -> float:
    """visual-<kind>.pt -> visual-<kind>.onnx; returns the parity error. ``invocation``: the export's record
    (:func:`~.train.invocation_record`, one for every file of an export; None: an unrecorded command)."""
    ckpt = load_checkpoint(ckpt_path)
    module = _VisualOutputs(build_net(ckpt, ckpt_path)).eval()
    cfg = module.net.cfg
    example = torch.zeros(2, cfg.channels, cfg.height, cfg.width)
    batch = torch.export.Dim("batch", min=1, max=64)
    _export(module, (example,), out_path, (["image"], ["uv", "depth_m", "zeta"]), {"image": {0: batch}})
    _set_metadata(out_path, EncoderMetadata(
        format=FORMAT_VERSION, kind="visual", name=ckpt["name"], config=cfg,
        camera=parse(CameraInfo, ckpt["camera"]), joint_names=JOINT_NAMES,
        training=provenance.hoist_ancestors(
            training_record(ckpt, ckpt_path) | {"export": invocation or invocation_record(None)}
        ),
        units="image: RGB - 0.5 (3) [+ depth m / 2] (C, h, w); uv normalised [0, 1] of the image; "
              "depth_m metres along the optical axis; zeta probability in view",
    ))  # fmt: skip
    # A body regressor fitted on the encoder this replaces would describe another network's keypoints.
    regressor_path(out_path).unlink(missing_ok=True)
    rng = np.random.default_rng(0)
    image = rng.uniform(-0.5, 0.5, (3, cfg.channels, cfg.height, cfg.width)).astype(np.float32)
    return _parity(module, out_path, {"image": image})


# Each batch norm of KeypointNet and the convolution before it, whose weights the exporter folded together.
_CONV_BEFORE_NORM = (("stem.1", "stem.0"), ("smooth.1", "smooth.0"), (".bn1", ".conv1"), (".bn2", ".conv2"),
                     (".shortcut.1", ".shortcut.0"))  # fmt: skip


def initial_visual_state(path: Path, cfg: VisualConfig) -> InitialVisual:
    """Where ``egoposevr train --init-visual`` starts an encoder: the weights of the exported encoder
    ``path``, read back into a :class:`KeypointNet` of ``cfg`` (the run's flags). The exporter folded each
    batch norm into its convolution, so each norm comes back as the identity on the stored statistics with
    the folded bias as its shift: exactly the exported function, in eval mode and with the statistics frozen
    (``KeypointNet.freeze_statistics``). Raises ValueError for a file that is not an encoder, one of another
    config, or one whose graph lacks a weight."""
    try:
        _, metadata = load_encoder(path)
    except ModelError as error:
        raise ValueError(str(error)) from error
    if metadata.config != cfg:
        raise ValueError(f"{path}: its encoder is configured otherwise than this run's flags make it")
    arrays = {i.name: onnx.numpy_helper.to_array(i) for i in onnx.load(str(path)).graph.initializer}
    net = KeypointNet(cfg)
    state = {}
    for key, want in net.state_dict().items():
        module, _, field = key.rpartition(".")
        conv = next((module.replace(norm, before) for norm, before in _CONV_BEFORE_NORM if module.endswith(norm)),
                    None)  # fmt: skip
        if conv is None:
            found = arrays.get(f"net.{key}")
        elif field == "weight":
            found = np.ones(want.shape, np.float32)
        elif field == "bias":
            found = arrays.get(f"net.{conv}.weight_bias")
        elif field == "running_mean":
            found = np.zeros(want.shape, np.float32)
        elif field == "running_var":  # (x - 0) / sqrt(var + eps) = x
            found = np.full(want.shape, 1.0 - net.get_submodule(module).eps, np.float32)
        else:  # num_batches_tracked
            found = np.zeros(want.shape, np.int64)
        if found is None or tuple(found.shape) != tuple(want.shape):
            raise ValueError(f"{path}: no weight for {key} {tuple(want.shape)} in the graph")
        state[key] = torch.from_numpy(np.array(found, copy=True))
    return InitialVisual(str(path), state, metadata.training)


def copy_encoder(source: Path, out_path: Path) -> None:
    """An exported encoder (and its body regressor, which is bound to its bytes) -> out_path, unchanged."""
    if source.resolve() == out_path.resolve():
        return
    shutil.copyfile(source, out_path)  # FileNotFoundError names a missing encoder
    if regressor_path(source).exists():
        shutil.copyfile(regressor_path(source), regressor_path(out_path))
    else:
        regressor_path(out_path).unlink(missing_ok=True)  # a stale one would not match these bytes


def export_model(
    name: str,
    runs_dirs: list[Path],
    out_path: Path,
    *,
    lean_gate: bool = False,
    invocation: dict[str, Any] | None = None,
    quiet_lift: bool = False,
) -> float:
    """The zoo entry ``name`` -> ``<name>.onnx`` (its fusion net, or with several runs their
    :class:`SeedEnsemble`); returns the parity error. ``lean_gate``: a model with KPO asks the runtime for
    the lean gate (``ModelMetadata.lean_gate``; the others plant no feet, so it means nothing there), and
    ``quiet_lift`` for the body estimate's quiet-head lift (``ModelMetadata.quiet_lift``; any model that keeps
    a body). ``invocation``: as :func:`export_visual`."""
    entry = ZOO[name]
    paths = [runs_dir / f"fusion-{entry.fusion_name}.pt" for runs_dir in runs_dirs]
    ckpts = [load_checkpoint(path) for path in paths]
    nets = [build_net(ckpt, path) for ckpt, path in zip(ckpts, paths, strict=True)]
    cfg = nets[0].cfg.served
    offsets = _rig_offsets(ckpts, paths)
    module = _served_module(nets)
    records = [training_record(ckpt, path) for ckpt, path in zip(ckpts, paths, strict=True)]
    training = {"ensemble": records} if len(records) > 1 else records[0]
    training = provenance.hoist_ancestors(training | {"export": invocation or invocation_record(None)})
    _export_fusion(module, cfg, out_path)
    _set_metadata(out_path, ModelMetadata(
        format=FORMAT_VERSION, kind="model", name=name, description=entry.description,
        inputs=tuple(entry.inputs), config=cfg, kpo=entry.kpo, lean_gate=lean_gate and entry.kpo,
        quiet_lift=quiet_lift,
        visual_encoder=f"visual-{entry.visual}.onnx" if entry.visual else "",
        joint_names=JOINT_NAMES, rig_offsets_m=offsets, training=training,
        units="hmd: 72-d features (model/hmd.py) in the heading frame [+ 6 of tracking state with "
              "config.device_validity]; visual: tokens (model/inputs.py); "
              "rot6d (B, J, 6): first two matrix columns, row 0 the pelvis in the heading frame, "
              "rows 1.. local rotations; contact (B, 2), with config.contact_head: probability that the "
              "left / right foot is on the floor",
    ))  # fmt: skip
    return max(_parity(module, out_path, _fusion_inputs(cfg, batch)) for batch in (1, 8))


def _rig_offsets(ckpts: list[dict[str, Any]], paths: list[Path]) -> tuple[tuple[float, ...], ...]:
    """The head and grip offsets (3, 3) the checkpoints' nets were trained with, which the runtime must
    anchor them at: a fine-tune's are its starting file's (train_fusion). A checkpoint that does not record
    them is exported with today's defaults, as every export did before they were recorded. Members of one
    graph must share them (raises ValueError)."""
    offsets = {tuple(map(tuple, ckpt.get("rig_offsets_m", DEFAULT_OFFSETS_M.tolist()))) for ckpt in ckpts}
    if len(offsets) > 1:
        names = ", ".join(map(str, paths))
        raise ValueError(f"{names} were trained with different rig offsets: one graph serves one")
    return offsets.pop()


def _served_module(nets: list[FusionNet], mirror_averaged: bool = False) -> torch.nn.Module:
    """The module a model file serves: several nets' :class:`SeedEnsemble`, or one net (with its contact
    probabilities where it has a contact head); with ``mirror_averaged``, that module's
    :class:`MirrorAveraged` (the file's training record says ``mirror_averaged``)."""
    if len(nets) > 1:
        module = SeedEnsemble(nets).eval()
    else:
        module = ContactOutputs(nets[0]).eval() if nets[0].cfg.contact_head else nets[0]
    return MirrorAveraged(module, nets[0].cfg).eval() if mirror_averaged else module


def export_mirror_averaged(path: Path, out_path: Path, command: Sequence[str] | None = None) -> float:
    """A model file -> the same nets served :class:`MirrorAveraged` at ``out_path`` (which may be ``path``),
    its metadata kept but for ``training["mirror_averaged"] = True`` and this invocation (``command``) as
    ``training["mirror_run"]``, a step of its recipe; returns the parity error against
    torch (batches 1 and 8). Raises ValueError for a file that is not an EgoPoseVR model, is
    mirror-averaged already, or whose graph misses parity (``out_path`` is then left as it was)."""
    _, metadata, nets = load_served_nets(path)
    if metadata.training.get("mirror_averaged"):
        raise ValueError(f"{path} is mirror-averaged already")
    module = _served_module(nets, mirror_averaged=True)
    with _replaced_if_checked(out_path, "mirror") as written:  # out_path may be path
        _export_fusion(module, metadata.config, written)
        training = {**metadata.training, "mirror_averaged": True, "mirror_run": invocation_record(command)}
        _set_metadata(written, dataclasses.replace(metadata, training=training))
        worst = max(_parity(module, written, _fusion_inputs(metadata.config, batch)) for batch in (1, 8))
        if worst > PARITY_TOL:
            raise ValueError(f"{path}: the mirror-averaged graph differs from torch by {worst:.2e}")
    return worst


@contextlib.contextmanager
def _replaced_if_checked(path: Path, tag: str) -> Iterator[Path]:
    """A file beside ``path`` for a graph to be written and checked in the block: it replaces ``path`` when
    the block ends, and is removed if the block raises (``path`` is then left as it was)."""
    written = path.with_name(f".{path.name}.{tag}")
    try:
        yield written
        written.replace(path)
    finally:
        written.unlink(missing_ok=True)


def _export_fusion(module: torch.nn.Module, cfg: FusionConfig, out_path: Path) -> None:
    """The served fusion module of nets configured by ``cfg`` -> an ONNX graph with a batch axis (no
    metadata yet)."""
    inputs = _fusion_inputs(cfg, batch=2)
    example = tuple(torch.from_numpy(v) for v in inputs.values())
    batch = torch.export.Dim("batch", min=1, max=64)  # the server batches sessions (server/scheduler.py)
    outputs = ["rot6d", "contact"] if cfg.contact_head else ["rot6d"]
    _export(module, example, out_path, (list(inputs), outputs), {name: {0: batch} for name in inputs})
    model = onnx.load(str(out_path))
    _attention_on_hidden_axis(model.graph, cfg.heads)
    onnx.checker.check_model(model)
    onnx.save(model, str(out_path))


def _attention_on_hidden_axis(graph: onnx.GraphProto, heads: int) -> None:
    """Let each ``Attention`` node read and write (B, L, D) itself (its ``q_num_heads`` and
    ``kv_num_heads`` attributes) instead of the (B, heads, L, D / heads) that the exporter splits its
    inputs into and merges its output back from: four Reshapes and four Transposes fewer per attention,
    the same arithmetic (outputs equal to the bit here), a fifth less time per fusion call. In place; an
    Attention in any other form is left as it is (the re-export test holds the bundled form to it)."""
    made_by = {out: node for node in graph.node for out in node.output}
    read_by: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for name in node.input:
            read_by.setdefault(name, []).append(node)

    def split_heads(name: str) -> str | None:
        """The 3-D tensor behind ``Transpose(0, 2, 1, 3)(Reshape(x))``, or None."""
        transpose = made_by.get(name)
        reshape = made_by.get(transpose.input[0]) if _is_head_swap(transpose) else None
        return reshape.input[0] if reshape is not None and reshape.op_type == "Reshape" else None

    for node in graph.node:
        if node.op_type != "Attention" or len(node.input) != 3 or len(read_by.get(node.output[0], [])) != 1:
            continue
        sources = [split_heads(name) for name in node.input]
        (merge,) = read_by[node.output[0]]
        merged = read_by.get(merge.output[0], [])
        if None in sources or not _is_head_swap(merge) or [n.op_type for n in merged] != ["Reshape"]:
            continue
        node.input[:] = sources
        node.output[0] = merged[0].output[0]  # the merging Reshape's output, which nothing else now makes
        merged[0].output[0] = f"{merged[0].output[0]}__unused"
        node.attribute.extend([onnx.helper.make_attribute(k, heads) for k in ("q_num_heads", "kv_num_heads")])
    _drop_unread(graph)


def _is_head_swap(node: onnx.NodeProto | None) -> bool:
    """A Transpose that swaps the heads and sequence axes of a 4-D tensor."""
    return (
        node is not None
        and node.op_type == "Transpose"
        and [list(a.ints) for a in node.attribute if a.name == "perm"] == [[0, 2, 1, 3]]
    )


def _drop_unread(graph: onnx.GraphProto) -> None:
    """Remove nodes whose outputs nothing reads (repeatedly), then initializers and shape records nothing
    names any more."""
    wanted = {out.name for out in graph.output}
    while True:
        read = wanted | {name for node in graph.node for name in node.input}
        kept = [node for node in graph.node if any(out in read for out in node.output)]
        if len(kept) == len(graph.node):
            break
        graph.ClearField("node")
        graph.node.extend(kept)
    initializers = [i for i in graph.initializer if i.name in read]
    graph.ClearField("initializer")
    graph.initializer.extend(initializers)
    made = {out for node in graph.node for out in node.output}
    shapes = [v for v in graph.value_info if v.name in made]
    graph.ClearField("value_info")
    graph.value_info.extend(shapes)


def _model_file(path: Path) -> tuple[onnx.ModelProto, ModelMetadata]:
    """A model file's graph and metadata; ValueError for a file that is not an EgoPoseVR model."""
    try:
        graph = onnx.load(str(path))
    except (OSError, DecodeError) as error:  # missing, truncated, or not ONNX at all
        raise ValueError(f"{path}: not an ONNX file ({error})") from error
    properties = {p.key.removeprefix("egoposevr."): p.value for p in graph.metadata_props}
    try:
        return graph, from_properties(ModelMetadata, properties)
    except ValueError as error:
        raise ValueError(f"{path}: not an EgoPoseVR model file ({error})") from error


def recorded_offsets(path: Path) -> np.ndarray:
    """(3, 3) the device -> joint offsets the model file ``path``'s nets were trained at (``egoposevr train
    --head-offsets-from``); ValueError for a file that is not an EgoPoseVR model."""
    return np.array(_model_file(path)[1].rig_offsets_m, dtype=np.float64)


def load_served_nets(path: Path) -> tuple[onnx.ModelProto, ModelMetadata, list[FusionNet]]:
    """A model file's graph, its metadata and its fusion nets (one, or each member of its ensemble) holding
    the weights it holds; raises ValueError for a file that is not an EgoPoseVR model or whose weights do
    not fill the nets its config describes."""
    original, metadata = _model_file(path)
    members = len(metadata.training.get("ensemble", [None]))
    nets = [FusionNet(metadata.config).eval() for _ in range(members)]
    module = _served_module(nets, bool(metadata.training.get("mirror_averaged")))
    module.load_state_dict(_state_dict_from_graph(original, module, path))
    # what was read back must serve what the file serves (a shared buffer read as the wrong one would not)
    worst = max(_parity(module, path, _fusion_inputs(metadata.config, batch)) for batch in (1, 2))
    if worst > PARITY_TOL:
        raise ValueError(f"{path}: its nets read back serve {worst:.2e} away from the file")
    return original, metadata, nets


def initial_fusion_state(source: Path, fusion_name: str, member: int, cfg: FusionConfig) -> InitialWeights:
    """Where ``egoposevr train --init-from`` starts the fusion net ``fusion_name``: the weights of
    ``source/<fusion_name>.onnx`` when ``source`` is a folder, else of the model file ``source`` itself
    (e.g. ``egoposevr-lite.onnx``, one net of ``hmd-rgbd``'s kind); its ``member``-th net when it serves
    several. Raises ValueError when the file is not there or not a model, when it serves fewer nets, or
    when its nets are configured otherwise than ``cfg`` (the flags of this run; a training-only timing head,
    which no file holds, may differ: the fine-tune starts it afresh)."""
    path = source / f"{fusion_name}.onnx" if source.is_dir() else source
    _, metadata, nets = load_served_nets(path)
    if not 0 <= member < len(nets):
        raise ValueError(f"{path} serves {len(nets)} net(s): no member {member}")
    if metadata.config != cfg.served:
        raise ValueError(f"{path}: its net is configured otherwise than this run's flags make it")
    return InitialWeights(
        str(path), member, nets[member].state_dict(), metadata.rig_offsets_m, metadata.training
    )


def reexport_model(path: Path) -> float:
    """Rewrite a model file in today's graph form (the exporter's opset and the nets' current forward
    pass), in place, from the weights it holds: no checkpoint is needed. Metadata is kept byte for byte.
    Returns the largest difference between the new graph's outputs and the old one's (batches of 1 and 8;
    1 alone for a graph exported for batch 1, which comes back with a batch axis);
    raises ValueError when the file's weights do not fill the net its config describes, or when the two
    graphs disagree by more than ``PARITY_TOL`` (the file is then left as it was)."""
    original, metadata, nets = load_served_nets(path)
    module = _served_module(nets, bool(metadata.training.get("mirror_averaged")))
    with _replaced_if_checked(path, "reexport") as rewritten:
        _export_fusion(module, metadata.config, rewritten)
        model = onnx.load(str(rewritten))
        model.metadata_props.extend(original.metadata_props)
        onnx.save(model, str(rewritten))
        batched = bool(original.graph.input[0].type.tensor_type.shape.dim[0].dim_param)
        batches = (1, 8) if batched else (1,)  # a graph exported for batch 1 runs batch 1 only
        worst = _graphs_differ(original, model, [_fusion_inputs(metadata.config, b) for b in batches])
        if worst > PARITY_TOL:
            raise ValueError(f"{path}: the re-exported graph differs from the original by {worst:.2e}")
    return worst


def _state_dict_from_graph(
    graph_model: onnx.ModelProto, module: torch.nn.Module, path: Path
) -> dict[str, torch.Tensor]:
    """The module's state dict read back from an exported graph's initializers. Most keep their torch
    names; the exporter stores a Linear's weight transposed, unnamed, as the second input of the MatMul
    whose output is added to the (named) bias."""
    graph = graph_model.graph
    arrays = {i.name: onnx.numpy_helper.to_array(i) for i in graph.initializer}
    matmul_of = {n.output[0]: n for n in graph.node if n.op_type == "MatMul"}
    transposed: dict[str, np.ndarray] = {}
    for node in graph.node:
        if node.op_type != "Add":
            continue
        bias = next((x for x in node.input if x.endswith(".bias") and x in arrays), None)
        matmul = next((matmul_of[x] for x in node.input if x in matmul_of), None)
        if bias is not None and matmul is not None and matmul.input[1] in arrays:
            transposed[bias.removesuffix(".bias") + ".weight"] = arrays[matmul.input[1]].T
    buffers = {name for name, _ in module.named_buffers()}
    state = {}
    for key, want in module.state_dict().items():
        found = arrays[key] if key in arrays else transposed.get(key)
        if found is None and key in buffers:  # the exporter keeps one copy of members' equal buffers
            found = next((arrays[k] for k in _other_members(key) if k in arrays), None)
        if found is None or tuple(found.shape) != tuple(want.shape):
            raise ValueError(f"{path}: no weight for {key} {tuple(want.shape)} in the graph")
        state[key] = torch.from_numpy(np.array(found, copy=True))  # writable, C order
    return state


def _other_members(key: str, most: int = 16) -> list[str]:
    """The same state-dict key in the other members of a SeedEnsemble (``….members.K.…``); none otherwise."""
    found = re.search(r"(?:^|\.)members\.(\d+)\.", key)
    if found is None:
        return []
    start, end = found.span(1)
    return [f"{key[:start]}{k}{key[end:]}" for k in range(most) if str(k) != found.group(1)]


def _graphs_differ(a: onnx.ModelProto, b: onnx.ModelProto, feeds: list[dict[str, np.ndarray]]) -> float:
    """Largest |a - b| over the two graphs' outputs, each feed given to both."""
    one, other = _cpu_session(a), _cpu_session(b)
    return max(
        float(np.abs(x - y).max())
        for feed in feeds
        for x, y in zip(one.run(None, feed), other.run(None, feed), strict=True)
    )


def export_zoo(
    names: list[str],
    runs_dirs: list[Path],
    out_dir: Path,
    encoders_dir: Path | None = None,
    lean_gate: bool = False,
    command: Sequence[str] | None = None,
    quiet_lift: bool = False,
) -> dict[str, float | None]:
    """Every named model and the visual encoders they use -> out_dir; {file name: parity error}. With
    ``encoders_dir`` (the fusion nets were trained with ``train --encoders``) the encoders and their body
    regressors are that folder's, copied as they are (None: nothing exported, nothing to check). Several
    runs folders make each model the :class:`SeedEnsemble` of their nets; they must then have been trained
    on one set of encoders, given as ``encoders_dir``. ``lean_gate``, ``quiet_lift``: as :func:`export_model`; ``command``: the
    command line every file's record names."""
    if len(runs_dirs) > 1 and encoders_dir is None:
        raise ValueError(
            "an ensemble of several runs needs --encoders: the encoders its nets were trained on"
        )
    runs_dir = runs_dirs[0]
    out_dir.mkdir(parents=True, exist_ok=True)
    invocation = invocation_record(command)  # one record for every file this export writes
    errors: dict[str, float | None] = {}
    for kind in sorted({ZOO[n].visual for n in names if ZOO[n].visual}):
        name = f"visual-{kind}.onnx"
        if encoders_dir is not None:
            copy_encoder(encoders_dir / name, out_dir / name)
            errors[name] = None
        else:
            errors[name] = export_visual(runs_dir / f"visual-{kind}.pt", out_dir / name, invocation)
    for name in names:
        out_path = out_dir / f"{name}.onnx"
        errors[f"{name}.onnx"] = export_model(
            name, runs_dirs, out_path, lean_gate=lean_gate, invocation=invocation, quiet_lift=quiet_lift
        )
    return errors
