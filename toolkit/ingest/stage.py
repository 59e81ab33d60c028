"""The recipe stage ``ingest``: a real recording in, a sequence folder out.

```yaml
- stage: ingest
  source: rosbag            # rosbag | tum_rgbd | carmen | sequence
  path: data/run.bag        # ROS 1 .bag (or a list of split ones), ROS 2 bag folder,
                            # TUM RGB-D folder, CARMEN log / g2o file, sequence folder
  sync: {tolerance_s: 0.05}
  decimate: {by: time, min_interval_s: 0.5}
  rosbag: {topics: {...}, frames: {...}, calibration: calib.yaml}
```

It prints what it found (topics, counts, rates, time span, the sync plan) before
converting, shows a progress bar while converting, and resumes an interrupted
conversion: the frames it had written are kept as long as the input and the settings
are the ones it was converting (a fingerprint in the stage folder says so).
"""

from __future__ import annotations

import functools
import hashlib
import json
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import model_validator

from toolkit.ingest.convert import ConvertResult, convert
from toolkit.ingest.recording import FrameData, IngestError, Recording
from toolkit.ingest.sync import DecimateOptions, SyncOptions
from toolkit.io.atomic import atomic_write_text
from toolkit.io.carmen_ingest import CarmenOptions
from toolkit.io.rosbag import RosbagOptions
from toolkit.io.tum_rgbd import TumRgbdOptions
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError

SOURCES = ("rosbag", "tum_rgbd", "carmen", "sequence")
KEY_FILE = "ingest.key"


class IngestConfig(StageConfig):
    """Settings of ``ingest`` (see the module docstring and docs/ingest.md)."""

    source: Literal["rosbag", "tum_rgbd", "carmen", "sequence"]
    path: str | list[str]
    name: str | None = None  # sequence name; default: the input's file or folder name
    sync: SyncOptions = SyncOptions()
    decimate: DecimateOptions = DecimateOptions()
    on_non_monotonic: Literal["error", "drop"] = "error"
    depth_format: Literal["png", "npy"] = "png"  # png: 0.2 mm steps; npy: exact float32
    resume: bool = True
    rosbag: RosbagOptions | None = None
    tum_rgbd: TumRgbdOptions | None = None
    carmen: CarmenOptions | None = None

    @model_validator(mode="after")
    def _options_match_source(self) -> IngestConfig:
        for key in ("rosbag", "tum_rgbd", "carmen"):
            if getattr(self, key) is not None and key != self.source:
                raise ValueError(f"'{key}' options are given but source is {self.source!r}; "
                                 f"remove them or set 'source: {key}'")
        if isinstance(self.path, list) and self.source != "rosbag":
            raise ValueError("a list of paths is only for split ROS 1 bags (source: rosbag)")
        return self

    def paths(self) -> list[Path]:
        return [Path(p) for p in ([self.path] if isinstance(self.path, str) else self.path)]


class IngestStage(Stage):
    """Convert a real recording (ROS bag, TUM RGB-D, CARMEN/g2o, sequence) into a sequence."""

    name = "ingest"
    Config = IngestConfig
    provides = ("sequence",)
    # 2: frames by (stamp, bag time); rectified R; lens models; decimation
    # 3: a JPEG frame's EXIF orientation tag is not applied (a 180-degree tag rolled the
    #    images against the rig; a 90-degree one failed the size check)
    # 4: a sequence's exposure gains and house.json kept; TUM beams beyond range_max +inf;
    #    frames kept without a scan counted; a dropped CARMEN line counted once
    # 5: a CompressedImage labelled 'compressed rgb8' keeps its channel order (red and blue
    #    were swapped); Bayer mosaics demosaiced (a compressed one was stored grey);
    #    a CameraInfo roi gives the window's intrinsics; scans of the common beam count
    #    keep their own bearings (they were resampled onto the first one's)
    # 6: YUV 4:2:2 and 16-bit images are read (they were refused); without an 8-bit colour
    #    topic a YUV / 16-bit colour one beats a Bayer mosaic, and a mosaic a grey (mono8,
    #    mono16) one (an 8-bit mosaic beside a raw YUV / 16-bit stream won; a mono8 topic
    #    beside either won); a depth topic's /compressed is no colour candidate
    # 7: a CompressedImage's JPEG (and a sequence's JPEG frames) stored as they are where
    #    every reader decodes them to the same pixels, not re-encoded as a PNG (7.7x
    #    the bag on disk, 14 of a frame's 17 ms)
    version = 7

    config: IngestConfig

    def external_inputs(self) -> list[Path]:
        """The recording (and calibration file): a changed bag reruns the stage."""
        paths = self.config.paths()
        if self.config.rosbag is not None and self.config.rosbag.calibration:
            paths.append(Path(self.config.rosbag.calibration))
        return paths

    def run(self, ctx: StageContext) -> None:
        cfg = self.config
        out = ctx.stage_dir / "sequence"
        key = _fingerprint(cfg, self.external_inputs())
        key_file = ctx.stage_dir / KEY_FILE
        old = key_file.read_text() if key_file.exists() else None
        if out.exists() and (not cfg.resume or old != key):
            # Another input or other settings: what is there must not be resumed into.
            shutil.rmtree(out)
        atomic_write_text(key_file, key)
        try:
            rec = open_source(cfg, ctx)
            result = convert(rec, out, cfg.sync, cfg.decimate, cfg.depth_format,
                             resume=cfg.resume, progress=ctx.progress, log=ctx.log)
        except (IngestError, FileNotFoundError) as e:
            raise StageError(str(e)) from e
        ctx.log.info("%s", result.summary())
        ctx.add_metrics(result.metrics())
        ctx.report(_report(cfg, rec, result))
        ctx.provide("sequence", out)


