"""Arm simulator node: a 2-joint planar arm, an object and textured background, seen by a fixed camera (Section 3).

    ./mm run mm_sim arm_sim --ros-args --params-file ros2_ws/src/mm_sim/config/arm_sim.yaml
    ros2 run mm_sim arm_sim --ros-args -p lockstep:=false -p real_time_factor:=1.0      # real install
    ros2 run mm_sim arm_sim --ros-args -p object_mode:=every_n_frames -p object_period_frames:=20

Publishes, per simulation step and in this order, all with the stamp of that step:
  /clock, `arm/camera/image_raw` (sensor_msgs/Image rgb8, 400x400), `arm/joint_states` (shoulder_roll,
  shoulder_pitch: position [rad], velocity [rad/s]), `arm/contact` (mm_msgs/Contact: the hand's touch sensor - the hand
  touched the object anywhere along the motion from the previous frame, checked on sub-steps of at most
  `contact_resolution` rad, and whether it touches it in the frame's pose - and the same for any arm part, the
  contact a real arm senses from its joint torques), and for evaluation only
  `arm/ground_truth/state` (mm_msgs/ArmGroundTruth: object place, hand-object distance, contact of any part - upper
  link, forearm, hand - along the motion, the smallest distance and clearance along it, running contact counts since
  the last placement) and `arm/ground_truth/object_pose` (geometry_msgs/PoseStamped, image pixels, frame `camera`).
Latched (TRANSIENT_LOCAL), at start and when `max_joint_speed` changes: `arm/robot_description` (std_msgs/String,
a URDF of the two revolute joints with their limits and speed limit), where image_embedding and dp_planner read the
joint box.
Consumes `arm/joint_position_controller/commands` (std_msgs/Float64MultiArray, [shoulder_roll, shoulder_pitch]
target angles [rad]): per step the arm moves straight toward the target, at most `max_joint_speed * dt` rad per joint,
clipped to the joint limits (see mm_sim.arm_motion). Targets beyond a limit by more than `command_margin`, NaN/inf or
of the wrong length are rejected with a throttled log line and counted in `commands_rejected`.

The object (paper 3.1: its place varies independently of the arm): `object_mode` 'fixed' keeps it where it is;
'every_n_frames' re-places it at random every `object_period_frames` frames (at the start of a step's motion);
'on_request' moves it only through the `arm/place_object` service (mm_msgs/srv/PlaceObject: an explicit [x, y] or a
random place; also accepted in 'every_n_frames', refused in 'fixed'), which publishes a new frame at once (a step of
its own in which the arm does not move; the ground truth's contact counts restart there). Random places come from
ArmModel.random_object_position with a generator seeded by `placement_seed` (deterministic), away from the arm's
current pose. A requested place outside the image, out of the hand's reach or on top of the arm is rejected with the
reason.

Lockstep (default): the frame of step k is out; one valid command advances exactly one step. Until the next command
arrives the last step is re-sent (same stamp) every `republish_period` wall seconds, at any step, so a late joiner
can start the loop and a lost message never stalls it. Free-running: a wall timer steps every dt / real_time_factor
toward the latest target; the camera then uses the sensor-data QoS (loss acceptable, latest frame matters).

Reset (no service type is needed): setting `object_seed` or `object_position` re-builds the scene (textures, layout
and object place from the seed; `object_position` [x, y] px overrides the place, [-1.0] = random) and setting
`initial_joints` moves the arm there; either publishes a new step at once (sim time stays monotonic).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseStamped
from mm_common.node_utils import array_problem, check_parameters, declare, reject_input, run_node
from mm_msgs.msg import ArmGroundTruth, Contact
from mm_msgs.srv import PlaceObject
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock as WallClock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray, String

from mm_sim.arm_model import JOINT_NAMES, ArmModel
from mm_sim.arm_motion import move_towards, sweep

# Lockstep topics are RELIABLE: the planner waits for each step and the recorder must not lose a frame; depth 50
# absorbs a briefly slow subscriber (50 frames of 480 kB at most). Ground truth is reliable too: an evaluator must
# see every frame's contacts (and the running counts cover a message lost anyway).
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The robot description is latched state (as robot_state_publisher's): a node that starts later still gets it.
DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
OBJECT_MODES = ('fixed', 'every_n_frames', 'on_request')
COMMAND_TOPIC = 'arm/joint_position_controller/commands'
# A lockstep loop idle this long [ns of wall time] with nobody able to command it is reported.
UNMATCHED_WARNING_NS = 5_000_000_000
# Random places drawn before giving up on one that keeps clear of the arm's current pose.
PLACEMENT_ATTEMPTS = 200


def _stamp(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


class ArmSim(Node):
    def __init__(self, **node_kwargs):
        super().__init__('arm_sim', **node_kwargs)
        self.dt = declare(self, 'dt', 0.1, 'Simulation step [s]', min_value=1e-3, max_value=1.0, read_only=True)
        self.lockstep = declare(self, 'lockstep', True, 'Advance one step per received command (deterministic)',
                                read_only=True)
        self.real_time_factor = declare(self, 'real_time_factor', 1.0, 'Free-running speed relative to wall time',
                                        min_value=0.01, max_value=100.0, read_only=True)
        self.republish_period = declare(self, 'republish_period', 0.5,
                                        'Lockstep: wall seconds after which the last step is re-sent (same stamp) '
                                        'while no command came', min_value=0.01, max_value=60.0, read_only=True)
        self.max_joint_speed = declare(self, 'max_joint_speed', 4.0, 'Joint speed limit of the position controller '
                                       '[rad/s]', min_value=1e-3, max_value=100.0)
        self.command_margin = declare(self, 'command_margin', 0.2, 'Targets beyond a joint limit by more than this '
                                      '[rad] are rejected (within it they are clipped)', min_value=0.0, max_value=10.0)
        self.contact_resolution = declare(self, 'contact_resolution', 0.02, 'Largest joint sub-step [rad] on which '
                                          'contact is checked along a motion', min_value=1e-3, max_value=0.1)
        self.initial_joints = declare(self, 'initial_joints', [-2.0, 1.1],
                                      'Joint angles [shoulder_roll, shoulder_pitch] at start and on reset [rad]')
        self.object_seed = declare(self, 'object_seed', 0, 'Seed of textures, background layout and object place',
                                   min_value=0, max_value=2**31 - 1)
        self.object_position = declare(self, 'object_position', [-1.0],
                                       'Object centre [x, y] in image pixels; [-1.0] = random place from object_seed')
        self.object_mode = declare(self, 'object_mode', 'fixed', "How the object moves: 'fixed', 'every_n_frames' "
                                   "(random re-place every object_period_frames frames) or 'on_request' (only through "
                                   "the arm/place_object service)", additional_constraints=' | '.join(OBJECT_MODES))
        self.object_period_frames = declare(self, 'object_period_frames', 50, 'every_n_frames: frames between two '
                                            'random re-placements', min_value=1, max_value=1_000_000)
        self.placement_seed = declare(self, 'placement_seed', 0, 'Seed of the generator of random re-placements '
                                      '(setting it re-seeds the generator)', min_value=0, max_value=2**31 - 1)
        self.frame_id = declare(self, 'frame_id', 'camera', 'frame_id of the image and ground-truth pose',
                                read_only=True)
        self.image_size = declare(self, 'image_size', 400, 'Square image size [px]', min_value=64, max_value=2048,
                                  read_only=True)
        problem = self._check_values({'object_mode': self.object_mode, 'object_position': self.object_position,
                                      'initial_joints': self.initial_joints,
                                      'image_size': self.image_size})
        if problem:
            raise ValueError(problem)
        self.commands_received = 0
        self.commands_rejected = 0
        self.step_index = 0
        self.placement_rng = np.random.default_rng(self.placement_seed)
        self.model = self._build_model(self.object_seed, self.object_position)
        self.joints = self.model.clip_joints(self.initial_joints)
        self.velocity = np.zeros(2)
        self.target = self.joints.copy()
        # Ground-truth bookkeeping since the last placement (the initial place is placement 0).
        self.placements = 0
        self.frames_since_placement = 0
        self.contact_steps = 0
        self.contact_events = 0
        self.previous_contact = False
        self.add_on_set_parameters_callback(self._on_set_parameters)

        # Free-running camera: sensor-data QoS (best effort, shallow) - a late frame is worth less than the next.
        image_qos = LOOP_QOS if self.lockstep else qos_profile_sensor_data
        self.clock_pub = self.create_publisher(Clock, '/clock', LOOP_QOS)
        self.image_pub = self.create_publisher(Image, 'arm/camera/image_raw', image_qos)
        self.joint_pub = self.create_publisher(JointState, 'arm/joint_states', LOOP_QOS)
        self.contact_pub = self.create_publisher(Contact, 'arm/contact', LOOP_QOS)
        self.truth_pub = self.create_publisher(ArmGroundTruth, 'arm/ground_truth/state', LOOP_QOS)
        self.object_pub = self.create_publisher(PoseStamped, 'arm/ground_truth/object_pose', LOOP_QOS)
        self.command_sub = self.create_subscription(Float64MultiArray, COMMAND_TOPIC, self._on_command, LOOP_QOS)
        self.create_service(PlaceObject, 'arm/place_object', self._on_place_object)
        self.description_pub = self.create_publisher(String, 'arm/robot_description', DESCRIPTION_QOS)
        self._publish_description()
        self._last_step: Optional[list] = None      # (publisher, message) pairs of the last step, for re-sending
        self._wall = WallClock(clock_type=ClockType.STEADY_TIME)
        self._last_sent_ns = 0
        self._last_step_ns = 0          # wall time of the last new step (not a re-send)
        if self.lockstep:
            # Wall clock: sim time stands still while the loop waits, which is exactly when re-sending matters.
            self.create_timer(min(self.republish_period, 0.05), self._resend_if_idle, clock=self._wall)
        else:
            self.create_timer(self.dt / self.real_time_factor, self._advance)
        self._new_frame(self.joints, placed=True)
        self.get_logger().info(
            f"arm_sim ready: {'lockstep' if self.lockstep else 'free-running'}, dt={self.dt}s, object mode "
            f"{self.object_mode}, object at {np.round(self.model.object_position_, 1).tolist()} px, "
            f'joints {self.joints.tolist()}')

    # --- scene --------------------------------------------------------------------------------------------------
    def _publish_description(self) -> None:
        """The arm as a URDF: the joint box the learner and planner read (their only source of joint limits)."""
        self.description_pub.publish(String(data=self.model.robot_description(self.max_joint_speed)))

    def _build_model(self, seed: int, position) -> ArmModel:
        pos = list(position)
        if pos == [-1.0]:
            return ArmModel(image_size=self.image_size, random_state=int(seed))
        return ArmModel(image_size=self.image_size, object_position=tuple(pos), random_state=int(seed))

    def _placement_problem(self, position: np.ndarray) -> str:
        """'' if the object may be put at `position` now; else why not."""
        r, size = self.model.object_radius, self.image_size
        if np.any(position < r) or np.any(position > size - r):
            return f'object at {position.tolist()} px would leave the {size} px image (radius {r} px)'
        if self.model.inverse_kinematics(position) is None:
            return f'{position.tolist()} px is out of the hand\'s reach within the joint limits'
        if np.any(self.model.part_clearances(self.joints, object_position=position) < 0.0):
            return f'object at {position.tolist()} px would overlap the arm in its current pose'
        return ''

    def _random_place(self) -> Optional[np.ndarray]:
        for _ in range(PLACEMENT_ATTEMPTS):
            p = self.model.random_object_position(self.placement_rng)
            if not self._placement_problem(p):
                return p
        return None

    def _place(self, position: np.ndarray) -> None:
        self.model.set_object_position(position)
        self.placements += 1
        self._reset_counts()

    # --- parameters ---------------------------------------------------------------------------------------------
    def _check_values(self, values) -> str:
        """Cross-parameter checks on proposed values ('' = fine)."""
        mode = values.get('object_mode')
        if mode not in OBJECT_MODES:
            return f'object_mode must be one of {OBJECT_MODES}, got {mode!r}'
        pos = list(values.get('object_position'))
        if pos != [-1.0]:
            problem = array_problem(pos, 'object_position', 2, (0.0, float(values.get('image_size'))))
            if problem:
                return problem + " (or [-1.0] for a random place)"
        return array_problem(list(values.get('initial_joints')), 'initial_joints', 2)

    def _on_set_parameters(self, params) -> SetParametersResult:
        result = check_parameters(self, params, [self._check_values])
        if not result.successful:
            return result
        values = {p.name: p.value for p in params}
        seed = int(values.get('object_seed', self.object_seed))
        position = list(values.get('object_position', self.object_position))
        rebuild = seed != self.object_seed or position != list(self.object_position)
        try:
            model = self._build_model(seed, position) if rebuild else self.model
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if 'max_joint_speed' in values:
            self.max_joint_speed = float(values['max_joint_speed'])
            self._publish_description()
        self.command_margin = float(values.get('command_margin', self.command_margin))
        self.contact_resolution = float(values.get('contact_resolution', self.contact_resolution))
        self.object_mode = values.get('object_mode', self.object_mode)
        self.object_period_frames = int(values.get('object_period_frames', self.object_period_frames))
        if 'placement_seed' in values:
            self.placement_seed = int(values['placement_seed'])
            self.placement_rng = np.random.default_rng(self.placement_seed)
        if rebuild or 'initial_joints' in values:
            if rebuild:
                self.model, self.object_seed, self.object_position = model, seed, position
            if 'initial_joints' in values:
                self.initial_joints = list(values['initial_joints'])
                self.joints = model.clip_joints(self.initial_joints)
            self.target = self.joints.copy()
            self.velocity = np.zeros(2)
            if rebuild:
                self.placements += 1
                self._reset_counts()
            self.step_index += 1      # a reset is a new step: sim time stays monotonic for every consumer
            self._new_frame(self.joints, placed=rebuild)
            self.get_logger().info(f'reset: object at {np.round(model.object_position_, 1).tolist()} px, '
                                   f'joints {self.joints.tolist()}, step {self.step_index}')
        return SetParametersResult(successful=True)

    def _reset_counts(self) -> None:
        self.frames_since_placement = 0
        self.contact_steps = self.contact_events = 0
        self.previous_contact = False

    # --- inputs -------------------------------------------------------------------------------------------------
    def _command_problem(self, data) -> str:
        problem = array_problem(data, 'joint target', 2)
        if problem:
            return f'{problem} [{", ".join(JOINT_NAMES)}]'
        for v, (lo, hi), name in zip(data, self.model.joint_limits, JOINT_NAMES):
            if v < lo - self.command_margin or v > hi + self.command_margin:
                return f'{name} target {v:.3f} rad beyond its limits [{lo}, {hi}] by more than {self.command_margin}'
        return ''

    def _on_command(self, msg: Float64MultiArray) -> None:
        problem = self._command_problem(msg.data)
        if problem:
            self.commands_rejected = reject_input(self, COMMAND_TOPIC, problem)
            return
        self.commands_received += 1
        self.target = np.clip(np.asarray(msg.data, dtype=float), self.model.joint_limits[:, 0],
                              self.model.joint_limits[:, 1])
        if self.lockstep:
            self._advance()

    def _on_place_object(self, request: PlaceObject.Request, response: PlaceObject.Response):
        response.position = [float(v) for v in self.model.object_position_]
        problem = ''
        if self.object_mode == 'fixed':
            problem = "object_mode is 'fixed'; set it to 'on_request' or 'every_n_frames' to move the object"
        elif request.random:
            if len(request.position):
                problem = 'random place requested together with a position: send one or the other'
            else:
                place = self._random_place()
                if place is None:
                    problem = f'no random place clear of the arm in {PLACEMENT_ATTEMPTS} draws'
        else:
            problem = array_problem(request.position, 'position', 2)
            if not problem:
                place = np.asarray(request.position, dtype=float)
                problem = self._placement_problem(place)
        if problem:
            reject_input(self, 'arm/place_object', problem)
            response.accepted, response.message = False, problem
            return response
        self._place(place)
        self.step_index += 1
        self._new_frame(self.joints, placed=True)
        response.accepted = True
        response.position = [float(v) for v in place]
        response.stamp = _stamp(self.sim_time_ns)
        response.message = f'object at {np.round(place, 1).tolist()} px from step {self.step_index}'
        self.get_logger().info(f'placement {self.placements}: {response.message}')
        return response

    # --- stepping -----------------------------------------------------------------------------------------------
    @property
    def sim_time_ns(self) -> int:
        return int(round(self.step_index * self.dt * 1e9))

    def _advance(self) -> None:
        placed = False
        if self.object_mode == 'every_n_frames' and self.frames_since_placement >= self.object_period_frames:
            place = self._random_place()
            if place is None:
                self.get_logger().warn(f'no random place clear of the arm in {PLACEMENT_ATTEMPTS} draws; the object '
                                       'stays', throttle_duration_sec=5.0)
            else:
                self._place(place)
                placed = True
        start = self.joints
        self.joints = move_towards(start, self.target, self.max_joint_speed * self.dt, self.model.joint_limits)
        self.velocity = (self.joints - start) / self.dt
        self.step_index += 1
        self._new_frame(start, placed)

    def _new_frame(self, start, placed: bool) -> None:
        """Ground truth of the motion start -> self.joints, then publish the frame."""
        s = sweep(self.model, start, self.joints, self.contact_resolution)
        self.frames_since_placement += 1
        if s.any_contact:
            self.contact_steps += 1
            self.contact_events += int(not self.previous_contact)
        self.previous_contact = s.any_contact
        stamp = _stamp(self.sim_time_ns)
        obj, hand = self.model.object_position_, self.model.hand_position(self.joints)
        gaps = self.model.part_clearances(self.joints)
        truth = ArmGroundTruth(
            step=self.step_index, placement=self.placements, object_placed=placed,
            object_position=Point(x=float(obj[0]), y=float(obj[1])), object_radius=self.model.object_radius,
            hand_position=Point(x=float(hand[0]), y=float(hand[1])),
            hand_object_distance=float(np.linalg.norm(hand - obj)), link_clearance=float(gaps.min()),
            min_hand_object_distance=s.min_hand_object_distance, min_link_clearance=s.min_clearance,
            hand_contact=s.hand_contact, link_contact=s.any_contact, contact_parts=s.contact_parts,
            contact_steps=self.contact_steps, contact_events=self.contact_events)
        truth.header.stamp, truth.header.frame_id = stamp, self.frame_id
        frame = self.model.render(self.joints)
        img = Image(height=frame.shape[0], width=frame.shape[1], encoding='rgb8', is_bigendian=0,
                    step=frame.shape[1] * 3)
        img.header.stamp, img.header.frame_id = stamp, self.frame_id
        img.data = frame.tobytes()
        joints = JointState(name=list(JOINT_NAMES), position=[float(v) for v in self.joints],
                            velocity=[float(v) for v in self.velocity])
        joints.header.stamp = stamp
        contact = Contact(in_contact=s.hand_contact, in_contact_at_frame=bool(gaps[2] < 0.0),
                          arm_in_contact=s.any_contact, arm_in_contact_at_frame=bool(gaps.min() < 0.0))
        contact.header.stamp = stamp
        pose = PoseStamped()
        pose.header.stamp, pose.header.frame_id = stamp, self.frame_id
        pose.pose.position.x, pose.pose.position.y = float(obj[0]), float(obj[1])
        pose.pose.orientation.w = 1.0
        self._last_step = [(self.clock_pub, Clock(clock=stamp)), (self.image_pub, img), (self.joint_pub, joints),
                           (self.contact_pub, contact), (self.truth_pub, truth), (self.object_pub, pose)]
        self._send_last_step()
        self._last_step_ns = self._last_sent_ns

    def _send_last_step(self) -> None:
        for publisher, msg in self._last_step:
            publisher.publish(msg)
        self._last_sent_ns = self._wall.now().nanoseconds

    def _resend_if_idle(self) -> None:
        now = self._wall.now().nanoseconds
        if now - self._last_sent_ns >= self.republish_period * 1e9:
            self._send_last_step()
        if now - self._last_step_ns > UNMATCHED_WARNING_NS and self.command_sub.get_publisher_count() == 0:
            self.get_logger().warn(f'lockstep loop waiting at step {self.step_index}: no publisher of '
                                   f'{COMMAND_TOPIC} is matched (check its name, type and QoS)',
                                   throttle_duration_sec=10.0)


def main(args=None):
    run_node(ArmSim, args)


if __name__ == '__main__':
    main()
