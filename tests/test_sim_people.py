"""Simulated people: the default walkers' tracks, and walkers who stand a while (people_stand_s)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from toolkit.sim.house import generate_house
from toolkit.sim.people import MIN_ROBOT_DIST, Walker, plan_people, primitives_at
from toolkit.sim.robot import RobotPath, plan_path
from toolkit.sim.simulate import SimConfig, _rng
from toolkit.sim.stage import SimulateConfig


def _walkers(seed: int, n_people: int,
             stand_s: tuple[float, float] | None = None) -> tuple[RobotPath, list[Walker]]:
    cfg = SimConfig(seed=seed, n_people=n_people, people_stand_s=stand_s)
    house = generate_house(cfg.preset, seed)
    path = plan_path(house.route, house.start_yaw, cfg.motion, cfg.duration_s)
    return path, plan_people(house.people_routes, path, n_people, _rng(cfg, "people"),
                             stand_s=stand_s)


def test_default_walkers_keep_the_tracks_drawn_before_the_standing_option() -> None:
    # Seed 0, three people, one lap: positions and gait at 7 evenly spaced samples, as the
    # code before people_stand_s drew them (the draws from the people stream must not move).
    old_xy = [
        [[1.430714, 2.066751], [1.159618, 2.048749], [4.69359, 2.213841], [5.455811, 2.909981],
         [3.486365, 2.20326], [1.159618, 2.048749], [2.068827, 2.109126]],
        [[2.664529, 2.148684], [4.610575, 2.213841], [5.455811, 2.909981], [2.410515, 2.131816],
         [1.159618, 2.048749], [2.569956, 2.142404], [4.099828, 2.213841]],
        [[2.891152, 2.163734], [5.455811, 2.909981], [5.455811, 2.909981], [5.455811, 2.909981],
         [2.107793, 2.111714], [2.265738, 2.122202], [5.455811, 2.909981]],
    ]
    old_gait = [
        [0.0, 0.271693, 4.227546, 9.052971, 16.002064, 22.904635, 31.227867],
        [0.0, 8.077172, 10.538045, 17.244686, 25.225477, 33.046476, 40.748677],
        [0.0, 6.352569, 6.352569, 6.352569, 11.920054, 19.095677, 24.821455],
    ]
    _, walkers = _walkers(0, 3)
    assert len(walkers) == 3
    for w, xy, gait in zip(walkers, old_xy, old_gait, strict=True):
        assert len(w.t) == 1289
        idx = np.linspace(0, len(w.t) - 1, 7).astype(int)
        np.testing.assert_allclose(w.xy[idx], xy, atol=1e-6)
        np.testing.assert_allclose(w.gait[idx], gait, atol=1e-6)
        # The default pause at the route's ends is 0.5-2 s.
        assert len(w.stops) and np.all((w.stops[:, 1] >= 0.5) & (w.stops[:, 1] <= 2.0))


@pytest.mark.parametrize("seed", [0, 3])
def test_people_stand_still_for_the_drawn_time_and_keep_clear_of_the_robot(seed: int) -> None:
    lo, hi = 20.0, 40.0
    path, walkers = _walkers(seed, 2, (lo, hi))
    assert len(walkers) == 2
    robot_xy = path.pose2d(walkers[0].t)[:, :2]  # [M, 2] on the walkers' time grid
    checked = 0
    for w in walkers:
        # The robot's clearance holds while people stand, as while they walk.
        assert np.linalg.norm(w.xy - robot_xy, axis=1).min() >= MIN_ROBOT_DIST
        assert len(w.stops) >= 1
        assert np.all((w.stops[:, 1] >= lo) & (w.stops[:, 1] <= hi))
        dt = w.t[1] - w.t[0]
        for t0, dur in w.stops:
            i0 = int(np.searchsorted(w.t, t0))
            i1 = int(np.searchsorted(w.t, t0 + dur - dt))  # the last sample of the stop
            if i1 >= len(w.t) - 1:
                continue  # the drive ends during the stop
            # Where the robot (2.5 s ahead) comes within 3 m the walker may step aside;
            # elsewhere it stands: no displacement, no gait (legs still), the same heading.
            ahead = robot_xy[i0:min(i1 + int(2.5 / dt) + 1, len(w.t))]
            if np.abs(ahead - w.xy[i0]).sum(1).min() < 3.0:
                continue
            np.testing.assert_array_equal(w.xy[i0:i1 + 1], np.broadcast_to(w.xy[i0],
                                                                           (i1 + 1 - i0, 2)))
            assert np.all(w.gait[i0:i1 + 1] == w.gait[i0])
            assert np.all(w.heading[i0:i1 + 1] == w.heading[i0])
            # It walks on after the stop.
            assert np.linalg.norm(w.xy[min(i1 + int(2.0 / dt), len(w.t) - 1)] - w.xy[i0]) > 0.3
            # The legs keep their pose too (the shapes the sensors see do not change).
            a = primitives_at([w], float(w.t[i0]))
            b = primitives_at([w], float(w.t[i1]))
            for pa, pb in zip(a, b, strict=True):
                np.testing.assert_array_equal(pa.params, pb.params)
            checked += 1
    assert checked >= 1


def test_the_stage_refuses_a_stand_range_the_wrong_way_round() -> None:
    ok = SimulateConfig(stage="simulate", people_stand_s=(20, 40))
    assert ok.sim_config().people_stand_s == (20, 40)
    assert SimulateConfig(stage="simulate").sim_config().people_stand_s is None
    # Left unset it is not in the settings: simulate stages made before it keep their key.
    assert "people_stand_s" not in SimulateConfig(stage="simulate").model_dump()
    for bad in ((40, 20), (-1, 5)):
        with pytest.raises(ValidationError, match="people_stand_s"):
            SimulateConfig(stage="simulate", people_stand_s=bad)
