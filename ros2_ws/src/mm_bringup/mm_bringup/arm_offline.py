"""The arm agent without ROS: mm_planner.arm_agent.ArmAgent driven frame by frame on the simulator's plain modules
(mm_sim.arm_model.ArmModel + mm_sim.arm_motion.JointMotion), exactly as the dp_planner node drives it on arm_sim's
topics. The node and this runner share the agent, so offline experiments measure the code the graph runs.

`drive(agent, scene, motion, joints, ...)` feeds the agent one observation per frame (stamp, joints, the hand's
touch reading along the motion into the frame), forwards commands to the motion model, answers the agent's map
requests with `map_for_frame(stamp, joints)` (e.g. a learner's prediction from the rendered frame), calls `learn()`
when the agent waits for its first map (both return a map as (collision, closeness or None, blocked_moves or None),
what a CollisionMap carries), and stops when the agent sends nothing and has nothing left to wait for.
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from mm_planner.arm_agent import (PHASE_EXECUTING, PHASE_FAILED, PHASE_GOAL_REACHED, PHASE_LEARNING,
                                  PHASE_WAITING_FOR_GOAL, ArmAgent, ArmObservation)

MapParts = Tuple[np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]      # collision, closeness, blocked_moves


def drive(agent: ArmAgent, scene, motion, joints: Sequence[float], stamp: int = 0, dt_ns: int = 100_000_000,
          contact: bool = False, goal: Optional[Sequence[float]] = None, goal_stamp: Optional[int] = None,
          learn: Optional[Callable[[], MapParts]] = None,
          map_for_frame: Optional[Callable[[int, np.ndarray], MapParts]] = None, max_frames: int = 5000,
          on_frame: Optional[Callable[[int, np.ndarray, np.ndarray], None]] = None) -> Dict[str, object]:
    """Run until the agent stops commanding (module docstring). `goal` is set once the agent waits for one
    (WAITING_FOR_GOAL), as a user does; call again with the returned joints, stamp and contact to continue. `on_frame(stamp, q_before, q_after)` is
    called for every simulated motion (for evaluation, e.g. ground-truth contact along it).
    Returns commands (list of arrays), frames (stamps observed), joints (final), stamp (last frame), phase, detail,
    goal_stamp, map_requests."""
    q = np.asarray(joints, dtype=float)
    commands: List[np.ndarray] = []
    frames: List[int] = []
    requests: List[int] = []
    goal_sent = goal is None
    for _ in range(max_frames):
        frames.append(stamp)
        observation = ArmObservation(stamp, q, bool(contact))
        command = None
        for _attempt in range(6):              # the node acts again on a frame when an event arrives for it
            if not goal_sent and agent.phase_ == PHASE_WAITING_FOR_GOAL:
                agent.set_goal(goal, stamp if goal_stamp is None else goal_stamp)
                goal_sent = True
            command = agent.step(observation)
            request = agent.take_map_request()
            if command is not None:
                break
            if not goal_sent and agent.phase_ == PHASE_WAITING_FOR_GOAL:
                continue
            if agent.phase_ == PHASE_LEARNING and learn is not None:
                collision, closeness, moves = learn()
                agent.set_map(collision, closeness, stamp, moves)
            elif request is not None and map_for_frame is not None:
                requests.append(request)
                collision, closeness, moves = map_for_frame(request, q)
                agent.set_map(collision, closeness, request, moves)
            else:
                break
        if command is None:
            break
        commands.append(np.asarray(command, dtype=float).copy())
        new, contact = motion.step(q, command)
        if on_frame is not None:
            on_frame(stamp + dt_ns, q, new)
        q = new
        stamp += dt_ns
    return dict(commands=commands, frames=frames, joints=q, stamp=stamp, contact=bool(contact),
                phase=agent.phase_, phase_name=agent.phase_name, detail=agent.detail_, goal_stamp=agent.goal_stamp_,
                map_requests=requests, finished=agent.phase_ in (PHASE_GOAL_REACHED, PHASE_FAILED),
                executing=agent.phase_ == PHASE_EXECUTING)
