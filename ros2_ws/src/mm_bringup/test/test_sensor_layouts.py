"""The named sensor layouts (mm_sim/layouts/*.yaml): `paper` has no pose at which both sensor groups see the wall,
`overlap` (the simulator's default) has such poses. Proven by a dense scan of the wall-relative poses (readings do not
depend on the position along the wall), vectorised with the same beam geometry as mm_sim.wheeled_model."""
import math

import numpy as np
import pytest

from mm_bringup.wall_experiment import layout_file, layout_robot, robot_from_params, simulator_params_file
from mm_common.wheeled_sensors import SENSOR1, SENSOR2
from mm_sim.wheeled_model import WheeledRobot

DISTANCES, HEADINGS = 1000, 1200       # 1.2 M poses


def scan_readings(robot: WheeledRobot, y: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Readings (..., 5) of every sensor at the poses (0, y, theta): ProximitySensor.read, vectorised."""
    c, s = np.cos(theta), np.sin(theta)
    out = []
    for sensor in robot.sensors:
        sensor_y = y + s * sensor.x + c * sensor.y
        toward_wall = -np.sin(theta + sensor.yaw)
        with np.errstate(divide='ignore', invalid='ignore'):
            distance = sensor_y / toward_wall
        r = np.where(toward_wall <= math.cos(sensor.max_incidence), np.inf, distance)
        r = np.where(np.isfinite(r) & (r > sensor.max_range), np.inf, r)
        r = np.where(np.isfinite(r) & (r < sensor.min_range), -np.inf, r)
        out.append(np.where(sensor_y <= 0.0, -np.inf, r))
    return np.stack(out, axis=-1)


def pose_grid(robot: WheeledRobot):
    """Every distance from touching the wall to beyond the front range, every heading."""
    y = np.linspace(robot.body_radius, 1.6, DISTANCES)
    theta = np.linspace(-math.pi, math.pi, HEADINGS, endpoint=False)
    return np.meshgrid(y, theta, indexing='ij')


@pytest.mark.parametrize('scale', [1.0, 1.5])
def test_paper_layout_has_no_pose_where_both_groups_see_the_wall(scale):
    robot, _ = layout_robot('paper', scale)
    y, theta = pose_grid(robot)
    r = np.isfinite(scan_readings(robot, y, theta))
    assert r.shape[0] * r.shape[1] >= 1_000_000
    group1, group2 = r[..., list(SENSOR1)].all(axis=-1), r[..., list(SENSOR2)].all(axis=-1)
    assert group1.any() and group2.any()          # each group alone does see the wall
    assert not (group1 & group2).any()


def test_overlap_layout_has_poses_where_both_groups_see_the_wall():
    robot, _ = layout_robot('overlap')
    y, theta = pose_grid(robot)
    r = np.isfinite(scan_readings(robot, y, theta))
    both = r[..., list(SENSOR1)].all(axis=-1) & r[..., list(SENSOR2)].all(axis=-1)
    assert both.mean() > 0.001
    # The example of the issue and the layout file: 0.2 m from the wall, heading -0.62 rad (wall along +x).
    pose = (0.0, 0.2, -0.62)
    assert np.all(np.isfinite(robot.read(pose, noisy=False)))


def test_scan_matches_the_simulator_sensor_model():
    robot, _ = layout_robot('paper')
    rng = np.random.default_rng(5)
    y, theta = rng.uniform(0.0, 1.6, 300), rng.uniform(-math.pi, math.pi, 300)
    scanned = scan_readings(robot, y, theta)
    exact = np.array([robot.read((0.0, a, b), noisy=False) for a, b in zip(y, theta)])
    assert np.array_equal(np.isfinite(scanned), np.isfinite(exact))
    assert np.array_equal(np.sign(scanned[~np.isfinite(scanned)]), np.sign(exact[~np.isfinite(exact)]))
    np.testing.assert_allclose(scanned[np.isfinite(scanned)], exact[np.isfinite(exact)], rtol=1e-12)


def test_layouts_load_as_params_files_on_top_of_the_simulator_file():
    default, dt = robot_from_params([simulator_params_file()])
    overlap, _ = layout_robot('overlap')
    paper, _ = layout_robot('paper')
    assert dt == 0.05 and default.sensors == overlap.sensors == WheeledRobot().sensors
    assert [s.max_incidence for s in paper.sensors[:3]] == [math.radians(60.0)] * 3
    assert [(s.min_range, s.max_range, s.max_incidence) for s in paper.sensors[3:]] == [
        (0.005, 0.15, math.radians(45.0))] * 2
    assert [(s.x, s.y, s.yaw) for s in paper.sensors] == [(s.x, s.y, s.yaw) for s in default.sensors]
    big, _ = layout_robot('paper', 1.5)
    assert (big.wheel_radius, big.wheel_separation) == pytest.approx((0.03, 0.06))
    assert big.sensors[3].y == pytest.approx(1.5 * paper.sensors[3].y)
    with pytest.raises(ValueError, match='unknown sensor layout'):
        layout_file('nope')
