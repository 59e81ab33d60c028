"""Look inside an ONNX depth network and say how the depth stage should run it.

    python -m toolkit.depth.inspect_model MODEL.onnx
    python -m toolkit.depth.inspect_model MODEL.onnx --image frame.png --png depth.png
    python -m toolkit.depth.inspect_model MODEL.onnx --image frame.png --camera 525,525,319.5,239.5

Lists the model's inputs, outputs and metadata, recognises the layouts of Metric3D's and
UniDepth V2's exports (and reads the metadata of this project's models), and prints a
``depth`` stage to paste into a recipe, with a comment for each setting it could not tell
from the file (a Depth Anything or MiDaS export does not say that it outputs disparity).
With ``--image`` it runs that stage's backend on the image and prints what came out
(latency, value range, share of pixels with depth), so a wrong mean/std or output kind shows
before a long run. Nothing is downloaded; the model is only read.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# Output names exporters give the depth map, best first.
_DEPTH_NAMES = ("depth", "pred_depth", "predicted_depth", "predicted_disparity", "disparity",
                "output")
_INTRINSICS_SHAPES = ((1, 3, 3), (3, 3), (1, 4), (4,))


@dataclass
class TensorInfo:
    """One model input or output: its name, shape (ints, or strings for symbolic axes)
    and element type ("tensor(float)")."""

    name: str
    shape: list[Any]
    type: str = "tensor(float)"

    @property
    def fixed(self) -> list[int] | None:
        """The shape if every axis is a number."""
        return list(self.shape) if all(isinstance(d, int) for d in self.shape) else None


@dataclass
class Suggestion:
    """Depth-stage settings read from a model, and what a person still has to say."""

    settings: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    recognised: str | None = None  # "Metric3D", "UniDepth V2", ... when the layout says so


def _image_input(inputs: list[TensorInfo]) -> tuple[TensorInfo | None, str]:
    """The input that takes the image and its layout: rank 4 with 3 channels first or
    last (named image/pixel_values/input first when several could be)."""
    cands = []
    for t in inputs:
        if len(t.shape) != 4:
            continue
        if t.shape[1] == 3:
            cands.append((t, "nchw"))
        elif t.shape[3] == 3:
            cands.append((t, "nhwc"))
        elif not isinstance(t.shape[1], int):
            cands.append((t, "nchw"))
    cands.sort(key=lambda c: c[0].name.lower() not in ("image", "pixel_values", "input", "rgb"))
    return (cands[0][0], cands[0][1]) if cands else (None, "nchw")


def _is_map(t: TensorInfo) -> bool:
    """Two axes other than unit ones, at least 4 long where known: a per-pixel map."""
    dims = [d for d in t.shape if d != 1]
    if len(dims) == 3 and not isinstance(dims[0], int):
        dims = dims[1:]  # a symbolic batch axis
    return len(dims) == 2 and all(not isinstance(d, int) or d >= 4 for d in dims)


def _intrinsics_shaped(t: TensorInfo) -> bool:
    return tuple(d if isinstance(d, int) else 1 for d in t.shape) in _INTRINSICS_SHAPES


def suggest(inputs: list[TensorInfo], outputs: list[TensorInfo],
            metadata: dict[str, str]) -> Suggestion:
    """Depth-stage settings for a model with these inputs, outputs and ONNX metadata."""
    sug = Suggestion()
    s, notes = sug.settings, sug.notes
    image, layout = _image_input(inputs)
    if image is None:
        notes.append("no input looks like an image batch [1, 3, H, W] / [1, H, W, 3]: the "
                     "onnx backend cannot feed this model")
        return sug
    if layout == "nhwc":
        s["layout"] = "nhwc"
    others = [t for t in inputs if t is not image]
    for t in others:
        if _intrinsics_shaped(t) and "intrinsics_input" not in s:
            s["intrinsics_input"] = t.name
        else:
            notes.append(f"input {t.name!r} {t.shape} is neither the image nor intrinsics: "
                         "re-export with it fixed inside the graph")
    maps = [i for i, t in enumerate(outputs) if _is_map(t)]
    if not maps:
        notes.append("no output is a per-pixel map: this is not a depth network's file, or "
                     "its depth output has an unusual shape")
        return sug

    def rank(i: int) -> tuple[int, int]:
        name = outputs[i].name.lower()
        if name in _DEPTH_NAMES:
            return 0, _DEPTH_NAMES.index(name)
        if ("depth" in name or "disp" in name) and not any(
                w in name for w in ("ssi", "normal", "conf", "uncert")):
            return 1, i
        return 2, i

    depth_i = min(maps, key=rank)
    if depth_i:
        s["output_index"] = depth_i
    conf = [i for i in maps if i != depth_i and "conf" in outputs[i].name.lower()]
    if conf:
        s["confidence_index"] = conf[0]
        notes.append(f"output {conf[0]} ({outputs[conf[0]].name!r}) is a confidence map: set "
                     "min_confidence (its scale is the network's own) to drop unsure pixels")
    # The height and width, fixed whatever the batch axis is (UniDepth's is symbolic).
    hw = list(image.shape[1:3] if layout == "nhwc" else image.shape[2:4])
    if not all(isinstance(d, int) for d in hw):
        hw = None
    depth_name = outputs[depth_i].name.lower()
    kind = metadata.get("depth_kind")
    names = {t.name.lower() for t in outputs}
    if depth_name == "pred_depth" and hw in ([616, 1064], [544, 1216]):
        # Metric3D's onnx/metric3d_onnx_export.py: raw pixels in, normalised in the graph,
        # canonical-camera depth out, padded with its mean colour.
        sug.recognised = "Metric3D"
        s.update({"output": "metric_depth", "resize": "letterbox", "canonical_focal": 1000.0,
                  "fill": [123.675, 116.28, 103.53], "interpolation": "linear",
                  "mean": [0.0, 0.0, 0.0], "std": [1 / 255] * 3})
        notes.append("looks like Metric3D's own export (input 'image' of raw pixels, "
                     "normalised in its graph): check that yours normalises inside too, "
                     "else use ImageNet's mean/std and no fill")
    elif {"out_k", "depth", "depth_ssi"} <= names:
        sug.recognised = "UniDepth V2"
        s["output"] = "metric_depth"
        notes.append("looks like UniDepth V2's export: ImageNet mean/std (the defaults)")
    elif kind is None:
        guess = ("relative_disparity" if "disp" in depth_name else
                 "metric_depth" if "metric" in depth_name else None)
        if guess:
            s["output"] = guess
            notes.append(f"output kind {guess!r} guessed from the output's name "
                         f"{outputs[depth_i].name!r}: check the model's documentation")
        else:
            notes.append("say what the network outputs (output: metric_depth, "
                         "relative_depth or relative_disparity; Depth Anything's and MiDaS's "
                         "relative models: relative_disparity)")
    if metadata.get("depth_kind"):
        notes.append(f"the model's metadata says what it needs (depth_kind "
                     f"{metadata['depth_kind']!r}" + ", ".join(
                         [""] + [k for k in ("input_height", "input_width", "mean", "std",
                                             "channel_order", "multiple_of")
                                 if k in metadata]) + ")")
    if hw is None and "input_size" not in s and "input_height" not in metadata:
        notes.append("the input size is free: set input_size (the size the network was "
                     "trained at; Depth Anything: 518, multiples of 14) or it runs at 518")
    elif hw is not None and s.get("resize") != "letterbox":
        notes.append(f"fixed input {hw[0]}x{hw[1]} (HxW): images of another aspect are "
                     "stretched; resize: letterbox keeps their aspect")
    if "mean" not in s and "mean" not in metadata and sug.recognised is None:
        notes.append("mean/std: ImageNet's unless set (Depth Anything, MiDaS DPT, UniDepth); "
                     "a model that normalises in its graph takes mean [0, 0, 0] and std 1/255")
    return sug


def read_model(path: Path) -> tuple[list[TensorInfo], list[TensorInfo], dict[str, str]]:
    """Inputs, outputs and metadata of an ONNX file, as onnxruntime sees them."""
    from toolkit.depth.onnx_backend import read_signature

    ins, outs, meta = read_signature(path)
    return ([TensorInfo(i.name, list(i.shape), i.type) for i in ins],
            [TensorInfo(o.name, list(o.shape), o.type) for o in outs], meta)


def stage_yaml(model: Path, sug: Suggestion) -> str:
    """A ``depth`` stage for a recipe, the open questions as comments above it."""
    import yaml

    stage = {"stage": "depth", "backend": "onnx", "model": str(model), **sug.settings}
    class Dumper(yaml.SafeDumper):
        """One key per line, lists inline: as a recipe is written."""

    Dumper.add_representer(list, lambda d, v: d.represent_sequence(
        "tag:yaml.org,2002:seq", v, flow_style=True))
    lines = yaml.dump(stage, Dumper=Dumper, sort_keys=False, default_flow_style=False,
                      width=92).splitlines()
    text = "".join(("- " if i == 0 else "  ") + line + "\n" for i, line in enumerate(lines))
    notes = "".join(textwrap.fill(n, 92, initial_indent="# ", subsequent_indent="#   ") + "\n"
                    for n in sug.notes)
    return notes + text


def _set_value(text: str) -> tuple[str, Any]:
    import yaml

    from toolkit.recipe.schema import read_yaml_value

    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--set {text!r}: give KEY=VALUE (e.g. "
                                         "output=relative_disparity, input_size=[518,518])")
    try:
        # As a recipe reads it (YAML 1.2): this prints a stage to paste into one.
        return key.strip(), read_yaml_value(value)
    except yaml.YAMLError as e:
        raise argparse.ArgumentTypeError(f"--set {text!r}: the value is not YAML ({e})"
                                         ) from None


def _camera(text: str) -> tuple[float, float, float, float]:
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--camera {text!r}: give fx,fy,cx,cy in pixels of "
                                         "the image") from None
    return fx, fy, cx, cy


def try_on_image(model: Path, settings: dict[str, Any], rgb: np.ndarray,
                 camera: tuple[float, float, float, float] | None) -> dict[str, Any]:
    """Run the depth stage's backend with ``settings`` on ``rgb`` [H, W, 3] uint8; what came
    out: latency, value percentiles, share of pixels with a value, and the prediction."""
    from toolkit.camera import PinholeCamera
    from toolkit.depth.stage import DepthConfig, make_backend

    cfg = DepthConfig(stage="depth", backend="onnx", model=model,
                      **{k: v for k, v in settings.items() if k not in ("stage", "backend",
                                                                         "model")})
    backend = make_backend(cfg)
    cam = None
    if camera is not None:
        cam = PinholeCamera(rgb.shape[1], rgb.shape[0], *camera)
    elif backend.needs_camera:
        raise ValueError("this model needs the camera (canonical_focal / intrinsics_input): "
                         "give --camera fx,fy,cx,cy")
    backend.predict(rgb, camera=cam)  # the first run pays for onnxruntime's warm-up
    pred = backend.predict(rgb, camera=cam)
    v = pred.values[np.isfinite(pred.values)]
    p1, p50, p99 = (np.percentile(v, [1, 50, 99]) if v.size else (np.nan,) * 3)
    return {"kind": pred.kind, "input_hw": list(pred.extra["input_hw"]),
            "latency_ms": 1000 * pred.latency_s, "valid_fraction": v.size / pred.values.size,
            "p1": float(p1), "median": float(p50), "p99": float(p99), "prediction": pred}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.depth.inspect_model",
                                 description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("model", type=Path, help="the .onnx file")
    ap.add_argument("--image", type=Path, default=None,
                    help="run the suggested settings on this image (PNG/JPEG)")
    ap.add_argument("--set", type=_set_value, action="append", default=[], metavar="KEY=VALUE",
                    help="override a suggested depth-stage setting (YAML value); repeatable")
    ap.add_argument("--camera", type=_camera, default=None, metavar="FX,FY,CX,CY",
                    help="the image's intrinsics (for canonical_focal / intrinsics_input)")
    ap.add_argument("--png", type=Path, default=None,
                    help="with --image: write the image beside its prediction here")
    a = ap.parse_args(argv)
    if a.image is not None and not a.image.is_file():
        # Said first, not after the model's whole printout as "not an image OpenCV can read"
        # (with OpenCV's own warning line above it) for a path that is simply not there.
        print(f"error: --image {a.image}: no such file (a relative path is read from "
              f"{Path.cwd()}); give the path of a PNG or JPEG frame", file=sys.stderr)
        return 2
    try:
        ins, outs, meta = read_model(a.model)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # onnxruntime's own types: a file it cannot load
        print(f"error: {a.model}: onnxruntime cannot load it ({str(e).strip()[:300]})",
              file=sys.stderr)
        return 2
    print(f"{a.model}")
    for title, items in (("inputs", ins), ("outputs", outs)):
        print(f"{title}:")
        for i, t in enumerate(items):
            print(f"  {i}: {t.name!r} {t.shape} {t.type}")
    print("metadata: " + (", ".join(f"{k}={v!r}" for k, v in sorted(meta.items())) or "none"))
    sug = suggest(ins, outs, meta)
    sug.settings.update(dict(a.set))
    from pydantic import ValidationError

    from toolkit.depth.stage import DepthConfig

    try:  # a misspelt --set key must not reach a recipe
        DepthConfig(stage="depth", backend="onnx", model=a.model, **sug.settings)
    except ValidationError as e:
        # The recipe's one-line messages (key, rule, value given, a close name for a typo),
        # not pydantic's dump with its web links.
        from toolkit.recipe.schema import format_validation_error

        given = " ".join(f"--set {k}" for k, _ in a.set)
        lines = format_validation_error(e, given or "the suggested settings", DepthConfig)
        print("error: these settings are not a valid depth stage: " + "\n  ".join(lines),
              file=sys.stderr)
        return 2
    if sug.recognised:
        print(f"recognised: {sug.recognised}")
    print("\ndepth stage:\n" + stage_yaml(a.model, sug))
    if a.image is None:
        return 0
    import cv2

    bgr = cv2.imread(str(a.image), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        print(f"error: {a.image}: not an image OpenCV can read", file=sys.stderr)
        return 2
    settings = dict(sug.settings)
    if "output" not in settings and "depth_kind" not in meta:
        settings["output"] = "relative_depth"
        print("(running as output: relative_depth to look at it; say the real kind)")
    try:
        res = try_on_image(a.model, settings, np.ascontiguousarray(bgr[..., ::-1]), a.camera)
    except Exception as e:  # the settings or the model: say which, do not trace
        print(f"error: running the model on {a.image}: {e}", file=sys.stderr)
        return 2
    print(f"ran on {a.image} ({bgr.shape[1]}x{bgr.shape[0]}): input {res['input_hw'][1]}x"
          f"{res['input_hw'][0]}, {res['latency_ms']:.0f} ms, {res['kind']}: 1 / 50 / 99 % "
          f"{res['p1']:.4g} / {res['median']:.4g} / {res['p99']:.4g}, "
          f"{100 * res['valid_fraction']:.1f} % of pixels have a value"
          + (" after the confidence threshold" if "confidence_index" in settings else ""))
    if a.png is not None:
        from toolkit.depth.stage import sample_figure

        sample_figure(a.png, 0, bgr[..., ::-1], res["prediction"])
        print(f"wrote {a.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
