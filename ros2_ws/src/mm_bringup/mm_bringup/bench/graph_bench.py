"""Graph benchmark (results/bench.json): lockstep simulator rate and latency, recorder throughput for camera images,
and, measured in the same run for comparison, plain rclpy ping-pong and image flow without recording."""
from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np
from mm_common.rosbag import read_metadata
from mm_common.testing import RosHarness
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, Range
from std_msgs.msg import Float64MultiArray, Header

from mm_bringup.process_graph import ProcessGraph, wait_for

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


def run(output_dir: Path, quick: bool) -> dict:
    work = output_dir / 'tmp' / 'graph_bench'
    work.mkdir(parents=True, exist_ok=True)
    steps = 500 if quick else 3000
    result = {}
    result.update(lockstep_loop(steps, work / 'logs'))
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
    shutil.rmtree(work, ignore_errors=True)
    return result
