"""Running test recipes: stages registered for the run only, a folder given as a sequence."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from toolkit.recipe import registry
from toolkit.recipe.runner import run_recipe
from toolkit.recipe.schema import load_recipe
from toolkit.recipe.stage import Stage, StageConfig


class SplatInputsConfig(StageConfig):
    frames: int = 12
    depth_folder: str = "scaled_depth"
    exposure_gain: float | None = None  # write this gain for every frame as fuse's would
    exposure_gain_frames: int | None = None  # ... for the first this many frames only
    exposure_gains: list[float] | None = None  # or each frame's own gain (all channels)
    width: int = 48
    height: int = 36
    gaussians: int = 2500


class SplatInputs(Stage):
    """A small synthetic room sequence and its fused folder, for the splat stage."""

    name = "t_splat_inputs"
    Config = SplatInputsConfig
    provides: tuple[str, ...] = ("sequence", "fused")

    def run(self, ctx: Any) -> None:
        from toolkit.splat.synthetic import write_synthetic_inputs

        cfg: Any = self.config
        seq, fused = write_synthetic_inputs(ctx.stage_dir, n_frames=cfg.frames, width=cfg.width,
                                            height=cfg.height, n_gaussians=cfg.gaussians,
                                            depth_folder=cfg.depth_folder)
        ctx.provide("sequence", seq)
        if cfg.exposure_gain is not None or cfg.exposure_gains is not None:
            from toolkit.fusion.exposure import EXPOSURE_FILE, write_exposure_gains

            if cfg.exposure_gains is not None:
                g = np.repeat(np.asarray(cfg.exposure_gains, np.float64)[:, None], 3, 1)
            else:
                n = cfg.frames if cfg.exposure_gain_frames is None else cfg.exposure_gain_frames
                g = np.full((n, 3), cfg.exposure_gain)
            write_exposure_gains(fused / EXPOSURE_FILE, [(i, float(i)) for i in range(len(g))],
                                 g)
        if "fused" in self.provides:
            ctx.provide("fused", fused)


class SplatSequenceOnly(SplatInputs):
    """The same room sequence without a fused map."""

    name = "t_seq_only"
    provides = ("sequence",)


class SequenceFolderConfig(StageConfig):
    path: str


class SequenceFolder(Stage):
    """Provide an existing sequence folder (copied: artifacts live in the stage's folder)."""

    name = "t_sequence"
    Config = SequenceFolderConfig
    provides = ("sequence",)

    def run(self, ctx: Any) -> None:
        dst = ctx.stage_dir / "seq"
        shutil.copytree(self.config.path, dst, dirs_exist_ok=True)  # type: ignore[attr-defined]
        ctx.provide("sequence", dst)


def run_stages(tmp_path: Path, stages: list[dict[str, Any]],
               register: dict[str, type[Stage]]) -> Any:
    """Run a recipe of ``stages`` (output ``tmp_path/run``) with ``register``'s stages
    added to the registry for this run only; returns the runner's result."""
    recipe = {"name": "t", "output": str(tmp_path / "run"), "stages": stages}
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    for name, cls in register.items():
        registry.register(name, cls)
    try:
        return run_recipe(load_recipe(path, []))
    finally:
        for name in register:
            registry.unregister(name)
