"""Arm benchmark (results/arm_task.json): paper Section 3 measured on the simulated arm.

Parts and where they run:
- Tables 1-2 (held-out collision prediction, LLE vs PCA): plain modules in this process
  (mm_manifold.arm_evaluation: random joint configurations with a contact-biased share, 70/30 split). Everything
  that is tuned - LLE's n_neighbors, the region's radius / threshold, the region model - is chosen by 5-fold
  cross-validation on the 70 % training frames; the 30 % held-out frames only score the result. Keys:
  `lle_*` / `pca_*` the region model chosen by cross-validation (`*_region`), `lle_sphere_*` / `pca_sphere_*` the
  paper's sphere (centre = mean of the contact frames), `*_ellipsoid_*` the Mahalanobis ellipsoid, `*_quadric_*`
  the quadric fitted by logistic regression; each with its own cross-validated n_neighbors and radius, and the
  cross-validation estimate (`*_cv_tpr`, `*_cv_fpr`) next to the held-out rates.
- Synthetic check (Section 3.4): plain modules; |Spearman| of the best LLE coordinate with hand-object distance.
- DP success over random object placements: plain modules in this process, the same code the nodes run
  (mm_planner.arm_exploration explorer -> mm_sim.arm_motion joint motion -> ArmModel frames -> SIFT ->
  mm_manifold.arm_learning.ArmStateLearner collision and closeness maps -> mm_planner.value_iteration.DPPlanner with
  its default clearance reward, executed cell by cell). A placement counts when a contact-free path between the
  chosen start and goal exists on the ground-truth cell map and the straight joint-space move between them would
  touch the object ("object in the way"). Success = the goal cell centre is reached and the hand never touches the
  object, checked on the swept motion of every simulator step every 0.02 rad (stricter than arm_sim's touch sensor,
  which reads the pose of each frame; that reading is counted too, `dp_sim_contact_count`). The learner's contact
  region is chosen per placement by cross-validation on the exploration frames (`dp_region_counts`).
- Full mode also runs one episode through the ROS graph (arm_sim + image_embedding + dp_planner as processes, see
  mm_bringup.arm_demo) and reports it under `graph_episode`.
"""
from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np
from scipy.stats import spearmanr
from threadpoolctl import threadpool_limits

from mm_manifold.arm_evaluation import evaluate_collision_prediction
from mm_manifold.arm_learning import ArmStateLearner
from mm_manifold.embedding import REGION_MODELS, ImageEmbedding, synthetic_keypoint_frames
from mm_manifold.keypoints import KeypointExtractor, KeypointVectorizer
from mm_planner.arm_exploration import ArmExplorer
from mm_planner.value_iteration import DPPlanner, JointGrid
from mm_sim.arm_model import ArmModel
from mm_sim.arm_motion import JointMotion, swept_contact

NAME = 'arm_task'
START_JOINTS = (-2.0, 1.1)


# --- shared helpers (also used by the figures) -------------------------------------------------------------------
def explore(model: ArmModel, n_frames: int, seed: int, motion: Optional[JointMotion] = None,
            start=START_JOINTS) -> Tuple[np.ndarray, np.ndarray]:
    """Joint angles and touch-sensor readings (contact in the pose of each frame) of `n_frames` exploration steps,
    exactly as dp_planner drives arm_sim during its exploration phase."""
    motion = motion or JointMotion(model)
    explorer = ArmExplorer(model.joint_limits, random_state=seed)
    q = np.asarray(start, dtype=float)
    joints, contact = [], []
    for _ in range(n_frames):
        c = model.in_contact(q)
        joints.append(q.copy())
        contact.append(c)
        q, _ = motion.step(q, explorer.next_command(q, c))
    return np.array(joints), np.array(contact)


def truth_cell_map(model: ArmModel, grid: JointGrid, samples: int = 7) -> np.ndarray:
    """Ground truth: a cell is blocked if the hand touches the object anywhere on a samples x samples lattice
    covering the cell (evaluation only)."""
    blocked = np.zeros(grid.shape, bool)
    frac = np.linspace(0.0, 1.0, samples)
    for r in range(grid.rows):
        for c in range(grid.cols):
            lo = grid.limits[:, 0] + np.array([r, c]) * grid.step
            blocked[r, c] = any(model.in_contact(lo + np.array([a, b]) * grid.step) for a in frac for b in frac)
    return blocked


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


def choose_task(model: ArmModel, grid: JointGrid, blocked: np.ndarray, rng: np.random.Generator,
                tries: int = 400):
    """Start and goal cells, both free, with a contact-free path between them and the object in the way of the
    straight move; None if no such pair was found."""
    free = np.argwhere(~blocked)
    for _ in range(tries):
        s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
        if abs(s[0] - g[0]) + abs(s[1] - g[1]) < 3:
            continue
        if swept_contact(model, grid.centre(s), grid.centre(g)) and free_path_exists(blocked, s, g):
            return s, g
    return None


