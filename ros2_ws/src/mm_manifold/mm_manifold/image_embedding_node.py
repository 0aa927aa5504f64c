"""Image embedding node: learns the arm's low-dimensional state from camera frames online (paper Section 3) and
builds the collision map the planner needs for the object where the current frame shows it.

    ./mm run mm_manifold image_embedding --ros-args -p use_sim_time:=true -p min_training_frames:=500

Subscribes only to what the robot senses: `arm/camera/image_raw` (sensor_msgs/Image rgb8/bgr8/mono8),
`arm/joint_states` and `arm/contact` (mm_msgs/Contact, stamped with its frame: the contact sensed in the frame's pose
is the frame's "contact" label; `contact_label` 'arm' (default) takes the contact of any arm part, which a real arm
senses from its joint torques, 'hand' the hand's touch sensor alone), plus `arm/embedding/map_request`
(std_msgs/Header from the planner: the stamp of the frame a map is needed of), and the robot's joint box from `arm/robot_description`
(std_msgs/String URDF, latched; frames are collected before it comes, the first fit waits for it). Never ground
truth.

Every image: SIFT keypoints (mm_manifold.keypoints). A frame whose joint state and touch reading of the same stamp
have arrived joins the training set. When `min_training_frames` frames are in, a background thread fits
mm_manifold.arm_learning.ArmStateLearner (keypoint labels, imputation, 3-D LLE and PCA, the contact region with a
cross-validated radius); it refits after every `refit_every` further frames, and a refit whose cross-validated
TPR - FPR is below the live model's is discarded (logged). Callbacks never wait for a fit: the new model is
swapped in by the executor thread; the fitting thread shares no mutable state with it (a snapshot in, a model out,
under a lock).

The model is kept across object placements. Collision maps come from the current image plus what was learned
(ArmStateLearner.predict_collision_map: the hand predicted in image space for every cell of the joint grid, the
predicted frame embedded, the contact region applied), built for the newest frame after each fit and for every map
request (from the requested frame, or the first later one, plus at most `map_recent_frames` frames before it).
Published on `arm/embedding/collision_map` (mm_msgs/CollisionMap, TRANSIENT_LOCAL so a late planner gets the latest
map) with `header.stamp` = the frame it was built from; the log line says how many frames went into it.
Publishes `arm/embedding/state` (mm_msgs/EmbeddingState) for every image, with `model_ready` false before the first
fit, so a lockstep explorer can pace itself on it.

With `model_path` set, each fitted model is written there atomically (np.savez + JSON, no pickle) and loaded once the
robot description has come; a file that cannot be read or does not fit this node's grid and the robot's joint box
is logged and the node learns from scratch.
Every input is validated; a bad one is dropped with a throttled log line and the node keeps running.
"""
from __future__ import annotations

import collections
import math
import threading
from pathlib import Path
from typing import Dict, Optional

import cv2
import numpy as np
from mm_common.node_utils import check_parameters, declare, ordered, reject_input, run_node
from mm_common.robot_description import joint_box
from mm_msgs.msg import CollisionMap, Contact, EmbeddingState
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Header, String

from mm_manifold.arm_learning import ArmStateLearner, ModelFileError
from mm_manifold.keypoints import KeypointExtractor

