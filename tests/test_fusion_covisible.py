"""Which lidar pairs both sensors see (``FramePairs.covisible``): known answers on ray-cast planar
scenes - a wall, thin posts, a wide post and a walking person - seen by a camera 10 cm
ahead of and 20 cm above the lidar, as on the simulated house."""

from collections.abc import Callable

import numpy as np
import pytest

from toolkit.camera import PinholeCamera
from toolkit.depth.protocol import DepthPrediction
from toolkit.fusion.pipeline import FramePairs, Fusion, FusionConfig
from toolkit.fusion.projection import LidarPixels, jump_near_side, occluded_lidar
from toolkit.fusion.synthetic import R_BASE_OPTICAL
from toolkit.geometry import se2_to_se3, se3
from toolkit.sensors import CameraFrame, LaserScan, Rig, Sequence

WALL_X = 4.0
W, H = 320, 240
RIG = Rig(PinholeCamera(W, H, 262.5, 262.5, 159.5, 119.5),
          se3(R_BASE_OPTICAL, [0.1, 0.0, 0.45]), se3(None, [0.0, 0.0, 0.25]))

# A post: centre (x, y) in the world at time t, and radius.
Post = Callable[[float], tuple[float, float, float]]


def _scan(T_world_laser: np.ndarray, stamp: float, posts: list[Post]) -> LaserScan:
    """A full-circle 1 deg scan ray-cast against the wall x = WALL_X and the posts."""
    ang = -np.pi + np.radians(np.arange(360))  # [B]
    yaw = np.arctan2(T_world_laser[1, 0], T_world_laser[0, 0])
    d = np.stack([np.cos(ang + yaw), np.sin(ang + yaw)], 1)  # [B, 2] world directions
    o = T_world_laser[:2, 3]
    r = np.full(360, np.inf)
    ahead = d[:, 0] > 1e-9
    r[ahead] = (WALL_X - o[0]) / d[ahead, 0]
    for post in posts:
        x, y, rad = post(stamp)
        q = np.array([x, y]) - o
        along = d @ q  # [B]
        miss2 = q @ q - along ** 2
        hit = (along > 0) & (miss2 < rad * rad)
        r[hit] = np.minimum(r[hit], along[hit] - np.sqrt(rad * rad - miss2[hit]))
    return LaserScan(stamp, r, -np.pi, np.radians(1.0), 0.1, 12.0)


def _scene(posts: list[Post], n_scans: int, image_lag_s: float, yaw_per_scan_deg: float = 0.0,
           **cfg: object) -> Fusion:
    """Scans at 10 Hz, each with an image ``image_lag_s`` before it; the robot at the origin,
    turning by ``yaw_per_scan_deg`` each scan."""
    def pose(t: float) -> np.ndarray:
        return se2_to_se3(0.0, 0.0, np.radians(yaw_per_scan_deg) * t / 0.1)

    ts = 0.1 * np.arange(n_scans)
    scans = [_scan(pose(t) @ RIG.T_base_laser, t, posts) for t in ts]
    frames = [CameraFrame.from_array(t - image_lag_s, np.zeros((H, W, 3), np.uint8))
              for t in ts]
    seq = Sequence(RIG, frames, scans)
    config = FusionConfig(scale="none", outlier_neighbors=0, exposure="none", **cfg)
    return Fusion(seq, config, np.stack([pose(t - image_lag_s) for t in ts]),
                  np.stack([pose(t) for t in ts]))


def _pairs(fusion: Fusion, index: int) -> FramePairs:
    return fusion.frame_pairs(index, DepthPrediction(np.full((H, W), 3.0), "metric_depth"))


def _bearing_deg(fusion: Fusion, lidar: LidarPixels) -> np.ndarray:
    """[N] world bearing of each pair's lidar point from the laser, in degrees."""
    scan = fusion.seq.scans[int(lidar.scan[0])]
    yaw = np.degrees(np.arctan2(fusion.scan_poses[lidar.scan[0]][1, 0],
                                fusion.scan_poses[lidar.scan[0]][0, 0]))
    return np.degrees(scan.angle_min) + lidar.beam + yaw


