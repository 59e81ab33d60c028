"""The recipe stage ``simulate``: a simulated house recording as a sequence folder.

```yaml
- stage: simulate
  preset: small_house      # small_house | large_building
  seed: 0
  duration_s: 60           # omit for exactly one lap of the route (start to start)
  n_people: 2
  people_stand_s: [20, 40]   # people stand 20-40 s at their routes' ends (default: walk on)
  camera: {pitch_deg: 5, noise_std: 2.0}
  lidar: {noise_std: 0.01}
  odometry: {scale_bias: 0.01}
```
"""

from __future__ import annotations

import shutil
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolkit.recipe.stage import Stage, StageConfig, StageContext
from toolkit.settings import AddedOptions
from toolkit.sim.robot import MotionLimits, OdometryNoise
from toolkit.sim.sensors import CameraSpec, LidarSpec
from toolkit.sim.simulate import SimConfig, simulate


class _Settings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraSettings(_Settings):
    """Pinhole camera on the robot (defaults: 640x480, f = 525 px, 10 Hz)."""

    width: int = Field(640, gt=0)
    height: int = Field(480, gt=0)
    fx: float = Field(525.0, gt=0)
    fy: float = Field(525.0, gt=0)
    cx: float | None = None  # None: image centre
    cy: float | None = None
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    rate_hz: float = Field(10.0, gt=0)
    mount_xyz: tuple[float, float, float] = (0.10, 0.0, 0.45)  # in base_link, metres
    pitch_deg: float = 5.0  # positive looks down
    noise_std: float = Field(0.0, ge=0)  # grey levels; 0 = noise-free images
    # Image stamps this much later than the exposures, as many camera drivers give
    # (python -m calibration time-offset measures it; ingest's sync.camera_delay_s undoes it).
    stamp_delay_s: float = Field(0.0, ge=-1.0, le=1.0)
    # Auto exposure: each frame's gain moves the mean grey level towards the target
    # (docs/simulator.md); ground truth gains in groundtruth/exposure_gain.csv.
    auto_exposure: bool = False
    exposure_target: float = Field(110.0, gt=0, lt=255)
    exposure_speed: float = Field(0.3, gt=0, le=1)
    exposure_gain_range: tuple[float, float] = (0.4, 2.5)

    @model_validator(mode="after")
    def _gain_range(self) -> CameraSettings:
        lo, hi = self.exposure_gain_range
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"exposure_gain_range {list(self.exposure_gain_range)}: give "
                             "[low, high] with 0 < low <= 1 <= high")
        return self

    def spec(self) -> CameraSpec:
        return CameraSpec(**self.model_dump())


class LidarSettings(_Settings):
    """Planar lidar (defaults: 360 beams over 360 deg, 10 Hz, 0.12-12 m, 1 cm noise)."""

    beams: int = Field(360, gt=1)
    fov_deg: float = Field(360.0, gt=0, le=360)
    rate_hz: float = Field(10.0, gt=0)
    range_min: float = Field(0.12, ge=0)
    range_max: float = Field(12.0, gt=0)
    noise_std: float = Field(0.01, ge=0)
    dropout: float = Field(0.01, ge=0, le=1)
    grazing_dropout: float = Field(0.5, ge=0, le=1)  # more at grazing incidence (0: none)
    mount_xyz: tuple[float, float, float] = (0.0, 0.0, 0.25)
    time_offset_s: float = Field(0.043, ge=0)
    sweep: bool = False  # beams fired one after another over 1 / rate_hz (time_increment)

    @model_validator(mode="after")
    def _range(self) -> LidarSettings:
        if self.range_min >= self.range_max:
            raise ValueError(f"range_min ({self.range_min}) must be below range_max "
                             f"({self.range_max}): no beam would return")
        return self

    def spec(self) -> LidarSpec:
        return LidarSpec(**self.model_dump())


class OdometrySettings(_Settings):
    """Wheel odometry drift: biases and random walk (see toolkit.sim.robot.OdometryNoise)."""

    scale_bias: float = 0.01
    yaw_bias: float = 0.01
    trans_std: float = Field(0.01, ge=0)
    rot_std: float = Field(0.01, ge=0)
    rot_per_m_std: float = Field(0.005, ge=0)


