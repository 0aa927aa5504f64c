"""Sensor-switching Jacobian control (paper Section 2.4, Fig. 5): reach a goal given as a sensor-2 reading.

The goal reading maps to the closest point of the virtual sensor-1 space (learned overlap). While sensor 1 is in range
the robot is driven toward that point in grid coordinates, while it is blind the same happens in the virtual space,
and once sensor 2 is in range control switches to the sensor-2 readings themselves until they match the goal.

In every space the learned Jacobian field J(y) predicts how a command moves the state (y' = J(y) u). Plain
one-step Jacobian control stalls at the nonholonomic singularity near "parallel to the wall" (no command moves the
distance-like reading there), so each step evaluates a set of constant commands over a short horizon with the learned
field and keeps the one that brings the state closest to the goal (plus the damped least-squares Jacobian step as one
candidate), with a small cost on wheel travel so rotating in place is preferred where it does the job.
"""
from __future__ import annotations

from itertools import product
from typing import Optional, Tuple

import numpy as np

from mm_manifold.jacobian import PolynomialJacobianField

SPACE_NONE, SPACE_SENSOR1, SPACE_VIRTUAL, SPACE_SENSOR2 = 0, 1, 2, 3


class SwitchingController:
    """Hyperparameters: dt, max_wheel_speed [rad/s], horizon [steps], speed levels of the candidate set,
    travel_weight (cost of wheel travel relative to the squared goal error), tolerance [m] on each sensor-2 reading,
    settle_steps (consecutive steps within tolerance before stopping), damping of the least-squares step,
    waypoint_tolerance [grid units]."""

    def __init__(self, dt: float, max_wheel_speed: float = 6.0, horizon: int = 12,
                 speed_levels=(1.0, 0.4, 0.12, 0.0), travel_weight: float = 1e-3, tolerance: float = 0.01,
                 settle_steps: int = 2, damping: float = 1e-2, waypoint_tolerance: float = 0.3):
        self.dt = dt
        self.max_wheel_speed = max_wheel_speed
        self.horizon = horizon
        self.tolerance = tolerance
        self.travel_weight = travel_weight
        self.settle_steps = settle_steps
        self.damping = damping
        levels = sorted({s * max_wheel_speed * sign for s in speed_levels for sign in (-1, 1)})
        self.candidates = np.array(list(product(levels, levels)), dtype=float)
        coarse = sorted({s * max_wheel_speed * sign for s in speed_levels[::2] for sign in (-1, 1)})
        self.coarse_candidates = np.array(list(product(coarse, coarse)), dtype=float)
        self.goal_sensor2: Optional[np.ndarray] = None
        self.goal_coordinates: Optional[np.ndarray] = None
        self.waypoint: Optional[np.ndarray] = None
        self.waypoint_tolerance = waypoint_tolerance
        self.settled = 0

    def set_goal(self, sensor2_goal: np.ndarray, goal_coordinates: np.ndarray,
                 waypoint: Optional[np.ndarray] = None) -> None:
        """`waypoint`: where in sensor-1 range the practised excursions toward this goal left the range; the robot
        first goes there with sensor-1 control, then aims at the goal's virtual coordinates."""
        self.goal_sensor2 = np.asarray(sensor2_goal, dtype=float)
        self.goal_coordinates = np.asarray(goal_coordinates, dtype=float)
        self.waypoint = None if waypoint is None else np.asarray(waypoint, dtype=float)
        self.settled = 0

    @property
    def target(self) -> Optional[np.ndarray]:
        return self.waypoint if self.waypoint is not None else self.goal_coordinates

    def _best_command(self, field, state: np.ndarray, goal: np.ndarray, scale: np.ndarray,
                      bounds: Optional[np.ndarray], two_segments: bool = False) -> Tuple[np.ndarray, float]:
        """Best first command among constant (or, with `two_segments`, piecewise-constant: first half, second half)
        command sequences, judged by the learned field's prediction of the state over the horizon."""
        dls = self.jacobian_step(field.jacobian(state[None])[0], goal - state)
        first = np.vstack([self.candidates, dls])
        if two_segments:
            second = self.coarse_candidates
            U1 = np.repeat(first, len(second), axis=0)
            U2 = np.tile(second, (len(first), 1))
        else:
            U1 = U2 = first
        y = np.repeat(state[None], len(U1), axis=0)
        best = np.full(len(U1), np.inf)
        travel = np.zeros(len(U1))
        half = self.horizon // 2
        for t in range(self.horizon):
            U = U1 if t < half else U2
            y = y + field.rates(y, U) * self.dt
            if bounds is not None:
                y = np.clip(y, bounds[0], bounds[1])
            travel += np.abs(U.sum(axis=1))
            cost = np.sum(((y - goal) / scale) ** 2, axis=1) + self.travel_weight * travel
            best = cost if two_segments else np.minimum(best, cost)
        i = int(np.argmin(best))
        return U1[i], float(np.linalg.norm((goal - state) / scale))

    def jacobian_step(self, J: np.ndarray, error: np.ndarray) -> np.ndarray:
        """Damped least-squares Jacobian control: the wheel command that closes `error` in about `horizon` steps."""
        u = J.T @ np.linalg.solve(J @ J.T + self.damping * np.eye(len(error)), error / (self.horizon * self.dt))
        peak = np.max(np.abs(u))
        return u * (self.max_wheel_speed / peak) if peak > self.max_wheel_speed else u

    def command(self, space: int, coordinates: Optional[np.ndarray], sensor2: Optional[np.ndarray],
                virtual_field, sensor2_field: PolynomialJacobianField, sensor1_jacobian: Optional[np.ndarray] = None,
                bounds: Optional[np.ndarray] = None, coordinate_scale: float = 1.0):
        """(wheel command, reached, error in the active space) for the current state. `sensor1_jacobian` is the local
        Jacobian of the grid coordinates at the current reading (used while sensor 1 is in range)."""
        if self.goal_sensor2 is None:
            raise ValueError('no goal set')
        if space == SPACE_SENSOR2:
            error = np.abs(sensor2 - self.goal_sensor2)
            if np.all(error < self.tolerance):
                self.settled += 1
                if self.settled >= self.settle_steps:
                    return np.zeros(2), True, float(error.max())
            else:
                self.settled = 0
            u, err = self._best_command(sensor2_field, np.asarray(sensor2, dtype=float), self.goal_sensor2,
                                        np.full(len(sensor2), self.tolerance), None, two_segments=True)
            return u, False, float(error.max())
        self.settled = 0
        if coordinates is None:
            return np.zeros(2), False, float('nan')
        coordinates = np.asarray(coordinates, dtype=float)
        if self.waypoint is not None and np.linalg.norm(coordinates - self.waypoint) < self.waypoint_tolerance:
            self.waypoint = None
        if space == SPACE_SENSOR1 and sensor1_jacobian is not None and self.waypoint is not None:
            error = self.waypoint - coordinates
            return self.jacobian_step(sensor1_jacobian, error), False, float(np.linalg.norm(error))
        u, err = self._best_command(virtual_field, coordinates, self.target,
                                    np.full(len(coordinates), coordinate_scale), bounds)
        return u, False, err
