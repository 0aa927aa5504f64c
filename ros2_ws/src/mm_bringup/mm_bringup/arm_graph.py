"""The Section 3 experiment through the ROS graph: arm_sim (lockstep) + image_embedding + dp_planner as separate
processes, driven and scored by an evaluation harness node (the experimenter, not part of the robot).

`start_arm_graph` starts the three nodes (the object re-placed every `object_period_frames` frames while the robot
explores, as the paper varies it); `ArmGraphDriver` waits for learning, switches arm_sim to placing the object on
request and runs placements: `run_placement` draws an object place and a goal with the object in the way on the
simulator's own scene model (ground truth chooses the task only), places the object (`arm/place_object`), sends the
goal (`arm/set_goal`, whose reply carries the goal's stamp) and scores the outcome that names that goal on
`arm/planner/status` against `arm/ground_truth/state` (contact of any arm part along the executed motion). The
learning and control nodes never see ground truth (`ground_truth_subscribers` lists who does).
Used by `make demo` (mm_bringup.arm_demo), the arm_reach benchmark and the graph tests.
"""
from __future__ import annotations

import re
import time
from collections import deque
from typing import Dict, List, Optional, Sequence

import numpy as np
import rclpy
from mm_msgs.msg import ArmGroundTruth, ControllerStatus
from mm_msgs.srv import PlaceObject, SetJointGoal
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from mm_bringup.process_graph import ProcessGraph

QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
P = ControllerStatus
GRID_SHAPE = (8, 12)
LATTICE = 7


def ns(t) -> int:
    return t.sec * 1_000_000_000 + t.nanosec


def truth_cell_map(scene, grid_limits: np.ndarray, shape, samples: int = LATTICE) -> np.ndarray:
    """(rows, cols) bool: some arm part overlaps the object somewhere on a samples x samples lattice of the cell."""
    rows, cols = shape
    step = (grid_limits[:, 1] - grid_limits[:, 0]) / np.array([rows, cols])
    frac = np.linspace(0.0, 1.0, samples)
    r, c, a, b = np.meshgrid(np.arange(rows), np.arange(cols), frac, frac, indexing='ij')
    q = grid_limits[:, 0] + np.stack([(r + a) * step[0], (c + b) * step[1]], -1)
    gaps = scene.part_clearances(q.reshape(-1, 2)).min(axis=1).reshape(rows, cols, -1)
    return np.any(gaps < 0.0, axis=2)


def free_path_exists(blocked: np.ndarray, start, goal) -> bool:
    """Breadth-first search over 4-connected free cells."""
    if blocked[start] or blocked[goal]:
        return False
    seen, todo = {tuple(start)}, deque([tuple(start)])
    while todo:
        r, c = todo.popleft()
        if (r, c) == tuple(goal):
            return True
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (r + dr, c + dc)
            if 0 <= n[0] < blocked.shape[0] and 0 <= n[1] < blocked.shape[1] and not blocked[n] and n not in seen:
                seen.add(n)
                todo.append(n)
    return False


def choose_placement(scene, joints: np.ndarray, shape, rng: np.random.Generator, tries: int = 200):
    """(object position, goal joints, start cell, goal cell, truth map) of a task with the object in the way, or
    None (module docstring, step 2). `scene` is the simulator's ArmModel; its object is moved here."""
    from mm_sim.arm_motion import sweep
    lim = scene.joint_limits
    step = (lim[:, 1] - lim[:, 0]) / np.array(shape)

    def cell_of(q):
        return tuple(int(v) for v in np.clip(np.floor((q - lim[:, 0]) / step), 0, np.array(shape) - 1))

    start = cell_of(joints)
    for _ in range(tries):
        position = scene.random_object_position(rng)
        scene.set_object_position(position)
        if scene.part_clearances(joints).min() <= 0.0:
            continue
        blocked = truth_cell_map(scene, lim, shape)
        if blocked[start]:
            continue
        free = [tuple(int(v) for v in c) for c in np.argwhere(~blocked)]
        for i in rng.permutation(len(free)):
            goal = free[i]
            if abs(goal[0] - start[0]) + abs(goal[1] - start[1]) < 3:
                continue
            goal_q = lim[:, 0] + (np.array(goal) + 0.5) * step
            if sweep(scene, joints, goal_q).any_contact and free_path_exists(blocked, start, goal):
                return np.asarray(position, float), goal_q, start, goal, blocked
    return None


