"""Wheeled-robot simulator node: a differential-drive robot with five proximity sensors near an infinite wall.

    ./mm run mm_sim wheeled_sim --ros-args --params-file ros2_ws/src/mm_sim/config/wheeled_sim.yaml
    ros2 run mm_sim wheeled_sim --ros-args -p lockstep:=false -p real_time_factor:=1.0      # real install

Publishes, per simulation step and in this order, all with the stamp of that step:
  /clock, the five `wheeled/range/<sensor>` (sensor_msgs/Range), the same five readings in one `wheeled/ranges`
  (mm_msgs/RangeGroup, for a consumer that needs every reading of a step: one delivery instead of five),
  `wheeled/bumper`, `wheeled/ground_truth/odom` and, every `marker_period` steps, `wheeled/markers`.
Consumes `wheeled/wheel_velocity_controller/commands` (std_msgs/Float64MultiArray, [left, right] wheel rad/s).

Lockstep (default): the readings of step k are out; one valid command advances exactly one step of `dt`. Whenever
no command has come for `republish_period` wall seconds (before the first command or at any later step) the current
step is re-published with its own stamp, so late joiners start the loop and a lost message or a restarted peer
never stalls it for good (consumers take a repeated stamp as no new sample). A warning says when no command
publisher has matched for `peer_timeout` seconds. Free-running: a wall timer steps at `real_time_factor` with the
latest command.

Invalid commands and reset requests are rejected with a throttled log line saying what was wrong; parameters that
only mean something at start-up are read-only.
"""
from __future__ import annotations

import math
import time
from typing import Callable, List

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from mm_common.node_utils import (array_problem, check_parameters, declare, publish_if_subscribed, reject_input,
                                  run_node)
from mm_common.qos import LOOP_QOS  # RELIABLE, deep history: see mm_common/qos.py
from mm_common.wheeled_sensors import SENSOR_NAMES, range_group
from mm_msgs.msg import RangeGroup
from mm_msgs.srv import ResetPose
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Range
from std_msgs.msg import Bool, Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

from mm_sim.wheeled_model import ProximitySensor, WheeledRobot, default_sensors

COMMAND_TOPIC = 'wheeled/wheel_velocity_controller/commands'
RESET_SERVICE = 'wheeled/reset'