def execute_plan(model: ArmModel, grid: JointGrid, planner: DPPlanner, start, goal, motion: JointMotion,
                 max_steps: int = 400, tolerance: float = 1e-6) -> Dict[str, object]:
    """Follow the planner from the start cell centre cell by cell, as dp_planner does: command the centre of the
    next cell, step the arm until it is there, repeat until at the goal cell centre. Contact is checked on the swept
    motion of every step."""
    planner.set_goal(goal)
    q = grid.centre(start)
    touched, touched_at_frame, steps, trajectory = False, False, 0, [q.copy()]
    target = q
    while steps < max_steps:
        cell = grid.cell_of(q)
        if np.max(np.abs(q - target)) <= tolerance:
            if cell == tuple(goal):
                break
            nxt = planner.next_cell(cell)
            if nxt is None:
                break
            target = grid.centre(nxt)
        new = motion.step(q, target)[0]
        touched |= swept_contact(model, q, new, 0.02)
        touched_at_frame |= model.in_contact(new)
        q = new
        trajectory.append(q.copy())
        steps += 1
    reached = grid.cell_of(q) == tuple(goal) and np.max(np.abs(q - grid.centre(goal))) <= 1e-6
    return dict(reached=bool(reached), contact=bool(touched), contact_at_frames=bool(touched_at_frame), steps=steps,
                trajectory=np.array(trajectory))


def learn_placement(seed: int, n_frames: int, extractor: KeypointExtractor, learner_params=None):
    """Explore, render, extract and learn for one object placement (seed = textures, layout and object place)."""
    model = ArmModel(random_state=seed)
    joints, contact = explore(model, n_frames, seed)
    t0 = time.perf_counter()
    kps = [extractor(model.render(q)) for q in joints]
    t_frames = time.perf_counter() - t0
    t0 = time.perf_counter()
    learner = ArmStateLearner(random_state=seed, **(learner_params or {})).fit(kps, joints, contact)
    return model, learner, dict(render_extract_s=t_frames, fit_s=time.perf_counter() - t0)


def dp_placements(n_placements: int, n_frames: int, seed0: int = 1000, max_seeds: Optional[int] = None,
                  log=print) -> Dict[str, object]:
    """DP success over random placements (module docstring)."""
    extractor = KeypointExtractor()
    results, skipped, failures = [], [], []
    solve_ms = []
    cell_stats = dict(truth_blocked=0, predicted_blocked=0, missed=0, false=0)
    seed = seed0
    max_seeds = max_seeds or 3 * n_placements
    while len(results) < n_placements and seed < seed0 + max_seeds:
        seed += 1
        t_place = time.perf_counter()
        model = ArmModel(random_state=seed)
        grid = JointGrid(*model.joint_limits)
        blocked = truth_cell_map(model, grid)
        task = choose_task(model, grid, blocked, np.random.default_rng(seed))
        if task is None:
            skipped.append(seed)
            continue
        try:
            model, learner, timing = learn_placement(seed, n_frames, extractor)
        except ValueError as exc:        # e.g. too few contact frames: counts as a failure of the method
            failures.append(dict(seed=seed, reason=str(exc)))
            results.append(dict(seed=seed, success=False, reached=False, contact=False, learned=False))
            continue
        planner = DPPlanner(grid)
        planner.update_collision(learner.collision_map_, learner.closeness_map_)
        t0 = time.perf_counter()
        planner.set_goal(task[1])
        solve_ms.append(1e3 * (time.perf_counter() - t0))
        run = execute_plan(model, grid, planner, task[0], task[1], JointMotion(model))
        pred = learner.collision_map_
        cell_stats['truth_blocked'] += int(blocked.sum())
        cell_stats['predicted_blocked'] += int(pred.sum())
        cell_stats['missed'] += int((blocked & ~pred).sum())
        cell_stats['false'] += int((pred & ~blocked).sum())
        ok = run['reached'] and not run['contact']
        results.append(dict(seed=seed, success=bool(ok), reached=run['reached'], contact=run['contact'],
                            contact_at_frames=run['contact_at_frames'], steps=run['steps'], learned=True,
                            region=learner.selection_['model'], start=list(task[0]), goal=list(task[1]),
                            placement_s=time.perf_counter() - t_place, **timing))
        if not ok:
            failures.append(dict(seed=seed, reached=run['reached'], contact=run['contact']))
        log(f'[arm_task] placement {len(results)}/{n_placements} seed {seed}: '
            f"{'ok' if ok else 'FAIL'} ({run['steps']} steps, fit {timing['fit_s']:.1f} s)")
    n = len(results)
    return dict(
        dp_success_rate=sum(r['success'] for r in results) / max(n, 1), dp_placements=n,
        dp_contact_count=sum(r['contact'] for r in results), dp_reached_count=sum(r['reached'] for r in results),
        dp_sim_contact_count=sum(r.get('contact_at_frames', False) for r in results),
        dp_region_counts={m: sum(r.get('region') == m for r in results) for m in REGION_MODELS},
        dp_skipped_no_valid_task=len(skipped), dp_failures=failures, dp_frames_per_placement=n_frames,
        dp_solve_ms=float(np.median(solve_ms)) if solve_ms else None, dp_cell_stats=cell_stats,
        dp_placement_fit_s=float(np.median([r['fit_s'] for r in results if r.get('learned')])) if n else None,
        dp_placement_s=float(np.median([r['placement_s'] for r in results if r.get('learned')])) if n else None)