class ArmGraphDriver:
    """The user and evaluator: one rclpy node (`name`) in a private context, spun by the calling thread. `nodes` are
    the graph's node processes: waiting stops with an error when one of them exits."""

    def __init__(self, name: str = 'arm_graph_driver', nodes: Sequence = ()):
        self.context = Context()
        rclpy.init(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = Node(name, context=self.context)
        self.nodes = list(nodes)
        self.executor.add_node(self.node)
        self.status: List[ControllerStatus] = []
        self.truth: Dict[int, ArmGroundTruth] = {}
        self.joints: Dict[int, np.ndarray] = {}
        self.node.create_subscription(ControllerStatus, 'arm/planner/status', self.status.append, QOS)
        self.node.create_subscription(ArmGroundTruth, 'arm/ground_truth/state',
                                      lambda m: self.truth.__setitem__(ns(m.header.stamp), m), QOS)
        self.node.create_subscription(JointState, 'arm/joint_states', lambda m: self.joints.__setitem__(
            ns(m.header.stamp), np.array(m.position)), QOS)
        self.place = self.node.create_client(PlaceObject, 'arm/place_object')
        self.set_goal = self.node.create_client(SetJointGoal, 'arm/set_goal')
        self.sim_params = self.node.create_client(SetParameters, 'arm_sim/set_parameters')

    def dead(self) -> List[str]:
        return [n.label for n in self.nodes if n.process is not None and n.process.poll() is not None]

    def spin_until(self, predicate, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if self.dead():
                raise RuntimeError(f'node(s) exited while waiting for {what}: {self.dead()}')
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.02)

    def call(self, client, request, timeout: float = 30.0):
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'service {client.srv_name} not available')
        future = client.call_async(request)
        self.spin_until(future.done, timeout, client.srv_name)
        return future.result()

    def set_sim_parameter(self, name: str, value: str) -> None:
        req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=value))])
        result = self.call(self.sim_params, req).results[0]
        if not result.successful:
            raise RuntimeError(f'arm_sim refused {name}={value}: {result.reason}')

    def phase(self) -> Optional[int]:
        return self.status[-1].phase if self.status else None

    def learn(self, timeout: float) -> float:
        """Wait until the planner has explored and received its first map (WAITING_FOR_GOAL), then have arm_sim place
        the object on request only. Returns the wall seconds it took."""
        t0 = time.monotonic()
        self.spin_until(lambda: self.phase() == P.PHASE_WAITING_FOR_GOAL, timeout, 'exploration and the first fit')
        self.set_sim_parameter('object_mode', 'on_request')
        return time.monotonic() - t0

    def run_placement(self, scene, seed: int, timeout: float) -> Dict[str, object]:
        """One held-out placement with the object in the way (module docstring); the result or {'skipped': why}."""
        return run_placement(self, scene, GRID_SHAPE, seed, timeout)

    def ground_truth_subscribers(self) -> Dict[str, List[str]]:
        out = {}
        for topic, _ in self.node.get_topic_names_and_types():
            if 'ground_truth' in topic:
                out[topic] = sorted(i.node_name for i in self.node.get_subscriptions_info_by_topic(topic))
        return out

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)