def _stamp(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


class WheeledSim(Node):
    def __init__(self, **node_kwargs):
        super().__init__('wheeled_sim', **node_kwargs)
        defaults = {s.name: s for s in default_sensors()}
        self.dt = declare(self, 'dt', 0.05, 'Simulation step [s]', min_value=1e-4, max_value=1.0, read_only=True)
        self.lockstep = declare(self, 'lockstep', True, 'Advance one step per received command (deterministic)',
                                read_only=True)
        self.real_time_factor = declare(self, 'real_time_factor', 1.0, 'Free-running speed relative to wall time',
                                        min_value=0.01, max_value=1000.0, read_only=True)
        self.republish_period = declare(self, 'republish_period', 0.5,
                                        'Lockstep: wall seconds without a command after which the current step is '
                                        're-published (late joiners, lost messages, restarted peers)',
                                        min_value=0.01, max_value=60.0)
        self.peer_timeout = declare(self, 'peer_timeout', 5.0,
                                    'Lockstep: warn when no command publisher has matched for this many wall seconds',
                                    min_value=0.1, max_value=3600.0)
        self.max_reset_distance = declare(self, 'max_reset_distance', 100.0,
                                          'Reset poses farther than this from the world origin are rejected [m]',
                                          min_value=0.0, max_value=1e6)
        self.command_timeout = declare(self, 'command_timeout', 0.5,
                                       'Free-running: sim seconds after which a stale command counts as zero',
                                       min_value=0.0, max_value=60.0)
        self.max_wheel_speed = declare(self, 'max_wheel_speed', 30.0,
                                       'Commands with |omega| above this [rad/s] are rejected',
                                       min_value=0.0, max_value=1e4)
        self.marker_period = declare(self, 'marker_period', 10, 'Publish markers every N steps', min_value=1,
                                     max_value=100000)
        initial_pose = declare(self, 'initial_pose', [0.0, 1.0, -math.pi / 2],
                               'Initial pose [x, y, theta] in the world frame (wall: y = 0); later poses: '
                               'the wheeled/reset service', read_only=True)
        initial_step = declare(self, 'initial_step', 0, 'Index of the first step (its stamp is initial_step * dt): '
                               "a restarted simulator continues its predecessor's time", min_value=0,
                               max_value=2**62, read_only=True)
        wheel_radius = declare(self, 'wheel_radius', 0.02, 'Wheel radius [m]', min_value=1e-4, max_value=1.0,
                               read_only=True)
        wheel_separation = declare(self, 'wheel_separation', 0.04, 'Distance between the wheels [m]',
                                   min_value=1e-4, max_value=2.0, read_only=True)
        body_radius = declare(self, 'body_radius', 0.03, 'Body radius used for wall contact [m]',
                              min_value=0.0, max_value=1.0, read_only=True)
        noise_std = declare(self, 'noise_std', 0.0, 'Gaussian reading noise [m] (0 = off)', min_value=0.0,
                            max_value=1.0)
        noise_fraction = declare(self, 'noise_range_fraction', 0.0, 'Gaussian reading noise with a std of this '
                                 "fraction of each sensor's max range (adds to noise_std)", min_value=0.0,
                                 max_value=1.0)
        dropout = declare(self, 'dropout', 0.0, 'Probability that a reading is lost (published as NaN)',
                          min_value=0.0, max_value=1.0)
        seed = declare(self, 'random_seed', 0, 'Seed of the noise and dropout generator (setting it restarts the '
                       'generator)', min_value=0, max_value=2**31 - 1)
        sensors: List[ProximitySensor] = []
        for name in SENSOR_NAMES:
            d = defaults[name]
            mount = declare(self, f'sensors.{name}.mount', [d.x, d.y, math.degrees(d.yaw)],
                            f'{name}: mount [x, y, yaw_deg] in base_link', read_only=True)
            rng = declare(self, f'sensors.{name}.range', [d.min_range, d.max_range],
                          f'{name}: [min_range, max_range] [m]', read_only=True)
            fov = declare(self, f'sensors.{name}.field_of_view', d.field_of_view, f'{name}: beam width [rad]',
                          min_value=0.0, max_value=math.pi, read_only=True)
            inc = declare(self, f'sensors.{name}.max_incidence_deg', math.degrees(d.max_incidence),
                          f'{name}: no return beyond this angle of incidence [deg]', min_value=0.0,
                          max_value=90.0, read_only=True)
            if len(mount) != 3 or len(rng) != 2 or not 0.0 <= rng[0] < rng[1]:
                raise ValueError(f'sensor {name}: mount needs [x, y, yaw_deg] and range [min < max]')
            sensors.append(ProximitySensor(name, mount[0], mount[1], math.radians(mount[2]), rng[0], rng[1], fov,
                                           math.radians(inc)))
        if len(initial_pose) != 3 or not all(math.isfinite(v) for v in initial_pose):
            raise ValueError('initial_pose must be three finite numbers [x, y, theta]')
        self.robot = WheeledRobot(wheel_radius, wheel_separation, body_radius, sensors, noise_std, dropout, seed,
                                  noise_fraction)
        self.pose = tuple(float(v) for v in initial_pose)
        self.pose = (self.pose[0], max(self.pose[1], body_radius), self.pose[2])
        self.step_index = initial_step
        self.bumped = self.robot.touching(self.pose)
        self.velocity = (0.0, 0.0)
        self.command = np.zeros(2)
        self.command_time_ns = None
        self.commands_received = 0
        self.commands_rejected = 0
        self.resets_rejected = 0
        self.republished = 0
        self.command_publishers_matched = 0
        self.unmatched_since = time.monotonic()
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.clock_pub = self.create_publisher(Clock, '/clock', LOOP_QOS)
        # Called with each /clock message as it is published: nodes composed with the simulator in one process take
        # its clock here instead of through their own /clock subscription (mm_bringup wheeled_container).
        self.clock_listeners: List[Callable[[Clock], None]] = []
        self.range_pubs = [self.create_publisher(Range, f'wheeled/range/{s.name}', LOOP_QOS) for s in sensors]
        self.range_group_pub = self.create_publisher(RangeGroup, 'wheeled/ranges', LOOP_QOS)
        self.bumper_pub = self.create_publisher(Bool, 'wheeled/bumper', LOOP_QOS)
        self.odom_pub = self.create_publisher(Odometry, 'wheeled/ground_truth/odom', LOOP_QOS)
        self.marker_pub = self.create_publisher(MarkerArray, 'wheeled/markers', LOOP_QOS)
        self.command_sub = self.create_subscription(
            Float64MultiArray, COMMAND_TOPIC, self._on_command, LOOP_QOS,
            event_callbacks=SubscriptionEventCallbacks(matched=self._on_command_matched))
        self.create_service(ResetPose, RESET_SERVICE, self._on_reset)

        # Messages are built once and only their changing fields are written each step (lean hot path).
        self.range_msgs = []
        for s in sensors:
            m = Range()
            m.header.frame_id = f'{s.name}_link'
            m.radiation_type = Range.INFRARED
            m.field_of_view = float(s.field_of_view)
            m.min_range = float(s.min_range)
            m.max_range = float(s.max_range)
            self.range_msgs.append(m)
        # the same readings, one array per Range field (only `range` changes from step to step)
        self.range_group = range_group([s.name for s in sensors], self.range_msgs)
        self.odom_msg = Odometry()
        self.odom_msg.header.frame_id = 'world'
        self.odom_msg.child_frame_id = 'base_link'
        self.clock_msg = Clock()
        self.bool_msg = Bool()

        if self.lockstep:
            # Restarted on every command, so it fires only after republish_period without one, at any step.
            self.republish_timer = self.create_timer(self.republish_period, self._republish)
            self.create_timer(1.0, self._check_command_peer)
        else:
            self.republish_timer = None
            self.create_timer(self.dt / self.real_time_factor, self._free_run_tick)
        self._publish_step()
        self.get_logger().info(
            f"wheeled_sim ready: {'lockstep' if self.lockstep else 'free-running'}, dt={self.dt}s, "
            f'pose={self.pose}')

    # --- parameters -------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = check_parameters(self, params, [])
        if not result.successful:
            return result
        for p in params:
            if p.name == 'noise_std':
                self.robot.noise_std = float(p.value)
            elif p.name == 'noise_range_fraction':
                self.robot.noise_range_fraction = float(p.value)
            elif p.name == 'dropout':
                self.robot.dropout = float(p.value)
            elif p.name == 'random_seed':
                self.robot.reseed(int(p.value))
            elif p.name == 'max_wheel_speed':
                self.max_wheel_speed = float(p.value)
            elif p.name == 'command_timeout':
                self.command_timeout = float(p.value)
            elif p.name == 'marker_period':
                self.marker_period = int(p.value)
            elif p.name == 'peer_timeout':
                self.peer_timeout = float(p.value)
            elif p.name == 'max_reset_distance':
                self.max_reset_distance = float(p.value)
            elif p.name == 'republish_period':
                self.republish_period = float(p.value)
                if self.republish_timer is not None:
                    self.destroy_timer(self.republish_timer)
                    self.republish_timer = self.create_timer(self.republish_period, self._republish)
        return SetParametersResult(successful=True)

    # --- inputs -----------------------------------------------------------------------------------------------
    def _validate(self, data) -> str:
        return array_problem(data, 'wheel speeds [left, right]', length=2,
                             bounds=(-self.max_wheel_speed, self.max_wheel_speed))

    def _on_command(self, msg: Float64MultiArray) -> None:
        problem = self._validate(msg.data)
        if problem:
            self.commands_rejected += 1
            reject_input(self, COMMAND_TOPIC, problem)
            return
        self.commands_received += 1
        self.command = np.asarray(msg.data, dtype=float)
        self.command_time_ns = self.sim_time_ns
        if self.lockstep:
            self.republish_timer.reset()
            self._advance(self.command)

    def _on_command_matched(self, info) -> None:
        """Count matched command publishers: a node on the graph whose publisher does not match cannot drive us."""
        self.command_publishers_matched = info.current_count
        if info.current_count == 0:
            self.unmatched_since = time.monotonic()
        self.get_logger().info(f'{COMMAND_TOPIC}: {info.current_count} matched publisher(s)')

    def _check_command_peer(self) -> None:
        unmatched_for = time.monotonic() - self.unmatched_since
        if self.command_publishers_matched == 0 and unmatched_for >= self.peer_timeout:
            graph = self.count_publishers(COMMAND_TOPIC)
            detail = (f'{graph} publisher(s) on the graph do not match (QoS?)' if graph
                      else 'no publisher on the graph')
            self.get_logger().warn(f'lockstep waits at step {self.step_index}: no command publisher matched for '
                                   f'{unmatched_for:.0f} s ({detail})', throttle_duration_sec=self.peer_timeout)

    def _reset_problem(self, request: ResetPose.Request) -> str:
        pose = (request.x, request.y, request.theta)
        if not all(math.isfinite(v) for v in pose):
            return f'pose {list(pose)} must be finite'
        if request.y < self.robot.body_radius:
            return f'y={request.y} puts the body ({self.robot.body_radius} m) into the wall (y=0)'
        if math.hypot(request.x, request.y) > self.max_reset_distance:
            return f'pose ({request.x}, {request.y}) is beyond max_reset_distance={self.max_reset_distance} m'
        return ''

    def _on_reset(self, request: ResetPose.Request, response: ResetPose.Response) -> ResetPose.Response:
        problem = self._reset_problem(request)
        if problem:
            self.resets_rejected += 1
            reject_input(self, RESET_SERVICE, problem)
            response.success, response.message = False, problem
            return response
        self.pose = (request.x, request.y, math.atan2(math.sin(request.theta), math.cos(request.theta)))
        self.velocity = (0.0, 0.0)
        self.command = np.zeros(2)
        self.step_index += 1          # a reset is a new step: sim time stays monotonic for every consumer
        self.bumped = self.robot.touching(self.pose)
        self._publish_step(markers=True)
        if self.republish_timer is not None:
            self.republish_timer.reset()
        response.success, response.message = True, f'reset to {self.pose} at step {self.step_index}'
        response.stamp = _stamp(self.sim_time_ns)
        return response

    # --- stepping ---------------------------------------------------------------------------------------------
    @property
    def sim_time_ns(self) -> int:
        return int(round(self.step_index * self.dt * 1e9))

    def _advance(self, wheel_speeds) -> None:
        self.pose, self.bumped = self.robot.step(self.pose, wheel_speeds, self.dt)
        self.velocity = self.robot.body_velocity(wheel_speeds)
        self.step_index += 1
        self._publish_step()

    def _free_run_tick(self) -> None:
        stale = (self.command_time_ns is None
                 or self.sim_time_ns - self.command_time_ns > self.command_timeout * 1e9)
        self._advance(np.zeros(2) if stale else self.command)

    def _republish(self) -> None:
        """No command for republish_period: send the current step again, same stamp (no new sample downstream)."""
        self.republished += 1
        self._publish_step(markers=True)

    def _publish_step(self, markers: bool = False) -> None:
        stamp = _stamp(self.sim_time_ns)
        self.clock_msg.clock = stamp
        self.clock_pub.publish(self.clock_msg)
        for listener in self.clock_listeners:
            listener(self.clock_msg)
        readings = self.robot.read(self.pose).tolist()
        for pub, msg, value in zip(self.range_pubs, self.range_msgs, readings):
            msg.header.stamp = stamp
            msg.range = value
            publish_if_subscribed(pub, msg)
        self.range_group.header.stamp = stamp
        self.range_group.range = readings
        publish_if_subscribed(self.range_group_pub, self.range_group)
        self.bool_msg.data = bool(self.bumped)
        self.bumper_pub.publish(self.bool_msg)
        x, y, theta = self.pose
        o = self.odom_msg
        o.header.stamp = stamp
        o.pose.pose.position.x, o.pose.pose.position.y = float(x), float(y)
        o.pose.pose.orientation.z, o.pose.pose.orientation.w = math.sin(theta / 2), math.cos(theta / 2)
        o.twist.twist.linear.x, o.twist.twist.angular.z = float(self.velocity[0]), float(self.velocity[1])
        publish_if_subscribed(self.odom_pub, o)
        if (markers or self.step_index % self.marker_period == 0) and self.marker_pub.get_subscription_count():
            self.marker_pub.publish(self._markers(stamp, readings))

    def _markers(self, stamp: Time, readings) -> MarkerArray:
        """Wall, robot body with heading, and the five beams (green: wall in range, grey: nothing seen)."""
        x, y, theta = self.pose
        c, s = math.cos(theta), math.sin(theta)
        out = MarkerArray()

        def marker(mid: int, kind: int, ns: str) -> Marker:
            m = Marker()
            m.header.frame_id = 'world'
            m.header.stamp = stamp
            m.ns, m.id, m.type, m.action = ns, mid, kind, Marker.ADD
            m.pose.orientation.w = 1.0
            m.color.a = 1.0
            return m

        wall = marker(0, Marker.LINE_STRIP, 'wall')
        wall.scale.x = 0.01
        wall.color.r = wall.color.g = wall.color.b = 0.2
        wall.points = [Point(x=x - 3.0), Point(x=x + 3.0)]
        body = marker(1, Marker.CYLINDER, 'robot')
        body.pose.position.x, body.pose.position.y = float(x), float(y)
        body.scale.x = body.scale.y = 2 * self.robot.body_radius
        body.scale.z = 0.02
        body.color.b, body.color.g = 0.8, 0.4
        heading = marker(2, Marker.ARROW, 'robot')
        heading.scale.x, heading.scale.y, heading.scale.z = 0.005, 0.01, 0.01
        heading.color.r = 1.0
        heading.points = [Point(x=float(x), y=float(y)),
                          Point(x=float(x + 2 * self.robot.body_radius * c), y=float(y + 2 * self.robot.body_radius * s))]
        out.markers = [wall, body, heading]
        for i, (sensor, value) in enumerate(zip(self.robot.sensors, readings)):
            sx, sy = x + c * sensor.x - s * sensor.y, y + s * sensor.x + c * sensor.y
            length = float(value) if math.isfinite(value) else sensor.max_range
            beam = marker(10 + i, Marker.LINE_LIST, 'beams')
            beam.scale.x = 0.004
            if math.isfinite(value):
                beam.color.g = 0.8
            else:
                beam.color.r = beam.color.g = beam.color.b = 0.6
                beam.color.a = 0.5
            yaw = theta + sensor.yaw
            beam.points = [Point(x=float(sx), y=float(sy)),
                           Point(x=float(sx + length * math.cos(yaw)), y=float(sy + length * math.sin(yaw)))]
            out.markers.append(beam)
        return out


def main(args=None):
    run_node(WheeledSim, args)


if __name__ == '__main__':
    main()
