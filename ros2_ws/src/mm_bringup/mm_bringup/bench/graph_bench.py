"""Graph benchmark (results/bench.json): lockstep simulator rate and latency, the full wheeled graph's rate
(wheeled_sim + sensor_manifold + switching_controller exploring in lockstep) as a ratio of the bare lockstep rate of
the same run, its start-up, the cost of a fit per 10 000 samples and of a wall episode, the arm graph's camera frames
per second (arm_sim + image_embedding + dp_planner exploring), recorder throughput for camera images, and,
measured in the same run for comparison, plain rclpy ping-pong and image flow without recording. The machine's load
(load average before and after, cpu count) and the versions and commit are recorded beside the figures."""
from __future__ import annotations

import math
import os
import shutil
import time
from pathlib import Path

import numpy as np
from mm_common.rosbag import read_metadata
from mm_common.ros_harness import RosHarness
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, Range
from std_msgs.msg import Float64MultiArray, Header

from mm_bringup.bench import code_version
from mm_bringup.process_graph import ProcessGraph, wait_for
from mm_bringup.wall_experiment import PAPER_START, explore, run_episode, sensor2_goal_reading
from mm_bringup.wall_graph import WallGraph
from mm_sim.wheeled_model import WheeledRobot

NAME = 'bench'
QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
IMAGE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _percentiles(samples_s):
    us = np.asarray(samples_s) * 1e6
    return float(np.percentile(us, 50)), float(np.percentile(us, 99))


def lockstep_loop(steps: int, log_dir: Path) -> dict:
    """wheeled_sim (own process) in lockstep with a trivial controller (this process) that answers every step."""
    ros = RosHarness()
    try:
        with ProcessGraph(log_dir=log_dir) as graph:
            sim = graph.start('mm_sim', 'wheeled_sim', {'republish_period': 0.2, 'marker_period': 100})
            node = ros.node('bench_trivial_controller')
            arrivals = []
            node.create_subscription(Range, 'wheeled/range/side_rear', lambda _m: arrivals.append(time.perf_counter()),
                                     QOS)
            cmd = node.create_publisher(Float64MultiArray, 'wheeled/wheel_velocity_controller/commands', QOS)
            assert ros.spin_until(lambda: arrivals and cmd.get_subscription_count() > 0, 20), graph.log_tail(sim)
            msg = Float64MultiArray(data=[0.5, -0.5])      # rotate in place: stays clear of the wall
            sent_at = []
            start = time.perf_counter()
            for _ in range(steps):
                n = len(arrivals)
                sent_at.append(time.perf_counter())
                cmd.publish(msg)
                while len(arrivals) == n:
                    ros.executor.spin_once(timeout_sec=1.0)
            elapsed = time.perf_counter() - start
            # side_rear is the last Range of a step: command -> complete set of readings of the next step
            rtt = np.array(arrivals[-steps:]) - np.array(sent_at)
    finally:
        ros.close()
    p50, p99 = _percentiles(rtt)
    return {'lockstep_steps_per_s': steps / elapsed, 'roundtrip_us_p50': p50, 'roundtrip_us_p99': p99,
            'lockstep_steps': steps}


def pingpong_reference(rounds: int) -> dict:
    """Two rclpy nodes in one process answering each other: the floor for any lockstep loop here."""
    ros = RosHarness()
    try:
        ping, pong = ros.node('bench_ping'), ros.node('bench_pong')
        got = []
        back = pong.create_publisher(Float64MultiArray, 'bench/pong', QOS)
        pong.create_subscription(Float64MultiArray, 'bench/ping', back.publish, QOS)
        ping.create_subscription(Float64MultiArray, 'bench/pong', lambda _m: got.append(time.perf_counter()), QOS)
        out = ping.create_publisher(Float64MultiArray, 'bench/ping', QOS)
        msg = Float64MultiArray(data=[0.0, 0.0])
        assert ros.spin_until(lambda: out.get_subscription_count() and back.get_subscription_count(), 10)
        rtt = []
        for _ in range(rounds):
            n = len(got)
            t = time.perf_counter()
            out.publish(msg)
            while len(got) == n:
                ros.executor.spin_once(timeout_sec=1.0)
            rtt.append(got[-1] - t)
    finally:
        ros.close()
    p50, p99 = _percentiles(rtt)
    return {'pingpong_us_p50': p50, 'pingpong_us_p99': p99}


