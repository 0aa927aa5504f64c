"""Differential-drive robot with proximity sensors near an infinite wall (paper Section 2.5). No rclpy here.

World frame: the wall is the line y = 0 and the robot lives in y > 0. Pose = (x, y, theta), theta measured from +x.
Input u = [omega_left, omega_right], the wheels' angular velocities [rad/s].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import numpy as np
from mm_common.wheeled_sensors import SENSOR1, SENSOR2


@dataclass(frozen=True)
class ProximitySensor:
    """A single-beam proximity (IR) sensor mounted on the robot.

    It returns the distance along its beam to the wall, +inf when the wall is beyond `max_range` or hit at a
    grazing angle above `max_incidence` (no reflection comes back), and -inf when closer than `min_range` (REP 117).
    """

    name: str
    x: float                 # mount position in the robot frame [m] (x forward, y left)
    y: float
    yaw: float               # beam direction in the robot frame [rad]
    min_range: float = 0.005
    max_range: float = 1.5
    field_of_view: float = 0.05
    max_incidence: float = math.radians(75.0)

    def read(self, pose: Sequence[float]) -> float:
        x, y, theta = pose
        c, s = math.cos(theta), math.sin(theta)
        sensor_y = y + s * self.x + c * self.y
        beam = theta + self.yaw
        toward_wall = -math.sin(beam)          # cosine of the angle between beam and the wall's inward normal (-y)
        if sensor_y <= 0.0:
            return -math.inf
        if toward_wall <= math.cos(self.max_incidence):
            return math.inf
        distance = sensor_y / toward_wall
        if distance > self.max_range:
            return math.inf
        if distance < self.min_range:
            return -math.inf
        return distance


def default_sensors() -> List[ProximitySensor]:
    """Three front sensors in a fan (sensor group 1) and two right-side sensors (sensor group 2)."""
    front = dict(min_range=0.005, max_range=1.5, max_incidence=math.radians(75.0))
    side = dict(min_range=0.005, max_range=0.25, max_incidence=math.radians(75.0))
    return [
        ProximitySensor('front_left', 0.025, 0.010, math.radians(20.0), **front),
        ProximitySensor('front_center', 0.025, 0.0, 0.0, **front),
        ProximitySensor('front_right', 0.025, -0.010, math.radians(-20.0), **front),
        ProximitySensor('side_front', 0.015, -0.025, math.radians(-90.0), **side),
        ProximitySensor('side_rear', -0.015, -0.025, math.radians(-90.0), **side),
    ]




@dataclass
class WheeledRobot:
    """Closed-form differential-drive kinematics with a wall that cannot be crossed."""

    wheel_radius: float = 0.02
    wheel_separation: float = 0.04
    body_radius: float = 0.03
    sensors: List[ProximitySensor] = field(default_factory=default_sensors)
    noise_std: float = 0.0           # Gaussian reading noise [m]
    dropout: float = 0.0             # probability that a reading is lost (NaN, REP 117 "invalid")
    random_state: Optional[int] = None
    noise_range_fraction: float = 0.0  # extra Gaussian noise, std as a fraction of each sensor's max range

    def __post_init__(self):
        self.reseed(self.random_state)

    def reseed(self, random_state: Optional[int]) -> None:
        """Restart the noise and dropout generator (same seed, same reading sequence from here on)."""
        self.random_state = random_state
        self._rng = np.random.default_rng(random_state)

    def body_velocity(self, wheel_speeds: Sequence[float]):
        """(v, omega) of the body from the wheel angular velocities [left, right]."""
        left, right = wheel_speeds
        v = self.wheel_radius * (left + right) / 2.0
        omega = self.wheel_radius * (right - left) / self.wheel_separation
        return v, omega

    def step(self, pose: Sequence[float], wheel_speeds: Sequence[float], dt: float):
        """Advance the pose by dt under constant wheel speeds. Returns (new_pose, bumped).

        The motion is integrated exactly (arc of a circle). If the body would cross the wall, the component of
        the motion toward the wall is removed: the robot slides along y = body_radius and `bumped` is True.
        """
        x, y, theta = pose
        v, omega = self.body_velocity(wheel_speeds)
        if abs(omega) < 1e-12:
            nx = x + v * dt * math.cos(theta)
            ny = y + v * dt * math.sin(theta)
        else:
            nx = x + v / omega * (math.sin(theta + omega * dt) - math.sin(theta))
            ny = y - v / omega * (math.cos(theta + omega * dt) - math.cos(theta))
        ntheta = math.atan2(math.sin(theta + omega * dt), math.cos(theta + omega * dt))
        bumped = False
        if ny < self.body_radius:
            bumped = True
            ny = self.body_radius
        return (nx, ny, ntheta), bumped

    def touching(self, pose: Sequence[float], tolerance: float = 1e-9) -> bool:
        return pose[1] <= self.body_radius + tolerance

    def read(self, pose: Sequence[float], noisy: bool = True) -> np.ndarray:
        """Noise-free readings of all sensors, plus optional noise and dropout (NaN)."""
        r = np.array([s.read(pose) for s in self.sensors], dtype=float)
        if noisy and (self.noise_std > 0.0 or self.noise_range_fraction > 0.0 or self.dropout > 0.0):
            finite = np.isfinite(r)
            std = self.noise_std + self.noise_range_fraction * np.array([s.max_range for s in self.sensors])
            r[finite] += self._rng.normal(0.0, std[finite])
            for i, sensor in enumerate(self.sensors):
                if finite[i] and r[i] > sensor.max_range:
                    r[i] = math.inf
            r[finite & (r < np.array([s.min_range for s in self.sensors]))] = -math.inf
            r[self._rng.random(r.shape) < self.dropout] = math.nan
        return r

    def in_range(self, readings: np.ndarray) -> np.ndarray:
        """Per sensor: does it report a usable distance (finite)?"""
        return np.isfinite(readings)


def wall_relative_state(pose: Sequence[float]):
    """(distance to the wall, angle of the heading from the wall's inward normal) -- for evaluation only."""
    _, y, theta = pose
    phi = math.atan2(math.sin(theta + math.pi / 2.0), math.cos(theta + math.pi / 2.0))
    return y, phi
