"""Recipe stage ``depth``: a monocular depth prediction for every camera frame."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from toolkit.depth.onnx_backend import (
    OnnxDepthBackend,
    OnnxDepthConfig,
    external_data_files,
    model_problem,
    positive_input_size,
    resize_problem,
    settings_problem,
)
from toolkit.depth.protocol import DepthKind
from toolkit.depth.simulated import PRESETS, SimulatedDepthBackend, SimulatedDepthParams
from toolkit.depth.store import DepthStore, DepthStoreWriter
from toolkit.io.prefetch import prefetched
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError
from toolkit.recipe.timing import WorkTimer


class DepthConfig(StageConfig):
    """Settings of the ``depth`` stage (onnx keys apply to ``backend: onnx`` only)."""

    # dav2s_random: a Depth-Anything-V2-Small-sized network (ViT-S/14 + DPT) with RANDOM
    # weights, built and exported here at ``input_size``: its depth is meaningless, it
    # exists so a benchmark can time a network of that size without any download.
    backend: Literal["onnx", "simulated", "dav2s_random"] = "onnx"
    # --- onnx
    model: Path | None = None
    output: DepthKind | None = None  # what the network outputs; None: the model's metadata
    input_size: tuple[int, int] | int | None = None
    resize: Literal["stretch", "keep_aspect", "letterbox"] = "stretch"
    multiple_of: int | None = Field(None, ge=1)  # 1: no rounding
    interpolation: Literal["linear", "cubic", "area", "nearest"] = "cubic"
    # per network input channel, in its channel_order (None: the model's metadata, else
    # ImageNet's, reversed for bgr)
    mean: tuple[float, float, float] | None = None
    std: tuple[float, float, float] | None = None
    channel_order: Literal["rgb", "bgr"] | None = None
    layout: Literal["nchw", "nhwc"] = "nchw"
    output_index: int = Field(0, ge=0)  # which output is the depth (models with several)
    output_scale: float = Field(1.0, gt=0)
    # Metric3D: the focal length (px) of the canonical camera its depth is for (1000)
    canonical_focal: float | None = Field(None, gt=0)
    # letterbox fill, 0-255 per network input channel (None: the mean colour)
    fill: tuple[float, float, float] | None = None
    intrinsics_input: str | None = None  # the model input that takes the camera (UniDepth)
    # a confidence output (UniDepth V2: 3); pixels below min_confidence are dropped
    confidence_index: int | None = Field(None, ge=0)
    min_confidence: float = 0.0
    threads: int = Field(2, ge=1)
    device: Literal["auto", "cpu", "cuda"] = "auto"  # cuda: needs onnxruntime-gpu
    # --- simulated: a preset, then per-parameter overrides
    preset: Literal["paper", "scale_only", "hard", "groundtruth"] = "paper"
    simulated: dict[str, Any] = Field(default_factory=dict)
    # --- storage
    # float16 halves the files; magnitudes above 65504 are then stored invalid (NaN) and
    # counted in pixels_beyond_float16, non-zero ones below 6e-8 as +-6e-8 (depth.store)
    dtype: Literal["float32", "float16"] = "float32"
    every: int = Field(1, ge=1)  # predict every n-th frame only
    # Decode the next images in a thread while the network runs (quickstart 13.4 -> 9.2 s);
    # the thread's CPU then counts in the measured work. Benchmarks that report it: false.
    prefetch: bool = True

    @field_validator("input_size")
    @classmethod
    def _positive_size(cls, v: Any) -> Any:
        return positive_input_size(v)

    @model_validator(mode="after")
    def _simulated_keys(self) -> DepthConfig:
        # Checked here, with the recipe, not when the stage finally runs: a typo under
        # simulated: must stop `validate`, as any other unknown key does.
        unknown = sorted(set(self.simulated) - set(SimulatedDepthParams.model_fields))
        if unknown:
            raise ValueError(f"simulated: unknown key(s) {unknown}; allowed: "
                             f"{sorted(SimulatedDepthParams.model_fields)}")
        params = {**PRESETS[self.preset], **self.simulated}
        try:
            SimulatedDepthParams(**params)
        except ValidationError as e:
            raise ValueError(f"simulated: {e}") from None
        if (self.backend == "simulated" and self.output is not None and "kind" in params
                and params["kind"] != self.output):
            # The preset's or simulated.kind's kind won without a word: the recipe said one
            # kind and the stage wrote another.
            where = "simulated.kind" if "kind" in self.simulated else f"preset {self.preset}"
            raise ValueError(f"output is {self.output} but {where} makes "
                             f"{params['kind']}; set one of them, or both alike")
        return self

    @model_validator(mode="after")
    def _backend_needs(self) -> DepthConfig:
        # With the recipe too, so that `validate` refuses what the stage would refuse
        # after hours of earlier stages.
        if self.backend == "onnx" and self.model is None:
            raise ValueError("backend 'onnx' needs 'model' (path to an .onnx file), e.g. "
                             "datasets/models/small-depth.onnx")
        problem = settings_problem(self.output, self.canonical_focal, self.min_confidence,
                                   self.confidence_index)
        if problem:
            raise ValueError(problem)
        problem = None if self.backend == "simulated" else resize_problem(self.resize,
                                                                          self.input_size)
        if problem:
            raise ValueError(problem)
        if self.backend == "dav2s_random":
            try:
                _input_hw(self.input_size)
            except StageError as e:
                raise ValueError(str(e).removeprefix("depth: ")) from None
        return self


def _input_hw(size: tuple[int, int] | int | None) -> tuple[int, int]:
    if size is None:
        raise StageError("depth: backend 'dav2s_random' needs input_size: [H, W] (multiples "
                         "of 14, e.g. [266, 350])")
    h, w = (size, size) if isinstance(size, int) else size
    if h % 14 or w % 14:
        raise StageError(f"depth: input_size {h}x{w}: a ViT-S/14 needs multiples of 14 "
                         f"(e.g. {14 * round(h / 14)}x{14 * round(w / 14)})")
    return int(h), int(w)


def _device(backend: Any) -> str:
    """cuda or cpu: where the backend's network ran."""
    providers = getattr(backend, "providers", ["CPUExecutionProvider"])
    return "cuda" if providers[0] == "CUDAExecutionProvider" else "cpu"


