"""The wall graph split across two "hosts": two network namespaces joined by a veth pair, nothing else.

Host A (198.51.100.1) runs the simulator, the recorder and the experimenter; host B (198.51.100.2) runs the
learner (sensor_manifold) and the controller (switching_controller). Each side discovers the other through
ROS_STATIC_PEERS with ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET; multicast is switched off on the veth link and only UDP is
allowed (no shared-memory shortcut between processes of one machine), so every message between the sides crosses
the link. The addresses exist only inside the two namespaces, which have no route anywhere else; they are deleted in a
finally block. The learner keeps no model file: the controller has the model only from its latched message.
The robot explores, learns, and reaches the paper's task goal; the bag recorded on A then holds every
simulator step exactly as often on every sensor topic and /clock (no lost message), and a command per step.

Creating namespaces needs root (CAP_NET_ADMIN/CAP_SYS_ADMIN) and iproute2; elsewhere the test is skipped with the
reason. The driver runs as a child process inside namespace A (this file, `drive` mode) and starts B's nodes inside
namespace B (setns around the fork), so the pytest process itself never changes namespace.
"""
from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

HOST_A, HOST_B = '198.51.100.1', '198.51.100.2'          # TEST-NET-2 (RFC 5737): never routed anywhere
EXPLORATION = 2000
GOAL_POSE = (0.0, 0.25, 0.0)
TOLERANCE = 0.005
DT = 0.05
SENSORS = ('front_left', 'front_center', 'front_right', 'side_front', 'side_rear')
RANGE_TOPICS = [f'/wheeled/range/{n}' for n in SENSORS]
COMMANDS = '/wheeled/wheel_velocity_controller/commands'
RECORDED = RANGE_TOPICS + ['/clock', '/wheeled/bumper', COMMANDS]
ON_HOST_B = ('sensor_manifold', 'switching_controller')
# Profiles ./mm may export for its loopback-only default; a two-host graph must not inherit them.
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE', 'MM_LOCALHOST_PROFILE')
CLONE_NEWNET = 0x40000000


def host_environment(peer: str) -> dict:
    """What a user sets on one host (README, "Two machines"), on top of this process's workspace environment."""
    env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES}
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', ROS_STATIC_PEERS=peer,
               # UDP only: processes of one machine would otherwise pass data through shared memory, and the test
               # must prove the network path (two real hosts have no shared memory between them anyway).
               FASTDDS_BUILTIN_TRANSPORTS='UDPv4')
    return env


def _ip(*args: str) -> None:
    subprocess.run(['ip', *args], check=True, capture_output=True, text=True, timeout=30)


def _netns_unavailable() -> str:
    if os.name != 'posix' or os.geteuid() != 0:
        return 'needs root to create network namespaces'
    if shutil.which('ip') is None:
        return 'needs iproute2 (`ip`)'
    probe = f'mm_probe_{os.getpid()}'
    try:
        _ip('netns', 'add', probe)
        _ip('netns', 'exec', probe, 'true')          # also needs a mount namespace of its own
    except (subprocess.CalledProcessError, OSError) as exc:
        return f'cannot create or enter a network namespace here: {getattr(exc, "stderr", exc)}'.strip()
    finally:
        subprocess.run(['ip', 'netns', 'del', probe], capture_output=True, timeout=30)
    return ''


def _link_bytes(namespace: str, link: str) -> int:
    stats = Path(f'/sys/class/net/{link}/statistics')
    out = subprocess.run(['ip', 'netns', 'exec', namespace, 'cat', str(stats / 'rx_bytes'), str(stats / 'tx_bytes')],
                         check=True, capture_output=True, text=True, timeout=30).stdout.split()
    return sum(int(v) for v in out)


