"""Simulate a recording: house -> robot drive -> camera + lidar -> sequence folder.

``simulate(config, out_dir)`` writes everything ``toolkit.io.sequence`` defines:
images, scans, odometry, rig, and the ground truth (``T_world_base`` at every sensor
stamp, z-depth per image, dynamic masks, per-beam dynamic flags, the static mesh,
held-out views off the driven path), plus ``groundtruth/house.json`` (layout, routes,
people tracks) for plots and evaluation.

Independent random streams (house, people, camera noise, lidar noise, odometry, stamps,
held-out views) come from one seed, so changing e.g. the number of people leaves the house
and the drive as they were, and the same seed reproduces the same bytes.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from toolkit.geometry import Trajectory, se2_to_se3
from toolkit.io.atomic import atomic_write_json, atomic_write_text
from toolkit.io.sequence import SequenceWriter
from toolkit.sensors import LaserScan, Rig
from toolkit.sim.house import House, generate_house
from toolkit.sim.people import Walker, plan_people, primitives_at
from toolkit.sim.robot import MotionLimits, OdometryNoise, RobotPath, plan_path, simulate_odometry
from toolkit.sim.scene import Scene
from toolkit.sim.sensors import CameraRenderer, CameraSpec, LidarRenderer, LidarSpec
from toolkit.sim.textures import build_texture_bank

log = logging.getLogger(__name__)
T_ = TypeVar("T_")

# Stream ids under the one seed (append only: changing one changes old outputs).
_STREAM = {"people": 2, "camera": 3, "lidar": 4, "odometry": 5, "heldout": 6, "stamps": 8}


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated recording."""

    preset: str = "small_house"  # small_house | large_building
    seed: int = 0
    duration_s: float | None = None  # None: one lap of the route (start to start)
    n_people: int = 2
    # (low, high) seconds: people stand this long (drawn per stop) at their routes' ends;
    # None: the usual 0.5-2 s pause
    people_stand_s: tuple[float, float] | None = None
    camera: CameraSpec = field(default_factory=CameraSpec)
    lidar: LidarSpec = field(default_factory=LidarSpec)
    motion: MotionLimits = field(default_factory=MotionLimits)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    n_heldout: int = 20
    depth_format: str = "png"  # png: 16-bit, 0.2 mm steps (compact); npy: float32 exact
    start_time: float = 1_700_000_000.0  # Unix seconds of the first stamp, as on a robot
    stamp_jitter_s: float = 0.002  # sensor stamps are not perfectly periodic
    name: str = "sim"


@dataclass
class SimWorld:
    """The world and drive of a configuration, before anything is rendered."""

    config: SimConfig
    house: House
    scene: Scene
    path: RobotPath
    walkers: list[Walker]
    rig: Rig


@dataclass
class SimResult:
    root: Path
    frames: int
    scans: int
    seconds: float
    frames_per_s: float
    loop_closed: bool
    world: SimWorld
    timings: dict[str, float] = field(default_factory=dict)


def _rng(config: SimConfig, stream: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([config.seed, _STREAM[stream]]))


def build_world(config: SimConfig) -> SimWorld:
    """House, scene (BVH built once), the robot's drive and the people's tracks."""
    house = generate_house(config.preset, config.seed)
    scene = Scene.from_boxes(house.boxes, build_texture_bank(config.seed))
    path = plan_path(house.route, house.start_yaw, config.motion, config.duration_s)
    walkers = plan_people(house.people_routes, path, config.n_people, _rng(config, "people"),
                          stand_s=config.people_stand_s)
    if len(walkers) < config.n_people:
        log.warning("placed %d of %d people: the others found no route clear of the robot",
                    len(walkers), config.n_people)
    rig = Rig(config.camera.camera(), config.camera.T_base_camera(), config.lidar.T_base_laser())
    return SimWorld(config, house, scene, path, walkers, rig)


