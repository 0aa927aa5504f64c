"""One agent, two drivers: the same ArmAgent run offline (mm_bringup.arm_offline on ArmModel + JointMotion) and through
the nodes (arm_sim + dp_planner in one process, own Context) on one seed gives the same commands, frame by frame:
exploration, the wait for learning, the goal, the map request of the current frame, and the planned reach around
the object. The test plays image_embedding's part with one fixed map (the simulator's ground-truth cell map), the
same for both drivers, with the moves between cell centres that touch the object (blocked_moves, in the message's
layout for the node), so only the drivers differ."""
import numpy as np
from mm_common.ros_harness import RosHarness
from mm_msgs.msg import CollisionMap, ControllerStatus
from mm_msgs.srv import SetJointGoal
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header

from mm_bringup.arm_offline import drive
from mm_bringup.arm_graph import free_path_exists, truth_cell_map
from mm_manifold.arm_learning import move_hits
from mm_planner.arm_agent import ArmAgent
from mm_planner.dp_planner_node import DpPlannerNode
from mm_sim.arm_model import ArmModel
from mm_sim.arm_motion import JointMotion
from mm_sim.arm_sim_node import ArmSim

SEED = 11
EXPLORATION = 40
START = (-2.0, 1.1)
QOS = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
P = ControllerStatus


def truth_moves(scene, resolution=4):
    """(4, 8, 12): the moves between cell centres on which some arm part touches the object."""
    lo, hi = scene.joint_limits[:, 0], scene.joint_limits[:, 1]
    axes = [np.linspace(lo[k], hi[k], n * resolution + 1) for k, n in enumerate((8, 12))]
    lattice = np.stack(np.meshgrid(*axes, indexing='ij'), -1)
    hit = scene.part_clearances(lattice.reshape(-1, 2)).min(axis=1).reshape(lattice.shape[:2]) < 0.0
    return move_hits(hit, (8, 12), resolution)


def offline(goal=None):
    scene = ArmModel(random_state=SEED)
    agent = ArmAgent(scene.joint_limits, exploration_steps=EXPLORATION, exploration_seed=SEED)
    blocked, moves = truth_cell_map(scene, scene.joint_limits, (8, 12)), truth_moves(scene)
    learned = drive(agent, scene, JointMotion(scene), START, learn=lambda: (blocked, None, moves))
    if goal is None:
        return learned, scene, blocked, moves
    reach = drive(agent, scene, JointMotion(scene), learned['joints'], stamp=learned['stamp'],
                  contact=learned['contact'], goal=goal, map_for_frame=lambda stamp, q: (blocked, None, moves))
    return learned, reach


def test_node_and_offline_runner_give_the_same_commands():
    learned, scene, blocked, moves = offline()
    assert learned['phase_name'] == 'WAITING_FOR_GOAL' and len(learned['commands']) == EXPLORATION
    lim = scene.joint_limits
    step = (lim[:, 1] - lim[:, 0]) / np.array([8, 12])
    start = tuple(int(v) for v in np.clip(np.floor((learned['joints'] - lim[:, 0]) / step), 0, [7, 11]))
    reachable = [tuple(c) for c in np.argwhere(~blocked) if free_path_exists(blocked, start, tuple(c))]
    far = max(reachable, key=lambda c: abs(c[0] - start[0]) + abs(c[1] - start[1]))
    grid_goal = lim[:, 0] + (np.array(far) + 0.5) * step
    _, reach = offline(grid_goal)
    offline_commands = learned['commands'] + reach['commands']
    assert reach['phase_name'] == 'GOAL_REACHED', reach['detail']

    ros = RosHarness()
    try:
        ros.add(ArmSim(context=ros.context, parameter_overrides=[
            Parameter('object_seed', value=SEED), Parameter('initial_joints', value=list(START)),
            Parameter('republish_period', value=0.5)]))
        ros.add(DpPlannerNode(context=ros.context, parameter_overrides=[
            Parameter('exploration_steps', value=EXPLORATION), Parameter('exploration_seed', value=SEED),
            Parameter('wait_for_embedding', value=False)]))
        client = ros.node('drivers_test_client')
        commands, status, requests, frames = [], [], [], []
        client.create_subscription(JointState, 'arm/joint_states', frames.append, QOS)
        client.create_subscription(Float64MultiArray, 'arm/joint_position_controller/commands', commands.append, QOS)
        client.create_subscription(ControllerStatus, 'arm/planner/status', status.append, QOS)
        client.create_subscription(Header, 'arm/embedding/map_request', requests.append, QOS)
        map_pub = client.create_publisher(CollisionMap, 'arm/embedding/collision_map', LATCHED)
        set_goal = client.create_client(SetJointGoal, 'arm/set_goal')

        def send_map(stamp):
            m = CollisionMap(rows=8, cols=12, joint0_limits=list(lim[0]), joint1_limits=list(lim[1]),
                             collision=[bool(v) for v in blocked.ravel()],
                             blocked_moves=[bool(v) for v in moves.transpose(1, 2, 0).ravel()])
            m.header.stamp = stamp
            map_pub.publish(m)

        def phase():
            return status[-1].phase if status else None

        assert ros.spin_until(lambda: phase() == P.PHASE_LEARNING, timeout=60), [s.detail for s in status[-3:]]
        send_map(frames[-1].header.stamp)            # as image_embedding does: a map of the newest frame
        assert ros.spin_until(lambda: phase() == P.PHASE_WAITING_FOR_GOAL, timeout=10)
        future = set_goal.call_async(SetJointGoal.Request(positions=[float(v) for v in grid_goal]))
        assert ros.spin_until(future.done, timeout=10) and future.result().accepted
        answered = 0

        def done():
            nonlocal answered
            if len(requests) > answered:          # play image_embedding: a map of the requested frame
                send_map(requests[answered].stamp)
                answered += 1
            return phase() in (P.PHASE_GOAL_REACHED, P.PHASE_FAILED)

        assert ros.spin_until(done, timeout=60)
        node_commands = [np.array(c.data) for c in commands]
        assert len(node_commands) == len(offline_commands)
        np.testing.assert_allclose(np.array(node_commands), np.array(offline_commands), atol=1e-12)
        assert phase() == P.PHASE_GOAL_REACHED
        assert len(requests) == len(reach['map_requests'])
    finally:
        ros.close()
