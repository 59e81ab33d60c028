"""CARMEN / g2o readers, map_server maps, and the Freiburg relations metric."""

from __future__ import annotations

import gzip
import os
from pathlib import Path

import numpy as np
import pytest

from toolkit.eval.relations import (
    Relations,
    read_relations,
    relation_errors,
    relations_metric,
    select_relations,
)
from toolkit.geometry import Trajectory, se2_to_se3
from toolkit.io.carmen import CarmenFormatError, CarmenLog, read_carmen, read_g2o
from toolkit.io.occupancy import OccupancyMap, read_occupancy, write_occupancy


def shared_data() -> Path:
    env = os.environ.get("TOOLKIT_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


def need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"shared data file {path} is not on this machine "
                    "(set TOOLKIT_SHARED_DATA to the folder holding slam2d/)")
    return path


# ------------------------------------------------------------------ synthetic lines

FLASER = "FLASER 4 1.0 2.0 0 3.5 0.1 0.2 0.3 0.11 0.21 0.31 12.5 host 12.6\n"
ROBOTLASER = ("ROBOTLASER1 0 -1.5 3.0 0.75 50.0 0.1 0 5 1.0 1.5 50.0 2.0 nan 2 9 9 "
              "1.17551651 0.09588511 0.5 1.0 0.0 0.5 0.1 0.0 0.5 0.2 0.3 100.25 host 100.3\n")
ODOM = "ODOM 1.5 -0.5 0.25 0.1 0 0 13.0 host 13.0\n"


def test_read_carmen_plain_and_gzip(tmp_path: Path):
    text = "# comment\nPARAM robot_frontlaser_offset 0.2 nohost 0\n" + FLASER + ODOM
    plain = tmp_path / "a.log"
    plain.write_text(text)
    gz = tmp_path / "a.log.gz"
    with gzip.open(gz, "wt") as fh:
        fh.write(text)
    for path in (plain, gz):
        log = read_carmen(path)
        assert len(log.scans) == 1
        s = log.scans[0]
        assert s.stamp == 12.5
        assert s.angle_min == pytest.approx(-np.pi / 2)
        assert s.angle_increment == pytest.approx(np.pi / 4)
        # Zero readings are invalid: stored as NaN, never as zero.
        assert np.isnan(s.ranges[2]) and s.ranges[3] == pytest.approx(3.5)
        assert np.allclose(log.scan_poses[0], [0.1, 0.2, 0.3])
        assert np.allclose(log.scan_odometry[0], [0.11, 0.21, 0.31])
        assert np.allclose(log.odom_poses, [[1.5, -0.5, 0.25]]) and log.odom_stamps[0] == 13.0
        assert log.T_base_laser[0, 3] == pytest.approx(0.2)


def test_read_robotlaser1_with_remissions_and_laser_offset(tmp_path: Path):
    path = tmp_path / "b.log"
    path.write_text(ROBOTLASER)
    log = read_carmen(path)
    s = log.scans[0]
    assert s.stamp == 100.25 and len(s) == 5
    assert s.angle_min == -1.5 and s.angle_increment == 0.75 and s.range_max == 50.0
    assert np.isnan(s.ranges[4])
    # A reading at max_range is a beam without return (+inf), not a wall 50 m away.
    assert s.ranges[2] == np.inf and not s.valid_mask()[2]
    # Laser 0.2 m ahead of the robot along its heading (0.5 rad).
    assert np.allclose(log.T_base_laser[:2, 3], [0.2, 0.0], atol=1e-6)


def test_bad_line_names_file_and_line(tmp_path: Path):
    path = tmp_path / "bad.log"
    path.write_text(FLASER + "FLASER 3 1.0 oops\n")
    with pytest.raises(CarmenFormatError, match=r"bad.log:2"):
        read_carmen(path)


def test_scan_without_beams_is_a_line_error(tmp_path: Path):
    path = tmp_path / "empty.log"
    path.write_text(FLASER + "FLASER 0 0 0 0 0 0 0 13.0 host 13.1\n")
    with pytest.raises(CarmenFormatError, match=r"empty.log:2: bad FLASER line: 0 beams"):
        read_carmen(path)