def test_occluders_from_elsewhere_hide_lidar_points_but_are_not_tested() -> None:
    # Wall points at 3 m every beam (9.2 px at fx 525); a point of another scan at 1 m,
    # 0.4 spacings left of the middle one, hides the three within 1.5 spacings of it.
    u = 319.5 + 9.2 * np.arange(-3, 4)
    lp = LidarPixels(np.stack([u, np.full(7, 240.0)], 1), np.full(7, 3.0), np.zeros((7, 3)),
                     np.arange(7), np.zeros(7, int))
    plain = occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 1.5)
    assert not plain.any()
    post = (np.array([319.5 + 9.2 * -0.4]), np.array([1.0]))
    occ = occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 1.5, occluders=post)
    assert occ.tolist() == [False, False, True, True, True, False, False]
    # The occluders are not tested: a far one next to near points adds nothing.
    far = (np.array([319.5]), np.array([10.0]))
    assert occluded_lidar(lp, 525.0, 319.5, np.radians(1.0), 1.5, occluders=far).tolist() == (
        plain.tolist())
    # One point alone is hidden by an occluder too.
    one = LidarPixels(lp.uv[3:4], lp.z[3:4], lp.points_cam[3:4], lp.beam[3:4], lp.scan[3:4])
    assert occluded_lidar(one, 525.0, 319.5, np.radians(1.0), 1.5, occluders=post).tolist() == [
        True]


def test_jump_near_side_flags_the_nearer_beam_of_each_jump() -> None:
    nan, inf = np.nan, np.inf
    r = np.array([4.0, 4.0, 2.0, 2.0, 2.0, 4.0, 4.1, nan, 3.0, 3.0, inf, 5.0, 12.0, 3.0, 3.0])
    partial = LaserScan(0.0, r, -0.5, np.radians(1.0), 0.1, 12.0)
    beams = np.arange(len(r))
    beams = beams[partial.valid_mask()]
    got = dict(zip(beams.tolist(), jump_near_side(partial, beams).tolist(), strict=True))
    # 2 and 4: near sides of the 2 m post; 6 beside a NaN (unknown) is no jump, nor is 5
    # (4.1 m is within 5 cm + 5 %); 9 and 11 beside a beam without return (+inf) are;
    # 13 is beside a return at range_max (no return for many drivers).
    assert [b for b, j in got.items() if j] == [2, 4, 9, 11, 13]
    # A partial scan's ends have one neighbour; a full circle's last beam neighbours its
    # first.
    ends = np.array([5.0, 3.0, 3.0, 3.0, 3.0])
    assert jump_near_side(LaserScan(0.0, ends, 0.0, np.radians(1.0)), np.arange(5)).tolist() == [
        False, True, False, False, False]
    full = LaserScan(0.0, np.concatenate([[5.0], np.full(359, 3.0)]), -np.pi, np.radians(1.0))
    assert np.flatnonzero(jump_near_side(full, np.arange(360))).tolist() == [1, 359]


def test_a_thin_post_the_own_scan_missed_hides_the_wall_point_behind_it() -> None:
    # A 3 cm post at 2 m, bearing 10.5 deg: the own scan's beams at 10 and 11 deg pass
    # 1.7 cm from its centre, beside it. The robot turns 0.5 deg a scan, so the scans
    # before and after hit it (a single beam each: no moving obstacle).
    c = np.radians(10.5)
    post = [lambda t: (2.0 * np.cos(c), 2.0 * np.sin(c), 0.015)]
    lag = 0.04
    on = _scene(post, 5, lag, yaw_per_scan_deg=-0.5)
    off = _scene(post, 5, lag, yaw_per_scan_deg=-0.5, pair_neighbour_scans=0)
    assert not any(f.any() for f in on.beam_dynamic)
    assert np.isfinite(on.seq.scans[1].ranges[191]) and on.seq.scans[1].ranges[191] < 2.0
    i = 2  # the own scan (2, yaw -1 deg) misses the post; scans 1 and 3 hit it
    p_on, p_off = _pairs(on, i), _pairs(off, i)
    assert (p_on.lidar.scan == 2).all()
    b = _bearing_deg(on, p_on.lidar)
    assert not (p_on.lidar.z < 3.0).any()  # the own scan has no point on the post
    beside = np.abs(b - 10.5) < 0.6  # the wall points at 10 and 11 deg
    assert beside.sum() == 2
    assert not p_on.covisible[beside].any()
    assert p_off.covisible[beside].all()
    # The shape correction still anchors to them (its maps were better so).
    assert p_on.visible[beside].all()
    # Further along the wall nothing changes.
    assert p_on.covisible[np.abs(b - 10.5) > 2.5].all()
    # A neighbouring point within 5 cm of an own-scan point is no new occluder: a 40 cm
    # post the own scan sees too, whose edge the scans before and after hit half a degree
    # further out (4 cm from the own edge point), hides no wall point more than the own
    # scan's edge does - with every neighbouring point an occluder it hid one more.
    wide = [lambda t: (2.0, 0.0, 0.2)]
    w_on = _scene(wide, 5, lag, yaw_per_scan_deg=-0.5)
    w_off = _scene(wide, 5, lag, yaw_per_scan_deg=-0.5, pair_neighbour_scans=0)
    assert np.array_equal(_pairs(w_on, i).covisible, _pairs(w_off, i).covisible)