class SimulateConfig(StageConfig, AddedOptions):
    """Settings of ``simulate``."""

    # Left at None, people_stand_s (session 26) is not part of the settings: simulate stages
    # made before it keep their cache key and are not simulated again for the same bytes.
    added_off = {"people_stand_s": None}

    preset: Literal["small_house", "large_building"] = "small_house"
    seed: int = 0
    duration_s: float | None = Field(None, gt=0)  # None: one lap, start to start
    n_people: int = Field(2, ge=0)
    # [low, high] seconds: each stop at a route's end lasts a time drawn from this range,
    # legs still (people who stand a while, then walk off); None: a 0.5-2 s pause
    people_stand_s: tuple[float, float] | None = None
    speed_m_s: float = Field(0.45, ge=0.3, le=0.6)  # cruise speed when duration_s is None
    n_heldout: int = Field(20, ge=0)
    depth_format: Literal["png", "npy"] = "png"
    camera: CameraSettings = CameraSettings()
    lidar: LidarSettings = LidarSettings()
    odometry: OdometrySettings = OdometrySettings()
    preview_frames: int = Field(4, ge=1)

    @model_validator(mode="after")
    def _stand_range(self) -> SimulateConfig:
        if self.people_stand_s is not None:
            lo, hi = self.people_stand_s
            if not 0 <= lo <= hi:
                raise ValueError(f"people_stand_s {list(self.people_stand_s)}: give [low, high] "
                                 "seconds with 0 <= low <= high")
        return self

    def sim_config(self, name: str = "sim") -> SimConfig:
        return SimConfig(
            preset=self.preset, seed=self.seed, duration_s=self.duration_s,
            n_people=self.n_people, people_stand_s=self.people_stand_s,
            camera=self.camera.spec(), lidar=self.lidar.spec(),
            motion=MotionLimits(v_max=self.speed_m_s),
            odometry=OdometryNoise(**self.odometry.model_dump()), n_heldout=self.n_heldout,
            depth_format=self.depth_format, name=name,
        )


class SimulateStage(Stage):
    """Simulate a robot with a camera and a 2D lidar driving a loop through a house."""

    name = "simulate"
    Config = SimulateConfig
    provides = ("sequence",)
    version = 3  # 2: swept scans: ground truth to the last beam, people per beam group;
    # 3: a lap whose south door lies beside the start closes, laps fill duration_s

    config: SimulateConfig

    def run(self, ctx: StageContext) -> None:
        from toolkit.sim.preview import plot_topdown, preview_strip

        cfg = self.config
        out = ctx.stage_dir / "sequence"
        if out.exists():
            # Regenerating is quicker than checking what an interrupted run left behind.
            shutil.rmtree(out)
        res = simulate(cfg.sim_config(f"{cfg.preset}-seed{cfg.seed}"), out, ctx.progress)
        ctx.log.info("simulated %d frames and %d scans in %.1f s (%.1f frames/s)", res.frames,
                     res.scans, res.seconds, res.frames_per_s)
        strip = preview_strip(out, ctx.stage_dir / "preview.png", cfg.preview_frames)
        top = plot_topdown(out, ctx.stage_dir / "topdown.png")
        path = res.world.path
        ctx.add_metrics({
            "frames": res.frames,
            "scans": res.scans,
            "seconds": round(res.seconds, 3),
            "frames_per_s": round(res.frames_per_s, 2),
            "duration_s": round(path.duration, 3),
            "path_length_m": round(path.length, 3),
            "loop_closed": res.loop_closed,
            "people": len(res.world.walkers),
            "rooms": len(res.world.house.rooms),
        })
        rel = ctx.stage_id
        ctx.report(
            f"Simulated `{cfg.preset}` (seed {cfg.seed}): {res.frames} images and {res.scans} "
            f"scans over {path.duration:.1f} s, {path.length:.1f} m driven at up to "
            f"{path.v_max:.2f} m/s, {len(res.world.walkers)} people, loop "
            f"{'closed' if res.loop_closed else 'NOT closed (duration too short)'}; "
            f"generated in {res.seconds:.1f} s (rendering and writing the frames: "
            f"{res.frames_per_s:.1f} frames/s).\n\n"
            f"![frames and ground-truth depth]({rel}/{strip.name})\n\n"
            "Top: camera frames, moving people outlined; below: ground-truth depth, blue "
            "near to red at 8 m, black none.\n\n"
            f"![house, path and lidar scans]({rel}/{top.name})"
        )
        ctx.provide("sequence", out)