def test_a_non_finite_pose_is_a_line_error(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    """Python reads 'nan' as a number: a log's NaN odometry went into odometry.tum, and the
    converted sequence was refused by the next stage, naming that file, not the log line."""
    path = tmp_path / "nan.log"
    path.write_text(FLASER + FLASER.replace("0.1 0.2 0.3", "nan 0.2 0.3"))
    with pytest.raises(CarmenFormatError, match=r"nan.log:2: bad FLASER line: laser pose "
                                                r".*\[nan, 0.2, 0.3\] is not finite"):
        read_carmen(path)
    # Odometry fields are read as they are: the ingest leaves a non-finite one out and
    # counts it (test_ingest_stage), as a bag's odometry message - one glitched reading
    # refused the whole log.
    path.write_text(FLASER + FLASER.replace("0.11 0.21 0.31", "nan 0.21 0.31")
                    + ODOM.replace("-0.5", "inf"))
    log = read_carmen(path)
    assert len(log.scans) == 2 and np.isnan(log.scan_odometry[1, 0])
    assert np.isinf(log.odom_poses[0, 1])
    # ROBOTLASER1's robot pose is that odometry too; its line gives no laser mount, the
    # others do. Its laser pose stays a line error, as FLASER's.
    path.write_text(ROBOTLASER + ROBOTLASER.replace("0.5 1.0 0.0 0.5", "0.5 nan 0.0 0.5"))
    log = read_carmen(path)
    assert len(log.scans) == 2 and log.scan_lines == ["ROBOTLASER1"] * 2
    assert np.isnan(log.scan_odometry[1, 0]) and np.isfinite(log.T_base_laser).all()
    assert np.allclose(log.T_base_laser, read_carmen_text(tmp_path, ROBOTLASER).T_base_laser)
    # None has one: the mount from PARAM (or none), with a warning.
    path.write_text("PARAM robot_frontlaser_offset 0.2 nohost 0\n"
                    + ROBOTLASER.replace("0.5 1.0 0.0 0.5", "0.5 nan 0.0 0.5"))
    with caplog.at_level("WARNING"):
        assert read_carmen(path).T_base_laser[0, 3] == pytest.approx(0.2)
    assert "no ROBOTLASER1 line has a finite robot pose" in caplog.text
    path.write_text(ROBOTLASER.replace("1.17551651", "nan"))
    with pytest.raises(CarmenFormatError, match=r"nan.log:1: bad ROBOTLASER1 line: laser pose"):
        read_carmen(path)
    path = tmp_path / "nan.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 nan 0 0\n")
    with pytest.raises(CarmenFormatError, match=r"nan.g2o:2: bad VERTEX_SE2 line: vertex pose"):
        read_g2o(path)
    # NaN ranges stay what they were: invalid beams
    path = tmp_path / "ok.log"
    path.write_text(ROBOTLASER)
    assert np.isnan(read_carmen(path).scans[0].ranges).any()


def read_carmen_text(folder: Path, text: str) -> CarmenLog:
    path = folder / "one.log"
    path.write_text(text)
    return read_carmen(path)


@pytest.mark.parametrize("reader", [read_carmen, read_g2o])
def test_a_truncated_gzip_names_the_file_and_the_fix(tmp_path: Path, reader):
    path = tmp_path / "cut.log.gz"
    whole = gzip.compress((FLASER * 400).encode())
    path.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(CarmenFormatError, match=r"cut.log.gz: .*cut short.*zcat"):
        reader(path)


def test_a_last_line_cut_short_says_the_file_looks_truncated(tmp_path: Path):
    path = tmp_path / "cut.log"
    path.write_text(FLASER + FLASER[:20])
    with pytest.raises(CarmenFormatError, match=r"cut.log:2: .*no end of line.*truncated"):
        read_carmen(path)