@pytest.fixture(scope='module')
def hosts():
    reason = _netns_unavailable()
    if reason:
        print(f'test_multihost skipped: {reason}')
        pytest.skip(reason)
    tag = os.getpid() % 100000
    a, b = f'mm_host_a_{tag}', f'mm_host_b_{tag}'
    link_a, link_b = f'mmveth{tag}a', f'mmveth{tag}b'
    try:
        _ip('netns', 'add', a)
        _ip('netns', 'add', b)
        _ip('link', 'add', link_a, 'type', 'veth', 'peer', 'name', link_b)
        _ip('link', 'set', link_a, 'netns', a)
        _ip('link', 'set', link_b, 'netns', b)
        for ns, link, address in ((a, link_a, HOST_A), (b, link_b, HOST_B)):
            _ip('-n', ns, 'addr', 'add', f'{address}/24', 'dev', link)
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
            _ip('-n', ns, 'link', 'set', link, 'multicast', 'off', 'up')
        yield dict(a=a, b=b, link_a=link_a)
    finally:
        for ns in (a, b):               # deleting a namespace also deletes its end of the veth pair
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True, timeout=30)


@pytest.fixture(scope='module')
def run(hosts, tmp_path_factory):
    work = tmp_path_factory.mktemp('multihost')
    env = host_environment(HOST_B)
    before = _link_bytes(hosts['a'], hosts['link_a'])
    proc = subprocess.run(['ip', 'netns', 'exec', hosts['a'], sys.executable, __file__, 'drive', str(work),
                           hosts['b']], env=env, capture_output=True, text=True, timeout=600)
    crossed = _link_bytes(hosts['a'], hosts['link_a']) - before
    result = work / 'result.json'
    assert proc.returncode == 0 and result.exists(), f'{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}'
    return dict(json.loads(result.read_text()), bag=work / 'bag', crossed=crossed, env=env)


