"""Where the wheeled loop's time goes: one node of the loop (sensor_manifold or switching_controller) runs in this
process while the other two run as processes; its rate, its CPU per step and (with --profile) a cProfile table.

    ./mm python -m mm_bringup.bench.profile_node manifold --steps 1500 [--executor single] [--profile]

Not a `make bench` part (no JSON): a tool for deciding what to make faster.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import tempfile
import time
from pathlib import Path

from mm_common.ros_harness import RosHarness
from rclpy.parameter import Parameter

from mm_bringup.process_graph import ProcessGraph


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('node', choices=('manifold', 'controller'))
    parser.add_argument('--steps', type=int, default=1500)
    parser.add_argument('--executor', choices=('single', 'events'), default='events',
                        help="this node's executor: rclpy.experimental.EventsExecutor (what run_node uses) or "
                             "SingleThreadedExecutor (for comparison)")
    parser.add_argument('--profile', action='store_true', help='print the cProfile table (inflates the CPU figure)')
    args = parser.parse_args(argv)
    sim_time = [Parameter('use_sim_time', value=True)]
    with tempfile.TemporaryDirectory(prefix='mm_profile_') as tmp, ProcessGraph(log_dir=Path(tmp)) as graph:
        ros = RosHarness()
        try:
            if args.executor == 'events':
                from rclpy.experimental import EventsExecutor
                ros.executor.shutdown()
                ros.executor = EventsExecutor(context=ros.context)
            graph.start('mm_sim', 'wheeled_sim', {'republish_period': 0.5})
            if args.node == 'manifold':
                from mm_manifold.sensor_manifold_node import SensorManifold
                graph.start('mm_planner', 'switching_controller', {'use_sim_time': True,
                                                                   'exploration_steps': 10_000_000})
                node = ros.add(SensorManifold(context=ros.context, parameter_overrides=sim_time + [
                    Parameter('learn_after', value=10_000_000)]))
                count = lambda: len(node.readings)              # noqa: E731
            else:
                from mm_planner.switching_controller_node import SwitchingControllerNode
                graph.start('mm_manifold', 'sensor_manifold', {'use_sim_time': True, 'learn_after': 10_000_000})
                node = ros.add(SwitchingControllerNode(context=ros.context, parameter_overrides=sim_time + [
                    Parameter('exploration_steps', value=10_000_000)]))
                count = lambda: node.explored                     # noqa: E731
            if not ros.spin_until(lambda: count() > 50, 60):
                raise SystemExit('the loop did not start within 60 s')
            profile = cProfile.Profile()
            n0, t0, c0 = count(), time.perf_counter(), time.process_time()
            if args.profile:
                profile.enable()
            ros.spin_until(lambda: count() >= n0 + args.steps, 300)
            profile.disable()
            n1, t1, c1 = count(), time.perf_counter(), time.process_time()
        finally:
            ros.close()
    print(f'{args.node} ({args.executor} executor): {n1 - n0} steps in {t1 - t0:.1f} s = '
          f'{(n1 - n0) / (t1 - t0):.0f} steps/s, {(c1 - c0) * 1000 / max(n1 - n0, 1):.2f} ms CPU per step here')
    if args.profile:
        out = io.StringIO()
        pstats.Stats(profile, stream=out).sort_stats('tottime').print_stats(20)
        print(out.getvalue())
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