def _camera_settings(backend: Any, camera: Any) -> dict[str, Any]:
    """Where the image lies in the network input and the canonical-focal factor, known
    before the first frame (``meta.json`` is written from ``describe()`` before any frame;
    a resumed run may predict none)."""
    hw = (camera.height, camera.width)
    out: dict[str, Any] = {}
    if callable(getattr(backend, "placement", None)):
        out["placement"] = list(backend.placement(hw))
    if getattr(getattr(backend, "config", None), "canonical_focal", None) is not None:
        out["focal_factor"] = backend.focal_factor(camera, hw)
    return out


def make_backend(cfg: DepthConfig) -> Any:
    """The configured backend (onnxruntime is imported only for ``onnx``)."""
    if cfg.backend == "simulated":
        params = {**PRESETS[cfg.preset], **cfg.simulated}
        if cfg.output is not None:
            params.setdefault("kind", cfg.output)
        return SimulatedDepthBackend(SimulatedDepthParams(**params))
    return OnnxDepthBackend(onnx_config(cfg))


def onnx_config(cfg: DepthConfig) -> OnnxDepthConfig:
    """The onnx backend's settings of a depth stage (``backend: onnx``)."""
    if cfg.model is None:
        raise StageError("depth: backend 'onnx' needs 'model' (path to an .onnx file), e.g. "
                         "datasets/models/small-depth.onnx")
    return OnnxDepthConfig(
        model=cfg.model, kind=cfg.output, input_size=cfg.input_size, resize=cfg.resize,
        multiple_of=cfg.multiple_of, interpolation=cfg.interpolation, mean=cfg.mean,
        std=cfg.std, channel_order=cfg.channel_order, layout=cfg.layout,
        output_index=cfg.output_index, output_scale=cfg.output_scale, threads=cfg.threads,
        device=cfg.device, canonical_focal=cfg.canonical_focal, fill=cfg.fill,
        intrinsics_input=cfg.intrinsics_input, confidence_index=cfg.confidence_index,
        min_confidence=cfg.min_confidence)


