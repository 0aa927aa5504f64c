"""Kinematics and sensor model of the wheeled robot against closed-form geometry."""
import math

import numpy as np
import pytest

from mm_common.wheeled_sensors import SENSOR1, SENSOR2
from mm_sim.wheeled_model import ProximitySensor, WheeledRobot, wall_relative_state


def far_pose(theta=0.0):
    return (0.0, 10.0, theta)


def test_straight_line_matches_closed_form():
    robot = WheeledRobot()
    pose, bumped = robot.step(far_pose(0.3), [5.0, 5.0], 2.0)
    v = 0.02 * 5.0
    assert not bumped
    assert pose == pytest.approx((2.0 * v * math.cos(0.3), 10.0 + 2.0 * v * math.sin(0.3), 0.3))


def test_rotation_in_place_keeps_position():
    robot = WheeledRobot()
    pose, _ = robot.step(far_pose(0.0), [-2.0, 2.0], 0.5)
    omega = 0.02 * 4.0 / 0.04
    assert pose[:2] == pytest.approx((0.0, 10.0))
    assert pose[2] == pytest.approx(omega * 0.5)


def test_arc_lies_on_the_analytic_circle():
    robot = WheeledRobot()
    left, right = 3.0, 5.0
    v, omega = robot.body_velocity([left, right])
    radius = v / omega
    centre = np.array([0.0, 10.0 + radius])        # start heading +x, turning left
    pose = far_pose(0.0)
    for _ in range(37):
        pose, _ = robot.step(pose, [left, right], 0.1)
        assert np.hypot(pose[0] - centre[0], pose[1] - centre[1]) == pytest.approx(abs(radius), rel=1e-9)
    assert pose[2] == pytest.approx(math.atan2(math.sin(omega * 3.7), math.cos(omega * 3.7)))


def test_many_small_steps_equal_one_big_step():
    robot = WheeledRobot()
    big, _ = robot.step(far_pose(1.0), [2.0, 7.0], 1.0)
    small = far_pose(1.0)
    for _ in range(100):
        small, _ = robot.step(small, [2.0, 7.0], 0.01)
    assert small == pytest.approx(big, abs=1e-9)


def test_facing_the_wall_readings():
    robot = WheeledRobot()
    d = 0.8
    r = robot.read((0.0, d, -math.pi / 2), noisy=False)
    centre_gap = d - 0.025
    assert r[1] == pytest.approx(centre_gap)
    # Fan sensors sit 0.01 m to the side and look 20 deg outward: same depth, longer slanted beam.
    assert r[0] == pytest.approx(centre_gap / math.cos(math.radians(20.0)))
    assert r[2] == pytest.approx(centre_gap / math.cos(math.radians(20.0)))
    assert np.all(np.isinf(r[list(SENSOR2)]))       # side beams run parallel to the wall


def test_out_of_range_grazing_and_too_close():
    s = ProximitySensor('s', 0.0, 0.0, 0.0, min_range=0.01, max_range=0.5, max_incidence=math.radians(60.0))
    assert s.read((0.0, 0.4, -math.pi / 2)) == pytest.approx(0.4)
    assert s.read((0.0, 0.6, -math.pi / 2)) == math.inf                       # beyond max range
    assert s.read((0.0, 0.1, -math.pi / 2 + math.radians(70.0))) == math.inf  # grazing: no return
    assert s.read((0.0, 0.005, -math.pi / 2)) == -math.inf                    # closer than min range
    assert s.read((0.0, 0.3, math.pi / 2)) == math.inf                        # facing away


def test_parallel_to_the_wall_only_the_side_group_sees_it():
    robot = WheeledRobot()
    r = robot.read((0.0, 0.2, 0.0), noisy=False)
    assert np.all(np.isfinite(r[list(SENSOR2)]))
    assert r[3] == pytest.approx(0.2 - 0.025)
    assert not np.all(np.isfinite(r[list(SENSOR1)]))


def test_wall_stops_motion_toward_it_and_reports_contact():
    robot = WheeledRobot()
    pose = (0.0, 0.05, -math.pi / 2)
    pose, bumped = robot.step(pose, [10.0, 10.0], 1.0)
    assert bumped
    assert pose[1] == pytest.approx(robot.body_radius)
    away, bumped_again = robot.step(pose, [-10.0, -10.0], 0.1)
    assert not bumped_again and away[1] > robot.body_radius


def test_noise_and_dropout_statistics():
    robot = WheeledRobot(noise_std=0.01, dropout=0.05, random_state=3)
    clean = robot.read((0.0, 0.8, -math.pi / 2), noisy=False)
    samples = np.array([robot.read((0.0, 0.8, -math.pi / 2)) for _ in range(4000)])
    front = samples[:, 1]
    lost = np.isnan(front)
    assert 0.03 < lost.mean() < 0.07
    assert np.std(front[~lost] - clean[1]) == pytest.approx(0.01, rel=0.1)
    assert abs(np.mean(front[~lost] - clean[1])) < 0.002
    again = WheeledRobot(noise_std=0.01, dropout=0.05, random_state=3)
    np.testing.assert_array_equal(again.read((0.0, 0.8, -math.pi / 2)), samples[0])


def test_wall_relative_state():
    assert wall_relative_state((3.0, 0.7, -math.pi / 2)) == pytest.approx((0.7, 0.0))
    assert wall_relative_state((0.0, 0.2, 0.0)) == pytest.approx((0.2, math.pi / 2))
