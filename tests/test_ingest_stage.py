"""The ``ingest`` recipe stage end to end, the CARMEN / sequence sources, and the pure sync
helpers."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_ingest_rosbag import make_bag, ns

from toolkit.ingest.convert import convert
from toolkit.ingest.recording import IngestError, uniform_scans
from toolkit.ingest.stage import IngestConfig, IngestStage, read_sequence_recording
from toolkit.ingest.sync import (
    DecimateOptions,
    SyncOptions,
    decimate_by_time,
    match_nearest,
    plan_frames,
    stamps_keep,
)
from toolkit.io.carmen_ingest import CarmenOptions, read_carmen_recording
from toolkit.io.rosbag import read_rosbag
from toolkit.io.sequence import SequenceWriter, read_sequence
from toolkit.recipe import RecipeError, load_recipe, registry, run_recipe
from toolkit.sensors import LaserScan

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def ingest_registered() -> Iterator[None]:
    # The lead adds "ingest" to registry.STAGES; until then the tests register it.
    registry.register("ingest", IngestStage)
    yield
    registry.unregister("ingest")


def recipe(tmp_path: Path, **ingest) -> Path:
    data = {"name": "ingest_test", "output": str(tmp_path / "out"),
            "stages": [{"stage": "ingest", **ingest}]}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ---------------------------------------------------------------------------- the stage


def test_stage_converts_caches_and_reruns_on_a_changed_bag(tmp_path):
    bag, c = make_bag(tmp_path, "sqlite3")
    path = recipe(tmp_path, source="rosbag", path=str(bag))
    res = run_recipe(load_recipe(path))
    assert res.ok, res.error
    m = res.metrics["ingest"]
    assert m["frames"] == len(c.image_t) and m["scans"] == len(c.scan_t)
    assert m["frames_dropped_no_scan"] == 0
    seq = read_sequence(res.run_dir / "ingest" / "sequence")
    assert len(seq.frames) == len(c.image_t)
    report = (res.run_dir / "report.md").read_text()
    assert "dropped: no scan within tolerance" in report
    log = (res.run_dir / "run.log").read_text()
    assert "/camera/color/image_raw" in log and "rate Hz" in log and "sync plan" in log

    assert run_recipe(load_recipe(path)).statuses == {"ingest": "cached"}
    db = next(bag.glob("*.db3"))
    st = db.stat()
    os.utime(db, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert run_recipe(load_recipe(path)).statuses == {"ingest": "ran"}


def test_stage_resumes_after_a_failure(tmp_path, monkeypatch):
    bag, c = make_bag(tmp_path, "ros1")
    path = recipe(tmp_path, source="rosbag", path=str(bag))
    real = SequenceWriter.add_frame

    def failing(self, *a, **kw):
        if self.num_frames == 3:
            raise OSError("disk full")
        return real(self, *a, **kw)

    monkeypatch.setattr(SequenceWriter, "add_frame", failing)
    res = run_recipe(load_recipe(path))
    assert not res.ok and "disk full" in res.error
    monkeypatch.setattr(SequenceWriter, "add_frame", real)
    res = run_recipe(load_recipe(path))
    assert res.ok and res.metrics["ingest"]["frames_resumed"] == 3
    seq = read_sequence(res.run_dir / "ingest" / "sequence")
    assert [f.stamp for f in seq.frames] == [ns(t) / 1e9 for t in c.image_t]
    for f, img in zip(seq.frames, c.images, strict=True):
        assert np.array_equal(f.image, img)

    # other settings: the partial folder is not resumed into
    res = run_recipe(load_recipe(path, ["ingest.decimate.by=time"]))
    assert res.ok and res.metrics["ingest"]["frames_resumed"] == 0


def test_stage_errors_are_readable(tmp_path):
    bag, _ = make_bag(tmp_path, "mcap", tf=False)
    res = run_recipe(load_recipe(recipe(tmp_path, source="rosbag", path=str(bag))))
    assert not res.ok
    assert "T_base_camera" in res.error and "calibration" in res.error

    with pytest.raises(RecipeError, match="'tum_rgbd' options are given but source is"):
        load_recipe(recipe(tmp_path, source="rosbag", path="x.bag", tum_rgbd={}))
    with pytest.raises(RecipeError, match="decimate"):
        load_recipe(recipe(tmp_path, source="rosbag", path="x.bag", decimate={"by": "space"}))


def test_from_rosbag_recipe_documents_a_valid_ingest_stage():
    data = yaml.safe_load((REPO / "recipes" / "from_rosbag.yaml").read_text())
    ingest = next(s for s in data["stages"] if s["stage"] == "ingest")
    cfg = IngestConfig.model_validate(ingest)
    assert cfg.source == "rosbag" and cfg.rosbag is not None


# ---------------------------------------------------------------------------- other sources


def write_flaser_log(path: Path, n: int = 6, beams: int = 180) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    lines, ranges = ["# CARMEN log", "PARAM robot_frontlaser_offset 0.1 nohost 0 0"], []
    for i in range(n):
        r = np.round(rng.uniform(0.5, 20.0, beams), 2)
        r[4] = 0.0  # CARMEN's "no reading"
        ranges.append(r)
        t = 1000.0 + 0.2 * i
        lines.append(f"ODOM {0.1 * i} 0 0 0 0 0 {t - 0.05} host {t}")
        values = " ".join(f"{v:g}" for v in r)
        lines.append(f"FLASER {beams} {values} {0.1 * i + 0.1:g} 0 0 {0.1 * i:g} 0 0 {t!r} "
                     f"host {t!r}")
    path.write_text("\n".join(lines) + "\n")
    return ranges


def test_carmen_log_is_a_lidar_only_sequence(tmp_path):
    log = tmp_path / "intel.log"
    ranges = write_flaser_log(log)
    rec = read_carmen_recording(log)
    res = convert(rec, tmp_path / "seq")
    seq = read_sequence(tmp_path / "seq")
    assert seq.frames == [] and seq.meta["has_camera"] is False and res.frames == 0
    assert len(seq.scans) == 6
    for s, r in zip(seq.scans, ranges, strict=True):
        want = r.astype(np.float32)
        want[want <= 0] = np.nan
        np.testing.assert_array_equal(s.ranges, want)
        assert s.angle_min == pytest.approx(-np.pi / 2)
    assert seq.odometry is not None and len(seq.odometry) == 6  # raw log: scan odometry
    assert seq.groundtruth is None or seq.groundtruth.poses_base is None

    corrected = tmp_path / "intel-corrected.log"
    corrected.write_text(log.read_text())
    rec = read_carmen_recording(corrected)
    assert rec.odometry is None and rec.groundtruth is not None
    assert "not surveyed" in rec.meta["groundtruth"]
    rec = read_carmen_recording(corrected, CarmenOptions(odometry="odom_lines"))
    assert len(rec.odometry) == 6

    # A raw log named as such in some collections is not a corrected one.
    uncorrected = tmp_path / "intel-uncorrected.log"
    uncorrected.write_text(log.read_text())
    rec = read_carmen_recording(uncorrected)
    assert rec.odometry is not None and rec.groundtruth is None


def test_carmen_stage(tmp_path):
    log = tmp_path / "aces.log"
    write_flaser_log(log)
    res = run_recipe(load_recipe(recipe(tmp_path, source="carmen", path=str(log))))
    assert res.ok, res.error
    assert res.metrics["ingest"]["scans"] == 6 and res.metrics["ingest"]["frames"] == 0


def test_sequence_source_decimates_a_copy(tmp_path):
    bag, c = make_bag(tmp_path, "sqlite3")
    convert(read_rosbag(bag), tmp_path / "a")
    rec = read_sequence_recording(tmp_path / "a")
    res = convert(rec, tmp_path / "b", decimate=DecimateOptions(by="time", min_interval_s=0.39))
    a, b = read_sequence(tmp_path / "a"), read_sequence(tmp_path / "b")
    assert res.frames == 4 and [f.stamp for f in b.frames] == [f.stamp for f in a.frames[::2]]
    for fa, fb in zip(a.frames[::2], b.frames, strict=True):
        assert np.array_equal(fa.image, fb.image)
    assert np.array_equal(b.groundtruth.depth(1), a.groundtruth.depth(2))
    assert np.stack([s.ranges for s in a.scans]).tobytes() == \
        np.stack([s.ranges for s in b.scans]).tobytes()
    assert b.meta["has_camera"] is True and b.meta["topics"] == a.meta["topics"]


def test_sequence_source_keeps_the_kept_frames_exposure_gains_and_the_house(tmp_path):
    # Re-synced or decimated, a sequence lost groundtruth/exposure_gain.csv (fuse then
    # dropped its gain figures without a word) and house.json.
    bag, c = make_bag(tmp_path, "sqlite3")
    convert(read_rosbag(bag), tmp_path / "a")
    a = read_sequence(tmp_path / "a")
    gains = 1.0 + 0.1 * np.arange(len(a.frames))
    rows = [f"{k},{f.stamp!r},{float(g)!r}\n"
            for k, (f, g) in enumerate(zip(a.frames, gains, strict=True))]
    (tmp_path / "a" / "groundtruth" / "exposure_gain.csv").write_text(
        "index,stamp,gain\n" + "".join(rows))
    (tmp_path / "a" / "groundtruth" / "house.json").write_text('{"rooms": []}')
    convert(read_sequence_recording(tmp_path / "a"), tmp_path / "b",
            decimate=DecimateOptions(by="time", min_interval_s=0.39))
    b = read_sequence(tmp_path / "b")
    np.testing.assert_array_equal(b.groundtruth.exposure_gain, gains[::2])
    assert (tmp_path / "b" / "groundtruth" / "house.json").read_text() == '{"rooms": []}'


# ---------------------------------------------------------------------------- sync helpers


def test_match_nearest_and_tolerance():
    ref = np.array([0.0, 1.0, 2.0])
    q = np.array([-0.2, 0.4, 0.5, 0.6, 2.04, 3.0])
    assert match_nearest(q, ref, 0.1).tolist() == [-1, -1, -1, -1, 2, -1]
    assert match_nearest(q, ref, 0.5).tolist() == [0, 0, 0, 1, 2, -1]  # tie -> earlier
    assert match_nearest(q, np.array([]), 1.0).tolist() == [-1] * 6
    assert match_nearest(np.array([5.0]), np.array([4.9]), 0.2).tolist() == [0]


def test_stamps_keep_and_decimation():
    st = np.array([0.0, 0.1, 0.1, 0.05, 0.3])
    with pytest.raises(IngestError, match=r"topic /x: stamps are not monotonic: message 2 "):
        stamps_keep(st, "topic /x", "error")
    assert stamps_keep(st, "x", "drop").tolist() == [True, True, False, False, True]
    # One stamp glitched into the future (or the past) costs that message only.
    ahead = np.array([0.0, 1.0, 2.0, 1000.0, 3.0, 4.0, 5.0])
    assert stamps_keep(ahead, "x", "drop").tolist() == [True] * 3 + [False] + [True] * 3
    behind = np.array([10.0, 11.0, 5.0, 12.0, 13.0])
    assert stamps_keep(behind, "x", "drop").tolist() == [True, True, False, True, True]
    # Integer nanoseconds compare exactly where float seconds would tie.
    ns = np.array([1_700_000_000_000_000_000, 1_700_000_000_000_000_001,
                   1_700_000_000_000_000_001], dtype=np.int64)
    assert stamps_keep(ns, "x", "drop", unit_s=1e-9).tolist() == [True, True, False]
    with pytest.raises(IngestError, match=r"message 2 at .* repeats"):
        stamps_keep(ns, "x", "error", unit_s=1e-9)
    # 10 Hz frames at Unix-epoch stamps: every other one at 0.2 s, as at small stamps.
    for t0 in (0.0, 1.7e9):
        kept = decimate_by_time(t0 + np.arange(100) * 0.1, 0.2)
        assert kept.sum() == 50 and set(np.diff(np.flatnonzero(kept))) == {2}
    assert decimate_by_time(np.arange(0, 1.01, 0.1), 0.25).tolist() == [
        True, False, False, True, False, False, True, False, False, True, False]
    # Stamps jittering by +-2 ms: still every other frame (0.2 and 0.3 s apart in turn).
    jitter = np.random.default_rng(0).uniform(-0.002, 0.002, 250)
    kept = decimate_by_time(1.7e9 + np.arange(250) * 0.1 + jitter, 0.2)
    assert kept.sum() == 125 and set(np.diff(np.flatnonzero(kept))) == {2}


def test_plan_counts_each_reason():
    frames = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    scans = np.array([0.01, 1.02, 1.49, 2.0])
    depth = np.array([0.0, 1.0, 1.6])
    p = plan_frames(frames, scans, depth, SyncOptions(tolerance_s=0.05, depth_tolerance_s=0.02),
                    DecimateOptions())
    assert p.frames.tolist() == [0, 2] and p.depth.tolist() == [0, 1]
    assert p.dropped == {"no_scan": 1, "no_depth": 2} and p.without_scan == 0
    # Kept without a scan (require_scan: false), they are counted: they were not at all.
    kept = plan_frames(frames, scans, None, SyncOptions(tolerance_s=0.05, require_scan=False),
                       DecimateOptions())
    assert kept.frames.tolist() == [0, 1, 2, 3, 4] and kept.dropped == {}
    assert kept.without_scan == 1
    with pytest.raises(IngestError, match="decimate.by: motion needs poses"):
        plan_frames(frames, scans, None, SyncOptions(), DecimateOptions(by="motion"))


def test_uniform_scans_resamples_odd_layouts():
    a = LaserScan(0.0, np.arange(5, dtype=np.float32), -1.0, 0.5)
    b = LaserScan(1.0, np.arange(3, dtype=np.float32) + 10, -0.5, 0.5)  # narrower layout
    c = LaserScan(2.0, np.arange(5, dtype=np.float32), -1.0, 0.5)
    out, n = uniform_scans([a, b, c])
    assert n == 1 and [len(s) for s in out] == [5, 5, 5]
    # bearings -1 and 1 lie outside b's span: no return there, never an invented range
    np.testing.assert_array_equal(out[1].ranges, [np.nan, 10, 11, 12, np.nan])
    assert out[0] is a and out[2] is c
    # A message without beams (a driver's start-up or dropout) is a scan without returns.
    empty = LaserScan(3.0, np.zeros(0, np.float32), 0.0, 0.1)
    out, n = uniform_scans([empty, a, c])
    assert n == 1 and len(out[0]) == 5 and np.isnan(out[0].ranges).all()
    with pytest.raises(IngestError, match="all 1 scans have no beams"):
        uniform_scans([empty])


def test_a_recording_of_empty_scans_names_its_source(tmp_path: Path) -> None:
    """Every scan message without beams: the error named no file ("all 3 scans have no
    beams ..."), so a user converting several bags could not tell which one."""
    from toolkit.camera import PinholeCamera
    from toolkit.ingest.recording import Recording, optical_mount
    from toolkit.sensors import Rig

    rig = Rig(PinholeCamera.from_fov(32, 24, 60.0), optical_mount(), np.eye(4))
    empty = [LaserScan(float(t), np.zeros(0, np.float32), 0.0, 0.1) for t in range(3)]
    rec = Recording(name="run", source="rosbag run.bag", rig=rig, scans=empty,
                    frame_stamps=np.arange(3.0), load=lambda i: None)
    with pytest.raises(IngestError) as err:
        convert(rec, tmp_path / "seq")
    text = str(err.value)
    assert text.startswith("rosbag run.bag: all 3 scans have no beams"), text
    assert "Fix: name the lidar's scan source" in text, text


def test_uniform_scans_keeps_each_scans_bearings():
    """The format keeps each scan's angle_min and step: only the beam count must be shared.
    Scans of the common count with another start bearing were resampled onto the first
    one's bearings (a turn starting 0.45 beam later stored rotated by 0.45 beam, up to
    2.3 cm off the walls of a 6 m room), and a full turn of another count starting 10 deg
    later lost the bearings before its first beam, which it holds past +180 deg."""
    def room(a: np.ndarray) -> np.ndarray:  # [B] ranges to the walls of a 6 m square room
        return (3.0 / np.maximum(np.abs(np.cos(a)), np.abs(np.sin(a)))).astype(np.float32)

    def turn(stamp: float, n: int, start: float) -> LaserScan:
        inc = 2 * np.pi / n
        return LaserScan(stamp, room(start + np.arange(n) * inc), start, inc, 0.05, 20.0,
                         time_increment=1e-4)

    ref = turn(0.0, 360, -np.pi)
    later = -np.pi + np.radians(10)
    nudged, shifted = turn(0.1, 360, -np.pi + 0.45 * np.radians(1)), turn(0.2, 360, later)
    out, changed = uniform_scans([ref, nudged, shifted])
    assert changed == 0 and out[1] is nudged and out[2] is shifted
    other = turn(0.3, 357, later)
    out, changed = uniform_scans([ref, nudged, other])
    assert changed == 1 and len(out[2]) == 360 and out[2].angle_min == ref.angle_min
    # every bearing holds the range of a source beam nearest to it (two where it lies
    # half way), around the turn
    gap = np.abs(np.angle(np.exp(1j * (other.angles()[None, :] - ref.angles()[:, None]))))
    nearest = gap <= gap.min(axis=1, keepdims=True) + 1e-9  # [B, 357]
    assert all(r in other.ranges[row] for r, row in zip(out[2].ranges, nearest, strict=True))


def test_sequence_writer_resume_mode(tmp_path):
    from toolkit.camera import PinholeCamera
    from toolkit.io.sequence import JOURNAL_NAME
    from toolkit.sensors import Rig

    rig = Rig(PinholeCamera.from_fov(8, 6, 60.0))
    img = np.zeros((6, 8, 3), np.uint8)
    w = SequenceWriter(tmp_path / "s", rig)
    for k in range(3):
        w.add_frame(float(k), img + k, gt_depth=np.full((6, 8), 1.0 + k, np.float32))
    w._journal.close()  # killed: no close(); then a torn line and a frame never journaled
    with open(tmp_path / "s" / JOURNAL_NAME, "a") as fh:
        fh.write('{"index": "3", "sta')
    (tmp_path / "s/camera/images/000003.png").write_bytes(b"half a png")

    w = SequenceWriter(tmp_path / "s", rig, resume=True)
    assert w.resumed_frames == 3 and w.last_frame_stamp == 2.0
    assert not (tmp_path / "s/camera/images/000003.png").exists()
    w.add_frame(3.0, img + 3, gt_depth=np.full((6, 8), 4.0, np.float32))
    w.add_scan(LaserScan(0.0, np.ones(4, np.float32), -1.0, 0.5))
    w.close()
    assert not (tmp_path / "s" / JOURNAL_NAME).exists()
    seq = read_sequence(tmp_path / "s")
    assert [f.stamp for f in seq.frames] == [0.0, 1.0, 2.0, 3.0]
    assert [float(seq.groundtruth.depth(k)[0, 0]) for k in range(4)] == [1.0, 2.0, 3.0, 4.0]
    assert np.array_equal(seq.frames[1].image, img + 1)


def test_frames_without_any_scan_name_the_setting(tmp_path):
    from toolkit.camera import PinholeCamera
    from toolkit.ingest.sync import SyncOptions
    from toolkit.sensors import Rig

    w = SequenceWriter(tmp_path / "in", Rig(PinholeCamera.from_fov(16, 12, 90.0)), "cam")
    for i in range(3):
        w.add_frame(100.0 + i, np.zeros((12, 16, 3), np.uint8))
    w.close()
    rec = read_sequence_recording(tmp_path / "in")
    with pytest.raises(IngestError, match="3 camera frames but no lidar scans.*require_scan"):
        convert(rec, tmp_path / "out")
    res = convert(rec, tmp_path / "out", sync=SyncOptions(require_scan=False))
    assert res.frames == 3


def test_unsynchronised_sensors_are_told_apart_from_clocks_that_disagree(tmp_path):
    """A 10 Hz camera 40 ms out of phase with a 10 Hz lidar has no scan within 30 ms: the
    message says so and names sync.tolerance_s (it blamed the clocks and suggested
    'stamps: bag', which made the result worse); clocks hours apart are still blamed, by
    the sequence reader, naming the files and their spans (not a bag's settings)."""
    from toolkit.camera import PinholeCamera
    from toolkit.ingest.sync import SyncOptions
    from toolkit.sensors import LaserScan, Rig

    for name, scan_offset, match in (
            ("phase", 0.04, r"nearest scan is 40 ms away.*not synchronised.*tolerance_s"),
            ("clock", 3600.0, r"frames.csv spans 100.000 .. 100.900 s and scans.npz "
                              r"3700.000 .. 3700.900 s.*different clocks")):
        w = SequenceWriter(tmp_path / name, Rig(PinholeCamera.from_fov(16, 12, 90.0)), "cam")
        for i in range(10):
            w.add_frame(100.0 + 0.1 * i, np.zeros((12, 16, 3), np.uint8))
            w.add_scan(LaserScan(100.0 + 0.1 * i + scan_offset, np.ones(8, np.float32), 0.0,
                                 0.1))
        w.close()
        with pytest.raises(IngestError, match=match):
            convert(read_sequence_recording(tmp_path / name), tmp_path / f"{name}_out",
                    sync=SyncOptions(tolerance_s=0.03))


def test_a_broken_image_in_a_sequence_is_named_at_ingest(tmp_path):
    """A truncated PNG at frame 3 was copied unread; depth failed later naming the run's
    copy, which a rerun overwrote with the bad source. Now ingest names the source file; a
    frame of another size is caught by the sequence reader, from its header."""
    import cv2

    from toolkit.fusion.synthetic import write_box_room

    src = write_box_room(tmp_path / "seq", n_frames=6)
    bad = sorted((src / "camera" / "images").glob("*.png"))[3]
    good = bad.read_bytes()
    bad.write_bytes(good[: len(good) // 3])
    res = run_recipe(load_recipe(recipe(tmp_path, source="sequence", path=str(src))))
    assert not res.ok and str(bad) in res.error and "not a readable PNG" in res.error
    # An empty file (a copy cut short at zero bytes) was OpenCV's "!buf.empty()" assertion,
    # naming no file.
    bad.write_bytes(b"")
    res = run_recipe(load_recipe(recipe(tmp_path, source="sequence", path=str(src))))
    assert not res.ok and str(bad) in res.error and "not a readable PNG" in res.error
    cv2.imwrite(str(bad), np.zeros((24, 32, 3), np.uint8))
    res = run_recipe(load_recipe(recipe(tmp_path, source="sequence", path=str(src))))
    assert not res.ok and f"{bad}: image is 32x24 but" in res.error  # the reader's check
    assert "says 160x120" in res.error
    bad.write_bytes(good)
    assert run_recipe(load_recipe(recipe(tmp_path, source="sequence", path=str(src)))).ok


def test_a_lidar_only_recording_passes_the_calibrate_check(tmp_path):
    """from_rosbag.yaml checks the extrinsic after ingest: a recording without images has
    nothing to check and must go on to the SLAM."""
    log = tmp_path / "intel.log"
    write_flaser_log(log)
    data = {"name": "t", "output": str(tmp_path / "out"), "stages": [
        {"stage": "ingest", "source": "carmen", "path": str(log)},
        {"stage": "calibrate", "mode": "check"}]}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    res = run_recipe(load_recipe(path))
    assert res.ok, res.error
    report = (res.run_dir / "report.md").read_text()
    assert "No camera in this recording (lidar only)" in report


def test_a_dropped_carmen_line_is_one_dropped_message(tmp_path):
    # The reference poses come from the scan lines: one glitched line was counted twice.
    lines = []
    for i in range(8):
        t = 999.0 if i == 4 else 1000.0 + 0.2 * i
        ranges = " ".join(["2.0"] * 181)
        lines.append(f"FLASER 181 {ranges} {0.1 * i} 0 0 {0.1 * i} 0 0 {t!r} host {t!r}")
    log = tmp_path / "intel-corrected.log"
    log.write_text("\n".join(lines) + "\n")
    rec = read_carmen_recording(log, on_non_monotonic="drop")
    assert rec.dropped == {"scans": 1}
    res = convert(rec, tmp_path / "seq")
    assert res.metrics()["messages_dropped_non_monotonic"] == 1
    seq = read_sequence(tmp_path / "seq")
    assert len(seq.scans) == 7 and len(seq.groundtruth.poses_base) == 7


def _flaser_log_with_bad_odometry(path: Path, n: int, bad: set[int],
                                  kind: str = "FLASER") -> list[float]:
    """A raw CARMEN log of ``n`` ``kind`` (FLASER or ROBOTLASER1) lines and ODOM lines,
    0.2 s apart, whose odometry fields (ROBOTLASER1: robot pose) are NaN on lines ``bad``;
    the laser is mounted 0.1 m ahead. Returns the stamps."""
    lines, stamps = [], []
    ranges = " ".join(["2.0"] * 181)
    for i in range(n):
        t = 1000.0 + 0.2 * i
        stamps.append(t)
        odom = "nan 0 0" if i in bad else f"{0.1 * i:g} 0 0"
        laser = f"{0.1 * i + 0.1:g} 0 0"
        lines.append(f"ODOM {odom} 0 0 0 {t - 0.05!r} host {t - 0.05!r}")
        if kind == "FLASER":
            lines.append(f"FLASER 181 {ranges} {laser} {odom} {t!r} host {t!r}")
        else:  # 181 beams over 180 deg, no remissions; tv rv safety margins turn axis
            lines.append(f"ROBOTLASER1 0 -1.5707963 3.1415927 0.017453293 50.0 0.01 0 181 "
                         f"{ranges} 0 {laser} {odom} 0 0 0.5 0.2 0.3 {t!r} host {t!r}")
    path.write_text("\n".join(lines) + "\n")
    return stamps


@pytest.mark.parametrize("kind", ["FLASER", "ROBOTLASER1"])
def test_a_carmen_log_with_one_bad_odometry_reading_is_kept(tmp_path, caplog, kind):
    """A NaN odometry pose on one line of 50 refused the whole log (a line error); the
    reading is left out and counted, the scan kept, as a bag's odometry message is.
    ROBOTLASER1 lines (their robot pose) were refused so until 2026-11-28, after FLASER's."""
    log = tmp_path / "intel.log"
    stamps = _flaser_log_with_bad_odometry(log, 50, {20}, kind)
    with caplog.at_level("WARNING"):
        rec = read_carmen_recording(log)
    assert len(rec.scans) == 50 and len(rec.odometry) == 49
    assert stamps[20] not in rec.odometry.stamps.tolist()
    assert rec.skipped["scan lines' odometry"]["count"] == 1
    assert rec.skipped["scan lines' odometry"]["first_stamps_s"] == [stamps[20]]
    field = "robot_x robot_y robot_theta" if kind == "ROBOTLASER1" else "odom_x odom_y"
    assert field in rec.skipped["scan lines' odometry"]["first_reason"]
    assert "scan lines' odometry: 1 of 50 messages left out as no pose" in caplog.text
    if kind == "ROBOTLASER1":  # the mount from the other lines' laser and robot poses
        assert np.allclose(rec.rig.T_base_laser[:3, 3], [0.1, 0, 0])
    rec = read_carmen_recording(log, CarmenOptions(odometry="odom_lines"))
    assert len(rec.odometry) == 49 and rec.skipped["ODOM lines"]["of"] == 50
    # all bad: refused, naming the fix
    log = tmp_path / "broken.log"
    _flaser_log_with_bad_odometry(log, 50, set(range(50)), kind)
    with pytest.raises(IngestError, match=r"scan lines' odometry: 50 of 50 messages are no "
                                          r"pose.*only 0 remain.*carmen.odometry: none"):
        read_carmen_recording(log)
    assert read_carmen_recording(log, CarmenOptions(odometry="none")).odometry is None
    # exactly half valid: kept, as the rule says
    log = tmp_path / "half.log"
    _flaser_log_with_bad_odometry(log, 50, set(range(0, 50, 2)), kind)
    assert len(read_carmen_recording(log).odometry) == 25


@pytest.mark.parametrize("kind", ["FLASER", "ROBOTLASER1"])
def test_skipped_odometry_reaches_the_stage_metrics_and_report(tmp_path, kind):
    log = tmp_path / "intel.log"
    _flaser_log_with_bad_odometry(log, 50, {20, 21}, kind)
    res = run_recipe(load_recipe(recipe(tmp_path, source="carmen", path=str(log))))
    assert res.ok, res.error
    assert res.metrics["ingest"]["messages_skipped_invalid"] == 2
    report = (res.run_dir / "report.md").read_text()
    assert "| odometry messages left out as no pose | scan lines' odometry: 2 of 50 (first " \
           "stamps 1004.000, 1004.200 s; longest gap 0.60 s, 0 not interpolated across) |" \
        in report
    (meta_file,) = res.run_dir.glob("**/meta.yaml")
    skipped = yaml.safe_load(meta_file.read_text())["ingest"]["skipped_invalid"]
    assert skipped["scan lines' odometry"]["count"] == 2


def test_carmen_source_on_a_folder_or_a_bag_names_the_fix(tmp_path: Path) -> None:
    """A folder given to 'source: carmen' failed with a bare IsADirectoryError; a file with
    no scan lines (a ROS bag) said only that no FLASER line was found."""
    with pytest.raises(IngestError, match=r"a folder, not a CARMEN log or g2o file; give the "
                       r"log file \(plain, .gz or .zip\), or the 'source'"):
        read_carmen_recording(tmp_path)
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + bytes(200))
    with pytest.raises(IngestError, match=r"no laser scans .* found; for another kind of "
                       r"recording set its 'source' \(rosbag"):
        read_carmen_recording(bag)
