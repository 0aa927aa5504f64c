"""Arm reach through the ROS graph (results/arm_reach.json): paper Section 3.3 as a user would run it, with a model
learned once and kept, and object placements it has never seen (mm_bringup.arm_graph does the driving).

1. Exploration and fit, once: arm_sim (lockstep) + image_embedding + dp_planner as processes; dp_planner explores
   `exploration_steps` frames while arm_sim re-places the object every `object_period_frames` frames (the model sees
   many object places, as in the paper); image_embedding fits once and keeps that model.
2. Held-out placements: arm_sim then places the object on request only. Per placement seed (PLACEMENT_SEED0 + 1,
   + 2, ...: never used for tuning anything; the planner's and learner's defaults were chosen on other seeds), the
   driver draws an object place and a goal on the simulator's scene model (ground truth chooses the task only): the
   object clear of the arm where it stands, the arm's cell and the goal cell free on the ground-truth cell map (no
   arm part - upper link, forearm, hand - touches the object anywhere on a 7x7 lattice of the cell), a contact-free
   4-connected cell path between them, and the straight joint-space move to the goal touching the object.
3. Scoring, independent of the planner: success = GOAL_REACHED (the outcome that names the goal's stamp) and no
   contact of any arm part anywhere along the executed motion (arm/ground_truth/state, checked along the motion
   between frames). New frames per placement = frames of the new placement the planner had before its first move.
   Plan failures are listed with the planner's reason.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from mm_bringup.arm_graph import ArmGraphDriver, start_arm_graph
from mm_bringup.process_graph import ProcessGraph
from mm_planner.arm_agent import EXPLORATION_STEPS

NAME = 'arm_reach'
SCENE_SEED = 7                    # textures and background; the exploration's object places follow it
PLACEMENT_SEED0 = 70_000          # held-out placements: seeds 70001, 70002, ...


def run(output_dir: Path, quick: bool, placements: Optional[int] = None, exploration_steps: Optional[int] = None,
        object_period_frames: int = 10, budget_s: float = 840.0, scene_seed: int = SCENE_SEED,
        placement_seed0: int = PLACEMENT_SEED0, planner_params: Optional[Dict] = None,
        embedding_params: Optional[Dict] = None) -> dict:
    """The benchmark (module docstring); mm_bringup.tune_arm_reach calls it with seeds of its own."""
    from mm_sim.arm_model import ArmModel
    n_placements = placements or (4 if quick else 30)
    n_explore = exploration_steps or (300 if quick else EXPLORATION_STEPS)
    t_start = time.monotonic()
    deadline = t_start + budget_s
    scene = ArmModel(random_state=scene_seed)
    out: Dict[str, object] = dict(
        ran_through_graph='arm_sim + image_embedding + dp_planner as processes, lockstep; driver = this process',
        scene_seed=scene_seed, placement_seeds_from=placement_seed0 + 1, exploration_steps=n_explore,
        exploration_object_period_frames=object_period_frames, planner_params=dict(planner_params or {}),
        embedding_params=dict(embedding_params or {}))
    results: List[Dict[str, object]] = []
    skipped = []
    with ProcessGraph(log_dir=Path(output_dir) / 'tmp' / 'arm_reach_logs') as graph:      # results/tmp: not kept
        nodes = start_arm_graph(graph, scene_seed, n_explore, object_period_frames, embedding_params, planner_params)
        driver = ArmGraphDriver('arm_reach_driver', nodes)
        try:
            out['learn_s'] = round(driver.learn(max(60.0, deadline - time.monotonic() - 60)), 1)
            out['exploration_frames'] = len(driver.joints)
            out['exploration_placements'] = len({t.placement for t in driver.truth.values()})
            seed = placement_seed0
            while len(results) < n_placements and time.monotonic() < deadline - 20:
                seed += 1
                r = driver.run_placement(scene, seed, min(120.0, deadline - time.monotonic()))
                if 'skipped' in r:
                    skipped.append(r)
                    continue
                results.append(r)
                print(f"[arm_reach] {len(results)}/{n_placements} seed {seed}: "
                      f"{'ok' if r['success'] else 'FAIL'} {r['outcome']} contact={r['contact']} "
                      f"steps={r['steps']} new_frames={r['new_frames']} ({r['wall_s']} s) {r['detail']}", flush=True)
            out['ground_truth_subscribers'] = driver.ground_truth_subscribers()
        finally:
            driver.close()
        out['node_exit_codes'] = graph.stop_all()
    n = len(results)
    new_frames = [r['new_frames'] for r in results]
    out.update(
        placements=n, placements_requested=n_placements, skipped_seeds=len(skipped),
        success_rate=sum(r['success'] for r in results) / max(n, 1),
        reached=sum(r['reached'] for r in results), contacts=sum(r['contact'] for r in results),
        contact_frames=sum(r['contact_frames'] for r in results),
        plan_failures=[dict(seed=r['seed'], reason=r['detail']) for r in results if r['outcome'] == 'FAILED'],
        failures=[dict(seed=r['seed'], outcome=r['outcome'], detail=r['detail'], contact=r['contact'],
                       contact_parts=r['contact_parts']) for r in results if not r['success']],
        new_frames_per_placement=dict(max=max(new_frames, default=None),
                                      mean=float(np.mean(new_frames)) if n else None),
        min_link_clearance_px=min((r['min_link_clearance_px'] for r in results
                                   if r['min_link_clearance_px'] is not None), default=None),
        median_steps=float(np.median([r['steps'] for r in results])) if n else None,
        median_placement_s=float(np.median([r['wall_s'] for r in results])) if n else None,
        wall_s=round(time.monotonic() - t_start, 1), targets=dict(success_rate=0.98, contacts=0),
        per_placement=results)
    return out