def test_read_g2o_odometry_chain(tmp_path: Path):
    lines = [
        "VERTEX_SE2 0 5.0 5.0 1.0",  # corrected poses: must not leak into odometry
        ROBOTLASER.replace("100.25", "1.0").strip(),
        "VERTEX_SE2 1 6.0 5.0 1.0",
        ROBOTLASER.replace("100.25", "2.0").strip(),
        "VERTEX_SE2 2 7.0 5.0 1.0",
        ROBOTLASER.replace("100.25", "3.0").strip(),
        "EDGE_SE2 0 1 1.0 0.0 0.5 500 0 0 500 0 5000",
        "EDGE_SE2 1 2 1.0 0.0 0.0 500 0 0 500 0 5000",
        "EDGE_SE2 0 2 2.0 0.0 0.0 500 0 0 500 0 5000",
    ]
    path = tmp_path / "g.g2o"
    path.write_text("\n".join(lines) + "\n")
    g = read_g2o(path)
    assert len(g.scans) == 3 and list(g.scan_vertex) == [0, 1, 2]
    assert g.sequential_edges().tolist() == [True, True, False]
    odo = g.odometry()
    assert np.allclose(odo.poses[0], np.eye(4))
    expect = se2_to_se3(1.0 + np.cos(0.5), np.sin(0.5), 0.5)
    assert np.allclose(odo.poses[2], expect)
    # Vertex ids 0 10 20 (a thinned graph): the chain runs from each id to the next one.
    gap = tmp_path / "gap.g2o"
    text = "\n".join(lines).replace("VERTEX_SE2 1 ", "VERTEX_SE2 10 ").replace(
        "VERTEX_SE2 2 ", "VERTEX_SE2 20 ").replace("EDGE_SE2 0 1 ", "EDGE_SE2 0 10 ").replace(
        "EDGE_SE2 1 2 ", "EDGE_SE2 10 20 ").replace("EDGE_SE2 0 2 ", "EDGE_SE2 0 20 ")
    gap.write_text(text + "\n")
    g = read_g2o(gap)
    assert list(g.scan_vertex) == [0, 10, 20]
    assert g.sequential_edges().tolist() == [True, True, False]
    assert np.allclose(g.odometry().poses[2], expect)
    # A chain with a hole names the missing edge.
    gap.write_text(text.replace("EDGE_SE2 10 20 ", "EDGE_SE2 10 21 ") + "\n")
    with pytest.raises(CarmenFormatError, match="no odometry edge 10 -> 20"):
        read_g2o(gap).odometry()


# ------------------------------------------------------------------ shipped logs


def test_shipped_killian_g2o():
    g = read_g2o(need(shared_data() / "slam2d" / "killian" / "killian.g2o.zip"))
    assert len(g.scans) == 3873 and len(g.vertex_ids) == 3873 and len(g.edges) == 4987
    assert int(g.sequential_edges().sum()) == 3872
    s = g.scans[0]
    assert len(s) == 180 and s.angle_increment == pytest.approx(np.radians(1.0), abs=1e-5)
    assert s.stamp == pytest.approx(1031745824.658)
    assert g.duration_s == pytest.approx(7672.69, abs=0.01)
    odo = g.odometry()
    assert len(odo) == 3873
    rel = read_relations(need(shared_data() / "slam2d" / "killian" / "mit-killian.relations"))
    assert len(rel) == 4677
    sel = select_relations(rel, np.array([s.stamp for s in g.scans]))
    assert int(sel.sum()) == 658
    # Dead-reckoned odometry on those relations (README: 0.93 m / 1.38 deg).
    m = relations_metric(odo, Relations(rel.t1[sel], rel.t2[sel], rel.delta[sel]))
    assert m["trans_abs_mean_m"] == pytest.approx(0.93, abs=0.01)
    assert m["rot_abs_mean_deg"] == pytest.approx(1.38, abs=0.01)
    # The corrected vertices score 0.039 m / 0.40 deg.
    m = relations_metric(g.reference(), Relations(rel.t1[sel], rel.t2[sel], rel.delta[sel]))
    assert m["trans_abs_mean_m"] == pytest.approx(0.039, abs=0.001)


