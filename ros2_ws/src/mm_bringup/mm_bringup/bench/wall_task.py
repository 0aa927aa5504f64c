"""Wall benchmark (results/wall_task.json): paper Section 2 measured through the ROS graph.

Each condition starts its own graph (wheeled_sim in lockstep + sensor_manifold + switching_controller as processes,
mm_bringup.wall_graph), lets it explore and learn from scratch, then runs randomised reaching tasks with fixed seeds:
a start where sensor 1 sees the wall, a goal pose close to the wall where only sensor 2 does, shown to the robot as
its sensor-2 reading. Scoring uses ground truth (evaluation only):
- success: the controller reports GOAL_REACHED and the noise-free sensor-2 reading at the final pose is within the
  tolerance of the goal reading (so a noisy estimate that "arrived" early does not count);
- final error: max |noise-free sensor-2 reading - goal reading| at the final pose [m] (inf when sensor 2 sees nothing);
- path ratio: travelled path over the oracle's (a controller that knows the geometry: turn in place, drive straight
  to the goal distance, turn in place; only the distance to the wall matters because readings do not depend on x);
- blind fraction: share of the path length travelled while no sensor group could see the wall (noise-free sensor
  model at the ground-truth poses).
The noisy condition adds Gaussian noise with a std of 1 % of each sensor's max range and 5 % dropped readings, to
exploration and tasks alike (the robot learns from noisy data too).
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np

from mm_bringup.wall_experiment import (PAPER_START, oracle_path_length, random_task, sensor2_goal_reading)
from mm_bringup.wall_graph import WallGraph
from mm_sim.wheeled_model import SENSOR2, WheeledRobot

NAME = 'wall_task'
PAPER_GOAL_POSE = (0.0, 0.25, 0.0)
PAPER_TOLERANCE = 0.005


def blind_fraction(robot: WheeledRobot, poses) -> float:
    """Share of the path length travelled while neither sensor group could see the wall (noise-free sensor model at
    the ground-truth poses, so dropped readings do not count as blind)."""
    P = np.asarray(poses, dtype=float)
    if len(P) < 2:
        return 0.0
    seen = [np.all(np.isfinite(r[:3])) or np.all(np.isfinite(r[3:])) for r in (robot.read(p, noisy=False) for p in P)]
    seg = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)
    blind = ~np.array(seen[:-1]) | ~np.array(seen[1:])
    return float(seg[blind].sum() / seg.sum()) if seg.sum() > 0 else 0.0


def score(robot: WheeledRobot, episode, start, goal_pose, goal_reading, tolerance: float) -> dict:
    final = robot.read(episode.poses[-1], noisy=False)[list(SENSOR2)]
    error = float(np.max(np.abs(final - goal_reading))) if np.all(np.isfinite(final)) else math.inf
    return {'reached': episode.reached, 'success': bool(episode.reached and error < tolerance),
            'final_error': error, 'path_ratio': episode.path_length() / oracle_path_length(start, goal_pose),
            'blind_fraction': blind_fraction(robot, episode.poses), 'steps': len(episode.poses) - 1,
            'wall_seconds': episode.wall_seconds, 'final_heading': float(episode.poses[-1][2]),
            'detail': episode.detail}


def run_task(graph: WallGraph, robot: WheeledRobot, start, goal_pose, tolerance: float,
             timeout: float = 120.0) -> dict:
    """One scored episode; a stalled lockstep loop (no outcome within `timeout` wall seconds) counts as a failure
    and the next task's reset restarts the loop, so one stall does not end the benchmark."""
    reading = sensor2_goal_reading(robot, goal_pose)
    try:
        episode = graph.run_episode(start, reading, tolerance, timeout=timeout)
    except TimeoutError as exc:
        return {'success': False, 'reached': False, 'final_error': math.inf, 'path_ratio': math.nan,
                'blind_fraction': math.nan, 'steps': 0, 'wall_seconds': timeout, 'final_heading': math.nan,
                'detail': f'stalled: {exc}'}
    return score(robot, episode, start, goal_pose, reading, tolerance)


def run_condition(work_dir: Path, n_tasks: int, exploration_steps: int, tolerance: float, noise_fraction: float,
                  dropout: float, seed: int) -> dict:
    robot = WheeledRobot()
    rng = np.random.default_rng(seed)
    tasks = [random_task(rng, robot) for _ in range(n_tasks)]
    began = time.monotonic()
    with WallGraph(work_dir, exploration_steps=exploration_steps, noise_range_fraction=noise_fraction,
                   dropout=dropout, seed=seed) as graph:
        graph.wait_learned(timeout=1800.0)
        learning_seconds = time.monotonic() - began
        learning_samples = graph.samples
        paper = run_task(graph, robot, PAPER_START, PAPER_GOAL_POSE, PAPER_TOLERANCE)
        episodes = [run_task(graph, robot, start, goal_pose, tolerance) for start, goal_pose in tasks]
    stalls = sum(e['detail'].startswith('stalled') for e in episodes + [paper])
    ok = [e for e in episodes if e['success']]
    finite_errors = [e['final_error'] for e in episodes]
    return {
        'tasks': n_tasks,
        'stalled_episodes': stalls,
        'success_rate': len(ok) / n_tasks,
        'median_final_error': float(np.median(finite_errors)),
        'median_path_ratio': float(np.median([e['path_ratio'] for e in ok])) if ok else None,
        'blind_fraction': float(np.mean([e['blind_fraction'] for e in ok])) if ok else None,
        'share_of_tasks_crossing_blind': float(np.mean([e['blind_fraction'] > 0 for e in ok])) if ok else None,
        'learning_samples': int(learning_samples),
        'learning_wall_seconds': round(learning_seconds, 1),
        'seconds_per_episode': float(np.mean([e['wall_seconds'] for e in episodes])),
        'steps_per_episode_median': float(np.median([e['steps'] for e in episodes])),
        'failures': [{'task': i, 'detail': e['detail'], 'final_error': e['final_error']}
                     for i, e in enumerate(episodes) if not e['success']],
        'paper_task': paper,
    }


def run(output_dir: Path, quick: bool) -> dict:
    n_tasks = 20 if quick else 120
    exploration_steps = 10000
    tolerance = 0.01
    with tempfile.TemporaryDirectory(prefix='wall_task_') as tmp:
        clean = run_condition(Path(tmp) / 'clean', n_tasks, exploration_steps, tolerance, 0.0, 0.0, seed=1)
        noisy = run_condition(Path(tmp) / 'noisy', n_tasks, exploration_steps, tolerance, 0.01, 0.05, seed=2)
    return {
        'success_rate': clean['success_rate'],
        'median_final_error': clean['median_final_error'],
        'median_path_ratio': clean['median_path_ratio'],
        'blind_fraction': clean['blind_fraction'],
        'learning_samples': clean['learning_samples'],
        'seconds_per_episode': clean['seconds_per_episode'],
        'success_rate_noisy': noisy['success_rate'],
        'tolerance_m': tolerance,
        'noise': {'std_fraction_of_max_range': 0.01, 'dropout': 0.05},
        'paper_task': clean['paper_task'],
        'clean': clean,
        'noisy': noisy,
        'targets': {'success_rate': 0.95, 'success_rate_noisy': 0.9, 'median_path_ratio_max': 1.3},
    }
