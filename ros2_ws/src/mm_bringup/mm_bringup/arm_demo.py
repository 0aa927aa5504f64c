"""The arm experiment through the ROS graph (paper Section 3): exploration with random arm motion, online learning of
the image embedding and collision map, then DP planning to a goal with the object in the way.

`run_arm_demo(graph, log, timeout_s)` starts arm_sim (lockstep) + image_embedding + dp_planner in an existing
ProcessGraph (a recorder may already be running in it), waits for the planner to finish learning, sends a goal,
waits for GOAL_REACHED or FAILED, stops the three nodes and returns a summary. The driver here plays the user: it
picks the goal with the simulator's own scene model (ground truth is fine for choosing a demo goal; no learning or
control node sees it) so that the straight joint-space move from where the arm stands would touch the object while a
contact-free way around exists.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional

import numpy as np
from mm_common.testing import RosHarness
from mm_msgs.msg import ArmGroundTruth, Contact, ControllerStatus
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from mm_bringup.process_graph import ProcessGraph

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
P = ControllerStatus


def choose_demo_goal(seed: int, joints, rng: Optional[np.random.Generator] = None):
    """Goal joints (a cell centre) such that the straight move from the current cell's centre touches the object
    and a contact-free cell path exists (ground truth, for choosing the task only). Returns (goal, object_in_way)."""
    from mm_bringup.bench.arm_task import free_path_exists, truth_cell_map
    from mm_planner.value_iteration import JointGrid
    from mm_sim.arm_model import ArmModel
    from mm_sim.arm_motion import swept_contact
    model = ArmModel(random_state=seed)
    grid = JointGrid(*model.joint_limits)
    blocked = truth_cell_map(model, grid)
    start = grid.cell_of(joints)
    # The arm stands in its cell without touching the object, so that cell is passable for the path check even when
    # the object reaches into another part of it (the lattice ground truth then marks the whole cell blocked).
    blocked[start] = blocked[start] and model.in_contact(joints)
    rng = rng or np.random.default_rng(seed)
    free = [tuple(int(v) for v in c) for c in np.argwhere(~blocked)]
    order = rng.permutation(len(free))
    fallback = None
    for i in order:
        g = free[i]
        if abs(g[0] - start[0]) + abs(g[1] - start[1]) < 3 or not free_path_exists(blocked, start, g):
            continue
        if swept_contact(model, grid.centre(start), grid.centre(g)):
            return grid.centre(g), True
        fallback = fallback or g
    if fallback is None:
        raise RuntimeError(f'no reachable goal cell from {start} for object seed {seed}')
    return grid.centre(fallback), False


def _stamps(messages) -> set:
    return {(m.header.stamp.sec, m.header.stamp.nanosec) for m in messages}


def run_arm_demo(graph: ProcessGraph, log: Callable[[str], None] = print, timeout_s: float = 170.0,
                 object_seed: int = 3, exploration_steps: int = 500,
                 embedding_params: Optional[Dict] = None) -> Dict:
    """Run the arm experiment in `graph` (module docstring). Summary keys: reached, phase, detail, contact_count
    (frames with a touch-sensor contact after the goal was sent), link_contact_steps (frames after the goal was
    sent whose motion touched the object with any part, ground truth), steps (simulator steps in total),
    execution_steps, exploration_steps, exploration_contact_frames, min_hand_object_distance_px (along the motion
    while executing, ground truth), goal, object_in_way, learn_s, total_s, ground_truth_subscribers (topic -> subscribing node names, taken while
    all nodes run: only evaluation tools such as the recorder may appear). `embedding_params` are extra parameters
    of image_embedding (e.g. model_path)."""
    t_start = time.monotonic()
    deadline = t_start + timeout_s
    ros = RosHarness()
    nodes = []
    # Frames are counted once by stamp: the lockstep simulator re-sends its last step while it waits for a command.
    seen = dict(status=[], joints=[], contact=set(), exec_contact=set(), distances=[], link_contact=set())
    state = dict(executing=False)
    try:
        node = ros.node('arm_demo_driver')
        node.create_subscription(ControllerStatus, 'arm/planner/status', seen['status'].append, QOS)
        node.create_subscription(JointState, 'arm/joint_states', seen['joints'].append, QOS)

        def on_contact(msg: Contact) -> None:
            if msg.in_contact:
                stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
                seen['contact'].add(stamp)
                if state['executing']:
                    seen['exec_contact'].add(stamp)

        def on_truth(msg: ArmGroundTruth) -> None:
            if state['executing']:
                seen['distances'].append(msg.min_hand_object_distance)
                if msg.link_contact:
                    seen['link_contact'].add((msg.header.stamp.sec, msg.header.stamp.nanosec))

        node.create_subscription(Contact, 'arm/contact', on_contact, QOS)
        node.create_subscription(ArmGroundTruth, 'arm/ground_truth/state', on_truth, QOS)
        goal_pub = node.create_publisher(Float64MultiArray, 'arm/goal', LATCHED)
        sim_args = dict(lockstep=True, object_seed=object_seed, republish_period=0.5)
        common = dict(use_sim_time=True)
        nodes.append(graph.start('mm_sim', 'arm_sim', sim_args))
        if any(n.label == 'recorder' and n.process.poll() is None for n in graph.nodes):
            # A recorder runs in this graph: let it subscribe to the camera loop before the loop starts, so the
            # bag holds every frame the learner sees (the simulator re-publishes step 0 until the first command).
            loop_topics = ['/arm/camera/image_raw', '/arm/joint_states', '/arm/contact']
            if not ros.spin_until(lambda: all(any(i.node_name == 'recorder' for i in
                                                  node.get_subscriptions_info_by_topic(t)) for t in loop_topics),
                                  timeout=30.0):
                log('[arm_demo] warning: the recorder has not subscribed to the camera loop after 30 s')
        nodes.append(graph.start('mm_manifold', 'image_embedding', dict(
            common, min_training_frames=exploration_steps, refit_every=0, random_seed=object_seed,
            **(embedding_params or {}))))
        nodes.append(graph.start('mm_planner', 'dp_planner', dict(
            common, exploration_steps=exploration_steps, exploration_seed=object_seed)))
        log(f'[arm_demo] exploring {exploration_steps} steps with object seed {object_seed} ...')

        def phase():
            return seen['status'][-1].phase if seen['status'] else None

        def dead():
            return [n.label for n in nodes if n.process.poll() is not None]

        t_explore = time.monotonic()
        while phase() not in (P.PHASE_WAITING_FOR_GOAL, P.PHASE_FAILED):
            if dead():
                raise RuntimeError(f'node(s) exited: {dead()}\n' + '\n'.join(graph.log_tail(n) for n in nodes))
            if time.monotonic() > deadline:
                raise TimeoutError(f'learning did not finish in {timeout_s:.0f} s (phase {phase()})\n'
                                   + graph.log_tail(nodes[1]))
            ros.executor.spin_once(timeout_sec=0.05)
        learn_s = time.monotonic() - t_explore
        gt_subscribers = {}
        for topic, _types in node.get_topic_names_and_types():
            if 'ground_truth' in topic:
                gt_subscribers[topic] = sorted(i.node_name for i in node.get_subscriptions_info_by_topic(topic))
        joints_now = np.array(seen['joints'][-1].position)
        goal, in_way = choose_demo_goal(object_seed, joints_now)
        log(f'[arm_demo] learned in {learn_s:.1f} s; goal {np.round(goal, 3).tolist()} from '
            f'{np.round(joints_now, 3).tolist()} (object in the way: {in_way})')
        n_joints_before = len(seen['joints'])
        state['executing'] = True
        goal_pub.publish(Float64MultiArray(data=[float(v) for v in goal]))
        while phase() not in (P.PHASE_GOAL_REACHED, P.PHASE_FAILED):
            if dead():
                raise RuntimeError(f'node(s) exited: {dead()}')
            if time.monotonic() > deadline:
                raise TimeoutError(f'goal not reached in time (phase {phase()})\n' + graph.log_tail(nodes[2]))
            ros.executor.spin_once(timeout_sec=0.05)
        ros.spin_for(0.2)          # the last step's contact / distance messages
        final = seen['status'][-1]
        summary = dict(
            reached=final.phase == P.PHASE_GOAL_REACHED, phase=final.phase_name, detail=final.detail,
            contact_count=len(seen['exec_contact']), link_contact_steps=len(seen['link_contact']),
            exploration_contact_frames=len(seen['contact'] - seen['exec_contact']),
            steps=len(_stamps(seen['joints'])),
            execution_steps=len(_stamps(seen['joints'][n_joints_before:]) - _stamps(seen['joints'][:n_joints_before])),
            exploration_steps=exploration_steps,
            min_hand_object_distance_px=float(min(seen['distances'])) if seen['distances'] else None,
            goal=[float(v) for v in goal], object_in_way=bool(in_way), object_seed=object_seed,
            learn_s=round(learn_s, 2), total_s=round(time.monotonic() - t_start, 2),
            ground_truth_subscribers=gt_subscribers)
        log(f"[arm_demo] {summary['phase']}: {summary['detail']}; contacts while executing: "
            f"{summary['contact_count']}, {summary['execution_steps']} steps")
        return summary
    finally:
        for n in reversed(nodes):
            graph.stop(n)
        ros.close()