@pytest.mark.parametrize("name,count", [("intel", 910), ("aces", 440)])
def test_shipped_radish_logs(name: str, count: int):
    log = read_carmen(need(shared_data() / "slam2d" / "radish" / f"{name}-corrected.log.gz"))
    assert len(log.scans) == count
    assert all(len(s) == 180 for s in log.scans)
    assert log.scans[0].angle_min == pytest.approx(-np.pi / 2)
    ref = log.reference()
    assert len(ref) == count - (4 if name == "intel" else 0)  # intel has 4 stamps going back
    assert len(log.odom_stamps) > count


# ------------------------------------------------------------------ map_server


def test_occupancy_roundtrip_and_flip(tmp_path: Path):
    occ = np.full((3, 4), np.nan, np.float32)
    occ[0, 0] = 0.9  # lowest row (min y) occupied
    occ[2, 3] = 0.05  # top row free
    occ[1, 1] = 0.5  # uncertain -> unknown
    grid = OccupancyMap(occ, 0.05, (-1.0, 2.0, 0.0))
    pgm = write_occupancy(tmp_path / "map.yaml", grid)
    raw = pgm.read_bytes()
    pixels = np.frombuffer(raw[-12:], np.uint8).reshape(3, 4)
    assert pixels[2, 0] == 0  # map_saver: bottom image row is the lowest y
    assert pixels[0, 3] == 254
    assert pixels[1, 1] == 205
    back = read_occupancy(tmp_path / "map.yaml")
    assert back.resolution == 0.05 and back.origin == (-1.0, 2.0, 0.0)
    assert back.occupancy[0, 0] == 1.0 and back.occupancy[2, 3] == 0.0
    assert np.isnan(back.occupancy[1, 1])


@pytest.mark.parametrize("free_thresh, occupied_thresh", [(0.25, 0.65), (0.05, 0.15),
                                                          (0.3, 0.9)])
def test_occupancy_written_with_other_thresholds_keeps_unknown_cells_unknown(
        tmp_path: Path, free_thresh: float, occupied_thresh: float) -> None:
    """The thresholds classify the probabilities; the pixels are then map_saver's constants
    (254, 0, 205), so the YAML must hold thresholds that read 205 as unknown. Writing the
    given ones made map_server (and read_occupancy) read every unknown cell as free with
    free_thresh 0.25 (nav2's default: (255 - 205) / 255 = 0.196 < 0.25), or as occupied with
    occupied_thresh 0.15: a planner then drives through unmapped space. ROS 1's map_saver
    and nav2's (ros-navigation/navigation2#5278) write 0.65 and 0.196 for trinary maps."""
    occ = np.array([[0.0, 1.0, np.nan, 0.5 * (free_thresh + occupied_thresh)]], np.float32)
    write_occupancy(tmp_path / "map.yaml", OccupancyMap(occ, 0.05, (0.0, 0.0, 0.0)),
                    occupied_thresh, free_thresh)
    back = read_occupancy(tmp_path / "map.yaml").occupancy
    assert back[0, 0] == 0.0 and back[0, 1] == 1.0
    assert np.isnan(back[0, 2]) and np.isnan(back[0, 3])


# ------------------------------------------------------------------ relations metric


def test_relations_metric_hand_computed():
    # Estimate: robot at (0,0,0), (1,0,0), (1,1,pi/2) at t = 0, 1, 2.
    stamps = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, np.pi / 2]])
    traj = Trajectory(stamps, np.stack([se2_to_se3(*p) for p in poses]))
    # Reference relations: (0 -> 1) is 1.1 m ahead, (1 -> 2) is (0, 1) turned by 80 deg,
    # and one relation whose stamp is not an estimate stamp.
    rel = Relations(np.array([0.0, 1.0, 5.0]), np.array([1.0, 2.0, 6.0]),
                    np.array([[1.1, 0.0, 0.0], [0.0, 1.0, np.radians(80.0)], [0, 0, 0]]))
    et, er, used = relation_errors(traj, rel)
    assert used.tolist() == [True, True, False]
    assert et[0] == pytest.approx(0.1) and er[0] == pytest.approx(0.0)
    assert et[1] == pytest.approx(0.0) and np.degrees(er[1]) == pytest.approx(10.0)
    m = relations_metric(traj, rel)
    assert m["relations_used"] == 2
    assert m["trans_abs_mean_m"] == pytest.approx(0.05)
    assert m["trans_abs_std_m"] == pytest.approx(0.05)
    assert m["trans_sq_mean_m2"] == pytest.approx(0.005)
    assert m["rot_abs_mean_deg"] == pytest.approx(5.0)
    assert m["rot_sq_mean_deg2"] == pytest.approx(50.0)
    assert m["rot_sq_std_deg2"] == pytest.approx(50.0)


