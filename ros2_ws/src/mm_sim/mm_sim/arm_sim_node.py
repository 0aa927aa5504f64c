"""Arm simulator node: a 2-joint planar arm, an object and textured background, seen by a fixed camera (Section 3).

    ./mm run mm_sim arm_sim --ros-args --params-file ros2_ws/src/mm_sim/config/arm_sim.yaml
    ros2 run mm_sim arm_sim --ros-args -p lockstep:=false -p real_time_factor:=1.0      # real install

Publishes, per simulation step and in this order, all with the stamp of that step:
  /clock, `arm/camera/image_raw` (sensor_msgs/Image rgb8, 400x400), `arm/joint_states` (shoulder_roll,
  shoulder_pitch: position [rad], velocity [rad/s]), `arm/contact` (std_msgs/Bool: the hand touches the object in
  the pose of this frame), and for evaluation only `arm/ground_truth/object_pose` (geometry_msgs/PoseStamped, image
  pixels, frame `camera`) and `arm/ground_truth/hand_object_distance` (std_msgs/Float64, pixels between centres).
Consumes `arm/joint_position_controller/commands` (std_msgs/Float64MultiArray, [shoulder_roll, shoulder_pitch]
target angles [rad]): per step the arm moves straight toward the target, at most `max_joint_speed * dt` rad per joint,
clipped to the joint limits (see mm_sim.arm_motion). Targets beyond a limit by more than `command_margin`, NaN/inf or
of the wrong length are rejected with a throttled log line and counted in `commands_rejected`.

Lockstep (default): the frame of step k is out; one valid command advances exactly one step; until the first command
arrives the current step is re-published every `republish_period` wall seconds so late joiners can start the loop.
Free-running: a wall timer steps every dt / real_time_factor toward the latest target; the camera then uses the
sensor-data QoS (loss acceptable, latest frame matters).

Reset (no service type is needed): setting `object_seed` or `object_position` re-builds the scene (textures, layout
and object place from the seed; `object_position` [x, y] px overrides the place, [] = random) and setting
`initial_joints` moves the arm there; either publishes a new step at once (sim time stays monotonic).
"""
from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from mm_common.node_utils import declare, reject_non_finite, run_node
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Bool, Float64, Float64MultiArray

from mm_sim.arm_model import JOINT_NAMES, ArmModel
from mm_sim.arm_motion import move_towards