def run_placement(driver: ArmGraphDriver, scene, shape, seed: int, timeout: float) -> Dict[str, object]:
    t0 = time.monotonic()
    joints = driver.joints[max(driver.joints)]
    task = choose_placement(scene, joints, shape, np.random.default_rng(seed))
    if task is None:
        return dict(seed=seed, skipped='no placement with the object in the way and a contact-free path')
    position, goal_q, start, goal, blocked = task
    reply = driver.call(driver.place, PlaceObject.Request(random=False, position=[float(v) for v in position]))
    if not reply.accepted:
        raise RuntimeError(f'arm_sim refused the placement {position.tolist()}: {reply.message}')
    placed = ns(reply.stamp)
    driver.spin_until(lambda: placed in driver.truth and placed in driver.joints, 30.0, 'the placement frame')
    reply = driver.call(driver.set_goal, SetJointGoal.Request(positions=[float(v) for v in goal_q]))
    if not reply.accepted:
        raise RuntimeError(f'dp_planner refused the goal {goal_q.tolist()}: {reply.message}')
    match = re.search(r'goal_stamp=(\d+)\.(\d{9})', reply.message)
    if match is None:
        raise RuntimeError(f'dp_planner did not say the goal stamp: {reply.message!r}')
    goal_stamp = int(match.group(1)) * 1_000_000_000 + int(match.group(2))

    def outcome():
        for s in driver.status:
            if ns(s.goal_stamp) == goal_stamp and s.phase in (P.PHASE_GOAL_REACHED, P.PHASE_FAILED):
                return s
        return None

    driver.spin_until(lambda: outcome() is not None, timeout, f'the outcome of placement seed {seed}')
    final = outcome()
    last = max(driver.joints)
    driver.spin_until(lambda: last in driver.truth, 10.0, 'the ground truth of the last frame')
    moved = [driver.truth[s] for s in sorted(driver.truth) if placed < s <= last]
    executing = [s for s in driver.status if ns(s.goal_stamp) == goal_stamp and s.phase == P.PHASE_EXECUTING]
    plan_detail = executing[0].detail if executing else final.detail
    # the frames the planner had of the new placement before it moved: up to the one it planned on (its status is
    # stamped with the sim time of that frame; in lockstep no newer frame exists before its first command)
    planned_on = ns(executing[0].header.stamp) if executing else last
    contact_frames = [t for t in moved if t.link_contact]
    reached = final.phase == P.PHASE_GOAL_REACHED
    return dict(
        seed=seed, object_position=position.round(2).tolist(), start_cell=list(start), goal_cell=list(goal),
        goal=goal_q.round(4).tolist(), truth_blocked_cells=int(blocked.sum()), reached=reached,
        contact=bool(contact_frames), success=reached and not contact_frames, outcome=final.phase_name,
        detail=final.detail, plan=plan_detail, goal_stamp=goal_stamp, placement_stamp=placed,
        executed_joints=[driver.joints[s].round(5).tolist() for s in sorted(driver.joints) if placed < s <= last],
        contact_frames=len(contact_frames), contact_parts=sorted({p for t in contact_frames for p in t.contact_parts}),
        min_link_clearance_px=float(min(t.min_link_clearance for t in moved)) if moved else None,
        min_hand_object_distance_px=float(min(t.min_hand_object_distance for t in moved)) if moved else None,
        steps=len(moved), new_frames=len([s for s in driver.joints if placed <= s <= planned_on]),
        final_joints=driver.joints[last].round(4).tolist(), wall_s=round(time.monotonic() - t0, 2))


def start_arm_sim(graph: ProcessGraph, scene_seed: int, object_period_frames: int = 10):
    """arm_sim in lockstep, the object re-placed every `object_period_frames` frames (exploration; the driver's
    `learn` switches it to placing on request)."""
    return graph.start('mm_sim', 'arm_sim', dict(lockstep=True, object_seed=scene_seed, object_mode='every_n_frames',
                                                object_period_frames=object_period_frames,
                                                placement_seed=scene_seed))


def start_learning_nodes(graph: ProcessGraph, seed: int, exploration_steps: int,
                         embedding_params: Optional[Dict] = None, planner_params: Optional[Dict] = None) -> list:
    """image_embedding (one fit after `exploration_steps` frames, kept) and dp_planner (exploring that many)."""
    return [graph.start('mm_manifold', 'image_embedding', dict(
                use_sim_time=True, min_training_frames=exploration_steps,
                max_training_frames=max(exploration_steps, 1500), refit_every=0, random_seed=seed,
                **(embedding_params or {}))),
            graph.start('mm_planner', 'dp_planner', dict(
                use_sim_time=True, exploration_steps=exploration_steps, exploration_seed=seed,
                **(planner_params or {})))]


def start_arm_graph(graph: ProcessGraph, scene_seed: int, exploration_steps: int, object_period_frames: int = 10,
                    embedding_params: Optional[Dict] = None, planner_params: Optional[Dict] = None) -> list:
    """arm_sim + image_embedding + dp_planner (start_arm_sim, start_learning_nodes)."""
    return [start_arm_sim(graph, scene_seed, object_period_frames),
            *start_learning_nodes(graph, scene_seed, exploration_steps, embedding_params, planner_params)]