def test_relations_metric_cartographer_composition():
    """Cartographer's compute_relations_metrics (Hess et al. 2016's figures) composes
    delta_est * delta*^-1: a relation 2 m ahead whose estimate ends turned by 0.1 rad has
    no translational error in the paper's composition and 2 * 2 sin(0.05) in that one."""
    stamps = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.1], [2.0, 1.0, np.pi / 2]])
    traj = Trajectory(stamps, np.stack([se2_to_se3(*p) for p in poses]))
    rel = Relations(np.array([0.0, 1.0]), np.array([1.0, 2.0]),
                    np.array([[2.0, 0.0, 0.0], [np.sin(0.1), np.cos(0.1), np.pi / 2 - 0.1]]))
    et, er, used = relation_errors(traj, rel)
    assert et[0] == pytest.approx(0.0, abs=1e-12) and er[0] == pytest.approx(0.1)
    etc, erc, usedc = relation_errors(traj, rel, composition="cartographer")
    assert etc[0] == pytest.approx(4 * np.sin(0.05)) and erc[0] == pytest.approx(0.1)
    # (1 -> 2): the estimate is the reference exactly, in both compositions
    assert et[1] == pytest.approx(0.0, abs=1e-12) and etc[1] == pytest.approx(0.0, abs=1e-12)
    m = relations_metric(traj, rel)
    assert m["trans_abs_mean_m"] == pytest.approx(0.0, abs=1e-12)
    assert m["trans_abs_mean_m_cartographer"] == pytest.approx(2 * np.sin(0.05))
    assert m["trans_abs_std_m_cartographer"] == pytest.approx(2 * np.sin(0.05))
    with pytest.raises(ValueError, match="composition"):
        relation_errors(traj, rel, composition="freiburg")


def test_a_laser_facing_backwards_keeps_its_heading(tmp_path):
    """ROBOTLASER1 offsets of a laser mounted backwards wrap to +pi-e on some lines and
    -pi+e on others: their per-component median heading was 0 (facing forwards)."""
    from toolkit.geometry import se3_to_se2
    from toolkit.io.carmen import read_carmen

    def line(stamp: int, robot_th: float) -> str:
        laser_th = (robot_th + 2 * np.pi) % (2 * np.pi) - np.pi  # robot heading + pi
        lx, ly = -0.2 * np.cos(robot_th), -0.2 * np.sin(robot_th)  # 0.2 m behind
        ranges = " ".join(["2.0"] * 180)
        return (f"ROBOTLASER1 0 -1.570796 3.141593 0.017453 50.0 0.01 0 180 {ranges} 0 "
                f"{lx:.6f} {ly:.6f} {laser_th:.6f} 0.000000 0.000000 {robot_th:.6f} 0 0 0 0 0 "
                f"{stamp:.6f} host {stamp:.6f}\n")

    path = tmp_path / "rear.log"
    path.write_text("".join(line(t, th) for t, th in enumerate([0.1, -0.1, 0.2, -0.2])))
    x, y, th = se3_to_se2(read_carmen(path).T_base_laser)
    assert (x, y) == pytest.approx((-0.2, 0.0), abs=1e-5)
    assert abs(abs(np.degrees(th)) - 180.0) < 1e-3