# Lockstep topics are RELIABLE: the planner waits for each step and the recorder must not lose a frame; depth 50
# absorbs a briefly slow subscriber (50 frames of 480 kB at most).
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def _stamp(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


class ArmSim(Node):
    def __init__(self, **node_kwargs):
        super().__init__('arm_sim', **node_kwargs)
        self.dt = declare(self, 'dt', 0.1, 'Simulation step [s]', min_value=1e-3, max_value=1.0)
        self.lockstep = declare(self, 'lockstep', True, 'Advance one step per received command (deterministic)')
        self.real_time_factor = declare(self, 'real_time_factor', 1.0, 'Free-running speed relative to wall time',
                                        min_value=0.01, max_value=100.0)
        self.republish_period = declare(self, 'republish_period', 0.5,
                                        'Lockstep: wall seconds between re-publications before the first command',
                                        min_value=0.01, max_value=60.0)
        self.max_joint_speed = declare(self, 'max_joint_speed', 4.0, 'Joint speed limit of the position controller '
                                       '[rad/s]', min_value=1e-3, max_value=100.0)
        self.command_margin = declare(self, 'command_margin', 0.2, 'Targets beyond a joint limit by more than this '
                                      '[rad] are rejected (within it they are clipped)', min_value=0.0, max_value=10.0)
        self.initial_joints = declare(self, 'initial_joints', [-2.0, 1.1],
                                      'Joint angles [shoulder_roll, shoulder_pitch] at start and on reset [rad]')
        self.object_seed = declare(self, 'object_seed', 0, 'Seed of textures, background layout and object place',
                                   min_value=0, max_value=2**31 - 1)
        self.object_position = declare(self, 'object_position', [-1.0],
                                       'Object centre [x, y] in image pixels; [-1.0] = random place from object_seed')
        self.frame_id = declare(self, 'frame_id', 'camera', 'frame_id of the image and ground-truth pose',
                                read_only=True)
        self.image_size = declare(self, 'image_size', 400, 'Square image size [px]', min_value=64, max_value=2048,
                                  read_only=True)
        self.commands_received = 0
        self.commands_rejected = 0
        self.step_index = 0
        self.model = self._build_model(self.object_seed, self.object_position)
        self.joints = self._checked_joints(self.initial_joints)
        self.velocity = np.zeros(2)
        self.target = self.joints.copy()
        self.add_on_set_parameters_callback(self._on_set_parameters)

        # Free-running camera: sensor-data QoS (best effort, shallow) - a late frame is worth less than the next.
        image_qos = LOOP_QOS if self.lockstep else qos_profile_sensor_data
        self.clock_pub = self.create_publisher(Clock, '/clock', LOOP_QOS)
        self.image_pub = self.create_publisher(Image, 'arm/camera/image_raw', image_qos)
        self.joint_pub = self.create_publisher(JointState, 'arm/joint_states', LOOP_QOS)
        self.contact_pub = self.create_publisher(Bool, 'arm/contact', LOOP_QOS)
        self.object_pub = self.create_publisher(PoseStamped, 'arm/ground_truth/object_pose', LOOP_QOS)
        self.distance_pub = self.create_publisher(Float64, 'arm/ground_truth/hand_object_distance', LOOP_QOS)
        self.create_subscription(Float64MultiArray, 'arm/joint_position_controller/commands', self._on_command,
                                 LOOP_QOS)
        self.clock_msg = Clock()
        self.joint_msg = JointState(name=list(JOINT_NAMES))
        self.joint_msg.header.frame_id = ''
        if self.lockstep:
            self.republish_timer = self.create_timer(self.republish_period, self._publish_step)
        else:
            self.republish_timer = None
            self.create_timer(self.dt / self.real_time_factor, self._free_run_tick)
        self._publish_step()
        self.get_logger().info(
            f"arm_sim ready: {'lockstep' if self.lockstep else 'free-running'}, dt={self.dt}s, "
            f'object at {np.round(self.model.object_position_, 1).tolist()} px, joints {self.joints.tolist()}')

    # --- scene --------------------------------------------------------------------------------------------------
    def _build_model(self, seed: int, position) -> ArmModel:
        pos = list(position)
        if pos == [-1.0] or not pos:
            return ArmModel(image_size=self.image_size, random_state=int(seed))
        if len(pos) != 2 or not all(math.isfinite(v) for v in pos):
            raise ValueError('object_position must be [x, y] (finite, px) or [-1.0] for a random place')
        if not all(0.0 <= v <= self.image_size for v in pos):
            raise ValueError(f'object_position {pos} is outside the {self.image_size} px image')
        return ArmModel(image_size=self.image_size, object_position=tuple(pos), random_state=int(seed))

    def _checked_joints(self, joints) -> np.ndarray:
        q = np.asarray(joints, dtype=float).reshape(-1)
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ValueError('initial_joints must be two finite angles [rad]')
        return self.model.clip_joints(q)

    # --- parameters ---------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if not result.successful:
            return result
        seed, position, joints = self.object_seed, self.object_position, None
        for p in params:
            if p.name in ('dt', 'lockstep', 'real_time_factor'):
                return SetParametersResult(successful=False, reason=f'{p.name} can only be set at start-up')
            if p.name == 'object_seed':
                seed = int(p.value)
            elif p.name == 'object_position':
                position = list(p.value)
            elif p.name == 'initial_joints':
                joints = list(p.value)
        rebuild = seed != self.object_seed or list(position) != list(self.object_position)
        try:
            model = self._build_model(seed, position) if rebuild else self.model
            q = None
            if joints is not None:
                q = np.asarray(joints, dtype=float).reshape(-1)
                if q.shape != (2,) or not np.all(np.isfinite(q)):
                    raise ValueError('initial_joints must be two finite angles [rad]')
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        for p in params:
            if p.name == 'max_joint_speed':
                self.max_joint_speed = float(p.value)
            elif p.name == 'command_margin':
                self.command_margin = float(p.value)
        if rebuild or q is not None:
            self.model, self.object_seed, self.object_position = model, seed, list(position)
            if q is not None:
                self.initial_joints = list(q)
                self.joints = model.clip_joints(q)
            self.target = self.joints.copy()
            self.velocity = np.zeros(2)
            self.step_index += 1      # a reset is a new step: sim time stays monotonic for every consumer
            self._publish_step()
            self.get_logger().info(f'reset: object at {np.round(model.object_position_, 1).tolist()} px, '
                                   f'joints {self.joints.tolist()}, step {self.step_index}')
        return SetParametersResult(successful=True)

    # --- inputs -------------------------------------------------------------------------------------------------
    def _validate(self, data) -> str:
        if len(data) != 2:
            return f'expected 2 joint targets [{", ".join(JOINT_NAMES)}], got {len(data)}'
        if not all(math.isfinite(v) for v in data):
            return f'non-finite joint target {list(data)}'
        lim = self.model.joint_limits
        for v, (lo, hi), name in zip(data, lim, JOINT_NAMES):
            if v < lo - self.command_margin or v > hi + self.command_margin:
                return f'{name} target {v:.3f} rad beyond its limits [{lo}, {hi}] by more than {self.command_margin}'
        return ''

    def _on_command(self, msg: Float64MultiArray) -> None:
        problem = self._validate(msg.data)
        if problem:
            self.commands_rejected += 1
            self.get_logger().warn(f'rejected command ({self.commands_rejected} so far): {problem}',
                                   throttle_duration_sec=1.0)
            return
        self.commands_received += 1
        self.target = np.clip(np.asarray(msg.data, dtype=float), self.model.joint_limits[:, 0],
                              self.model.joint_limits[:, 1])
        if self.lockstep:
            if self.republish_timer is not None:
                self.republish_timer.cancel()
                self.destroy_timer(self.republish_timer)
                self.republish_timer = None
            self._advance()

    # --- stepping -----------------------------------------------------------------------------------------------
    @property
    def sim_time_ns(self) -> int:
        return int(round(self.step_index * self.dt * 1e9))

    def _advance(self) -> None:
        new = move_towards(self.joints, self.target, self.max_joint_speed * self.dt, self.model.joint_limits)
        self.velocity = (new - self.joints) / self.dt
        self.joints = new
        self.step_index += 1
        self._publish_step()

    def _free_run_tick(self) -> None:
        self._advance()

    def _publish_step(self) -> None:
        stamp = _stamp(self.sim_time_ns)
        self.clock_msg.clock = stamp
        self.clock_pub.publish(self.clock_msg)
        frame = self.model.render(self.joints)
        img = Image(height=frame.shape[0], width=frame.shape[1], encoding='rgb8', is_bigendian=0,
                    step=frame.shape[1] * 3)
        img.header.stamp, img.header.frame_id = stamp, self.frame_id
        img.data = frame.tobytes()
        self.image_pub.publish(img)
        j = self.joint_msg
        j.header.stamp = stamp
        j.position = [float(v) for v in self.joints]
        j.velocity = [float(v) for v in self.velocity]
        self.joint_pub.publish(j)
        self.contact_pub.publish(Bool(data=bool(self.model.in_contact(self.joints))))
        pose = PoseStamped()
        pose.header.stamp, pose.header.frame_id = stamp, self.frame_id
        pose.pose.position.x, pose.pose.position.y = (float(v) for v in self.model.object_position_)
        pose.pose.orientation.w = 1.0
        self.object_pub.publish(pose)
        self.distance_pub.publish(Float64(data=self.model.hand_object_distance(self.joints)))


def main(args=None):
    run_node(ArmSim, args)


if __name__ == '__main__':
    main()
