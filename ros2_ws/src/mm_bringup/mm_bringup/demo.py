"""`make demo`: both experiments of the paper through the ROS graph, recorded into one rosbag2 (MCAP) bag.

    ./mm run mm_bringup demo --output results/demo_bag

1. A recorder starts first (all topics, reliable where the publishers are) and writes `--output`, replacing it.
2. Section 2: wheeled_sim (lockstep) + sensor_manifold + switching_controller on the `paper` sensor layout (no pose
   where both sensor groups see the wall, as in the paper; `--layout overlap` for the simulator's default), composed
   in one process (mm_bringup wheeled_container: the same nodes and topics, the same learning to the byte, about
   1.7x the loop's rate, and the other core left to the arm; `--separate-processes` for one process each). The
   robot explores (the sample-bound setting the wall_task benchmark's headline measures on five seeds:
   wall_experiment.SAMPLE_BOUND_EXPLORATION steps and SAMPLE_BOUND_REHEARSALS rehearsals), the manifold node learns
   the grid, Jacobians and virtual sensor space, then the paper's task runs: start facing the wall perpendicularly
   at 1 m, goal shown as the sensor-2 reading of the pose parallel to the wall at the layout's goal distance
   (wall_experiment.PAPER_GOAL_POSES), reached across the blind stretch.
3. Section 3, at the same time as Section 2 (the two graphs share nothing but the recorder; no wall-clock timing
   decides what the wheeled loop learns or commands, so the arm beside it changes its results in nothing, only its
   pace): arm_sim + image_embedding + dp_planner: random arm exploration while the object moves, online LLE (kept),
   then the object is re-placed where the model never saw it and in the way, and the planner plans on a map of that
   frame before moving (mm_bringup.arm_demo; how many frames of a new placement pass before its goal arrives
   depends on the machine's pace).
4. The recorder is stopped with SIGINT (it finalises the MCAP summary and metadata.yaml); the bag is summarised,
   and the Section 2 figures (Figs. 7-9) are drawn from what the graph did into `--figures`.
"""
from __future__ import annotations

import argparse
import json
import shutil
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from mm_bringup.arm_demo import run_arm_demo
from mm_bringup.bag_tool import format_info, topic_counts
from mm_bringup.process_graph import ProcessGraph
from mm_bringup.wall_experiment import (LAYOUTS, PAPER_GOAL_POSES, PAPER_START, SAMPLE_BOUND_EXPLORATION,
                                        SAMPLE_BOUND_REHEARSALS, layout_file, layout_robot,
                                        oracle_path_length, sensor2_goal_reading, simulator_params_file)
from mm_bringup.wall_graph import WallGraph
from mm_common.rosbag import iter_messages
from mm_common.wheeled_sensors import SENSOR2
from mm_manifold.sensor_manifold import SensorManifoldModel

