"""Figures of the arm experiment (paper Section 3) as PNGs under results/figures/, plus Tables 1-2 as markdown.

    ./mm python -m mm_bringup.figures_arm [--output results/figures] [--bench results/arm_task.json]

fig11_synthetic_lle.png   synthetic keypoints of one frame and the LLE of 1000 such frames coloured by hand-object
                          distance (Section 3.4)
fig12_arm_embedding.png   LLE of rendered exploration frames: contact / no-contact training frames, held-out frames
                          mapped out of sample and the contact region; closeness of the held-out frames against the
                          true hand-object distance (Section 3.5)
fig13_planned_motion.png  snapshots of the arm following the DP plan around the object, and the predicted collision
                          map with the path on the joint grid (Section 3.3)
tables_arm.md             Tables 1-2 (held-out collision prediction, LLE vs PCA; the paper's sphere, the ellipsoid, the
                          quadric and the cross-validated choice) from the benchmark JSON if present, otherwise
                          measured here
All data are computed here with the plain modules (the same code the nodes run); nothing is read from the ROS graph.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mm_bringup.bench.arm_task import (choose_task, execute_plan, learn_placement,  # noqa: E402
                                       truth_cell_map)
from mm_manifold.embedding import ImageEmbedding, format_confusion, synthetic_keypoint_frames  # noqa: E402
from mm_manifold.keypoints import KeypointExtractor, NearestImputer  # noqa: E402
from mm_planner.value_iteration import DPPlanner, JointGrid  # noqa: E402
from mm_sim.arm_model import ArmModel  # noqa: E402
from mm_sim.arm_motion import JointMotion  # noqa: E402


def fig11(out: Path) -> None:
    X, dist = synthetic_keypoint_frames(1000, random_state=0)
    Xf = NearestImputer().fit(X).transform(X)
    Y = ImageEmbedding(n_components=3, n_neighbors=20, random_state=0).fit_transform(Xf)
    from scipy.stats import spearmanr
    rho = [abs(spearmanr(Y[:, i], dist)[0]) for i in range(3)]
    best = int(np.argmax(rho))
    other = [i for i in range(3) if i != best][0]
    fig = plt.figure(figsize=(13, 4.2))
    ax = fig.add_subplot(1, 3, 1)
    pts = X[0].reshape(-1, 2)
    for sl, colour, label in ((slice(0, 10), 'tab:red', 'object'), (slice(10, 20), 'tab:blue', 'hand'),
                              (slice(20, 25), 'grey', 'background')):
        ax.scatter(pts[sl, 0], pts[sl, 1], c=colour, s=18, label=label)
    ax.set_xlim(0, 400), ax.set_ylim(400, 0), ax.set_aspect('equal')
    ax.set_title('virtual keypoints of one frame (10 % removed)')
    ax.legend(fontsize=8, loc='lower right')
    ax = fig.add_subplot(1, 3, 2, projection='3d')
    sc = ax.scatter(Y[:, 0], Y[:, 1], Y[:, 2], c=dist, cmap='viridis', s=5)
    ax.set_title('LLE (3-D) of 1000 frames')
    fig.colorbar(sc, ax=ax, shrink=0.7, label='hand-object distance [px]')
    ax = fig.add_subplot(1, 3, 3)
    ax.scatter(Y[:, best], Y[:, other], c=dist, cmap='viridis', s=5)
    ax.set_xlabel(f'LLE axis {best + 1} (|Spearman| with distance = {rho[best]:.2f})')
    ax.set_ylabel(f'LLE axis {other + 1}')
    ax.set_title('one LLE axis follows the distance')
    fig.tight_layout()
    fig.savefig(out / 'fig11_synthetic_lle.png', dpi=110)
    plt.close(fig)


def fig12(out: Path, seed: int = 0, n_frames: int = 600, n_held_out: int = 200) -> None:
    extractor = KeypointExtractor()
    model, learner, _ = learn_placement(seed, n_frames, extractor)
    rng = np.random.default_rng(seed + 1)
    q_test = model.sample_joints(n_held_out, rng)
    c_test = np.array([model.in_contact(q) for q in q_test])
    d_test = np.array([model.hand_object_distance(q) for q in q_test])
    states = [learner.transform(extractor(model.render(q))) for q in q_test]
    Y_test = np.array([s['embedding'] for s in states])
    close_test = np.array([s['closeness'] for s in states])
    Y, c = learner.lle_.embedding_, learner.train_contact_
    sel = learner.selection_
    fig = plt.figure(figsize=(17, 5))
    ax = fig.add_subplot(1, 3, 1, projection='3d')
    ax.scatter(*Y[~c].T, s=4, c='tab:blue', alpha=0.35, label='no contact (training)')
    ax.scatter(*Y[c].T, s=6, c='tab:red', alpha=0.6, label='contact (training)')
    ax.scatter(*Y_test[~c_test].T, s=14, marker='x', c='navy', label='no contact (held out)')
    ax.scatter(*Y_test[c_test].T, s=14, marker='x', c='darkred', label='contact (held out)')
    region = learner.region_
    if hasattr(region, 'radius_'):          # sphere or ellipsoid: draw it
        u, v = np.mgrid[0:2 * np.pi:24j, 0:np.pi:12j]
        unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1) * region.radius_
        pts = unit @ np.linalg.inv(region.whitening_).T + region.centre_
        ax.plot_wireframe(pts[..., 0], pts[..., 1], pts[..., 2], color='k', linewidth=0.3, alpha=0.5)
    else:                                   # quadric: mark the training frames on its surface
        near = np.abs(learner.train_closeness_) < 0.15
        ax.scatter(*Y[near].T, s=10, facecolors='none', edgecolors='k', linewidths=0.5,
                   label='on the contact surface')
    ax.set_title(f'LLE of {n_frames} exploration frames, contact region: {sel["model"]}\n'
                 f'(cross-validated TPR {sel["cv_tpr"]:.3f} / FPR {sel["cv_fpr"]:.3f})', fontsize=9)
    ax.legend(fontsize=7, loc='upper left')
    ax = fig.add_subplot(1, 3, 2)
    ax.scatter(d_test[~c_test], close_test[~c_test], s=10, c='navy', marker='x', label='no contact')
    ax.scatter(d_test[c_test], close_test[c_test], s=10, c='darkred', marker='x', label='contact')
    ax.axhline(0.0, color='k', linewidth=0.8, label='region surface (closeness 0)')
    ax.axvline(model.contact_distance, color='grey', linestyle='--', linewidth=0.8, label='contact distance')
    ax.set_xlabel('true hand-object distance [px] (not seen by the robot)')
    ax.set_ylabel('closeness to the contact region')
    ax.set_ylim(max(-6.0, close_test.min() - 0.2), close_test.max() + 0.2)
    ax.set_title(f'{n_held_out} held-out frames mapped out of sample', fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 3, 3)
    ax.imshow(model.render(learner.train_joints_[int(np.argmax(c))]))
    ax.set_title('a training frame with contact', fontsize=9)
    ax.axis('off')
    fig.tight_layout()
    fig.savefig(out / 'fig12_arm_embedding.png', dpi=110)
    plt.close(fig)


def fig13(out: Path, seed: int = 3, n_frames: int = 500) -> None:
    model = ArmModel(random_state=seed)
    grid = JointGrid(*model.joint_limits)
    task = choose_task(model, grid, truth_cell_map(model, grid), np.random.default_rng(seed))
    model, learner, _ = learn_placement(seed, n_frames, KeypointExtractor())
    planner = DPPlanner(grid)
    planner.update_collision(learner.collision_map_, learner.closeness_map_)
    run = execute_plan(model, grid, planner, task[0], task[1], JointMotion(model))
    traj = run['trajectory']
    picks = np.unique(np.linspace(0, len(traj) - 1, 6).round().astype(int))
    fig, axes = plt.subplots(1, len(picks) + 1, figsize=(3.1 * (len(picks) + 1), 3.4))
    hand = np.array([model.hand_position(q) for q in traj])
    for ax, k in zip(axes, picks):
        ax.imshow(model.render(traj[k]))
        ax.plot(hand[:k + 1, 0], hand[:k + 1, 1], 'y-', linewidth=1.5)
        ax.set_title(f'step {k}', fontsize=9)
        ax.axis('off')
    ax = axes[-1]
    ax.imshow(learner.collision_map_, cmap='Reds', origin='upper', vmin=0, vmax=1.5)
    cells = np.array([grid.cell_of(q) for q in traj])
    ax.plot(cells[:, 1], cells[:, 0], 'b.-')
    ax.plot(task[0][1], task[0][0], 'go', label='start')
    ax.plot(task[1][1], task[1][0], 'k*', markersize=10, label='goal')
    ax.set_xlabel('shoulder_pitch cell'), ax.set_ylabel('shoulder_roll cell')
    ax.set_title(f"predicted collision map\n{'reached' if run['reached'] else 'NOT reached'}, "
                 f"{'contact!' if run['contact'] else 'no contact'}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / 'fig13_planned_motion.png', dpi=100)
    plt.close(fig)


def tables(out: Path, bench_json: Path) -> None:
    keys = (('lle', 'Table 1: LLE embedding, contact region chosen by cross-validation'),
            ('lle_sphere', 'Table 1 (paper\'s method): LLE embedding, contact sphere'),
            ('lle_ellipsoid', 'LLE embedding, contact ellipsoid (Mahalanobis)'),
            ('lle_quadric', 'LLE embedding, contact quadric (logistic regression)'),
            ('pca', 'Table 2: PCA embedding, contact region chosen by cross-validation'),
            ('pca_sphere', 'Table 2 (paper\'s method): PCA embedding, contact sphere'),
            ('pca_ellipsoid', 'PCA embedding, contact ellipsoid (Mahalanobis)'),
            ('pca_quadric', 'PCA embedding, contact quadric (logistic regression)'))
    if bench_json.is_file():
        b = json.loads(bench_json.read_text())
        source = f'{bench_json} (held-out frames, {b.get("eval_test")} of {b.get("eval_frames")})'
        conf = {m: {k: b.get(f'{m}_{k}') for k in ('tp', 'fn', 'fp', 'tn', 'region', 'n_neighbors', 'C')}
                for m, _ in keys if f'{m}_tp' in b}
    else:
        from mm_manifold.arm_evaluation import evaluate_collision_prediction
        ev = evaluate_collision_prediction(700, 0)
        source = f'measured by figures_arm (held-out frames, {ev["n_test"]} of {ev["n_frames"]})'
        conf = {m: ev[m] for m, _ in keys}
    text = ['# Arm collision prediction (paper Tables 1-2)', '', f'Source: {source}.', '',
            'n_neighbors, the radius / threshold and (first rows) the region model were chosen by 5-fold '
            'cross-validation on the training frames only.', '']
    for m, title in keys:
        if m not in conf:
            continue
        k = conf[m]
        detail = f"region {k['region']}, n_neighbors {k['n_neighbors']}" + (f", C {k['C']:g}" if k.get('C') else '')
        text += [f'## {title}', '', f'({detail})', '', '```', format_confusion(k), '```', '']
    text += ['Paper: LLE 82.6 % / 18.0 %, PCA 54.8 % / 21.4 % (collision recognised / false alarms).', '']
    (out / 'tables_arm.md').write_text('\n'.join(text))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/figures')
    parser.add_argument('--bench', default='results/arm_task.json')
    args = parser.parse_args(argv)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for name, fn in (('fig11', fig11), ('fig12', fig12), ('fig13', fig13)):
        fn(out)
        print(f'[figures_arm] {name} written', flush=True)
    tables(out, Path(args.bench))
    print(f'[figures_arm] tables written to {out / "tables_arm.md"}', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
