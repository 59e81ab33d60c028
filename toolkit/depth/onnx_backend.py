"""Any monocular depth network exported to ONNX, run with onnxruntime on the CPU.

Preprocessing is spelled out in ``OnnxDepthConfig`` (input size, resize mode, mean/std,
channel order, layout) because every exporter (Depth Anything V1/V2, MiDaS, DPT, UniDepth,
Metric3D) differs there, and a wrong one silently gives plausible-looking garbage.
Defaults come from the model's own ONNX metadata when it has them (the project's small
model writes them; see ``METADATA_KEYS``), then from the config, then Depth Anything's.

Weights are never downloaded: a missing file is an error that says where to put it.
"""

from __future__ import annotations

import functools
import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from toolkit.depth.protocol import DEPTH_KINDS, DepthKind, DepthPrediction
from toolkit.errors import InputError, MissingInputError

_log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# Custom metadata keys read from the ONNX file (``onnx.helper.set_model_props``).
METADATA_KEYS = ("depth_kind", "input_height", "input_width", "mean", "std", "channel_order",
                 "multiple_of")

# onnxruntime's refusal of an input's fixed axes: "Got invalid dimensions for input: image
# for the following indices\n index: 1 Got: 3 Expected: 1".
_BAD_DIMS = re.compile(r"invalid dimensions for input: (\S+) for the following indices"
                       r"((?:\s*index: \d+ Got: \d+ Expected: \d+)+)")

_INTERP = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "area": cv2.INTER_AREA,
           "nearest": cv2.INTER_NEAREST}


def positive_input_size(v: Any) -> Any:
    """``v`` (an input size: one side or (height, width)) when every side is positive."""
    if v is None:
        return v
    hw = (v, v) if isinstance(v, int) else v
    if min(hw) <= 0:
        raise ValueError(f"input_size must be positive, got {v}")
    return v


