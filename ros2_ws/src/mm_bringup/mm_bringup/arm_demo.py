"""The arm experiment through the ROS graph (paper Section 3): exploration with random arm motion while the object is
moved around, online learning of the image embedding (kept afterwards), then reaches with the object re-placed where
the model never saw it and in the way, each planned before moving on a collision map of the current frame.

`run_arm_demo(graph, log, timeout_s)` starts arm_sim (lockstep) + image_embedding + dp_planner in an existing
ProcessGraph (a recorder may already be running in it) through mm_bringup.arm_graph, waits for the planner to finish
learning, runs `placements` re-placements (object place and goal drawn on the simulator's scene model: ground truth
chooses the demo task only, no learning or control node sees it), stops the three nodes and returns a summary.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional

from mm_bringup.arm_graph import ArmGraphDriver, start_arm_sim, start_learning_nodes
from mm_bringup.bench.arm_reach import SCENE_SEED
from mm_bringup.process_graph import ProcessGraph

LOOP_TOPICS = ('/arm/camera/image_raw', '/arm/joint_states', '/arm/contact')


def _smallest(values):
    """Smallest of the values that are not None (None when the arm never moved)."""
    return min((v for v in values if v is not None), default=None)


def run_arm_demo(graph: ProcessGraph, log: Callable[[str], None] = print, timeout_s: float = 170.0,
                 object_seed: int = SCENE_SEED, exploration_steps: int = 500, placements: int = 2,
                 object_period_frames: int = 10, embedding_params: Optional[Dict] = None) -> Dict:
    """Run the arm experiment in `graph` (module docstring). Summary keys: reached (every placement's goal),
    contact_count (frames after a goal whose motion touched the object with any arm part, ground truth),
    hand_contact_placements (placements whose executed motion touched the object with the hand, what the touch
    sensor feels), phase and detail (of the last placement),
    placements (per placement: outcome, detail, plan, steps, new_frames, contact, clearance), execution_steps,
    new_frames (most frames of a new placement seen before moving), min_hand_object_distance_px, min_link_clearance_px
    (along the executed motions), exploration_steps, exploration_contact_frames (touch readings while exploring),
    exploration_placements, object_in_way (every goal needed a way round), learn_s, total_s, ground_truth_subscribers
    (topic -> subscribing node names, taken while all nodes run: only evaluation tools may appear).
    successes (placements whose goal was reached without contact of any arm part), contact_placements (placements
    whose executed motion touched the object with some arm part).
    `embedding_params` are extra parameters of image_embedding (e.g. model_path). The default scene is the
    arm_reach benchmark's (README says why not scene 3, the one used before)."""
    from mm_sim.arm_model import ArmModel
    t_start = time.monotonic()
    deadline = t_start + timeout_s
    nodes = []
    driver = ArmGraphDriver('arm_demo_driver', nodes)
    try:
        if any(n.label == 'recorder' and n.process.poll() is None for n in graph.nodes):
            # A recorder runs in this graph: let it subscribe to the camera loop before the loop starts, so the
            # bag holds every frame the learner sees (the simulator re-sends step 0 until the first command).
            nodes.append(start_arm_sim(graph, object_seed, object_period_frames))
            try:
                driver.spin_until(lambda: all(any(i.node_name == 'recorder' for i in
                                                  driver.node.get_subscriptions_info_by_topic(t))
                                              for t in LOOP_TOPICS), 30.0, 'the recorder')
            except TimeoutError:
                log('[arm_demo] warning: the recorder has not subscribed to the camera loop after 30 s')
        else:
            nodes.append(start_arm_sim(graph, object_seed, object_period_frames))
        nodes.extend(start_learning_nodes(graph, object_seed, exploration_steps, embedding_params))
        driver.nodes = nodes
        log(f'[arm_demo] exploring {exploration_steps} steps, the object re-placed every {object_period_frames} '
            f'frames (scene seed {object_seed}) ...')
        learn_s = driver.learn(max(10.0, deadline - time.monotonic()))
        gt_subscribers = driver.ground_truth_subscribers()
        exploration_contacts = sum(t.hand_contact for t in driver.truth.values())
        exploration_placements = len({t.placement for t in driver.truth.values()})
        log(f'[arm_demo] learned in {learn_s:.1f} s; now the object is placed where the model never saw it')
        scene = ArmModel(random_state=object_seed)
        results = []
        seed = 1000 * object_seed
        while len(results) < placements and seed < 1000 * object_seed + 20:
            seed += 1
            r = driver.run_placement(scene, seed, max(5.0, deadline - time.monotonic()))
            if 'skipped' in r:
                continue
            results.append(r)
            log(f"[arm_demo] placement {len(results)}: object at {r['object_position']} px, goal cell "
                f"{r['goal_cell']} from {r['start_cell']}: {r['outcome']} ({r['detail']}); {r['new_frames']} "
                f"frame(s) of the new place before moving; {r['steps']} steps; contact: {r['contact']}")
        if not results:
            raise RuntimeError('no placement with the object in the way was found')
        last = results[-1]
        return dict(
            reached=all(r['reached'] for r in results), phase=last['outcome'], detail=last['detail'],
            successes=sum(r['success'] for r in results), contact_placements=sum(r['contact'] for r in results),
            contact_count=sum(r['contact_frames'] for r in results),
            hand_contact_placements=sum('hand' in r['contact_parts'] for r in results),
            placements=results, execution_steps=sum(r['steps'] for r in results),
            new_frames=max(r['new_frames'] for r in results),
            min_hand_object_distance_px=_smallest(r['min_hand_object_distance_px'] for r in results),
            min_link_clearance_px=_smallest(r['min_link_clearance_px'] for r in results),
            exploration_steps=exploration_steps, exploration_contact_frames=int(exploration_contacts),
            exploration_placements=exploration_placements,
            object_in_way=True, object_seed=object_seed, learn_s=round(learn_s, 2),
            total_s=round(time.monotonic() - t_start, 2), ground_truth_subscribers=gt_subscribers)
    finally:
        driver.close()
        for n in reversed(nodes):
            graph.stop(n)