def _image(width=400, height=400) -> Image:
    img = Image(height=height, width=width, encoding='rgb8', step=width * 3)
    img.data = np.random.default_rng(0).integers(0, 255, size=width * height * 3, dtype=np.uint8).tobytes()
    img.header = Header(frame_id='camera')
    return img


def image_flow_reference(count: int) -> dict:
    """400x400 rgb8 images from a publisher to a raw subscriber in one process, no recording."""
    ros = RosHarness()
    try:
        pub_node, sub_node = ros.node('bench_image_pub'), ros.node('bench_image_sub')
        got = []
        sub_node.create_subscription(Image, 'bench/image', lambda d: got.append(len(d)), IMAGE_QOS, raw=True)
        pub = pub_node.create_publisher(Image, 'bench/image', IMAGE_QOS)
        img = _image()
        assert ros.spin_until(lambda: pub.get_subscription_count() > 0, 10)
        start = time.perf_counter()
        for _ in range(count):
            pub.publish(img)
            ros.executor.spin_once(timeout_sec=0)
        ros.spin_until(lambda: len(got) >= count, 30)
        elapsed = time.perf_counter() - start
    finally:
        ros.close()
    return {'image_flow_per_s': len(got) / elapsed, 'image_flow_mb_per_s': sum(got) / elapsed / 1e6,
            'image_flow_received': len(got), 'image_flow_sent': count}