def test_the_near_side_of_a_range_jump_is_not_covisible() -> None:
    # A 40 cm post at 2 m straight ahead in front of the wall at 4 m: the post's outermost
    # beams are next to wall beams, the ones inside are not.
    post = [lambda t: (2.0, 0.0, 0.2)]
    on = _scene(post, 3, 0.04)
    off = _scene(post, 3, 0.04, pair_jump_filter=False)
    p_on, p_off = _pairs(on, 1), _pairs(off, 1)
    b = np.rint(_bearing_deg(on, p_on.lidar)).astype(int)
    scan = on.seq.scans[1]
    hit = np.flatnonzero(scan.ranges < 3.0) - 180  # bearings on the post
    edge = {int(hit.min()), int(hit.max())}
    assert len(hit) >= 9
    on_post = p_on.lidar.z < 3.0
    got = {int(x) for x in b[on_post & ~p_on.covisible]}
    assert got == edge
    assert p_off.covisible[on_post].all()
    # Only the near side: the wall points beside the post go by the occlusion test as
    # before, with or without it.
    assert np.array_equal(p_on.covisible[~on_post], p_off.covisible[~on_post])


@pytest.mark.parametrize("ray_m", [0.3, 0.0])
def test_a_person_between_camera_and_wall_hides_the_pairs_behind(ray_m: float) -> None:
    # A person (30 cm wide) walks across at 1.5 m, 2 m/s, the image 45 ms before each scan:
    # the scan sees the wall past the 9 cm the person moved, where the image shows them.
    def person(t: float) -> tuple[float, float, float]:
        return 1.5, -2.0 + 2.0 * t, 0.15

    lag = 0.045
    fusion = _scene([person], 21, lag, pair_moving_ray_m=ray_m)
    i = 10
    pairs = _pairs(fusion, i)
    lid = pairs.lidar
    assert fusion.beam_dynamic[i].any()  # the lidar saw the person move
    on_person = fusion.pairs_on_moving(lid)
    assert on_person.any() and not pairs.covisible[on_person].any()
    # Wall pairs whose camera ray (floor plane) crosses the person at the image's time.
    T = fusion.T_world_camera(i)
    X = lid.points_cam @ T[:3, :3].T + T[:3, 3]  # [N, 3] world
    o = T[:2, 3]
    px, py, rad = person(fusion.seq.frame_stamps[i])
    d = X[:, :2] - o
    s = np.clip((np.array([px, py]) - o) @ d.T / np.einsum("nd,nd->n", d, d), 0, 1)
    gap = np.linalg.norm(o + s[:, None] * d - np.array([px, py]), axis=1)
    wall = X[:, 0] > WALL_X - 0.01
    behind = wall & (gap < rad)
    assert behind.sum() >= 3
    if ray_m > 0:
        assert not pairs.covisible[behind].any()
    else:
        # Without the ray test the ones the scan's own occlusion test does not reach stay.
        assert pairs.covisible[behind].any()
    # The wall well away from the person stays, either way.
    assert pairs.covisible[wall & (gap > 1.0)].all()