def synthetic_check(random_state: int = 0) -> Dict[str, float]:
    """Paper Section 3.4: 1000 frames, 25 virtual keypoints (10 object, 10 hand, 5 background), 10 % removed,
    nearest-neighbour imputation, 3-D LLE; the largest |Spearman| of one coordinate with hand-object distance."""
    from mm_manifold.keypoints import NearestImputer
    X, dist = synthetic_keypoint_frames(1000, random_state=random_state)
    Xf = NearestImputer().fit(X).transform(X)
    t0 = time.perf_counter()
    with threadpool_limits(1, user_api='blas'):
        emb = ImageEmbedding(n_components=3, n_neighbors=20, random_state=random_state).fit(Xf)
    fit_s = time.perf_counter() - t0
    rho = [abs(spearmanr(emb.embedding_[:, i], dist)[0]) for i in range(3)]
    return dict(synthetic_abs_spearman=float(max(rho)), synthetic_abs_spearman_per_axis=[float(r) for r in rho],
                synthetic_lle_fit_s=fit_s)


def lle_fit_timing(n_frames: int = 1000, seed: int = 0) -> Dict[str, float]:
    """LLE fit time on `n_frames` imputed keypoint vectors of rendered frames (and the vectoriser's time)."""
    model = ArmModel(random_state=seed)
    joints = model.sample_joints(n_frames, np.random.default_rng(seed))
    vec = KeypointVectorizer(random_state=seed)
    frames = [model.render(q) for q in joints]
    t0 = time.perf_counter()
    kps = [vec.extract(f) for f in frames]
    extract_ms = 1e3 * (time.perf_counter() - t0) / n_frames
    t0 = time.perf_counter()
    vec.fit(kps)
    X = vec.fill_missing(vec.training_vectors_)
    vec_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    with threadpool_limits(1, user_api='blas'):
        ImageEmbedding(n_components=3, n_neighbors=20, random_state=seed).fit(X)
    return dict(lle_fit_s=time.perf_counter() - t0, lle_fit_frames=n_frames,
                vectorizer_fit_and_impute_s=vec_s, feature_extraction_ms_per_frame=extract_ms)


def run(output_dir: Path, quick: bool) -> dict:
    n_eval = 400 if quick else 1000
    out: Dict[str, object] = dict(
        ran_through_graph=('graph_episode (full mode only): arm_sim + image_embedding + dp_planner processes'),
        ran_in_process=['tables (lle/pca tpr/fpr)', 'synthetic check', 'dp_success_rate over placements', 'timings'])
    ev = evaluate_collision_prediction(n_frames=n_eval, random_state=0)
    for method in ('lle', 'pca'):
        for key in (method,) + tuple(f'{method}_{m}' for m in REGION_MODELS):
            c = ev[key]
            for k in ('tpr', 'fpr', 'tp', 'fn', 'fp', 'tn', 'region', 'n_neighbors', 'C', 'radius', 'relative_radius',
                      'cv_tpr', 'cv_fpr', 'closeness_distance_spearman'):
                out[f'{key}_{k}'] = c[k]
        out[f'{method}_selection_s'] = ev[method]['select_s']
        out[f'{method}_cv_candidates'] = ev[f'{method}_cv_candidates']
    out.update(eval_frames=ev['n_frames'], eval_train=ev['n_train'], eval_test=ev['n_test'],
               eval_contact_share=ev['contact_share'], eval_labels=ev['n_labels'],
               eval_observed_share=ev['observed_share'], render_ms_per_frame=ev['render_ms'],
               vectorize_ms_per_frame=ev['vectorize_ms'], vectorizer_fit_s=ev['vectorizer_fit_s'])
    out.update(synthetic_check())
    out.update(lle_fit_timing(400 if quick else 1000))
    out.update(dp_placements(4 if quick else 100, 300 if quick else 500))
    if not quick:
        try:
            from mm_bringup.arm_demo import run_arm_demo
            from mm_bringup.process_graph import ProcessGraph
            with ProcessGraph(log_dir=Path(output_dir) / 'arm_bench_logs') as graph:
                summary = run_arm_demo(graph, print, timeout_s=240.0)
            out['graph_episode'] = {k: v for k, v in summary.items() if isinstance(v, (int, float, str, bool))}
        except Exception as exc:      # the in-process numbers stay valid; say what happened
            out['graph_episode'] = dict(error=repr(exc))
    return out
