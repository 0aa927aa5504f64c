"""No stall lasts (issue 13 item 2): each node of the running wheeled graph is killed (SIGKILL, no clean-up) and
restarted in turn during exploration; every time the lockstep loop is running again within seconds, and the graph
still learns and completes the paper's task.

The simulator is the world: its restart continues its predecessor's time and pose (`initial_step`, `initial_pose`,
taken by this experimenter from the evaluation-only odometry), as a supervisor would restore a crashed simulator.
The controller restarts from nothing, the manifold node with the samples it had appended to its samples file (none of
the explored data is lost); both must rejoin the loop by themselves."""
import math
import os
import signal
import time

from rosgraph_msgs.msg import Clock

from mm_bringup.wall_experiment import PAPER_START, sensor2_goal_reading
from mm_bringup.wall_graph import DONE, LOOP_QOS, LearningFailed, WallGraph
from mm_msgs.msg import ControllerStatus
from mm_sim.wheeled_model import WheeledRobot

# The node's default budget. The kills change what is explored (the restarted controller explores from its seed's
# beginning), so each run learns from other data: with 3 000 steps 2 runs in about 16 ended without the paper's
# task (a model rehearsed 5/5 that then missed it; one never ready within the cap), as 3 000-step models on this
# layout sometimes do (results/wall_task.json: overlap, default robot, seed 1004 0.925); at 10 000 all five seeds
# reach 1.0. What learning needs is the benchmark's to measure; this test is about the restarts.
EXPLORATION = 10000
DT = 0.05
RESUMED_STEPS = 30          # steps beyond the kill that show the loop runs again
RECOVERY_TIMEOUT = 30.0     # wall seconds; the simulator re-sends its step every 0.5 s


def _step(wall: WallGraph) -> int:
    return round(wall.recent_odom[-1][0] / (DT * 1e9)) if wall.recent_odom else -1


def _clock_step(clock: list) -> int:
    """The newest step on /clock: the simulator publishes it first, so no reading of a later step exists."""
    return round((clock[-1].clock.sec * 1e9 + clock[-1].clock.nanosec) / (DT * 1e9)) if clock else -1


def _kill_and_restart(wall: WallGraph, executable: str, clock: list) -> float:
    """SIGKILL one node, start it again, return the wall seconds until the loop advanced RESUMED_STEPS steps."""
    index = next(i for i, n in enumerate(wall.nodes) if n.executable == executable)
    old = wall.nodes[index]
    parameters = dict(old.parameters)
    killed_at = time.monotonic()
    os.killpg(old.process.pid, signal.SIGKILL)
    old.process.wait(10)
    step = _step(wall)
    if executable == 'wheeled_sim':
        # whatever it published before it died: this process may be seconds behind on a loaded machine, so wait
        # until /clock has been quiet for a second (a stale step made the restart go back in time)
        _until_quiet(wall, lambda: clock[-1] if clock else None)
        step = max(_clock_step(clock), _step(wall))
        parameters.update(initial_step=step + 1, initial_pose=list(wall.last_pose))
    old.log_path.rename(old.log_path.with_name(f'{executable}.killed.log'))
    if executable == 'sensor_manifold':
        # the dead learner's last state (this process may still be receiving them): wait until none came for 1 s
        _until_quiet(wall, lambda: len(wall.recent_states) and wall.recent_states[-1])
        last = wall.recent_states[-1]
    wall.nodes[index] = wall.graph.start(old.package, old.executable, parameters)
    try:
        wall.spin_until(lambda: _step(wall) >= step + RESUMED_STEPS, RECOVERY_TIMEOUT,
                        f'the loop to run again after {executable} was killed at step {step}')
    except TimeoutError as stall:
        # An intermittent stall after a restart (a new participant that never takes a state) has no root cause yet:
        # the nodes' logs go with the failure, since the test's tmp directory may be gone before anyone looks.
        raise TimeoutError(f'{stall}\n{wall.log_tails(30)}') from stall
    if executable == 'sensor_manifold':
        # Its samples were on disk (samples_path): the restarted learner counts on from where the dead one stopped;
        # one that had lost them would count only the steps since its restart.
        def newer():
            return next((m for m in wall.recent_states if _ns(m.header.stamp) > _ns(last.header.stamp)), None)
        wall.spin_until(lambda: newer() is not None, RECOVERY_TIMEOUT, 'a state of the restarted learner')
        assert newer().samples > last.samples, f'{newer().samples} samples after the restart, {last.samples} before'
    return time.monotonic() - killed_at


def _until_quiet(wall: WallGraph, newest, quiet: float = 1.0, timeout: float = 20.0) -> None:
    """Spin until `newest()` has not changed for `quiet` seconds (at most `timeout`)."""
    deadline, seen, since = time.monotonic() + timeout, newest(), time.monotonic()
    while time.monotonic() - since < quiet and time.monotonic() < deadline:
        wall.ros.spin_for(0.1)
        if newest() is not seen:
            seen, since = newest(), time.monotonic()


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_killed_nodes_rejoin_and_the_paper_task_completes(tmp_path):
    robot = WheeledRobot()
    with WallGraph(tmp_path, exploration_steps=EXPLORATION, dt=DT) as wall:
        wall.watch_ground_truth()        # the steps and the simulator's restart pose come from the true odometry
        clock: list = []
        wall.node.create_subscription(Clock, '/clock', clock.append, LOOP_QOS)
        recovery = {}
        for executable, at_step in (('switching_controller', 200), ('sensor_manifold', 500), ('wheeled_sim', 800)):
            wall.spin_until(lambda: _step(wall) >= at_step, 120.0, f'step {at_step}')
            recovery[executable] = _kill_and_restart(wall, executable, clock)
        print('recovery after SIGKILL + restart [s]:', {k: round(v, 2) for k, v in recovery.items()})
        try:
            # Learning may take several fits (a model whose held-out predictions miss the bound explores on), so
            # the bound is generous: the loop stalling for good is what this test must catch.
            wall.wait_learned(timeout=600.0)
        except (TimeoutError, LearningFailed) as exc:
            logs = '\n'.join(f'--- {n.label}:\n{wall.graph.log_tail(n, 40)}' for n in wall.nodes)
            raise AssertionError(f'no model after the restarts (step {_step(wall)}, controller phase '
                                 f'{wall.status.phase_name if wall.status else None!r}, manifold samples '
                                 f'{wall.samples}, learn_after {EXPLORATION}): {exc}\n{logs}') from exc
        episode = wall.run_episode(PAPER_START, sensor2_goal_reading(robot, (0.0, 0.25, 0.0)), 0.005,
                                   timeout=120.0)
    print(f'paper task after the kills: {episode.phase} ({episode.detail}), {len(episode.poses)} poses')
    assert episode.phase in DONE
    assert episode.phase == ControllerStatus.PHASE_GOAL_REACHED, episode.detail
    final = episode.poses[-1]
    # Both side readings within the 5 mm tolerance allow a heading of up to ~0.33 rad off parallel (sensors 3 cm apart).
    assert abs(final[1] - 0.25) < 0.02 and abs(math.sin(final[2])) < 0.35, final