class OnnxDepthConfig(BaseModel):
    """How to feed a given ONNX depth network and how to read its output."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: Path
    # What the output means; None: the model's metadata must say (``depth_kind``).
    kind: DepthKind | None = None
    # Network input (height, width) or one side for a square input; None: the model's fixed
    # input shape, else its metadata, else 518 (Depth Anything's training size).
    input_size: tuple[int, int] | int | None = None
    # keep_aspect: height = input_size, width from the image aspect, both rounded to
    # ``multiple_of`` (needs a model exported with dynamic height/width). letterbox: the
    # whole image scaled into the input at its own aspect, centred, the rest filled with
    # ``fill`` (Metric3D's fixed 616x1064 input); the fill is cut from the output.
    resize: Literal["stretch", "keep_aspect", "letterbox"] = "stretch"
    # 14 for ViT/14 backbones, 1 for no rounding; None: metadata or 14
    multiple_of: int | None = Field(None, ge=1)
    interpolation: Literal["linear", "cubic", "area", "nearest"] = "cubic"
    mean: tuple[float, float, float] | None = None  # in [0, 1] units; None: metadata/ImageNet
    std: tuple[float, float, float] | None = None
    channel_order: Literal["rgb", "bgr"] | None = None
    layout: Literal["nchw", "nhwc"] = "nchw"
    output_index: int = 0
    output_scale: float = 1.0  # e.g. 0.001 for a network that outputs millimetres
    # Metric3D predicts depth as seen by a canonical camera of this focal length (1000 px):
    # its output is multiplied by the camera's focal length at the network input / this.
    canonical_focal: float | None = None
    # The letterbox fill in 0-255 pixel units per network input channel (channel_order);
    # None: the mean colour. Metric3D's own export normalises inside its graph (it takes
    # raw pixels: mean 0, std 1/255) and is padded with [123.675, 116.28, 103.53].
    fill: tuple[float, float, float] | None = None
    # A model input that takes the camera's intrinsics at the network input (UniDepth
    # exports with a camera input): [1, 3, 3] / [3, 3] K, or [1, 4] / [4] fx, fy, cx, cy.
    intrinsics_input: str | None = None
    # A confidence map among the outputs (UniDepth V2's export: output 3, higher is more
    # sure): pixels below ``min_confidence`` are dropped (NaN), as glass, mirrors and
    # open sky are where such networks guess.
    confidence_index: int | None = None
    min_confidence: float = 0.0
    threads: int = 2  # onnxruntime intra-op threads
    # Where the network runs: cuda needs the onnxruntime-gpu package (in place of
    # onnxruntime); auto takes CUDA when that package finds a GPU, else the CPU.
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # Busy-waiting worker threads win a little latency on an idle machine but burn the
    # cores that SLAM and fusion need in the same process chain (and other jobs on a
    # shared machine), which made everything several times slower here; off by default.
    spin: bool = False

    @field_validator("input_size")
    @classmethod
    def _positive(cls, v: Any) -> Any:
        return positive_input_size(v)

    @model_validator(mode="after")
    def _consistent(self) -> OnnxDepthConfig:
        problem = settings_problem(self.kind, self.canonical_focal, self.min_confidence,
                                   self.confidence_index) or resize_problem(self.resize,
                                                                            self.input_size)
        if problem:
            raise ValueError(problem)
        return self

    @field_validator("canonical_focal")
    @classmethod
    def _positive_focal(cls, v: float | None) -> float | None:
        if v is not None and not v > 0:
            raise ValueError(f"canonical_focal must be a positive focal length in pixels "
                             f"(Metric3D: 1000), got {v}")
        return v


def settings_problem(kind: str | None, canonical_focal: float | None, min_confidence: float,
                     confidence_index: int | None) -> str | None:
    """What is wrong with these settings together (the depth stage checks them with the
    recipe, the backend again once the model's metadata has said its kind); None: nothing."""
    if min_confidence and confidence_index is None:
        return "min_confidence needs confidence_index (the output that holds the confidence)"
    if canonical_focal is not None and kind not in (None, "metric_depth"):
        return (f"canonical_focal converts a canonical camera's metric depth (Metric3D) to "
                f"this camera's; the output is {kind}, which a scale fit makes metric "
                "anyway: drop it, or set output: metric_depth if the network is metric")
    return None


def execution_providers(device: str, available: list[str]) -> list[str]:
    """onnxruntime providers, in order of preference, for ``device`` given the ones this
    onnxruntime build has (``onnxruntime.get_available_providers()``)."""
    cuda = "CUDAExecutionProvider" in available
    if device == "cuda" and not cuda:
        raise ValueError(
            "device: cuda, but this onnxruntime has no CUDA provider (it has "
            f"{', '.join(available)}): replace it with the GPU build (pip uninstall onnxruntime"
            " && pip install onnxruntime-gpu) on a machine with an NVIDIA driver, or set "
            "device: cpu")
    if device in ("cuda", "auto") and cuda:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


def folder_model_message(path: Path) -> str:
    return f"{path}: is a folder; give the .onnx file in it as 'model'"


def model_file_problem(path: Path) -> str | None:
    """Why the file at ``path`` cannot be an ONNX model, from its first bytes (cheap enough
    for ``validate``: a Git LFS pointer or a text file failed in onnxruntime with
    INVALID_PROTOBUF after the stages before depth had run); None when it may be one."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError as e:
        return f"{path}: cannot read the model: {e}"
    if head.startswith(b"version https://git-lfs"):
        return (f"{path}: a Git LFS pointer, not the model: fetch the file itself "
                "(git lfs pull) or copy the exported .onnx there")
    # An ONNX file is a protobuf ModelProto: its first field (ir_version, field 1, varint)
    # starts with the byte 0x08; text, HTML or a zip never do.
    if not head or head[0] != 0x08:
        return (f"{path}: not an ONNX model (it starts {head[:16]!r}); give the .onnx file "
                "the network was exported to (torch.onnx.export)")
    return None


# A model file this large keeps its weights inside (protobuf's 2 GB limit is why exports
# move them out, leaving a graph of a few MB): not parsed for external data, which would
# read the whole file on every run's cache check.
EXTERNAL_DATA_SCAN_BYTES = 256 * 2**20


def external_data_files(path: Path) -> list[Path]:
    """The files beside the model ``path`` that hold its weights when it was saved with
    external data (``model.onnx.data``: exports of networks over 2 GB, e.g. Depth Anything
    V2 Giant), as its tensors name them, in order; [] for a self-contained model, or a file
    that is none (the depth stage says what is wrong with it)."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        return []
    if not path.is_file() or st.st_size > EXTERNAL_DATA_SCAN_BYTES:
        return []
    # The cache keys, the pre-run check and the stage each ask: the graph is parsed once
    # per version of the file.
    return [path.parent / name for name in
            _external_data_names(str(path), st.st_size, st.st_mtime_ns)]


@functools.lru_cache(maxsize=16)
def _external_data_names(path: str, _size: int, _mtime_ns: int) -> tuple[str, ...]:
    """The external data locations the model at ``path`` names (size and mtime: the cache
    key of the file's version)."""
    import onnx
    from onnx.external_data_helper import uses_external_data

    try:
        model = onnx.load(path, load_external_data=False)
    except Exception:  # noqa: BLE001 - not a model: model_problem reports it
        return ()
    names: dict[str, None] = {}

    def visit(graph: Any) -> None:
        tensors = list(graph.initializer)
        for node in graph.node:
            for attr in node.attribute:
                tensors += [attr.t] if attr.HasField("t") else []
                tensors += list(attr.tensors)
                for sub in ([attr.g] if attr.HasField("g") else []) + list(attr.graphs):
                    visit(sub)
        for t in tensors:
            if uses_external_data(t):
                names.update({e.value: None for e in t.external_data if e.key == "location"})

    visit(model.graph)
    return tuple(names)


def missing_model_message(path: Path) -> str:
    """What to do about a model file that is not there: where to put it (a relative path is
    read from the working directory, which a run started elsewhere does not make obvious:
    the absolute path is named too), what the project ships, how to make one."""
    path = Path(path)
    where = str(path) if path.is_absolute() else (
        f"{path} ({Path.cwd() / path}: a relative 'model' is read from the working "
        "directory)")
    return (
        f"ONNX depth model not found at {where}. This toolkit never downloads weights: put the "
        f"exported .onnx file there (or point the recipe's 'model' at it). The project's small "
        f"model is datasets/models/small-depth.onnx (rebuild it with "
        f"`python -m toolkit.depth.train_small`); for Depth Anything V2 or MiDaS export the "
        f"model to ONNX yourself and copy it (see docs/depth_fusion.md)."
    )


def resize_problem(resize: str, input_size: tuple[int, int] | int | None) -> str | None:
    """What is wrong with ``resize`` and ``input_size`` together (no model needed: the
    depth stage refuses it with the recipe); None: nothing."""
    if resize == "keep_aspect" and isinstance(input_size, tuple | list):
        return (f"resize: keep_aspect takes one input_size (the height; the width follows "
                f"the image's aspect), not {list(input_size)}: give input_size: "
                f"{input_size[0]}, or resize: stretch for a {input_size[0]}x{input_size[1]} "
                "(HxW) input")
    return None


@dataclass(frozen=True)
class ModelPlan:
    """How the backend feeds a model and reads it, decided from the model's signature and
    metadata with the settings, before anything runs."""

    input_name: str
    input_dtype: type
    intrinsics: _IntrinsicsInput | None
    output_name: str
    outputs_text: str  # every output with its shape, for error messages
    confidence_name: str | None
    fixed_hw: tuple[int, int] | None  # the image input's fixed (height, width), if fixed
    meta_hw: tuple[int | None, int | None]
    kind: DepthKind
    multiple_of: int
    channel_order: str
    mean: np.ndarray  # [3]
    std: np.ndarray  # [3]
    warning: str | None


def plan_model(config: OnnxDepthConfig, inputs: Sequence[Any], outputs: Sequence[Any],
               metadata: dict[str, str]) -> ModelPlan:
    """Check ``config`` against a model's ``inputs`` and ``outputs`` (onnxruntime's
    ``NodeArg``s: name, shape, type) and ``metadata``; a ``ValueError`` naming the file, the
    setting and the fix for what would fail. The backend runs it when it loads the model,
    and the depth stage before any stage of a recipe runs (``read_signature``)."""
    path = Path(config.model)
    listed = ", ".join(f"{i.name!r} {i.shape}" for i in inputs)
    intrinsics = None
    images = list(inputs)
    if config.intrinsics_input is not None:
        named = [i for i in inputs if i.name == config.intrinsics_input]
        if not named:
            raise InputError(f"{path}: intrinsics_input {config.intrinsics_input!r} is not an "
                             f"input of the model; its inputs are {listed}")
        intrinsics = _IntrinsicsInput.of(path, named[0])
        images = [i for i in inputs if i.name != config.intrinsics_input]
    if len(images) != 1:
        raise InputError(
            f"{path}: the model takes {len(inputs)} inputs ({listed}); this backend feeds one "
            "image, and the camera intrinsics where intrinsics_input names their input. "
            "Re-export it with any other input fixed inside the graph")
    inp = images[0]
    _check_image_input(path, inp.name, list(inp.shape), config.layout)
    # A half-precision export takes float16: the image is cast, not refused.
    input_dtype = {"tensor(float)": np.float32, "tensor(float16)": np.float16}.get(inp.type)
    if input_dtype is None:
        raise InputError(f"{path}: input {inp.name!r} is {inp.type}; expected a float or "
                         "float16 image tensor")
    outputs_text = ", ".join(f"{i}: {o.name!r} {o.shape}" for i, o in enumerate(outputs))
    if not 0 <= config.output_index < len(outputs):
        raise InputError(f"{path}: output_index {config.output_index}, but the model has "
                         f"{len(outputs)} output(s): {outputs_text}; set output_index to the "
                         "depth map's")
    output_name = outputs[config.output_index].name
    shape = outputs[config.output_index].shape
    if _fixed_non_map(shape):
        raise InputError(not_depth_message(path, config.output_index, output_name, shape,
                                           outputs_text))
    confidence_name = None
    if config.confidence_index is not None:
        ci = config.confidence_index
        if not 0 <= ci < len(outputs) or ci == config.output_index:
            raise InputError(f"{path}: confidence_index {ci} is not another output of the "
                             f"model; its outputs are {outputs_text}")
        if _fixed_non_map(outputs[ci].shape):
            raise InputError(f"{path}: output {ci} ({outputs[ci].name!r}) has shape "
                             f"{list(outputs[ci].shape)}, not one confidence image; the "
                             f"model's outputs are {outputs_text}")
        confidence_name = outputs[ci].name
    kind = config.kind or metadata.get("depth_kind")
    if kind is None:
        raise InputError(
            f"{path}: the model has no 'depth_kind' metadata; say what the network outputs "
            f"with the depth stage's 'output' setting (OnnxDepthConfig.kind from Python), one "
            f"of {DEPTH_KINDS} (Depth Anything's and MiDaS's relative models: "
            "relative_disparity)")
    if kind not in DEPTH_KINDS:
        raise InputError(f"{path}: depth kind {kind!r} is not one of {DEPTH_KINDS}")
    problem = settings_problem(kind, config.canonical_focal, config.min_confidence,
                               config.confidence_index)
    if problem:  # the kind may come from the model's metadata
        raise InputError(f"{path}: {problem}")
    multiple = config.multiple_of  # >= 1, as the metadata's
    if multiple is None:
        multiple = _meta_int(path, metadata, "multiple_of")
    order = str(config.channel_order or metadata.get("channel_order", "rgb")).lower()
    if order not in ("rgb", "bgr"):
        raise InputError(f"{path}: channel_order {order!r} is neither rgb nor bgr")
    # mean / std are per network input channel, in its order; ImageNet's defaults are
    # written R, G, B, so a BGR network takes them reversed.
    flip = slice(None, None, -1 if order == "bgr" else 1)
    mean = np.asarray(config.mean or _floats(path, metadata, "mean") or IMAGENET_MEAN[flip],
                      dtype=np.float32)  # [3]
    std = np.asarray(config.std or _floats(path, metadata, "std") or IMAGENET_STD[flip],
                     dtype=np.float32)  # [3]
    if mean.max() > 1.0 or std.max() > 1.0:
        # mmcv/Metric3D configs give 123.675, 58.395...: the image here is in [0, 1].
        raise InputError(f"{path}: mean {mean.tolist()} / std {std.tolist()} are in 0-255 "
                         "units; give them divided by 255 (the image is scaled to [0, 1] "
                         "first)")
    if ("input_height" in metadata) != ("input_width" in metadata):
        raise InputError(f"{path}: metadata names one of input_height / input_width without "
                         "the other; give input_size in the recipe")
    meta_hw = (_meta_int(path, metadata, "input_height"),
               _meta_int(path, metadata, "input_width"))
    fixed = _fixed_input_hw(list(inp.shape), config.layout)
    if fixed is not None:
        if config.resize == "keep_aspect":
            raise InputError(f"{path}: resize: keep_aspect needs a model exported with "
                             f"dynamic height/width; this one takes a fixed input "
                             f"{inp.shape}: use resize: stretch (or letterbox to keep the "
                             "image's aspect)")
        size = config.input_size
        hw = (size, size) if isinstance(size, int) else size
        if hw is not None and tuple(hw) != fixed:
            # input_size is [h, w] in the recipe: both sides are given in that order, so
            # that a swapped pair reads as one (a WxH figure read as the recipe's order).
            raise InputError(f"{path}: the model takes a fixed input of height {fixed[0]}, "
                             f"width {fixed[1]}, but input_size asks for "
                             f"[{hw[0]}, {hw[1]}] ([height, width]); set input_size: "
                             f"[{fixed[0]}, {fixed[1]}] or drop it, or re-export the model "
                             "with dynamic height/width")
    # A timing stand-in (``bench_latency --export``) runs like a real network; its depth
    # is noise, which the backend says loudly.
    warning = metadata.get("warning") or (
        "random weights: depth is meaningless" if metadata.get("weights") == "random" else None)
    return ModelPlan(
        input_name=inp.name, input_dtype=input_dtype, intrinsics=intrinsics,
        output_name=output_name, outputs_text=outputs_text, confidence_name=confidence_name,
        fixed_hw=fixed, meta_hw=meta_hw, kind=kind,  # type: ignore[arg-type]
        multiple_of=int(multiple if multiple is not None else 14), channel_order=order,
        mean=mean, std=std, warning=warning)


def _check_image_input(path: Path, name: str, shape: list[Any], layout: str) -> None:
    """One RGB image of rank 4 with its channel axis where ``layout`` says: fixed axes
    that disagree are refused when the model is loaded, not at its first frame."""
    if len(shape) != 4:
        raise InputError(f"{path}: input shape {shape}: expected an image batch "
                         "[1, 3, H, W] (layout: nchw) or [1, H, W, 3] (layout: nhwc)")
    c_first, c_last = shape[1], shape[3]
    if layout == "nchw" and c_first != 3 and c_last == 3:
        raise InputError(f"{path}: input shape {shape} has its 3 channels last; set "
                         "layout: nhwc in the depth stage")
    if layout == "nhwc" and c_last != 3 and c_first == 3:
        raise InputError(f"{path}: input shape {shape} has its 3 channels first; set "
                         "layout: nchw in the depth stage")
    channels = c_first if layout == "nchw" else c_last
    if isinstance(channels, int) and channels != 3:
        # A grayscale or RGB-D network: onnxruntime refused the first frame, with advice
        # about input sizes.
        raise InputError(f"{path}: input {name!r} {shape} takes {channels} channel(s); this "
                         "backend feeds RGB images (3 channels), so a grayscale or RGB-D "
                         "network cannot run on it: use a model that takes a 3-channel image "
                         f"(layout: {layout})")
    if isinstance(shape[0], int) and shape[0] != 1:
        raise InputError(f"{path}: input {name!r} {shape} takes a batch of {shape[0]} images; "
                         "this backend feeds one: re-export with batch 1 or a dynamic batch "
                         "axis")


def _fixed_input_hw(shape: list[Any], layout: str) -> tuple[int, int] | None:
    """The image input's (height, width) when both are fixed."""
    dims = shape[2:4] if layout == "nchw" else shape[1:3]
    return (int(dims[0]), int(dims[1])) if all(isinstance(d, int) for d in dims) else None


def not_depth_message(path: Path, index: int, name: str, shape: Any, outputs_text: str) -> str:
    return (f"{path}: output {index} ({name!r}) has shape {list(shape)}, not one depth "
            f"image; the model's outputs are {outputs_text}. Set output_index to the depth "
            "map's")


def _open_session(path: Path, opts: Any, providers: list[str]) -> Any:
    """An onnxruntime session of the model at ``path``; ``FileNotFoundError`` for a
    folder or a missing file, a ``ValueError`` saying to re-export it when onnxruntime
    cannot load it."""
    import onnxruntime as ort

    if path.is_dir():
        raise MissingInputError(folder_model_message(path))
    if not path.is_file():
        raise MissingInputError(missing_model_message(path))
    problem = model_file_problem(path)
    if problem:
        raise InputError(problem)
    try:
        return ort.InferenceSession(str(path), opts, providers=providers)
    except (RuntimeError, ort.capi.onnxruntime_pybind11_state.Fail,
            ort.capi.onnxruntime_pybind11_state.InvalidProtobuf,
            ort.capi.onnxruntime_pybind11_state.InvalidGraph) as e:
        # A copy cut short reads as an invalid protobuf too: copying again is the cheaper fix.
        raise InputError(f"{path}: onnxruntime cannot load the model ({e}); if the file "
                         f"({path.stat().st_size} bytes) was copied or downloaded, copy it "
                         "again in full, else re-export it (torch.onnx.export, opset 17 or "
                         "newer)") from None


def read_signature(path: Path) -> tuple[list[Any], list[Any], dict[str, str]]:
    """A model's inputs and outputs (onnxruntime's ``NodeArg``s, shapes as the backend
    sees them after onnxruntime's shape inference) and metadata, without running it: a
    CPU session with graph optimisations off (5-19 ms for the shipped 4.4 MB model, 1.4-2 s
    for 400 MB of weights, which it reads)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    sess = _open_session(path, opts, ["CPUExecutionProvider"])
    return (list(sess.get_inputs()), list(sess.get_outputs()),
            dict(sess.get_modelmeta().custom_metadata_map))


def model_problem(config: OnnxDepthConfig) -> str | None:
    """Why the backend would refuse ``config`` when it loads its model (the file, its
    inputs, outputs and metadata against the settings), found without running the model:
    what the depth stage says before the stages before it run; None: nothing."""
    from onnxruntime.capi import onnxruntime_pybind11_state as ort_state

    # onnxruntime's own error types beyond those that say the file is no loadable model
    # (a ValueError here): an op with no CPU kernel (NOT_IMPLEMENTED) may have one on the
    # GPU the stage runs on, where the backend finds what is wrong when it loads.
    unknown = tuple(c for c in vars(ort_state).values()
                    if isinstance(c, type) and issubclass(c, Exception))
    try:
        plan_model(config, *read_signature(Path(config.model)))
    except (FileNotFoundError, ValueError) as e:
        return str(e)
    except unknown:
        return None
    return None


class OnnxDepthBackend:
    """``DepthBackend`` over an onnxruntime session."""

    def __init__(self, config: OnnxDepthConfig) -> None:
        import onnxruntime as ort

        self.config = config
        path = Path(config.model)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(config.threads)
        opts.inter_op_num_threads = 1
        # Sequential execution: with 2 cores, parallel graph branches only fight each other.
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.add_session_config_entry("session.intra_op.allow_spinning",
                                      "1" if config.spin else "0")
        self.session = _open_session(
            path, opts, execution_providers(config.device, ort.get_available_providers()))
        # What onnxruntime actually uses (it falls back to the CPU when CUDA cannot start).
        self.providers: list[str] = list(self.session.get_providers())
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        plan = plan_model(config, self.session.get_inputs(), self.session.get_outputs(),
                          self.metadata)
        self.input_name = plan.input_name
        self.input_dtype = plan.input_dtype
        self.intrinsics = plan.intrinsics
        self.output_name = plan.output_name
        self._outputs_text = plan.outputs_text
        self.confidence_name = plan.confidence_name
        self._fixed_hw = plan.fixed_hw
        self._meta_hw = plan.meta_hw
        self.kind: DepthKind = plan.kind
        self.multiple_of = plan.multiple_of
        self.channel_order = plan.channel_order
        self.mean, self.std = plan.mean, plan.std
        self.warning = plan.warning
        self.last_confident_fraction: float | None = None
        self.last_input_hw: tuple[int, int] | None = None
        # Where the image lies in the last input (top, left, height, width): all of it,
        # except in a letterbox.
        self.last_placement: tuple[int, int, int, int] | None = None
        self.last_focal_factor: float | None = None
        self._warned_round: tuple[int, int] | None = None  # the rounding said in the log
        self.last_timing: dict[str, float] = {}
        if self.warning:
            _log.warning("%s: %s", path, self.warning)

    # ------------------------------------------------------------------ sizes
    def input_hw(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """Network input (height, width) for an image of ``image_hw``."""
        cfg = self.config
        if self._fixed_hw is not None:
            return self._fixed_hw  # an input_size other than it was refused at load
        size = cfg.input_size
        if size is None and self._meta_hw[0] is not None:
            size = self._meta_hw  # type: ignore[assignment]
        if size is None:
            size = 518
        h, w = (size, size) if isinstance(size, int) else size
        m = self.multiple_of
        if cfg.resize == "keep_aspect":
            h = max(m, int(round(h / m)) * m)
            w = max(m, int(round(h * image_hw[1] / image_hw[0] / m)) * m)
        elif h % m or w % m:
            # A ViT/14 sees only whole patches: the rest of a 480x640 input would be cut off
            # and its output stretched back over the whole image (edges moved by pixels).
            # Said in the log: a network of 16 or 32 px patches needs multiple_of set.
            rh, rw = max(m, int(round(h / m)) * m), max(m, int(round(w / m)) * m)
            if (rh, rw) != self._warned_round:
                _log.warning("%s: input %dx%d rounded to %dx%d (multiple_of %d)", cfg.model,
                             w, h, rw, rh, m)
                self._warned_round = (rh, rw)
            h, w = rh, rw
        return h, w

    def placement(self, image_hw: tuple[int, int]) -> tuple[int, int, int, int]:
        """Where an image of ``image_hw`` lies in the network input: (top, left, height,
        width); the whole input except with ``resize: letterbox``."""
        return self._place(self.input_hw(image_hw), image_hw)

    def _place(self, input_hw: tuple[int, int], image_hw: tuple[int, int]
               ) -> tuple[int, int, int, int]:
        h, w = input_hw
        if self.config.resize != "letterbox":
            return 0, 0, h, w
        s = min(h / image_hw[0], w / image_hw[1])
        nh = min(h, max(1, int(round(image_hw[0] * s))))
        nw = min(w, max(1, int(round(image_hw[1] * s))))
        return (h - nh) // 2, (w - nw) // 2, nh, nw

    def network_intrinsics(self, camera: Any, image_hw: tuple[int, int]
                           ) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of ``camera`` (a ``PinholeCamera`` of the image) as the network
        input sees it: scaled with the image (pixel-centre aware) and shifted by a
        letterbox's fill."""
        if (int(camera.height), int(camera.width)) != tuple(image_hw):
            raise InputError(f"{self.config.model}: the camera is {camera.width}x"
                             f"{camera.height} but the image is {image_hw[1]}x{image_hw[0]}; "
                             "the intrinsics must be those of the images the network sees")
        top, left, nh, nw = self.placement(image_hw)
        sx, sy = nw / image_hw[1], nh / image_hw[0]
        return (float(camera.fx) * sx, float(camera.fy) * sy,
                (float(camera.cx) + 0.5) * sx - 0.5 + left,
                (float(camera.cy) + 0.5) * sy - 0.5 + top)

    def focal_factor(self, camera: Any, image_hw: tuple[int, int]) -> float:
        """What ``canonical_focal`` multiplies the output by: the camera's focal length at
        the network input / the canonical one. The geometric mean of fx and fy there: a
        stretched input has two focal lengths, the canonical camera one (equal to fx for
        any aspect-keeping resize)."""
        if self.config.canonical_focal is None:
            raise InputError(f"{self.config.model}: no canonical_focal set")
        fx, fy, _, _ = self.network_intrinsics(camera, image_hw)
        return self._focal_factor(fx, fy)

    def _focal_factor(self, fx: float, fy: float) -> float:
        return float(np.sqrt(fx * fy)) / float(self.config.canonical_focal)  # type: ignore

    @property
    def needs_camera(self) -> bool:
        """Whether ``predict`` needs the camera (a canonical focal or an intrinsics input)."""
        return self.config.canonical_focal is not None or self.intrinsics is not None

    # ------------------------------------------------------------------ steps
    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8 RGB -> network input [1, 3, h, w] (or [1, h, w, 3]) float32."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an RGB uint8 [H, W, 3] image, got {rgb.dtype} {rgb.shape}")
        h, w = self.input_hw(rgb.shape[:2])
        top, left, nh, nw = self._place((h, w), rgb.shape[:2])
        self.last_placement = (top, left, nh, nw)
        img = rgb if self.channel_order == "rgb" else rgb[..., ::-1]
        if (nh, nw) != img.shape[:2]:
            img = cv2.resize(np.ascontiguousarray(img), (nw, nh),
                             interpolation=_INTERP[self.config.interpolation])
        x = (img.astype(np.float32) / np.float32(255.0) - self.mean) / self.std  # [nh, nw, 3]
        if (nh, nw) != (h, w):
            # The mean colour is zero once normalised.
            full = np.zeros((h, w, 3), np.float32)  # [h, w, 3]
            if self.config.fill is not None:
                full[:] = (np.asarray(self.config.fill, np.float32) / np.float32(255.0)
                           - self.mean) / self.std
            full[top:top + nh, left:left + nw] = x
            x = full
        if self.config.layout == "nchw":
            x = x.transpose(2, 0, 1)
        return np.ascontiguousarray(x[None], dtype=self.input_dtype)

    def postprocess(self, raw: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
        """Network output ([1, 1, h, w], [1, h, w] or [h, w]) -> [H, W] float32, NaN invalid."""
        out = _squeezed(raw)
        if not _image_shaped(out.shape, self.last_input_hw):
            raise InputError(not_depth_message(self.config.model, self.config.output_index,
                                               self.output_name, np.shape(raw),
                                               self._outputs_text))
        out = out * np.float32(self.config.output_scale)
        return self._to_image(out, self._invalid(out), image_hw)

    def confidence(self, raw: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
        """The confidence output -> [H, W] float32 over the image, as the depth is placed."""
        conf = _squeezed(raw)
        if not _image_shaped(conf.shape, self.last_input_hw):
            raise InputError(f"{self.config.model}: output {self.config.confidence_index} "
                             f"({self.confidence_name!r}) has shape {list(np.shape(raw))}, "
                             "not one confidence image")
        return self._to_image(conf, ~np.isfinite(conf), image_hw)

    def _to_image(self, out: np.ndarray, bad: np.ndarray, image_hw: tuple[int, int]
                  ) -> np.ndarray:
        """[h, w] output -> [H, W]: a letterbox's fill cut, resized to the image from the
        valid pixels, NaN where ``bad``."""
        if self.config.resize == "letterbox" and self.last_placement is not None:
            # Cut the fill at the input's resolution: an output at a fraction of it (1/2,
            # 1/4) cut at whole output pixels moved the depth by up to 2 image columns.
            top, left, nh, nw = self.last_placement
            if out.shape != self.last_input_hw:
                # Output pixels wholly in the fill are no depth of the image: upsampled
                # with the rest, they blended the network's guess for the flat fill into
                # the image's border (a quarter of it into the first row at 1/2 resolution).
                # Pixels straddling the image's edge mixed the two in the network itself.
                (oh, ow), (ih, iw) = out.shape, self.last_input_hw
                rows, cols = np.arange(oh) * (ih / oh), np.arange(ow) * (iw / ow)  # starts
                fill_r = (rows + ih / oh <= top) | (rows >= top + nh)  # [oh]
                fill_c = (cols + iw / ow <= left) | (cols >= left + nw)  # [ow]
                bad = bad | fill_r[:, None] | fill_c[None, :]
                out = self._resize(out, bad, self.last_input_hw)
                bad = ~np.isfinite(out)
            out = out[top:top + nh, left:left + nw]
            bad = bad[top:top + nh, left:left + nw]
        if out.shape != tuple(image_hw):
            return self._resize(out, bad, image_hw)
        if bad.any():
            out = out.copy()
            out[bad] = np.nan
        return out

    def _invalid(self, out: np.ndarray) -> np.ndarray:
        """[h, w] bool: no value (a depth of zero or less is no depth; disparity 0 is)."""
        bad = ~np.isfinite(out)
        if self.kind != "relative_disparity":
            bad |= out <= 0
        return bad

    @staticmethod
    def _resize(out: np.ndarray, bad: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        """Bilinear with half-pixel centres, as torch's align_corners=False; from the valid
        pixels only where some are not."""
        if bad.any():
            return _resize_valid(out, bad, hw)
        return cv2.resize(out, (hw[1], hw[0]), interpolation=cv2.INTER_LINEAR)

    def predict(self, rgb: np.ndarray, camera: Any = None, **_: Any) -> DepthPrediction:
        """Run the network on one RGB frame [H, W, 3] uint8. ``camera`` (the image's
        ``PinholeCamera``) is needed with ``canonical_focal`` or ``intrinsics_input``."""
        t0 = time.perf_counter()
        if self.needs_camera and camera is None:
            raise InputError(f"{self.config.model}: canonical_focal / intrinsics_input need "
                             "the camera's intrinsics: pass camera= (the depth stage passes "
                             "the sequence's)")
        x = self.preprocess(rgb)
        hw = x.shape[2:4] if self.config.layout == "nchw" else x.shape[1:3]
        self.last_input_hw = (int(hw[0]), int(hw[1]))
        feeds = {self.input_name: x}
        if self.needs_camera:
            fx, fy, cx, cy = self.network_intrinsics(camera, rgb.shape[:2])
            if self.intrinsics is not None:
                feeds[self.intrinsics.name] = self.intrinsics.tensor(fx, fy, cx, cy)
        t1 = time.perf_counter()
        names = [self.output_name] + ([self.confidence_name] if self.confidence_name else [])
        try:
            raws = self.session.run(names, feeds)
        except Exception as e:  # onnxruntime's own exception types, from its C++ core
            raise InputError(
                f"{self.config.model}: onnxruntime failed on a {hw[1]}x{hw[0]} input: "
                f"{str(e).strip()[:400]}. {self._failure_hint(str(e))}") from e
        t2 = time.perf_counter()
        values = self.postprocess(raws[0], rgb.shape[:2])
        extra: dict[str, Any] = {}
        if self.confidence_name is not None:
            unsure = ~(self.confidence(raws[1], rgb.shape[:2]) >= self.config.min_confidence)
            had = int(np.isfinite(values).sum())
            values[unsure] = np.nan
            # A frame without depth has no share to tell (0 would read as all dropped).
            self.last_confident_fraction = (float(np.isfinite(values).sum() / had) if had
                                            else None)
            if had:
                extra["confident_fraction"] = self.last_confident_fraction
        if self.config.canonical_focal is not None:
            self.last_focal_factor = self._focal_factor(fx, fy)
            values *= np.float32(self.last_focal_factor)
        t3 = time.perf_counter()
        self.last_timing = {"preprocess_s": t1 - t0, "network_s": t2 - t1,
                            "postprocess_s": t3 - t2}
        return DepthPrediction(values, self.kind, latency_s=t2 - t1,
                               extra={"input_hw": hw, **self.last_timing, **extra})

    def _failure_hint(self, error: str) -> str:
        """What to change after onnxruntime refused an input: its size (``multiple_of``),
        unless onnxruntime says that axes of the image other than height and width were
        refused, where a size would not help."""
        m = _BAD_DIMS.search(error)
        if m and m.group(1) == self.input_name:
            axes = {int(a) for a in re.findall(r"index: (\d+)", m.group(2))}
            spatial = {2, 3} if self.config.layout == "nchw" else {1, 2}
            if axes and not axes <= spatial:
                return (f"It refused axes {sorted(axes)} of input {self.input_name!r}, not only "
                        f"its height and width (layout: {self.config.layout}): the model "
                        "must take one RGB image")
        return ("If the network takes only sizes that are multiples of 32 (MiDaS, ZoeDepth) "
                f"or 16 (DPT-BEiT), set multiple_of (now {self.multiple_of}) or an "
                "input_size it takes")

    def describe(self) -> dict[str, Any]:
        """Settings actually used (for the report and the depth index)."""
        return {"backend": "onnx", "model": str(self.config.model), "kind": self.kind,
                "mean": self.mean.tolist(), "std": self.std.tolist(),
                "channel_order": self.channel_order, "layout": self.config.layout,
                "resize": self.config.resize, "threads": self.config.threads,
                "input_hw": list(self.last_input_hw) if self.last_input_hw else None,
                "multiple_of": self.multiple_of, "interpolation": self.config.interpolation,
                "output_index": self.config.output_index, "output": self.output_name,
                "output_scale": self.config.output_scale,
                "canonical_focal": self.config.canonical_focal, "fill": self.config.fill,
                "focal_factor": self.last_focal_factor,
                "intrinsics_input": self.config.intrinsics_input,
                "confidence_index": self.config.confidence_index,
                "confidence_output": self.confidence_name,
                "min_confidence": self.config.min_confidence,
                "placement": list(self.last_placement) if self.last_placement else None,
                "providers": self.providers,
                "spin": self.config.spin, "metadata": self.metadata,
                **({"warning": self.warning} if self.warning else {})}


class _IntrinsicsInput:
    """A model input that takes the camera: K [1, 3, 3] / [3, 3] or fx, fy, cx, cy
    [1, 4] / [4], in the input's float type."""

    def __init__(self, name: str, shape: tuple[int, ...], dtype: type) -> None:
        self.name, self.shape, self.dtype = name, shape, dtype

    @classmethod
    def of(cls, path: Path, inp: Any) -> _IntrinsicsInput:
        # A symbolic batch axis takes one camera.
        dims = tuple(d if isinstance(d, int) else 1 for d in inp.shape)
        dtype = {"tensor(float)": np.float32, "tensor(float16)": np.float16,
                 "tensor(double)": np.float64}.get(inp.type)
        if dims not in ((1, 3, 3), (3, 3), (1, 4), (4,)) or dtype is None:
            raise InputError(f"{path}: intrinsics input {inp.name!r} is {inp.type} "
                             f"{inp.shape}; expected a float K [1, 3, 3] / [3, 3] or fx, fy, "
                             "cx, cy [1, 4] / [4]")
        return cls(inp.name, dims, dtype)

    def tensor(self, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
        if self.shape[-1] == 4:
            values = np.array([fx, fy, cx, cy])
        else:
            values = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return values.reshape(self.shape).astype(self.dtype)


def _squeezed(raw: np.ndarray) -> np.ndarray:
    """float32 with the unit axes dropped: [1, 1, h, w], [1, h, w, 1], [1, h, w] -> [h, w]."""
    out = np.asarray(raw, dtype=np.float32)
    if out.ndim > 2:
        out = out.reshape([n for n in out.shape if n != 1] or [1])
    return out


def _resize_valid(values: np.ndarray, bad: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """[H, W] bilinear resize of ``values`` [h, w] from its valid pixels only (normalised
    by the resized validity): a 0 or NaN must not blend into its neighbours as a depth
    that exists nowhere. Pixels that take less than half their weight from valid ones
    are NaN."""
    H, W = hw
    v = np.where(bad, np.float32(0), values).astype(np.float32)
    w = (~bad).astype(np.float32)
    rv = cv2.resize(v, (W, H), interpolation=cv2.INTER_LINEAR)
    rw = cv2.resize(w, (W, H), interpolation=cv2.INTER_LINEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rw > 0.5, rv / rw, np.float32(np.nan)).astype(np.float32)


def _image_shaped(shape: Any, input_hw: tuple[int, int] | None = None) -> bool:
    """Two axes other than unit ones: a depth map, not a vector or a batch of maps; with the
    network input's (h, w) at least 1/32 of it on each axis - not the intrinsics ([3, 3])
    a UniDepth export puts first."""
    dims = [d for d in shape if d != 1]
    if len(dims) != 2:
        return False
    if input_hw is None:
        return True
    return all(d * 32 >= n for d, n in zip(dims, input_hw, strict=True))


def _fixed_non_map(shape: Any) -> bool:
    """A fully fixed output shape that is no per-pixel map (two axes of at least 4 besides
    unit ones): known wrong before any run; a symbolic shape is checked on the output."""
    return all(isinstance(d, int) for d in shape) and not (
        _image_shaped(shape) and min(d for d in shape if d != 1) >= 4)


def _floats(path: Path, metadata: dict[str, str], key: str) -> tuple[float, ...] | None:
    """Three numbers of ONNX metadata ``key`` ("0.485 0.456 0.406", commas or a bracketed
    list also read)."""
    text = metadata.get(key)
    if not text:
        return None
    try:
        vals = tuple(float(v) for v in text.translate({ord(c): " " for c in "[](),"}).split())
    except ValueError:
        vals = ()
    if len(vals) != 3:
        raise InputError(f"{path}: ONNX metadata {key!r} is {text!r}, not 3 numbers; give "
                         f"'{key}' in the depth stage (it wins over the metadata)")
    return vals


def _meta_int(path: Path, metadata: dict[str, str], key: str) -> int | None:
    text = metadata.get(key)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value.is_integer() and value > 0):
        raise InputError(f"{path}: ONNX metadata {key!r} is {text!r}, not a positive whole "
                         f"number; give it in the depth stage (input_size / multiple_of)")
    return int(value)