PAPER_TOLERANCE = 0.005
# wheeled_sim publishes each of these exactly once per step (a re-sent step included); all but the bumper's Bool
# begin with a std_msgs/Header, whose stamp names the step
STAMPED_PER_STEP_TOPICS = ['/wheeled/ranges', '/wheeled/ground_truth/odom'] + [
    f'/wheeled/range/{n}' for n in ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')]
PER_STEP_TOPICS = STAMPED_PER_STEP_TOPICS + ['/wheeled/bumper']
# The recorder must hold these from the loop's first step (see WallGraph).
LOOP_TOPICS = ['/clock', '/wheeled/wheel_velocity_controller/commands', '/wheeled/controller/status'] + PER_STEP_TOPICS


def log(text: str) -> None:
    print(f'[demo] {text}', flush=True)


class Phases:
    """Wall time of each phase of the demo (demo_summary.json), so a user sees where the time goes: the main line's
    phases one after the other (`done`), and the arm part, which runs beside them, as its own span (`add`)."""

    def __init__(self):
        self.seconds = {}
        self.began = self.mark = time.monotonic()

    def done(self, name: str) -> float:
        now = time.monotonic()
        self.seconds[name] = round(now - self.mark, 2)
        self.mark = now
        return self.seconds[name]

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = round(seconds, 2)

    def total(self) -> float:
        return round(time.monotonic() - self.began, 2)


def explore_with_progress(wall: WallGraph, steps: int, every_s: float = 2.0) -> None:
    """Wait for the exploration, one progress line every `every_s` seconds (samples so far and the loop's rate)."""
    began = last_line = time.monotonic()

    def explored() -> bool:
        nonlocal last_line
        now = time.monotonic()
        if now - last_line >= every_s and wall.samples < steps:
            log(f'exploring {wall.samples}/{steps} at {wall.samples / (now - began):.0f} steps/s')
            last_line = now
        return wall.samples >= steps

    wall.spin_until(explored, 1800.0, 'the exploration')


def header_stamp_ns(cdr: bytes) -> int:
    """The header stamp of a serialized message that begins with a std_msgs/Header (CDR: a 4-byte encapsulation,
    then sec int32 and nanosec uint32 in its byte order), without deserializing the rest."""
    order = '<' if cdr[1] & 1 else '>'
    sec, nanosec = struct.unpack_from(order + 'iI', cdr, 4)
    return sec * 1_000_000_000 + nanosec


def bag_completeness(bag: Path) -> dict:
    """Whether the bag holds every step of the wheeled loop on every per-step topic. The simulator publishes them
    all once per step, and again (same stamp) when no command came for its republish period - also at start-up,
    when the recorder may have matched some topics and not yet the others: such a step is on some topics twice,
    which is no loss, so the steps are counted by stamp (the steps are those on any of the topics: one missing from
    all of them at once would go unnoticed). The bumper's Bool has no stamp: it must hold at least as many messages
    as there are steps."""
    counts = topic_counts(bag)
    stamps = {t: set() for t in STAMPED_PER_STEP_TOPICS}
    for message in iter_messages(bag, STAMPED_PER_STEP_TOPICS):
        if len(message.data) >= 12:          # shorter holds no stamp: no step (the check then fails)
            stamps[message.topic].add(header_stamp_ns(message.data))
    steps = set().union(*stamps.values())
    complete = all(s == steps for s in stamps.values()) and counts.get('/wheeled/bumper', 0) >= len(steps)
    return {'per_step_topic_counts': {t: counts.get(t, 0) for t in PER_STEP_TOPICS},
            'per_step_topic_steps': {t: len(s) for t, s in stamps.items()}, 'steps': len(steps),
            'complete': complete}


def learn_with_progress(wall: WallGraph, every_s: float = 5.0) -> None:
    """Wait until the controller waits for a goal: a line whenever its phase changes (a model that is not ready sends
    it exploring on, with the reason) and every `every_s` seconds; LearningFailed if the controller gives up."""
    last = {'phase': None, 'at': time.monotonic()}

    def progress(status) -> None:
        now = time.monotonic()
        if status is not None and (status.phase_name != last['phase'] or now - last['at'] >= every_s):
            reason = f' ({status.detail})' if status.phase_name != last['phase'] and status.detail else ''
            log(f'{status.phase_name.lower()}: {wall.samples} samples{reason}')
            last.update(phase=status.phase_name, at=now)

    wall.wait_learned(1800.0, on_status=progress)


def wall_experiment(graph: ProcessGraph, work: Path, exploration_steps: int, figures: Path, phases: Phases,
                    layout: str = 'paper', composed: bool = True,
                    rehearsals: Optional[int] = None) -> Tuple[dict, 'Beside']:
    """The Section 2 part: its summary, and the thread drawing its figures (joined by the caller, so the drawing
    overlaps the nodes' and the recorder's shutdown)."""
    robot, dt = layout_robot(layout)       # the simulator's sensor model: ground truth chooses the goal reading only
    goal_pose = PAPER_GOAL_POSES[layout]
    began = time.monotonic()
    sim_files = [simulator_params_file(), layout_file(layout)]
    with WallGraph(work, exploration_steps=exploration_steps, graph=graph, recorder='recorder', dt=dt,
                   recorded_topics=LOOP_TOPICS, sim_params_files=sim_files, composed=composed,
                   rehearsals=rehearsals) as wall:
        log(f'wheeled graph ({layout} sensor layout) started in {phases.done("wheeled_start")} s; exploring '
            f'{exploration_steps} steps')
        explore_with_progress(wall, exploration_steps)
        seconds = phases.done('exploring')
        log(f'explored {exploration_steps}/{exploration_steps} at {exploration_steps / seconds:.0f} steps/s; fitting')
        learn_with_progress(wall)
        learned_s = time.monotonic() - began
        log(f'fitting done in {phases.done("fitting")} s: learned from {wall.samples} samples')
        goal = sensor2_goal_reading(robot, goal_pose)
        log(f'paper task: start {tuple(round(v, 3) for v in PAPER_START)}, goal sensor-2 reading '
            f'{np.round(goal, 4).tolist()} m (tolerance {PAPER_TOLERANCE} m)')
        episode = wall.run_episode(PAPER_START, goal, PAPER_TOLERANCE)
        samples = np.array(wall.sensor1_samples, dtype=float)
        # Drawn while the wheeled nodes and the recorder shut down (a second or so), from the learner's saved model
        # (loaded here: the work directory goes with the demo's temporary directory).
        try:
            model = SensorManifoldModel.load(work / 'wall_model.npz')
        except ValueError as exc:
            drawing = Beside(lambda: f'cannot read the learned model: {exc}')
        else:
            drawing = Beside(draw_figures_or_say_why, model, samples, episode, goal, figures)
    phases.done('task')
    final = robot.read(episode.poses[-1], noisy=False)[list(SENSOR2)]
    error = float(np.max(np.abs(final - goal))) if np.all(np.isfinite(final)) else float('inf')
    summary = {'layout': layout, 'composed': composed, 'reached': episode.reached, 'detail': episode.detail,
               'final_error_m': error,
               'final_pose': [round(v, 4) for v in episode.poses[-1]], 'steps': len(episode.poses) - 1,
               'path_ratio': episode.path_length() / oracle_path_length(PAPER_START, goal_pose),
               'blind_fraction': episode.blind_fraction(), 'learning_samples': wall.samples,
               'learning_s': round(learned_s, 1)}
    log(f"paper task: {'reached' if episode.reached else 'NOT reached'} ({episode.detail}); noise-free final "
        f"error {error * 1000:.1f} mm, heading {episode.poses[-1][2]:+.3f} rad, blind share of the path "
        f"{summary['blind_fraction']:.2f}, path {summary['path_ratio']:.2f}x the oracle's")
    return summary, drawing


class Beside(threading.Thread):
    """Runs `function(*args)` in a daemon thread from construction on; result() waits and returns it or re-raises
    its exception. Daemon: when the main line fails or is interrupted, the graph's nodes are stopped and the process
    exits without waiting for this part to time out."""

    def __init__(self, function, *args):
        super().__init__(daemon=True, name=function.__name__)
        self._call = (function, args)
        self._outcome = None
        self.start()

    def run(self) -> None:
        function, args = self._call
        try:
            self._outcome = (True, function(*args))
        except BaseException as exc:       # handed to the main line by result()
            self._outcome = (False, exc)

    def result(self):
        self.join()
        ok, value = self._outcome
        if not ok:
            raise value
        return value


def arm_experiment(graph: ProcessGraph, exploration_steps: int):
    """The Section 3 part (run beside Section 2): its summary and wall seconds."""
    began = time.monotonic()
    log('arm: exploring with the object moving, learning the image embedding, then planning around re-placed '
        'objects')
    summary = run_arm_demo(graph, log=log, exploration_steps=exploration_steps, timeout_s=900.0)
    return summary, time.monotonic() - began


def draw_figures_or_say_why(*args) -> str:
    """draw_figures; '' when drawn, else why not (the figures are a by-product: the demo's result stands)."""
    try:
        draw_figures(*args)
    except Exception as exc:
        return repr(exc)
    return ''


def draw_figures(model: SensorManifoldModel, samples: np.ndarray, episode, goal: np.ndarray, figures: Path) -> None:
    from mm_bringup.figures_wheeled import plot_samples_and_grid, plot_trajectory_spaces, plot_world_trajectory
    figures.mkdir(parents=True, exist_ok=True)
    plot_samples_and_grid(model, samples, figures / 'fig7_sensor1_grid.png')
    plot_trajectory_spaces(model, episode.coordinates, episode.spaces, episode.sensor2,
                           model.virtual_.goal_route(goal)[1], goal, figures / 'fig8_trajectory_spaces.png')
    plot_world_trajectory(episode.poses, episode.blind, figures / 'fig9_world_trajectory.png')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/demo_bag', help='bag directory (replaced)')
    parser.add_argument('--figures', default='results/demo_figures',
                        help="where the demo run's Section 2 figures go (results/figures keeps Figs. 7-9 of "
                             "figures_wheeled, from the benchmark's exploration)")
    parser.add_argument('--layout', choices=LAYOUTS, default='paper', help='sensor layout of the wheeled robot')
    parser.add_argument('--exploration-steps', type=int, default=SAMPLE_BOUND_EXPLORATION,
                        help='wheeled-robot exploration steps (the learner asks for more when its model is not ready)')
    parser.add_argument('--rehearsals', type=int, default=SAMPLE_BOUND_REHEARSALS,
                        help='practice reaches a ready model must pass before it is announced')
    parser.add_argument('--arm-exploration-steps', type=int, default=500, help='arm exploration steps')
    parser.add_argument('--skip-arm', action='store_true', help='run the Section 2 experiment only')
    parser.add_argument('--separate-processes', action='store_true',
                        help='the wheeled loop as three processes instead of composed in one')
    args = parser.parse_args(argv)
    bag = Path(args.output).resolve()
    if bag.exists():
        shutil.rmtree(bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    results = {}
    phases = Phases()
    with tempfile.TemporaryDirectory(prefix='mm_demo_') as tmp, ProcessGraph(log_dir=Path(tmp) / 'logs') as graph:
        recorder = graph.start('mm_bringup', 'recorder', {'output': str(bag), 'discovery_period': 0.05})
        try:
            arm = None if args.skip_arm else Beside(arm_experiment, graph, args.arm_exploration_steps)
            results['wall'], drawing = wall_experiment(graph, Path(tmp) / 'wall', args.exploration_steps,
                                                       Path(args.figures), phases, args.layout,
                                                       composed=not args.separate_processes,
                                                       rehearsals=args.rehearsals)
            if arm is not None:
                results['arm'], arm_s = arm.result()
                phases.add('arm', arm_s)
                log(f'arm part done in {arm_s:.1f} s (beside the wheeled robot; '
                    f'{phases.done("arm_after_wheeled")} s after it)')
        finally:
            code = graph.stop(recorder, timeout=60.0)
            if code != 0:
                log(f'recorder exited with {code}:\n{graph.log_tail(recorder)}')
    print(format_info(bag), flush=True)
    results['bag'] = bag_completeness(bag)
    if not results['bag']['complete']:
        log(f"WARNING: the bag lost messages of the wheeled loop: the simulator publishes each of these once per "
            f"step ({results['bag']['steps']} steps), yet the bag holds steps {results['bag']['per_step_topic_steps']} "
            f"and messages {results['bag']['per_step_topic_counts']}")
    log(f'bag closed and summarised in {phases.done("bag")} s')
    problem = drawing.result()
    log(f'figures failed: {problem}' if problem else
        f'figures (Figs. 7-9) in {args.figures} ({phases.done("figures")} s after the bag)')
    results['phase_seconds'] = phases.seconds
    results['total_s'] = phases.total()
    (bag.parent / 'demo_summary.json').write_text(json.dumps(results, indent=2, default=str) + '\n')
    log(f'summary written to {bag.parent / "demo_summary.json"}')
    wall_ok = results['wall']['reached'] and results['wall']['final_error_m'] < PAPER_TOLERANCE
    # The arm part succeeds when its pipeline ran (learned, planned and executed every placement); how well it did
    # (goals reached, contacts of any arm part from the simulator's ground truth) is reported above and in the summary.
    arm_ok = args.skip_arm or bool(results['arm'].get('placements'))
    if not args.skip_arm:
        arm = results['arm']
        log(f"arm: {arm['successes']}/{len(arm['placements'])} placements reached without contact; "
            f"{arm['contact_placements']} with contact of some arm part (ground truth)")
    return 0 if wall_ok and arm_ok else 1


if __name__ == '__main__':
    sys.exit(main())