def sensor_stamps(config: SimConfig, duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Relative camera and scan times [F], [S] (seconds from the start of the drive)."""
    rng = _rng(config, "stamps")
    j = config.stamp_jitter_s

    def stream(rate: float, offset: float) -> np.ndarray:
        t = offset + np.arange(0.0, duration - offset, 1.0 / rate)
        t = t + rng.uniform(-j, j, len(t))
        return np.unique(np.clip(t, 0.0, duration))  # sorted, no repeats (jitter > period)

    cam = stream(config.camera.rate_hz, 0.5 * j + 1e-3)
    las = stream(config.lidar.rate_hz, config.lidar.time_offset_s)
    if config.lidar.sweep:
        # A swept scan's beams run on past its stamp: only sweeps that end on the drive
        # (its last beams were rendered from the end pose, stamped past the ground truth).
        las = las[las + (config.lidar.beams - 1) * config.lidar.time_increment <= duration]
    return cam, las


def _identity(it: Iterable[T_], total: int | None = None, description: str = "") -> Iterator[T_]:
    return iter(it)


def simulate(config: SimConfig, out_dir: Path | str,
             progress: Callable[..., Iterator[Any]] | None = None) -> SimResult:
    """Render the recording of ``config`` into the sequence folder ``out_dir``."""
    progress = progress or _identity
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    world = build_world(config)
    timings["world_s"] = time.perf_counter() - t_start
    path, scene = world.path, world.scene
    cam_t, las_t = sensor_stamps(config, path.duration)
    if not len(cam_t) or not len(las_t):
        raise ValueError(
            f"the {path.duration:.3f} s drive holds {len(cam_t)} camera frames and "
            f"{len(las_t)} scans: make duration_s longer than lidar.time_offset_s "
            f"({config.lidar.time_offset_s} s) and than one period of each sensor")
    t0 = config.start_time

    writer = SequenceWriter(out_dir, world.rig, name=config.name,
                            source=f"toolkit.sim {config.preset} seed {config.seed}",
                            depth_format=config.depth_format)
    cam_r = CameraRenderer(scene, world.rig.camera)
    las_r = LidarRenderer(scene, config.lidar)
    T_bc, T_bl = world.rig.T_base_camera, world.rig.T_base_laser
    T_wb_cam = path.T_world_base(cam_t)
    T_wb_las = path.T_world_base(las_t)
    cam_rng, las_rng = _rng(config, "camera"), _rng(config, "lidar")
    spec = config.lidar

    t_render = time.perf_counter()
    # One writer thread: it keeps frames.csv in order, and PNG encoding (which releases
    # the GIL) overlaps the next frame's rendering.
    pending: deque[Future[int]] = deque()
    si = 0
    gains = np.ones(len(cam_t))  # the auto exposure's, frame by frame
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-writer") as pool:
        for k in progress(range(len(cam_t)), total=len(cam_t), description="simulate"):
            # The scans up to this image first: a frame is "its image and its scans".
            t_next = cam_t[k + 1] if k + 1 < len(cam_t) else np.inf
            while si < len(las_t) and las_t[si] < t_next:
                T_wl = T_wb_las[si] @ T_bl
                people = primitives_at(world.walkers, las_t[si])
                by_beams = None
                if spec.sweep:  # each beam from where the laser was when it fired
                    tb = np.minimum(las_t[si] + np.arange(spec.beams) * spec.time_increment,
                                    path.duration)
                    T_wl = path.T_world_base(tb) @ T_bl
                    # ... and the people where they were then (they walk 0.1 m in a sweep):
                    # in groups of beams a few milliseconds long.
                    by_beams = [(g, primitives_at(world.walkers, float(tb[g].mean())))
                                for g in np.array_split(np.arange(spec.beams),
                                                        max(1, spec.beams // 12))]
                ret = las_r.render(T_wl, people, las_rng, people_by_beams=by_beams)
                writer.add_scan(LaserScan(t0 + las_t[si], ret.ranges.astype(np.float32),
                                          spec.angle_min, spec.angle_increment,
                                          spec.range_min, spec.range_max,
                                          time_increment=spec.time_increment), ret.dynamic)
                si += 1
            img = cam_r.render(T_wb_cam[k] @ T_bc, primitives_at(world.walkers, cam_t[k]),
                               config.camera.noise_std, cam_rng, gain=gains[k])
            if k + 1 < len(cam_t):
                gains[k + 1] = config.camera.next_gain(gains[k], float(img.rgb.mean()))
            pending.append(pool.submit(writer.add_frame,
                                       t0 + cam_t[k] + config.camera.stamp_delay_s, img.rgb,
                                       img.depth, img.dynamic))
            while len(pending) > 6:
                pending.popleft().result()
        while pending:
            pending.popleft().result()
    timings["render_write_s"] = time.perf_counter() - t_render

    t_extra = time.perf_counter()
    _heldout(world, writer, cam_r, _rng(config, "heldout"), config.n_heldout)
    scene.write_ply(writer.mesh_path())

    sweep_ends = las_t + (spec.beams - 1) * spec.time_increment if spec.sweep else las_t[:0]
    # Ground truth and odometry at every sensor time, a sweep's last beam included (each
    # beam has a pose to be checked or de-skewed with).
    # With a camera stamp delay, the times the frames are stamped at too (the truth there
    # is where the robot was then, not where it took the image; before and after the drive
    # it stands at its ends).
    stamped = cam_t + config.camera.stamp_delay_s
    # The path's own samples inside each sweep too: the yaw rate changes within a sweep at
    # a corner, so interpolating between a sweep's first and last beam alone put a
    # mid-sweep beam's pose up to 0.74 deg off the one it was rendered from.
    in_sweep = np.zeros(len(path.t), dtype=bool)
    if spec.sweep:
        k = np.searchsorted(las_t, path.t, side="right") - 1  # the sweep begun last
        in_sweep = (k >= 0) & (path.t < sweep_ends[np.maximum(k, 0)])
    stamps = np.unique(np.concatenate([cam_t, las_t, sweep_ends, stamped, path.t[in_sweep]]))
    poses2d = path.pose2d(stamps)
    writer.groundtruth_poses = Trajectory(t0 + stamps, path.T_world_base(stamps), "world",
                                          "base_link")
    odo = simulate_odometry(poses2d, config.odometry, _rng(config, "odometry"))
    writer.odometry = Trajectory(t0 + stamps, np.stack([se2_to_se3(*p) for p in odo]), "odom",
                                 "base_link")
    loop_closed = path.laps >= 1.0 - 1e-9
    writer.extra_meta = {
        "simulator": {
            "preset": config.preset, "seed": config.seed, "duration_s": float(path.duration),
            "laps": float(path.laps), "loop_closed": bool(loop_closed),
            "cruise_speed_m_s": float(path.v_max), "path_length_m": float(path.length),
            "people": len(world.walkers), "start_time": config.start_time,
            "depth": "z-depth in metres (not ray length); masks: 255 = moving person",
            "scans": "NaN = dropout, +inf = beyond range_max or no return, -inf = too close",
            "config": _plain(_settings(config)),
        }
    }
    summary = world.house.summary()
    tt = np.arange(0.0, path.duration, 0.5)
    summary["people_tracks"] = [np.column_stack([t0 + tt, *[np.interp(tt, w.t, w.xy[:, i])
                                                             for i in range(2)]]).tolist()
                                for w in world.walkers]
    atomic_write_json(writer.root / "groundtruth" / "house.json", summary)
    if config.camera.auto_exposure:
        atomic_write_text(writer.root / "groundtruth" / "exposure_gain.csv",
                          "index,stamp,gain\n" + "".join(
                              f"{k},{float(t0 + cam_t[k] + config.camera.stamp_delay_s)!r},"
                              f"{float(gains[k])!r}\n" for k in range(len(cam_t))))
    writer.close()
    timings["extras_s"] = time.perf_counter() - t_extra
    seconds = time.perf_counter() - t_start
    return SimResult(writer.root, len(cam_t), len(las_t), seconds,
                     len(cam_t) / max(timings["render_write_s"], 1e-9), loop_closed, world,
                     timings)


def _settings(config: SimConfig) -> dict[str, Any]:
    """The configuration for meta.yaml; options left at None that recordings made before
    they existed did not have are left out, so those recordings come out byte for byte."""
    out = asdict(config)
    if out["people_stand_s"] is None:
        del out["people_stand_s"]
    return out


def _plain(x: Any) -> Any:
    """Tuples -> lists and numpy scalars -> Python numbers, for YAML."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def heldout_poses(world: SimWorld, rng: np.random.Generator, n: int) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Relative times [n] and ``T_world_camera`` [n, 4, 4] of views off the driven path.

    Each view starts from the robot's pose at a random time, then moves sideways by
    0.3-0.7 m, up or down, and turns and tilts, so it is near what the camera saw (novel
    view synthesis can be judged) but never on the path. Views inside furniture or closer
    than 0.3 m to a surface are redrawn.
    """
    from toolkit.sim.heldout import sample_heldout

    return sample_heldout(world, rng, n)


def _heldout(world: SimWorld, writer: SequenceWriter, cam_r: CameraRenderer,
             rng: np.random.Generator, n: int) -> None:
    if n <= 0:
        return
    times, poses = heldout_poses(world, rng, n)
    for t, T in zip(times, poses, strict=True):
        img = cam_r.render(T)  # static scene, noise-free: a clean reference image
        writer.add_heldout(world.config.start_time + t, T, img.rgb, img.depth)
