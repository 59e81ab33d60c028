"""Which lidar pairs both sensors see (``FramePairs.covisible``): the tests' geometry on
known answers."""

import numpy as np

from toolkit.fusion.projection import LidarPixels, jump_near_side, occluded_lidar
from toolkit.sensors import LaserScan


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