class DepthStage(Stage):
    """Monocular depth for every frame (onnx network or simulated from ground truth)."""

    name = "depth"
    Config = DepthConfig
    requires = ("sequence",)
    # rig: a calibrated camera (calibrate), whose intrinsics a Metric3D / UniDepth export
    # takes, as the fuse stage uses them (it used the sequence's own)
    optional_requires = ("rig",)
    provides = ("depth",)
    # 2: BGR default normalisation; input_hw recorded; order-free wander. 3: simulated: the
    # wander's first value drawn before its steps (no jump at frames 256, 512, ...), the
    # noise normalised by OpenCV's own kernel. 4: simulated: invalid ground truth stays
    # invalid (was filled with 20 m and blurred into its valid neighbours)
    # 5: onnx letterbox: output pixels wholly in the fill left out of the resize back (a
    #    coarse output blended the fill's guess into the image's border); float16 storage
    #    writes magnitudes above 65504 invalid and counts them (they were inf)
    version = 5
    # The same depth maps on any thread count or device (up to float rounding): an
    # interrupted run's frames stay, and a finished run stays cached (--only reruns it
    # for its timings).
    speed_settings = frozenset({"threads", "device", "prefetch"})
    outputs_repeat = False  # index.csv holds each frame's latency
    # The model is keyed by its bytes: the same file in a moved checkout, a git worktree or
    # a colleague's copy of the run folder keeps an hour of depth cached, and other weights
    # copied over it (same size, mtime kept) rerun it.
    external_by_content = True

    def external_inputs(self) -> list[Path]:
        cfg: DepthConfig = self.config  # type: ignore[assignment]
        if cfg.backend != "onnx" or cfg.model is None:
            return []
        # With the weights in files of their own (external data), those are the network
        # too: other weights copied over model.onnx.data must rerun the stage.
        return [Path(cfg.model), *external_data_files(Path(cfg.model))]

    def input_problems(self) -> list[str]:
        # The model's inputs, outputs and metadata against the settings, as the backend
        # checks them when it loads the model: a missing depth_kind, an output_index past
        # the outputs or keep_aspect on a fixed input stopped the run only once the stages
        # before depth had run.
        cfg: DepthConfig = self.config  # type: ignore[assignment]
        if cfg.backend != "onnx" or cfg.model is None:
            return []
        problem = model_problem(onnx_config(cfg))
        return [problem] if problem else []

    @staticmethod
    def _random_model(cfg: DepthConfig, ctx: StageContext) -> DepthConfig:
        """Export the random-weight ViT-S/14 + DPT once into the stage folder; run it as an
        ONNX model."""
        from toolkit.depth.bench_latency import export_onnx, vit_s14_dpt

        h, w = _input_hw(cfg.input_size)
        path = ctx.stage_dir / f"dav2s_random_{h}x{w}.onnx"
        if not path.exists():
            import torch

            torch.manual_seed(0)
            ctx.log.info("depth: exporting a random-weight ViT-S/14 + DPT at %dx%d", h, w)
            export_onnx(vit_s14_dpt(), path, h, w, random_weights=True)
        return cfg.model_copy(update={"backend": "onnx", "model": path})

    def run(self, ctx: StageContext) -> None:
        from toolkit.io.sequence import SequenceFormatError, read_sequence, sequence_with_rig

        cfg: DepthConfig = self.config  # type: ignore[assignment]
        seq = read_sequence(ctx.artifact("sequence"))
        if ctx.has_artifact("rig"):
            try:
                seq = sequence_with_rig(seq, ctx.artifact("rig"))
            except SequenceFormatError as e:
                raise StageError(f"depth: {e}") from None
        if not seq.frames:
            raise StageError(f"depth: sequence {seq.name} has no camera frames")
        random_weights = cfg.backend == "dav2s_random"
        if random_weights:
            cfg = self._random_model(cfg, ctx)
        try:
            backend = make_backend(cfg)
        except FileNotFoundError as e:
            raise StageError(str(e)) from None
        except ValueError as e:  # settings the model or this machine cannot honour
            raise StageError(f"depth: {e}") from None
        gt = seq.groundtruth
        if cfg.backend == "simulated" and (gt is None or gt.depth_paths is None):
            raise StageError(f"depth: backend 'simulated' needs ground-truth depth, which "
                             f"sequence {seq.name} lacks; use backend 'onnx' for real data")
        out = ctx.stage_dir / "depth"
        info = backend.describe()
        input_hw = getattr(backend, "input_hw", None)
        if callable(input_hw) and info.get("input_hw") is None:
            # The network input these frames take (after rounding to whole patches), known
            # before the first prediction: meta.json recorded null.
            info["input_hw"] = list(input_hw((seq.rig.camera.height, seq.rig.camera.width)))
        try:
            info.update(_camera_settings(backend, seq.rig.camera))
        except ValueError as e:  # intrinsics that are not those of the images
            raise StageError(f"depth: {e}") from None
        writer = DepthStoreWriter(out, backend.kind, info, cfg.dtype,
                                  resume_key=ctx.resume_key or None)
        indices = list(range(0, len(seq.frames), cfg.every))
        done = writer.done
        todo = [i for i in indices if i not in done]
        if writer.resumed:
            ctx.log.info("depth: resuming, %d of %d frames kept from an interrupted run",
                         len(indices) - len(todo), len(indices))
        # Only inference is work: image decoding and the simulated backend's ground-truth
        # read stand for what a live camera driver delivers.
        timer = WorkTimer()
        simulated = cfg.backend == "simulated"

        # A Metric3D / UniDepth export needs the camera the images were taken with.
        camera = ({"camera": seq.rig.camera} if getattr(backend, "needs_camera", False)
                  else {})

        def load(i: int) -> tuple[np.ndarray, dict]:
            # In a thread, ahead of the network (image decoding releases the GIL).
            return seq.frames[i].image, (
                {"gt_depth": gt.depth(i), "frame_index": i} if simulated else camera)

        frames = prefetched(load, todo, 2 if cfg.prefetch else 0)
        for i, (rgb, kwargs) in ctx.progress(frames, total=len(todo), description="depth"):
            with timer:
                pred = backend.predict(rgb, **kwargs)
            writer.add(i, seq.frames[i].stamp, pred)
        writer.close()
        ctx.provide("depth", out)
        lat = np.array([float(r["latency_s"]) for r in writer.rows])
        kept = [float(r["confident_fraction"]) for r in writer.rows if "confident_fraction" in r]
        metrics = {"frames": len(indices), "kind": backend.kind, "backend": cfg.backend,
                   "frames_resumed": len(indices) - len(todo),
                   "latency_mean_s": float(lat.mean()), "latency_median_s": float(np.median(lat)),
                   "fps": float(1.0 / lat.mean()) if lat.mean() > 0 else None,
                   "device": _device(backend),
                   **timer.metrics(len(todo)),
                   # of the pixels with depth, the share the confidence kept
                   **({"confident_fraction_mean": float(np.mean(kept))} if kept else {}),
                   # magnitudes above 65504, stored as invalid (NaN), not as inf
                   **({"pixels_beyond_float16": writer.beyond_float16}
                      if cfg.dtype == "float16" else {})}
        if writer.beyond_float16:
            ctx.log.warning("depth: %d pixels beyond float16's range (magnitude above 65504) "
                            "stored as invalid; store dtype float32 to keep them",
                            writer.beyond_float16)
        # The first frame as stored, whichever run predicted it: a resumed run draws the
        # figure a whole one does (it drew the first frame predicted after the restart).
        i = indices[0]
        first_pred = (i, seq.frames[i].image, DepthStore(out).read(i))
        ctx.add_metrics(metrics)
        if random_weights:
            ctx.add_metrics({"random_weights": True})
        label = ("**simulated** monocular depth (made from ground truth with the documented "
                 f"errors of preset `{cfg.preset}`; true sequence scale "
                 f"{info.get('sequence_scale', float('nan')):.3f})"
                 if cfg.backend == "simulated" else f"ONNX network `{cfg.model}`"
                 + (" (**RANDOM WEIGHTS, timing only: the depth is meaningless**)"
                    if random_weights else ""))
        resumed = (f" ({metrics['frames_resumed']} kept from an interrupted run)"
                   if metrics["frames_resumed"] else "")
        where = "" if simulated else (" on the GPU (onnxruntime CUDA)" if (
            metrics["device"] == "cuda") else f" on the CPU ({cfg.threads} threads)")
        md = [f"Depth from {label}; output kind `{backend.kind}`, {len(indices)} frames"
              f"{resumed}, {'simulation' if simulated else 'network'} time "
              f"{metrics['latency_mean_s'] * 1000:.1f} ms/frame "
              f"(median {metrics['latency_median_s'] * 1000:.1f} ms){where}."]
        if writer.beyond_float16:
            md.append(f"**{writer.beyond_float16} pixels beyond float16's range** (magnitude "
                      "above 65504) were stored as invalid (`dtype: float32` keeps them).")
        if kept:
            md.append(f"The network's confidence (output {cfg.confidence_index}, at least "
                      f"{cfg.min_confidence:g}) kept {100 * float(np.mean(kept)):.1f} % of the "
                      "pixels with depth (mean over frames).")
        if info.get("focal_factor") is not None:
            md.append(f"Canonical camera depth (focal {cfg.canonical_focal:g} px) times "
                      f"{info['focal_factor']:.4f}, this camera's focal length at the network "
                      "input over it.")
        fig = ctx.stage_dir / "depth_sample.png"
        sample_figure(fig, *first_pred)
        md.append(f"![image and prediction]({ctx.stage_id}/{fig.name})")
        ctx.report("\n\n".join(md))


def sample_figure(path: Path, index: int, rgb: np.ndarray, pred: Any) -> None:
    """Frame ``index``'s image [H, W, 3] beside its prediction (turbo, with a colour bar)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from toolkit.io.atomic import atomic_path

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    ax[0].imshow(rgb)
    ax[0].set_title(f"frame {index}")
    im = ax[1].imshow(pred.values, cmap="turbo")
    ax[1].set_title(pred.kind.replace("_", " "))
    fig.colorbar(im, ax=ax[1], fraction=0.046)
    for a in ax:
        a.axis("off")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
