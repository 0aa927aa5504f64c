"""Section 2 experiment without ROS: exploration, learning and reaching episodes in a closed loop with the simulator
model. Used to test the algorithms end to end and to draw the figures; the benchmark runs the same through the graph.

Evaluation-side code: it may use the simulator's ground truth (poses) to score and plot, never to control.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from mm_manifold.sensor_manifold import SENSOR2, SensorManifoldModel, StateTracker
from mm_planner.exploration import RandomExplorer
from mm_planner.switching_controller import SPACE_NONE, SPACE_SENSOR2, SwitchingController
from mm_sim.wheeled_model import WheeledRobot, wall_relative_state

PAPER_START = (0.0, 1.0, -math.pi / 2)          # facing the wall perpendicularly at 1 m
PAPER_GOAL = (0.0, 0.2, 0.0)                    # close to the wall, parallel, only sensor 2 sees it


@dataclass
class ExplorationLog:
    readings: np.ndarray
    commands: np.ndarray
    continuous: np.ndarray
    poses: np.ndarray


def explore(robot: WheeledRobot, steps: int, start=PAPER_START, random_state: int = 0,
            explorer: Optional[RandomExplorer] = None, dt: float = 0.05) -> ExplorationLog:
    explorer = explorer or RandomExplorer(random_state=random_state)
    pose, bumped = tuple(start), False
    R, U, P = [], [], []
    for _ in range(steps):
        r = robot.read(pose)
        u = explorer.command(r, bumped)
        R.append(r)
        U.append(u)
        P.append(pose)
        pose, bumped = robot.step(pose, u, dt)
    cont = np.ones(steps, dtype=bool)
    cont[-1] = False
    return ExplorationLog(np.array(R), np.array(U), cont, np.array(P))


@dataclass
class Episode:
    poses: List[Tuple[float, float, float]] = field(default_factory=list)
    spaces: List[int] = field(default_factory=list)
    coordinates: List[Optional[np.ndarray]] = field(default_factory=list)
    readings: List[np.ndarray] = field(default_factory=list)
    commands: List[np.ndarray] = field(default_factory=list)
    reached: bool = False

    def path_length(self) -> float:
        p = np.array(self.poses)[:, :2]
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

    def blind_fraction(self) -> float:
        """Share of control steps in which no sensor group was in range."""
        s = np.array(self.spaces)
        return float(np.mean((s != SPACE_SENSOR2) & (s != 1))) if len(s) else 0.0


def sensor2_goal_reading(robot: WheeledRobot, goal_pose) -> np.ndarray:
    """The observation that defines the task (the experimenter shows the robot the goal reading)."""
    r = robot.read(goal_pose, noisy=False)[list(SENSOR2)]
    if not np.all(np.isfinite(r)):
        raise ValueError(f'sensor 2 does not see the wall at the goal pose {goal_pose}')
    return r


def run_episode(robot: WheeledRobot, model: SensorManifoldModel, start, goal_reading: np.ndarray,
                controller: Optional[SwitchingController] = None, max_steps: int = 1500,
                dt: float = 0.05) -> Episode:
    controller = controller or SwitchingController(dt)
    controller.set_goal_from_routes(model.virtual_, goal_reading, model.sensor2_noise_)
    tracker = StateTracker(model)
    pose, last = tuple(start), None
    ep = Episode()
    bounds = model.virtual_bounds()
    for _ in range(max_steps):
        r = robot.read(pose)
        space, coords, s2, _ = tracker.update(r, last)
        ep.poses.append(pose)
        ep.spaces.append(space)
        ep.coordinates.append(None if coords is None else coords.copy())
        ep.readings.append(r)
        if space == SPACE_NONE:
            u, done = np.zeros(2), False
        else:
            J1 = model.regions1_.interpolate(coords) if space == 1 else None
            u, done, _ = controller.command(space, coords, s2, model.virtual_.field_, model.field2_, J1, bounds,
                                            model.sensor2_box_, sensor2_measured=bool(np.all(np.isfinite(r[3:]))))
        if done:
            ep.reached = True
            break
        ep.commands.append(u)
        pose, _ = robot.step(pose, u, dt)
        last = u
    return ep


def oracle_path_length(start, goal) -> float:
    """Shortest travel of a controller that knows the geometry: turn in place to face the wall (or away), drive
    straight to the goal distance, turn in place to the goal heading. Along the wall the goal is free (the task is
    given by readings, which do not depend on x)."""
    return abs(start[1] - goal[1])


def success(robot: WheeledRobot, episode: Episode, goal_reading: np.ndarray, tolerance: float) -> Tuple[bool, float]:
    """Scored on the noise-free reading at the final pose."""
    final = robot.read(episode.poses[-1], noisy=False)[list(SENSOR2)]
    error = float(np.max(np.abs(final - goal_reading))) if np.all(np.isfinite(final)) else math.inf
    return episode.reached and error < tolerance, error


def random_task(rng: np.random.Generator, robot: WheeledRobot) -> Tuple[tuple, tuple]:
    """A start where sensor 1 sees the wall and a goal where only sensor 2 does, both random."""
    while True:
        start = (0.0, rng.uniform(0.4, 1.1), -math.pi / 2 + rng.uniform(-0.25, 0.25))
        goal = (0.0, rng.uniform(0.12, 0.24), rng.uniform(-0.25, 0.25))
        rs, rg = robot.read(start, noisy=False), robot.read(goal, noisy=False)
        if np.all(np.isfinite(rs[:3])) and np.all(np.isfinite(rg[3:])) and not np.all(np.isfinite(rg[:3])):
            return start, goal


__all__ = ['explore', 'run_episode', 'oracle_path_length', 'success', 'random_task', 'sensor2_goal_reading',
           'PAPER_START', 'PAPER_GOAL', 'wall_relative_state']
