"""Image embedding node: learns the arm's low-dimensional state from camera frames online (paper Section 3).

    ./mm run mm_manifold image_embedding --ros-args -p use_sim_time:=true -p min_training_frames:=500

Subscribes only to what the robot senses: `arm/camera/image_raw` (sensor_msgs/Image rgb8/bgr8/mono8),
`arm/joint_states` and `arm/contact` (the touch sensor on the hand, the "contact" label). Never ground truth.

Every image: SIFT keypoints (mm_manifold.keypoints). A frame whose joint state and touch reading of the same stamp
have arrived joins the training set. When `min_training_frames` frames are in, a background thread fits
mm_manifold.arm_learning.ArmStateLearner (keypoint labels, nearest-neighbour imputation, 3-D LLE and PCA, the
contact region - sphere, ellipsoid or quadric - with a cross-validated radius, the collision map on the joint grid);
it refits after every
`refit_every` further frames. Callbacks never wait for a fit: the new model is swapped in by the next callback.
Publishes `arm/embedding/state` (mm_msgs/EmbeddingState) for every image - with `model_ready` false before the first
fit, so a lockstep explorer can pace itself on it - and `arm/embedding/collision_map` (mm_msgs/CollisionMap,
TRANSIENT_LOCAL so a late planner gets the latest map) after each fit. How a cell is predicted: see
mm_manifold.arm_learning (share of the cell's training frames whose region closeness is at least -map_margin); the
map also carries each cell's closeness, from which dp_planner keeps clear of the contact region.

With `model_path` set, each fitted model is written there atomically (np.savez + JSON, no pickle) and loaded at start;
an unreadable file is logged as an error and the node learns again from scratch.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Dict, Optional

import cv2
import numpy as np
from mm_common.node_utils import declare, reject_non_finite, run_node
from mm_msgs.msg import CollisionMap, Contact, EmbeddingState
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState

from mm_manifold.arm_learning import ArmStateLearner, ModelFileError
from mm_manifold.keypoints import KeypointExtractor

# Inputs of a lockstep loop and our per-frame output: RELIABLE, nothing may be lost (the explorer paces on it).
LOOP_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# The collision map is latched state: TRANSIENT_LOCAL, the latest one is what a (late) planner needs.
MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST)
ENCODINGS = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def image_to_array(msg: Image, expected_size: Optional[int] = None) -> np.ndarray:
    """(H, W, 3) RGB or (H, W) grey uint8 array of an Image; ValueError on unsupported encoding or bad sizes."""
    channels = ENCODINGS.get(msg.encoding)
    if channels is None:
        raise ValueError(f'unsupported encoding {msg.encoding!r} (expected one of {sorted(ENCODINGS)})')
    if expected_size and (msg.width != expected_size or msg.height != expected_size):
        raise ValueError(f'image is {msg.width}x{msg.height}, expected {expected_size}x{expected_size}')
    if msg.width == 0 or msg.height == 0 or msg.step < msg.width * channels:
        raise ValueError(f'bad image geometry {msg.width}x{msg.height}, step {msg.step}')
    if len(msg.data) != msg.step * msg.height:
        raise ValueError(f'image data has {len(msg.data)} bytes, expected {msg.step * msg.height}')
    buf = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray)) else msg.data, np.uint8)
    rows = buf.reshape(msg.height, msg.step)[:, :msg.width * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    img = rows.reshape(msg.height, msg.width, 3)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if msg.encoding == 'bgr8' else np.ascontiguousarray(img)


class ImageEmbeddingNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__('image_embedding', **node_kwargs)
        self.min_training_frames = declare(self, 'min_training_frames', 500, 'Frames before the first fit',
                                           min_value=20, max_value=100000)
        self.refit_every = declare(self, 'refit_every', 300, 'Refit after this many new frames (0 = never)',
                                   min_value=0, max_value=100000)
        self.max_training_frames = declare(self, 'max_training_frames', 1500,
                                           'Most frames kept for fitting (older ones are dropped at random)',
                                           min_value=20, max_value=100000)
        self.image_size = declare(self, 'image_size', 400, 'Expected square image size [px] (0 = any)',
                                  min_value=0, max_value=4096)
        image_qos = declare(self, 'image_qos', 'reliable', "Camera subscription QoS: 'reliable' (lockstep) or "
                            "'sensor_data' (free-running camera)", read_only=True,
                            additional_constraints="one of reliable, sensor_data")
        self.model_path = declare(self, 'model_path', '', 'Where to save / load the model (.npz); empty = never',
                                  read_only=True)
        self.random_seed = declare(self, 'random_seed', 0, 'Seed of every random choice in learning',
                                   min_value=0, max_value=2**31 - 1)
        p = dict(
            n_components=declare(self, 'n_components', 3, 'Embedding dimension', min_value=1, max_value=10,
                                 read_only=True),
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
            joint_limits=(declare(self, 'joint0_limits', [-3.2, -0.8], 'shoulder_roll [min, max] rad',
                                  read_only=True),
                          declare(self, 'joint1_limits', [0.0, 2.2], 'shoulder_pitch [min, max] rad',
                                  read_only=True)),
        )
        if image_qos not in ('reliable', 'sensor_data'):
            raise ValueError("image_qos must be 'reliable' or 'sensor_data'")
        self.learner_params = p
        ArmStateLearner(**p)        # validate the combination now, not in the first fit
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.extractor = KeypointExtractor()
        self.model: Optional[ArmStateLearner] = None
        self.frames: Dict[str, list] = {'kp': [], 'joints': [], 'contact': [], 'stamp': []}
        self.pending: Dict[int, dict] = {}
        self.known_stamps = set()
        self.images_received = 0
        self.images_rejected = 0
        self.fits_done = 0
        self.fits_failed = 0
        self._frames_at_last_attempt = 0
        self._last_attempt_failed = False
        self._rng = np.random.default_rng(self.random_seed)
        self._lock = threading.Lock()
        self._fit_thread: Optional[threading.Thread] = None
        self._fitted: Optional[ArmStateLearner] = None

        self.state_pub = self.create_publisher(EmbeddingState, 'arm/embedding/state', LOOP_QOS)
        self.map_pub = self.create_publisher(CollisionMap, 'arm/embedding/collision_map', MAP_QOS)
        self.create_subscription(Image, 'arm/camera/image_raw', self._on_image,
                                 LOOP_QOS if image_qos == 'reliable' else qos_profile_sensor_data)
        self.create_subscription(JointState, 'arm/joint_states', self._on_joints, LOOP_QOS)
        self.create_subscription(Contact, 'arm/contact', self._on_contact, LOOP_QOS)
        # Wall-clock timer: picks up a finished fit even while sim time stands still (lockstep loop waiting).
        self.create_timer(0.1, self._install_fitted, clock=Clock(clock_type=ClockType.STEADY_TIME))
        if self.model_path:
            self._load_model()
        self.get_logger().info(f'image_embedding ready: first fit after {self.min_training_frames} frames, '
                               f'refit every {self.refit_every}, model_path={self.model_path or "(none)"}')

    # --- parameters -------------------------------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        result = reject_non_finite(params)
        if not result.successful:
            return result
        for p in params:
            if p.name == 'min_training_frames':
                self.min_training_frames = int(p.value)
            elif p.name == 'refit_every':
                self.refit_every = int(p.value)
            elif p.name == 'max_training_frames':
                if int(p.value) < self.min_training_frames:
                    return SetParametersResult(successful=False,
                                               reason='max_training_frames must be >= min_training_frames')
                self.max_training_frames = int(p.value)
            elif p.name == 'image_size':
                self.image_size = int(p.value)
            elif p.name in ('cell_min_frames', 'cell_collision_fraction', 'map_margin'):
                self.learner_params[p.name] = p.value     # used from the next fit on
        return SetParametersResult(successful=True)

    # --- persistence ------------------------------------------------------------------------------------------
    def _load_model(self) -> None:
        path = Path(self.model_path)
        if not path.exists():
            self.get_logger().info(f'no saved model at {path}; learning from scratch')
            return
        try:
            self.model = ArmStateLearner.load(path)
        except ModelFileError as exc:
            self.get_logger().error(f'cannot use the saved model, learning from scratch: {exc}')
            return
        self.get_logger().info(f'loaded model from {path} ({self.model.n_frames_} training frames)')
        self._publish_map(self.model)

    # --- inputs -----------------------------------------------------------------------------------------------
    def _entry(self, stamp: int) -> Optional[dict]:
        if stamp in self.known_stamps:
            return None          # a re-published step (lockstep start-up): already in the training set
        entry = self.pending.get(stamp)
        if entry is None:
            entry = self.pending[stamp] = {}
            if len(self.pending) > 200:         # parts that never completed (lost messages): forget the oldest
                for old in sorted(self.pending)[:len(self.pending) - 200]:
                    del self.pending[old]
        return entry

    def _on_joints(self, msg: JointState) -> None:
        if len(msg.position) != 2 or not np.all(np.isfinite(msg.position)):
            self.get_logger().warn(f'ignoring joint state with {len(msg.position)} positions (need 2 finite)',
                                   throttle_duration_sec=2.0)
            return
        stamp = stamp_ns(msg.header)
        entry = self._entry(stamp)
        if entry is not None:
            entry['joints'] = np.asarray(msg.position, dtype=float)
            self._complete(stamp)

    def _on_contact(self, msg: Contact) -> None:
        # The touch reading of a frame carries the frame's stamp: it joins the joint state and image of that stamp.
        stamp = stamp_ns(msg.header)
        entry = self._entry(stamp)
        if entry is not None:
            entry['contact'] = bool(msg.in_contact)
            self._complete(stamp)

    def _on_image(self, msg: Image) -> None:
        self._install_fitted()
        try:
            image = image_to_array(msg, self.image_size or None)
        except ValueError as exc:
            self.images_rejected += 1
            self.get_logger().warn(f'rejected image ({self.images_rejected} so far): {exc}',
                                   throttle_duration_sec=2.0)
            return
        self.images_received += 1
        kp = self.extractor(image)
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
        entry = self._entry(stamp)
        if entry is not None:
            entry['kp'] = kp
            self._complete(stamp)
        self.state_pub.publish(out)

    def _complete(self, stamp: int) -> None:
        entry = self.pending.get(stamp)
        if entry is None or not {'kp', 'joints', 'contact'} <= set(entry):
            return
        del self.pending[stamp]
        self.known_stamps.add(stamp)
        with self._lock:
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

    # --- learning ---------------------------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.frames['kp'])

    def _maybe_fit(self) -> None:
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
        with self._lock:
            snapshot = {k: list(v) for k, v in self.frames.items()}
        self._frames_at_last_attempt = n
        self._fit_thread = threading.Thread(target=self._fit, args=(snapshot, dict(self.learner_params)),
                                            name='embedding_fit', daemon=True)
        self._fit_thread.start()

    def _fit(self, data: dict, params: dict) -> None:
        """Background thread: fit, save, hand the model over (installed by the executor thread)."""
        try:
            learner = ArmStateLearner(random_state=self.random_seed, **params).fit(
                data['kp'], np.array(data['joints']), np.array(data['contact']), np.array(data['stamp']))
            if self.model_path:
                learner.save(self.model_path)
        except Exception as exc:        # keep collecting and retry; the node must not die on a bad batch
            self.get_logger().error(f'fit on {len(data["kp"])} frames failed: {exc}')
            with self._lock:
                self.fits_failed += 1
                self._last_attempt_failed = True
                self._fit_thread = None
            return
        with self._lock:
            self._fitted = learner
            self._last_attempt_failed = False

    def _install_fitted(self) -> None:
        with self._lock:
            learner, self._fitted = self._fitted, None
            if learner is not None:
                self._fit_thread = None
        if learner is None:
            return
        self.model = learner
        self.fits_done += 1
        v = learner.selection_
        self.get_logger().info(
            f'fit {self.fits_done}: {learner.n_frames_} frames, {learner.vectorizer_.n_labels_} labels, '
            f"{int(learner.train_contact_.sum())} contact frames, contact region {v['model']} "
            f"(cross-validated TPR {v['cv_tpr']:.3f} FPR {v['cv_fpr']:.3f}), "
            f'{int(learner.collision_map_.sum())} collision cells')
        self._publish_map(learner)
        self._maybe_fit()

    def _publish_map(self, learner: ArmStateLearner) -> None:
        m = CollisionMap()
        m.header.stamp = self.get_clock().now().to_msg()
        m.header.frame_id = 'joint_grid'
        m.rows, m.cols = learner.grid_shape
        m.joint0_limits = [float(v) for v in learner.joint_limits[0]]
        m.joint1_limits = [float(v) for v in learner.joint_limits[1]]
        m.collision = [bool(v) for v in learner.collision_map_.ravel()]
        m.closeness = [float(v) for v in learner.closeness_map_.ravel()]
        self.map_pub.publish(m)


def main(args=None):
    run_node(ImageEmbeddingNode, args)


if __name__ == '__main__':
    main()