def test_a_zip_with_a_readme_reads_the_log(tmp_path):
    """The log member is read before a README.txt listed first in the zip."""
    import zipfile

    from toolkit.io.carmen import read_carmen

    ranges = " ".join(["2.0"] * 180)
    log = "".join(f"FLASER 180 {ranges} 0 0 0 0 0 0 {t}.0 host {t}.0\n" for t in range(5))
    with zipfile.ZipFile(tmp_path / "run.zip", "w") as zf:
        zf.writestr("README.txt", "Recorded at the lab.\n")
        zf.writestr("intel.log", log)
    (tmp_path / "intel.log").write_text(log)
    assert len(read_carmen(tmp_path / "run.zip").scans) == len(
        read_carmen(tmp_path / "intel.log").scans) == 5


def test_flaser_beam_counts_give_the_scanner_mode_carmen_reads(tmp_path: Path, caplog):
    """FLASER lines carry no angles: 401 beams is a SICK LMS at 0.25 deg over 100 deg
    (CARMEN's readlog.c), not 0.45 deg over 180 deg (beam 100 was at -45 deg, not -25);
    a count no scanner has is read as 180 deg and said so."""
    from toolkit.io.carmen import flaser_angles

    for n, inc in ((180, 1.0), (181, 1.0), (360, 0.5), (361, 0.5)):
        amin, step = flaser_angles(n)
        assert np.degrees(amin) == pytest.approx(-90.0) and np.degrees(step) == pytest.approx(inc)
    amin, step = flaser_angles(401)
    assert np.degrees(step) == pytest.approx(0.25)
    assert np.degrees(amin + 100 * step) == pytest.approx(-25.0)
    assert np.degrees(amin + 400 * step) == pytest.approx(50.0)
    path = tmp_path / "odd.log"
    path.write_text("".join(f"FLASER 5 1 1 1 1 1 0 0 0 0 0 0 {t} host {t}\n" for t in (1, 2)))
    with caplog.at_level("WARNING"):
        log = read_carmen(path)
    assert len(log.scans) == 2
    assert sum("FLASER lines of 5 beams" in r.getMessage() for r in caplog.records) == 1


def test_a_reference_stamp_glitched_into_the_future_costs_one_pose(tmp_path: Path):
    """Corrected logs' stored poses are the ground truth: keeping whatever came after the
    last kept stamp, one stamp glitched ahead cut off every pose after it (11 of 100
    kept); the scans keep the longest increasing run, and so does the truth now."""
    import logging

    from toolkit.io.carmen_ingest import read_carmen_recording

    lines = []
    for i in range(100):
        t = 100000.0 if i == 10 else 100.0 + 0.2 * i
        lines.append(f"FLASER 180 {' '.join(['2.0'] * 180)} {0.05 * i} 0 0 {0.05 * i} 0 0 "
                     f"{t} host {t}\n")
    path = tmp_path / "lab-corrected.log"
    path.write_text("".join(lines))
    rec = read_carmen_recording(path, on_non_monotonic="drop", log=logging.getLogger("t"))
    assert len(rec.scans) == 99 and len(rec.groundtruth) == 99
    assert rec.groundtruth.stamps[-1] == rec.scans[-1].stamp
    assert rec.dropped == {"scans": 1}  # one line: its pose goes with its scan


@pytest.mark.parametrize("g2o", [False, True])
def test_a_scan_stamp_going_backwards_names_its_line(tmp_path: Path, g2o: bool):
    """'message 295' sent a user counting scans through a 5000-line log; the error names
    the file's line of the scan (FLASER / ROBOTLASER1) that goes backwards."""
    from toolkit.ingest.sync import IngestError
    from toolkit.io.carmen_ingest import read_carmen_recording

    if g2o:
        text = ""
        for i, t in enumerate((100.25, 101.25, 100.75)):  # the third scan goes back
            text += f"VERTEX_SE2 {i} {0.1 * i} 0 0\n" + ROBOTLASER.replace(
                "100.25 host 100.3", f"{t} host {t}")
        path, bad_line = tmp_path / "run.g2o", 6
    else:
        text = "# a comment\n" + FLASER + ODOM + FLASER.replace("12.5 host", "12.4 host")
        path, bad_line = tmp_path / "run.log", 4
    path.write_text(text)
    with pytest.raises(IngestError, match=rf"{path.name}: scans: stamps are not monotonic: "
                                          rf"line {bad_line} at "):
        read_carmen_recording(path)