def open_source(cfg: IngestConfig, ctx: StageContext | None = None) -> Recording:
    """The ``Recording`` of the configured source (the reader's index pass)."""
    log = ctx.log if ctx is not None else None
    progress = ctx.progress if ctx is not None else None
    paths = cfg.paths()
    if cfg.source == "rosbag":
        from toolkit.io.rosbag import read_rosbag

        return read_rosbag(paths if len(paths) > 1 else paths[0], cfg.rosbag,
                           cfg.on_non_monotonic, progress, log, cfg.name)
    if cfg.source == "tum_rgbd":
        from toolkit.io.tum_rgbd import read_tum_rgbd

        return read_tum_rgbd(paths[0], cfg.tum_rgbd, cfg.on_non_monotonic, progress, log,
                             cfg.name)
    if cfg.source == "carmen":
        from toolkit.io.carmen_ingest import read_carmen_recording

        return read_carmen_recording(paths[0], cfg.carmen, cfg.on_non_monotonic, log, cfg.name)
    return read_sequence_recording(paths[0], cfg.name)


def read_sequence_recording(root: Path, name: str | None = None) -> Recording:
    """An existing sequence folder as a ``Recording`` (to re-sync, decimate or copy it)."""
    from toolkit.io.sequence import SequenceFormatError, copy_groundtruth_files, read_sequence

    try:
        seq = read_sequence(root)
    except SequenceFormatError as e:
        raise IngestError(str(e)) from None
    gt = seq.groundtruth

    def load(pairs: Sequence[tuple[int, int]]) -> Iterator[FrameData]:
        for f, _ in pairs:
            fr = seq.frames[f]
            yield FrameData(stamp=fr.stamp, image_path=fr.path,
                            depth=gt.depth(f) if gt is not None and gt.depth_paths else None,
                            mask=gt.mask(f) if gt is not None and gt.mask_paths else None)

    meta = {k: v for k, v in seq.meta.items()
            if k not in ("format", "version", "name", "source", "frames", "scans", "ingest")}
    ingest = seq.meta.get("ingest")
    applied = float(ingest.get("camera_delay_s") or 0.0) if isinstance(ingest, dict) else 0.0
    return Recording(
        name=name or seq.name, source=f"sequence {root}", rig=seq.rig, scans=seq.scans,
        frame_stamps=seq.frame_stamps, load=load, odometry=seq.odometry,
        groundtruth=gt.poses_base if gt is not None else None,
        has_camera=bool(meta.pop("has_camera", True)) and bool(seq.frames), meta=meta,
        scan_dynamic=gt.scan_dynamic if gt is not None else None,
        finish=functools.partial(copy_groundtruth_files, seq),
        camera_delay_applied_s=applied)


def _fingerprint(cfg: IngestConfig, inputs: list[Path]) -> str:
    """Settings plus size and mtime of every input file (a bag folder: each file)."""
    files = []
    for p in inputs:
        p = p.absolute()
        for f in sorted([p] if p.is_file() else (x for x in p.rglob("*") if x.is_file())):
            st = f.stat()
            files.append([str(f), st.st_size, st.st_mtime_ns])
    text = json.dumps({"config": cfg.model_dump(mode="json", exclude={"id"}), "files": files},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _report(cfg: IngestConfig, rec: Recording, res: ConvertResult) -> str:
    p = res.plan
    rows = [
        ("source", f"{cfg.source}: `{rec.source.split(' ', 1)[-1]}`"),
        ("camera frames", f"{res.frames} of {p.candidates}" if rec.has_camera else
         "none (lidar only)"),
        ("dropped: no scan within tolerance", str(p.dropped.get("no_scan", 0))),
        *([("kept without a scan within tolerance", str(p.without_scan))]
          if p.without_scan else []),
        ("dropped: no depth within tolerance", str(p.dropped.get("no_depth", 0))),
        ("decimated", f"{p.decimated} ({cfg.decimate.by})"),
        ("scans", str(res.scans)),
        ("odometry / ground truth", f"{'yes' if res.has_odometry else 'no'} / "
         f"{'yes' if res.has_groundtruth else 'no'}"),
        ("resumed frames", str(res.frames_resumed)),
    ]
    if res.dropped_indexing:
        rows.append(("non-monotonic messages dropped", ", ".join(
            f"{k}: {v}" for k, v in res.dropped_indexing.items())))
    if res.skipped_invalid:
        rows.append(("odometry messages left out as no pose", "; ".join(
            f"{k}: {r['count']} of {r['of']} (first stamps "
            f"{', '.join(f'{t:.3f}' for t in r['first_stamps_s'])} s; longest gap "
            f"{r['longest_gap_s']:.2f} s, {r['gaps_not_interpolated']} not interpolated "
            "across)" for k, r in res.skipped_invalid.items())))
    if res.frames_16bit_scaled:
        rows.append(("16-bit frames scaled to 8 bits", f"{res.frames_16bit_scaled} (brightest "
                     f"sample {res.peak_16bit} of 65535)"))
    if res.frames_16bit_clipped:
        rows.append(("16-bit frames clipped at 255 by the recording's JPEG codec",
                     str(res.frames_16bit_clipped)))
    if res.tf_skipped_invalid:
        rows.append(("tf transforms skipped (no rigid motion)", ", ".join(
            f"{k}: {n}" for k, n in res.tf_skipped_invalid.items())))
    span = [s.stamp for s in rec.scans]
    if span:
        rows.append(("time span", f"{float(np.ptp(span)):.1f} s"))
    lines = ["| | |", "|---|---|"] + [f"| {a} | {b} |" for a, b in rows]
    return "\n".join(lines)