def recorder_images(count: int, rate_hz: float, work: Path) -> dict:
    """Images published by this process, recorded by the recorder node in its own process; dropped = sent - recorded.
    Throughput is measured from the bag's own receive times (recorded bytes / receive span)."""
    bag = work / 'image_bag'
    shutil.rmtree(bag, ignore_errors=True)
    ros = RosHarness()
    try:
        with ProcessGraph(log_dir=work / 'logs') as graph:
            recorder = graph.start('mm_bringup', 'recorder', {'output': str(bag), 'topics': ['/bench/camera'],
                                                               'discovery_period': 0.05, 'drain_period': 1.0})
            node = ros.node('bench_camera')
            pub = node.create_publisher(Image, 'bench/camera', IMAGE_QOS)
            wait_for(lambda: pub.get_subscription_count() > 0, 20, message='recorder subscription')
            img = _image()
            period = 1.0 / rate_hz if rate_hz > 0 else 0.0
            start = time.perf_counter()
            for i in range(count):
                img.header.stamp.nanosec = i
                pub.publish(img)
                if period:
                    delay = start + (i + 1) * period - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
            pub.wait_for_all_acked()
            graph.stop(recorder)
    finally:
        ros.close()
    info = read_metadata(bag)
    recorded = info['message_count']
    span_s = max(info['duration']['nanoseconds'], 1) / 1e9
    size = len(_image().data)
    shutil.rmtree(bag, ignore_errors=True)
    return {'recorded': recorded, 'dropped': count - recorded, 'sent': count,
            'mb_per_s': recorded * size / span_s / 1e6 if recorded > 1 else 0.0, 'publish_rate_hz': rate_hz}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (Linux /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def wheeled_graph(steps: int, work: Path, composed: bool = False) -> dict:
    """The full wheeled loop (three processes, or with `composed` the three nodes in one: keys prefixed
    `composed_`) exploring `steps` steps with the learner's and the explorer's work included; the rate is taken
    between the 100th and the last exploration sample (start-up excluded), with the CPU each process spent per step
    over that stretch (where the time goes). Then one paper-task episode when the model can map the goal (seconds
    per wall episode through the graph, reset included)."""
    marks = {}
    result = {'graph_steps': steps}
    began = time.perf_counter()
    with WallGraph(work, exploration_steps=steps, model_path='', composed=composed) as wall:
        result['graph_startup_s'] = time.perf_counter() - began     # three nodes started until the loop's 2nd step
        processes = {n.label: n.process.pid for n in wall.nodes}
        wall.spin_until(lambda: wall.samples >= 100, 120.0, '100 samples')
        cpu_from = {k: _cpu_seconds(pid) for k, pid in processes.items()}
        cpu_from['experimenter (this process)'] = time.process_time()
        marks['from'] = (wall.samples, time.perf_counter())
        wall.spin_until(lambda: wall.samples >= steps, 600.0, f'{steps} samples')
        marks['to'] = (wall.samples, time.perf_counter())
        cpu_to = {k: _cpu_seconds(pid) for k, pid in processes.items()}
        cpu_to['experimenter (this process)'] = time.process_time()
        wall.spin_until(lambda: wall.model_msg is not None, 600.0, 'the first model')
        result['graph_fit_and_model_s'] = time.perf_counter() - marks['to'][1]
        result['graph_model_ready'] = bool(wall.model_msg.ready)
        # A first model that is not ready sends the robot exploring on: the episode waits for a ready one.
        wall.wait_learned(timeout=600.0)
        result['graph_samples_until_ready'] = wall.samples
        robot = WheeledRobot()
        episode = wall.run_episode(PAPER_START, sensor2_goal_reading(robot, (0.0, 0.25, 0.0)), 0.005)
        result.update(graph_episode_s=episode.wall_seconds, graph_episode_steps=len(episode.poses) - 1,
                      graph_episode_reached=episode.reached)
    (n0, t0), (n1, t1) = marks['from'], marks['to']
    result['graph_steps_per_s'] = (n1 - n0) / (t1 - t0)
    result['graph_cpu_ms_per_step'] = {k: (cpu_to[k] - cpu_from[k]) * 1000 / (n1 - n0) for k in cpu_from}
    return {f'composed_{k}': v for k, v in result.items()} if composed else result


def composed_unobserved(steps: int, log_dir: Path) -> dict:
    """The composed loop (mm_bringup wheeled_container, the learner on the grouped readings as WallGraph has it)
    exploring `steps` steps with no other process taking a message of every step: from the stamp of the simulator's
    `ready` log line (it keeps the system clock) to the arrival here of the controller's `EXPLORING -> LEARNING` line,
    both on /rosout and the system clock (the loop's start-up and the delivery inside the span: the rate is if
    anything low). Every process that takes the state each step (graph_bench's experimenter above, a recorder) costs
    the loop its deliveries."""
    from rcl_interfaces.msg import Log
    marks = {}

    def on_log(msg: Log) -> None:
        if msg.name == 'wheeled_sim' and 'wheeled_sim ready' in msg.msg:
            marks.setdefault('ready', msg.stamp.sec + msg.stamp.nanosec * 1e-9)
        elif msg.name == 'switching_controller' and 'EXPLORING -> LEARNING' in msg.msg:
            marks.setdefault('learning', time.time())
    ros = RosHarness()
    try:
        node = ros.node('bench_log_listener')
        # /rosout keeps each node's last lines for late subscribers (transient local): none is missed
        node.create_subscription(Log, '/rosout', on_log, QoSProfile(
            depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        with ProcessGraph(log_dir=log_dir) as graph:
            container = graph.start('mm_bringup', 'wheeled_container',
                                    {'switching_controller:exploration_steps': steps,
                                     'sensor_manifold:learn_after': steps, 'sensor_manifold:model_path': '',
                                     'sensor_manifold:samples_path': '', 'wheeled_sim:republish_period': 0.5,
                                     # the readings as the observed loop above takes them (WallGraph): one group
                                     'sensor_manifold:range_input': 'grouped'})
            assert ros.spin_until(lambda: len(marks) == 2, 120.0), graph.log_tail(container)
    finally:
        ros.close()
    return {'composed_unobserved_steps_per_s': steps / (marks['learning'] - marks['ready']),
            'composed_unobserved_steps': steps}


def arm_graph(frames: int, work: Path) -> dict:
    """arm_sim + image_embedding + dp_planner (three processes) exploring `frames` camera frames in lockstep, the
    learner extracting SIFT keypoints from every 400x400 frame: frames/s from the 50th frame to the end of the
    exploration, with the CPU each process spent per frame over that stretch; then the seconds of the fit until the
    planner has its first map."""
    from mm_bringup.arm_graph import ArmGraphDriver, start_arm_graph
    from mm_bringup.bench.arm_reach import SCENE_SEED
    from mm_msgs.msg import ControllerStatus
    with ProcessGraph(log_dir=work / 'logs') as graph:
        nodes = start_arm_graph(graph, SCENE_SEED, frames)
        driver = ArmGraphDriver('bench_arm_driver', nodes)
        try:
            driver.spin_until(lambda: len(driver.joints) >= 50, 120.0, '50 arm frames')
            n0, t0 = len(driver.joints), time.perf_counter()
            cpu_from = {n.label: _cpu_seconds(n.process.pid) for n in nodes}
            driver.spin_until(lambda: driver.phase() == ControllerStatus.PHASE_LEARNING, 600.0, 'the exploration')
            n1, t1 = len(driver.joints), time.perf_counter()
            cpu_to = {n.label: _cpu_seconds(n.process.pid) for n in nodes}
            driver.spin_until(lambda: driver.phase() == ControllerStatus.PHASE_WAITING_FOR_GOAL, 600.0, 'the fit')
            fit_s = time.perf_counter() - t1
        finally:
            driver.close()
    return {'arm_frames_per_s': (n1 - n0) / (t1 - t0), 'arm_frames': frames, 'arm_fit_and_map_s': fit_s,
            'arm_cpu_ms_per_frame': {k: (cpu_to[k] - cpu_from[k]) * 1000 / (n1 - n0) for k in cpu_from}}


def offline_costs(samples: int) -> dict:
    """Fit of `samples` exploration samples (reported per 10 000) and one paper-task episode with the learned model
    (the offline runner drives the same WallAgent and StateTracker the nodes do), on the exploration seed 0."""
    from mm_manifold.sensor_manifold import SensorManifoldModel
    robot = WheeledRobot()
    log = explore(robot, samples, random_state=0, dt=0.05)
    start = time.perf_counter()
    model = SensorManifoldModel(0.05).fit(log.readings, log.commands, log.continuous)
    fit_s = time.perf_counter() - start
    result = {'fit_s_per_10k_samples': fit_s * 10000 / samples, 'fit_samples': samples, 'fit_model_ready': model.ready}
    if model.ready:
        start = time.perf_counter()
        episode = run_episode(robot, model, PAPER_START, sensor2_goal_reading(robot, (0.0, 0.25, 0.0)), 0.005)
        result.update(offline_episode_s=time.perf_counter() - start, offline_episode_steps=len(episode.commands),
                      offline_episode_reached=episode.reached)
    return result


def machine_load() -> dict:
    """What else the machine did: load averages, and the versions and commit the figures belong to."""
    import rclpy
    try:
        from importlib.metadata import version
        rclpy_version = version('rclpy')
    except Exception:                 # rclpy from a ROS install has no distribution metadata
        rclpy_version = getattr(rclpy, '__version__', 'unknown')
    return {**code_version(), 'rclpy_version': rclpy_version}


def run(output_dir: Path, quick: bool) -> dict:
    work = output_dir / 'tmp' / 'graph_bench'
    work.mkdir(parents=True, exist_ok=True)
    steps = 500 if quick else 3000
    result = {'load_average_before': list(os.getloadavg()), 'cpu_count': os.cpu_count()}
    result.update(machine_load())
    result.update(lockstep_loop(steps, work / 'logs'))
    result.update(wheeled_graph(1000 if quick else 5000, work / 'wheeled'))
    result['graph_over_lockstep'] = result['graph_steps_per_s'] / result['lockstep_steps_per_s']
    result.update(wheeled_graph(1000 if quick else 5000, work / 'composed', composed=True))
    result['composed_graph_over_lockstep'] = result['composed_graph_steps_per_s'] / result['lockstep_steps_per_s']
    result.update(composed_unobserved(1000 if quick else 5000, work / 'unobserved'))
    result['composed_unobserved_over_lockstep'] = (result['composed_unobserved_steps_per_s']
                                                   / result['lockstep_steps_per_s'])
    result.update(arm_graph(200 if quick else 500, work / 'arm'))
    result.update(offline_costs(2000 if quick else 10000))
    result.update(pingpong_reference(steps))
    result['lockstep_over_pingpong_latency'] = result['roundtrip_us_p50'] / result['pingpong_us_p50']
    n_images = 200 if quick else 1000
    result.update(image_flow_reference(n_images))
    max_rate = recorder_images(n_images, 0.0, work)
    camera_rate = recorder_images(n_images // 2, 100.0, work)
    result['recorder_mb_per_s'] = max_rate['mb_per_s']
    result['recorder_dropped'] = max_rate['dropped']
    result['recorder_images_sent'] = max_rate['sent']
    result['recorder_at_100hz_dropped'] = camera_rate['dropped']
    result['recorder_at_100hz_sent'] = camera_rate['sent']
    result['recorder_over_image_flow'] = (result['recorder_mb_per_s'] / result['image_flow_mb_per_s']
                                          if result['image_flow_mb_per_s'] else math.nan)
    result['load_average_after'] = list(os.getloadavg())
    shutil.rmtree(work, ignore_errors=True)
    return result