def test_environment_is_subnet_with_static_peers_and_no_localhost_profile(run):
    env = run['env']
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET' and env['ROS_STATIC_PEERS'] == HOST_B
    assert not set(PROFILE_VARIABLES) & set(env)
    assert set(run['node_env']) == {'A', 'B'}
    for side, peer in (('A', HOST_B), ('B', HOST_A)):
        seen = run['node_env'][side]
        assert seen['ROS_STATIC_PEERS'] == peer and seen['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
        assert not any(seen.get(k) for k in PROFILE_VARIABLES), seen


def test_learner_and_controller_ran_on_the_other_host(run):
    assert run['placement'] == {'recorder': 'A', 'wheeled_sim': 'A', 'switching_controller': 'B',
                                'sensor_manifold': 'B'}
    # Every sensor reading, command, state and status crossed the veth link: far more than discovery alone.
    assert run['crossed'] > 2_000_000, run['crossed']


def test_paper_task_is_reached_across_hosts(run):
    assert run['model_files'] == []             # the model travelled as a message, never as a file
    assert run['phase'] == 'GOAL_REACHED', run['detail']
    assert run['final_error'] < TOLERANCE
    print('multihost run:', {k: run[k] for k in ('detail', 'final_heading', 'seconds', 'crossed')})


def test_bag_has_every_step_on_every_topic(run):
    from mm_common.rosbag import iter_messages
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Range

    per_topic = {t: {} for t in RANGE_TOPICS + ['/clock']}
    totals = {t: 0 for t in RECORDED}
    for record in iter_messages(run['bag']):
        totals[record.topic] = totals.get(record.topic, 0) + 1
        if record.topic in RANGE_TOPICS:
            stamp = deserialize_message(record.data, Range).header.stamp
        elif record.topic == '/clock':
            stamp = deserialize_message(record.data, Clock).clock
        else:
            continue
        step = round((stamp.sec * 10**9 + stamp.nanosec) / (DT * 1e9))
        per_topic[record.topic][step] = per_topic[record.topic].get(step, 0) + 1
    steps = sorted(per_topic['/clock'])
    assert steps and steps == list(range(steps[0], steps[-1] + 1)), 'a simulator step is missing in the bag'
    assert steps[-1] >= EXPLORATION
    # Step 0 is published as the simulator starts, before the recorder may have matched every topic; every later
    # step (re-publications of a paused loop included) must be in the bag equally often on every topic.
    later = {t: {s: n for s, n in counts.items() if s > 0} for t, counts in per_topic.items()}
    for topic in RANGE_TOPICS:
        assert later[topic] == later['/clock'], f'{topic} lost or duplicated messages'
    step0 = max(per_topic[t].get(0, 0) for t in per_topic)
    assert 0 <= totals['/wheeled/bumper'] - sum(later['/clock'].values()) <= step0
    # Lockstep: every step after step 0 was produced by one command, except the episode's reset step.
    assert totals[COMMANDS] == len(steps) - 1 - run['resets'], (totals[COMMANDS], len(steps), run['resets'])


# --- driver: runs inside namespace A ---------------------------------------------------------------------------------
def drive(work: Path, namespace_b: str) -> None:
    import numpy as np
    from mm_bringup.process_graph import ProcessGraph
    from mm_bringup.wall_experiment import PAPER_START, sensor2_goal_reading
    from mm_bringup.wall_graph import WallGraph
    from mm_msgs.msg import ControllerStatus
    from mm_common.wheeled_sensors import SENSOR2
    from mm_sim.wheeled_model import WheeledRobot

    libc = ctypes.CDLL(None, use_errno=True)

    def setns(path: str) -> None:
        fd = os.open(path, os.O_RDONLY)
        try:
            if libc.setns(fd, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), f'setns({path})')
        finally:
            os.close(fd)

    host_a = os.readlink('/proc/thread-self/ns/net')
    env_b = host_environment(HOST_A)
    placement = {}

    class TwoHostGraph(ProcessGraph):
        """Starts the learner and controller inside namespace B: this thread enters B for the fork only (the child
        inherits it), then returns to A; sockets opened earlier stay in A."""

        def start(self, package, executable, *args, **kwargs):
            on_b = executable in ON_HOST_B
            placement[executable] = 'B' if on_b else 'A'
            if not on_b:
                return super().start(package, executable, *args, **kwargs)
            env_a, self.env = self.env, env_b
            back = os.open('/proc/thread-self/ns/net', os.O_RDONLY)
            try:
                setns(f'/run/netns/{namespace_b}')
                return super().start(package, executable, *args, **kwargs)
            finally:
                libc.setns(back, CLONE_NEWNET)
                os.close(back)
                self.env = env_a
                assert os.readlink('/proc/thread-self/ns/net') == host_a

    started = time.monotonic()
    robot = WheeledRobot()
    goal = sensor2_goal_reading(robot, GOAL_POSE)
    graph = TwoHostGraph(log_dir=work / 'logs')
    with graph:
        recorder = graph.start('mm_bringup', 'recorder', {
            'output': str(work / 'bag'), 'discovery_period': 0.05,
            'topics': ['/wheeled/range/.*', COMMANDS, '/clock', '/wheeled/bumper']})
        # No model file (model_path ''): the controller gets the learned model only as the latched message.
        with WallGraph(work, exploration_steps=EXPLORATION, graph=graph, recorder='recorder',
                       recorded_topics=RECORDED, model_path='') as wall:
            node_env = {}
            for node in graph.nodes:
                environ = Path(f'/proc/{node.process.pid}/environ').read_bytes().split(b'\0')
                pairs = dict(item.decode().split('=', 1) for item in environ if b'=' in item)
                node_env[placement[node.executable]] = {k: pairs.get(k, '') for k in (
                    'ROS_STATIC_PEERS', 'ROS_AUTOMATIC_DISCOVERY_RANGE', *PROFILE_VARIABLES)}
            began = time.monotonic()
            wall.wait_learned(timeout=400.0)
            learned = time.monotonic()
            episode = wall.run_episode(PAPER_START, goal, TOLERANCE, timeout=200.0)
        code = graph.stop(recorder)
        if code != 0:
            raise RuntimeError(f'recorder exited with {code}:\n{graph.log_tail(recorder)}')
    final = robot.read(episode.poses[-1], noisy=False)[list(SENSOR2)]
    phases = {v: k[len('PHASE_'):] for k, v in vars(ControllerStatus).items() if k.startswith('PHASE_')}
    heading = episode.poses[-1][2]
    (work / 'result.json').write_text(json.dumps(dict(
        phase=phases.get(episode.phase, str(episode.phase)), detail=episode.detail,
        final_error=float(np.max(np.abs(final - goal))),
        final_heading=math.atan2(math.sin(heading), math.cos(heading)), resets=1,
        placement=placement, node_env=node_env, model_files=[str(p) for p in work.rglob('*.npz')], seconds=dict(
            start=began - started, explore_and_learn=learned - began, episode=episode.wall_seconds))))


if __name__ == '__main__' and len(sys.argv) == 4 and sys.argv[1] == 'drive':
    drive(Path(sys.argv[2]), sys.argv[3])