# Inputs of a lockstep loop and our per-frame output: RELIABLE, nothing may be lost (the explorer paces on it).
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The collision map is latched state: TRANSIENT_LOCAL, the latest one is what a (late) planner needs.
MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST)
# Map requests: RELIABLE (the planner waits for the answer), volatile (a request is about the present frame only).
REQUEST_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The robot description is latched state: TRANSIENT_LOCAL, so this node gets it whenever it starts.
DESCRIPTION_QOS = MAP_QOS
# Stands in for the robot's joint box while the settings are checked before arm/robot_description has come.
UNIT_BOX = ((0.0, 1.0), (0.0, 1.0))
ENCODINGS = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}
MIN_IMAGE_SIZE = 16          # px: smaller images carry no usable keypoints (and break the half-scale SIFT pass)
MAX_IMAGE_SIZE = 4096
RECENT_FRAMES = 50           # keypoints of the newest frames kept for map requests
MAX_PENDING = 200


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def image_to_array(msg: Image, expected_size: Optional[int] = None) -> np.ndarray:
    """(H, W, 3) RGB or (H, W) grey uint8 array of an Image; ValueError on unsupported encoding or bad sizes."""
    channels = ENCODINGS.get(msg.encoding)
    if channels is None:
        raise ValueError(f'unsupported encoding {msg.encoding!r} (expected one of {sorted(ENCODINGS)})')
    if expected_size and (msg.width != expected_size or msg.height != expected_size):
        raise ValueError(f'image is {msg.width}x{msg.height}, expected {expected_size}x{expected_size}')
    if not (MIN_IMAGE_SIZE <= msg.width <= MAX_IMAGE_SIZE and MIN_IMAGE_SIZE <= msg.height <= MAX_IMAGE_SIZE):
        raise ValueError(f'image is {msg.width}x{msg.height}; sides must be {MIN_IMAGE_SIZE}-{MAX_IMAGE_SIZE} px')
    if msg.step < msg.width * channels:
        raise ValueError(f'row step {msg.step} is shorter than {msg.width} px x {channels} channels')
    if len(msg.data) != msg.step * msg.height:
        raise ValueError(f'image data has {len(msg.data)} bytes, expected {msg.step * msg.height}')
    buf = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray)) else msg.data, np.uint8)
    rows = buf.reshape(msg.height, msg.step)[:, :msg.width * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    img = rows.reshape(msg.height, msg.width, 3)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if msg.encoding == 'bgr8' else np.ascontiguousarray(img)


def learner_problem(params: dict) -> str:
    """'' if ArmStateLearner accepts these settings, else why not (UNIT_BOX while the joint box is unknown)."""
    try:
        ArmStateLearner(**{**params, 'joint_limits': UNIT_BOX if params['joint_limits'] is None
                           else params['joint_limits']})
    except ValueError as exc:
        return str(exc)
    return ''


def model_score(learner: ArmStateLearner) -> float:
    """Cross-validated TPR - FPR of the model's contact region (on its own training frames)."""
    return float(learner.selection_['cv_tpr']) - float(learner.selection_['cv_fpr'])


class ImageEmbeddingNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('image_embedding', **node_kwargs)
        self.min_training_frames = declare(self, 'min_training_frames', 1000, 'Frames before the first fit',
                                           min_value=20, max_value=100000)
        self.refit_every = declare(self, 'refit_every', 300, 'Refit after this many new frames (0 = never)',
                                   min_value=0, max_value=100000)
        self.max_training_frames = declare(self, 'max_training_frames', 1500,
                                           'Most frames kept for fitting (older ones are dropped at random); '
                                           '>= min_training_frames', min_value=20, max_value=100000)
        self.image_size = declare(self, 'image_size', 400, 'Expected square image size [px] (0 = any size from '
                                  f'{MIN_IMAGE_SIZE} to {MAX_IMAGE_SIZE})', min_value=0, max_value=MAX_IMAGE_SIZE)
        self.map_recent_frames = declare(self, 'map_recent_frames', 0, 'Frames before the mapped one that a '
                                         'collision map may also use (0 = the mapped frame alone)', min_value=0,
                                         max_value=RECENT_FRAMES - 1)
        image_qos = declare(self, 'image_qos', 'reliable', "Camera subscription QoS: 'reliable' (lockstep) or "
                            "'sensor_data' (free-running camera)", read_only=True,
                            additional_constraints="one of reliable, sensor_data")
        self.model_path = declare(self, 'model_path', '', 'Where to save / load the model (.npz); empty = never',
                                  read_only=True)
        self.random_seed = declare(self, 'random_seed', 0, 'Seed of every random choice in learning',
                                   min_value=0, max_value=2**31 - 1, read_only=True)
        p = dict(
            n_components=declare(self, 'n_components', 4, 'Embedding dimension (4: chosen by mm_bringup.tune_arm on '
                                 'scenes and seeds of its own)', min_value=1, max_value=10, read_only=True),
            n_neighbors=declare(self, 'n_neighbors', 20, 'LLE neighbours', min_value=3, max_value=200,
                                read_only=True),
            region=declare(self, 'contact_region', 'auto', "Contact region in the LLE space: 'sphere' (paper), "
                           "'ellipsoid', 'quadric', or 'auto' (chosen by cross-validation)", read_only=True,
                           additional_constraints='one of auto, sphere, ellipsoid, quadric'),
            cell_min_frames=declare(self, 'cell_min_frames', 3, 'Frames per cell (nearest ones fill up)',
                                    min_value=1, max_value=1000),
            cell_collision_fraction=declare(self, 'cell_collision_fraction', 0.1,
                                            'Share of a cell\'s frames predicted as collision that marks the cell',
                                            min_value=0.001, max_value=1.0),
            map_margin=declare(self, 'map_margin', 0.1, 'Frames with closeness >= -map_margin count as collision '
                               'for the map (region inflated by this share for planning)', min_value=0.0,
                               max_value=5.0),
            grid_shape=(declare(self, 'grid_rows', 8, 'Joint grid rows (joint 0)', min_value=1, max_value=200,
                                read_only=True),
                        declare(self, 'grid_cols', 12, 'Joint grid cols (joint 1)', min_value=1, max_value=200,
                                read_only=True)),
            joint_limits=None,          # the robot's joint box, from arm/robot_description
            map_method=declare(self, 'map_method', 'keypoint_distance', "Collision map of a new placement: "
                               "'keypoint_distance' (the learned object placed where the frame shows it, against "
                               "the robot's predicted segments with the contact distances learned from the touch "
                               "labels) or 'embedding' (the predicted frame embedded, the contact region applied; "
                               "the paper's route)", read_only=True,
                               additional_constraints='one of keypoint_distance, embedding'),
            map_threshold=declare(self, 'map_threshold', 0.25, 'Closeness to the contact region at or above which a '
                                  'predicted frame counts as contact (embedding route; chosen by mm_bringup.tune_arm)',
                                  min_value=-9.9, max_value=9.9, read_only=True),
            object_tolerance=declare(self, 'object_tolerance', 3.0, 'px: keypoint labels whose mutual offsets stay '
                                     'this steady move as one rigid object (keypoint_distance)', min_value=0.1,
                                     max_value=99.0, read_only=True),
            margin_quantile=declare(self, 'margin_quantile', 0.0, "Share of the no-contact frames allowed inside a "
                                    "segment's contact distance (keypoint_distance; chosen through the graph by "
                                    "mm_bringup.tune_arm_reach)",
                                    min_value=0.0, max_value=0.5, read_only=True),
            move_clearance=declare(self, 'move_clearance', 3.0, 'px of predicted clearance a move between cell '
                                   'centres must keep to count as free in the map\'s blocked_moves (keypoint_distance; '
                                   'chosen through the graph by mm_bringup.tune_arm_reach: 0 px let the hand graze '
                                   'the object)', min_value=0.0,
                                   max_value=99.0, read_only=True),
            unplaced_object=declare(self, 'unplaced_object', 'block', "keypoint_distance map of a frame that does not "
                                    "show the object where it is: 'block' every cell (dp_planner refuses the goal; "
                                    "on scenes 17-20 the embedding fallback caused every contact) or 'embedding' "
                                    "(fall back to the paper's route)", read_only=True,
                                    additional_constraints='one of block, embedding'),
        )
        self.contact_label = declare(self, 'contact_label', 'arm', "Which contact sense labels the frames: 'arm' "
                                     "(any arm part, from joint torques) or 'hand' (the hand's touch sensor, the "
                                     "paper's)", read_only=True, additional_constraints='one of arm, hand')
        if self.contact_label not in ('arm', 'hand'):
            raise ValueError("contact_label must be 'arm' or 'hand'")
        if image_qos not in ('reliable', 'sensor_data'):
            raise ValueError("image_qos must be 'reliable' or 'sensor_data'")
        if self.min_training_frames > self.max_training_frames:
            raise ValueError(f'min_training_frames={self.min_training_frames} must be <= '
                             f'max_training_frames={self.max_training_frames}')
        self.learner_params = p
        problem = learner_problem(p)            # validate the settings now, not in the first fit
        if problem:
            raise ValueError(problem)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.extractor = KeypointExtractor()
        self.model: Optional[ArmStateLearner] = None
        self.frames: Dict[str, list] = {'kp': [], 'joints': [], 'contact': [], 'stamp': []}
        self.pending: Dict[int, dict] = {}
        self.recent = collections.OrderedDict()     # stamp -> keypoints of the newest frames
        self.known_stamps = set()
        self.map_request: Optional[int] = None
        self.maps_published = 0
        self.images_received = 0
        self.images_rejected = 0
        self.fits_done = 0
        self.fits_discarded = 0
        self._frames_at_last_attempt = 0
        self._rng = np.random.default_rng(self.random_seed)
        # Hand-over between the fitting thread and the executor: only these three, only under the lock.
        self._lock = threading.Lock()
        self._fit_thread: Optional[threading.Thread] = None
        self._fit_result: Optional[tuple] = None          # (learner or None, error message)
        self._last_attempt_failed = False

        self.state_pub = self.create_publisher(EmbeddingState, 'arm/embedding/state', LOOP_QOS)
        self.map_pub = self.create_publisher(CollisionMap, 'arm/embedding/collision_map', MAP_QOS)
        self.create_subscription(Image, 'arm/camera/image_raw', self._on_image,
                                 LOOP_QOS if image_qos == 'reliable' else qos_profile_sensor_data)
        self.create_subscription(JointState, 'arm/joint_states', self._on_joints, LOOP_QOS)
        self.create_subscription(Contact, 'arm/contact', self._on_contact, LOOP_QOS)
        self.create_subscription(Header, 'arm/embedding/map_request', self._on_map_request, REQUEST_QOS)
        self.create_subscription(String, 'arm/robot_description', self._on_robot_description, DESCRIPTION_QOS)
        # Wall-clock timer: picks up a finished fit even while sim time stands still (lockstep loop waiting).
        self.create_timer(0.1, self._install_fitted, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'image_embedding ready: first fit after {self.min_training_frames} frames, '
                               f'refit every {self.refit_every}, model_path={self.model_path or "(none)"}; the joint '
                               'box comes from arm/robot_description')

    # --- parameters -------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = check_parameters(self, params, [ordered('min_training_frames', 'max_training_frames')])
        if not result.successful:
            return result
        learner_update = {p.name: p.value for p in params
                          if p.name in ('cell_min_frames', 'cell_collision_fraction', 'map_margin')}
        if learner_update:
            problem = learner_problem({**self.learner_params, **learner_update})
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        for p in params:
            if p.name == 'min_training_frames':
                self.min_training_frames = int(p.value)
            elif p.name == 'refit_every':
                self.refit_every = int(p.value)
            elif p.name == 'max_training_frames':
                self.max_training_frames = int(p.value)
            elif p.name == 'image_size':
                self.image_size = int(p.value)
            elif p.name == 'map_recent_frames':
                self.map_recent_frames = int(p.value)
        self.learner_params.update(learner_update)        # used from the next fit on
        return SetParametersResult(successful=True)

    # --- the robot ----------------------------------------------------------------------------------------------
    def _on_robot_description(self, msg: String) -> None:
        """Take the joint box from the robot's URDF once; a later description with another box is refused (a model
        learned over one box cannot serve another: restart the node for a new robot)."""
        try:
            limits = joint_box(msg.data, 2)
        except ValueError as exc:
            reject_input(self, 'arm/robot_description', str(exc))
            return
        known = self.learner_params['joint_limits']
        if known is not None:
            if not np.allclose(known, limits):
                reject_input(self, 'arm/robot_description', f'joint box {limits.tolist()} differs from the one this '
                                                            f'node learns over, {known.tolist()}; restart the node '
                                                            'for a new robot')
            return
        problem = learner_problem({**self.learner_params, 'joint_limits': limits})
        if problem:
            reject_input(self, 'arm/robot_description', problem)
            return
        self.learner_params['joint_limits'] = limits
        self.get_logger().info(f'joint box from arm/robot_description: {limits.tolist()} rad')
        if self.model_path:
            self._load_model()
        self._maybe_fit()

    # --- persistence ------------------------------------------------------------------------------------------
    def _load_model(self) -> None:
        path = Path(self.model_path)
        if not path.exists():
            self.get_logger().info(f'no saved model at {path}; learning from scratch')
            return
        try:
            model = ArmStateLearner.load(path)
        except ModelFileError as exc:
            self.get_logger().error(f'cannot use the saved model, learning from scratch: {exc}')
            return
        want_shape = tuple(self.learner_params['grid_shape'])
        want_limits = self.learner_params['joint_limits']
        if model.grid_shape != want_shape or not np.allclose(model.joint_limits, want_limits):
            self.get_logger().error(f'saved model {path} is for a {model.grid_shape} grid over '
                                    f'{model.joint_limits.tolist()}, this node uses {want_shape} over '
                                    f'{want_limits.tolist()}: learning from scratch')
            return
        self.model = model
        self.map_request = 0            # a map of the first frame that comes in
        self.get_logger().info(f'loaded model from {path} ({model.n_frames_} training frames)')

    # --- inputs -----------------------------------------------------------------------------------------------
    def _entry(self, stamp: int) -> Optional[dict]:
        if stamp in self.known_stamps:
            return None          # a re-published step (lockstep start-up): already in the training set
        entry = self.pending.get(stamp)
        if entry is None:
            entry = self.pending[stamp] = {}
            if len(self.pending) > MAX_PENDING:         # parts that never completed (lost messages): forget oldest
                for old in sorted(self.pending)[:len(self.pending) - MAX_PENDING]:
                    del self.pending[old]
        return entry

    def _on_joints(self, msg: JointState) -> None:
        if len(msg.position) != 2 or not all(math.isfinite(v) for v in msg.position):
            reject_input(self, 'arm/joint_states', f'need 2 finite positions, got {list(msg.position)}')
            return
        stamp = stamp_ns(msg.header)
        entry = self._entry(stamp)
        if entry is not None:
            entry['joints'] = np.asarray(msg.position, dtype=float)
            self._complete(stamp)

    def _on_contact(self, msg: Contact) -> None:
        stamp = stamp_ns(msg.header)
        entry = self._entry(stamp)
        if entry is not None:
            # the label of what the image shows: contact in the frame's own pose
            entry['contact'] = bool(msg.arm_in_contact_at_frame if self.contact_label == 'arm'
                                    else msg.in_contact_at_frame)
            self._complete(stamp)

    def _on_map_request(self, msg: Header) -> None:
        stamp = stamp_ns(msg)
        if stamp < 0 or (self.recent and stamp < next(iter(self.recent))):
            reject_input(self, 'arm/embedding/map_request', f'frame {stamp} ns is older than every frame kept')
            return
        self.map_request = stamp
        self._serve_map_request()

    def _on_image(self, msg: Image) -> None:
        self._install_fitted()
        try:
            image = image_to_array(msg, self.image_size or None)
            kp = self.extractor(image)
        except (ValueError, cv2.error) as exc:
            self.images_rejected += 1
            reject_input(self, 'arm/camera/image_raw', f'{exc} ({self.images_rejected} rejected so far)')
            return
        self.images_received += 1
        stamp = stamp_ns(msg.header)
        out = EmbeddingState(header=msg.header, keypoints_detected=len(kp), model_ready=self.model is not None)
        if self.model is not None:
            s = self.model.transform(kp)
            out.embedding = [float(v) for v in s['embedding']]
            out.pca_embedding = [float(v) for v in s['pca_embedding']]
            out.keypoints_labelled = s['labelled']
            out.training_frames = self.model.n_frames_
            out.collision_predicted = s['collision']
            out.closeness = s['closeness']
        self.recent[stamp] = kp
        self.recent.move_to_end(stamp)
        while len(self.recent) > RECENT_FRAMES:
            self.recent.popitem(last=False)
        entry = self._entry(stamp)
        if entry is not None:
            entry['kp'] = kp
            self._complete(stamp)
        self._serve_map_request()
        self.state_pub.publish(out)

    def _complete(self, stamp: int) -> None:
        entry = self.pending.get(stamp)
        if entry is None or not {'kp', 'joints', 'contact'} <= set(entry):
            return
        del self.pending[stamp]
        self.known_stamps.add(stamp)
        f = self.frames
        f['kp'].append(entry['kp'])
        f['joints'].append(entry['joints'])
        f['contact'].append(entry['contact'])
        f['stamp'].append(stamp)
        if len(f['kp']) > self.max_training_frames:
            drop = int(self._rng.integers(len(f['kp'])))
            for key in f:
                f[key].pop(drop)
        self._maybe_fit()

    # --- collision maps ---------------------------------------------------------------------------------------
    def _serve_map_request(self) -> None:
        """Build the requested map once the model and a frame at or after the requested stamp are there."""
        if self.map_request is None or self.model is None:
            return
        later = [s for s in self.recent if s >= self.map_request]
        if not later:
            return
        self.map_request = None
        self._publish_map(min(later))

    def _publish_map(self, stamp: int) -> None:
        stamps = list(self.recent)
        i = stamps.index(stamp)
        recent = [self.recent[s] for s in stamps[max(0, i - self.map_recent_frames):i]]
        try:
            pred = self.model.predict_collision_map(self.recent[stamp], recent)
            collision = np.asarray(pred['collision'], dtype=bool)
            closeness = np.asarray(pred['closeness'], dtype=float)
            moves = np.asarray(pred['blocked_moves'], dtype=bool)
            if (collision.shape != self.model.grid_shape or closeness.shape != collision.shape
                    or moves.shape != (4,) + collision.shape):
                raise ValueError(f'prediction of shape {collision.shape} for a {self.model.grid_shape} grid')
        except Exception as exc:     # a failed prediction must not end the node; the planner times out and says so
            self.get_logger().error(f'collision map of frame {stamp * 1e-9:.3f} s failed: {exc}')
            return
        m = CollisionMap()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        m.header.frame_id = 'joint_grid'
        m.rows, m.cols = self.model.grid_shape
        m.joint0_limits = [float(v) for v in self.model.joint_limits[0]]
        m.joint1_limits = [float(v) for v in self.model.joint_limits[1]]
        m.collision = [bool(v) for v in collision.ravel()]
        m.closeness = [float(v) for v in np.where(np.isnan(closeness), -np.inf, closeness).ravel()]
        m.blocked_moves = [bool(v) for v in moves.transpose(1, 2, 0).ravel()]      # (row * cols + col) * 4 + move
        self.map_pub.publish(m)
        self.maps_published += 1
        self.get_logger().info(f'collision map {self.maps_published} of frame {stamp * 1e-9:.3f} s from '
                               f'{1 + len(recent)} frame(s) of the current scene: {int(collision.sum())} '
                               f"collision cells, {int(moves.sum())} blocked moves ({pred['method']}, "
                               f"{pred['objects_placed']} object(s) placed)")

    # --- learning ---------------------------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.frames['kp'])

    def _maybe_fit(self) -> None:
        with self._lock:
            if self._fit_thread is not None:
                return
        n, since = self.n_frames, self.n_frames - self._frames_at_last_attempt
        if self.model is None and not self._last_attempt_failed:
            due = n >= self.min_training_frames
        elif self._last_attempt_failed:
            due = since >= 50                       # e.g. too few contact frames: retry with more
        else:
            due = self.refit_every > 0 and since >= self.refit_every
        if not due:
            return
        if self.learner_params['joint_limits'] is None:
            self.get_logger().warn('enough frames to learn, but no joint box yet: waiting for arm/robot_description',
                                   throttle_duration_sec=5.0)
            return
        snapshot = {k: list(v) for k, v in self.frames.items()}
        self._frames_at_last_attempt = n
        thread = threading.Thread(target=self._fit, name='embedding_fit', daemon=True,
                                  args=(snapshot, dict(self.learner_params), self.random_seed, self.model_path))
        with self._lock:
            self._fit_thread = thread
        thread.start()

    def _fit(self, data: dict, params: dict, seed: int, model_path: str) -> None:
        """Background thread: fit on its own snapshot and hand the result over under the lock. It touches no other
        attribute of the node (saving happens on the executor once the model is accepted)."""
        try:
            learner = ArmStateLearner(random_state=seed, **params).fit(
                data['kp'], np.array(data['joints']), np.array(data['contact']), np.array(data['stamp']))
            result = (learner, '')
        except Exception as exc:        # keep collecting and retry; the node must not die on a bad batch
            result = (None, f'fit on {len(data["kp"])} frames failed: {exc}')
        with self._lock:
            self._fit_result = result

    def _install_fitted(self) -> None:
        with self._lock:
            result, self._fit_result = self._fit_result, None
            if result is not None:
                self._fit_thread = None
        if result is None:
            return
        learner, error = result
        self._last_attempt_failed = learner is None
        if learner is None:
            self.get_logger().error(error)
            return
        if self.model is not None and model_score(learner) < model_score(self.model):
            self.fits_discarded += 1
            self.get_logger().warn(
                f'refit on {learner.n_frames_} frames discarded: cross-validated TPR-FPR {model_score(learner):.3f} '
                f'is below the live model\'s {model_score(self.model):.3f} ({self.model.n_frames_} frames)')
            self._maybe_fit()
            return
        self.model = learner
        self.fits_done += 1
        if self.model_path:
            try:
                learner.save(self.model_path)
            except OSError as exc:
                self.get_logger().error(f'cannot save the model to {self.model_path}: {exc}')
        v = learner.selection_
        self.get_logger().info(
            f'fit {self.fits_done}: {learner.n_frames_} frames, {learner.vectorizer_.n_labels_} labels, '
            f"{int(learner.train_contact_.sum())} contact frames, contact region {v['model']} "
            f"(cross-validated TPR {v['cv_tpr']:.3f} FPR {v['cv_fpr']:.3f}), {learner.n_objects_} object(s) "
            f"learned, placed in {learner.object_frames_} frames")
        if self.recent:
            self._publish_map(next(reversed(self.recent)))       # the newest frame: the scene as it is now
        self._serve_map_request()
        self._maybe_fit()


def main(args=None):
    run_node(ImageEmbeddingNode, args)


if __name__ == '__main__':
    main()
