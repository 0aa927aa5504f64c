"""Figures of the arm experiment (paper Section 3) as PNGs under results/figures/, plus Tables 1-2 as markdown.

    ./mm python -m mm_bringup.figures_arm [--output results/figures] [--bench results/arm_task.json]

fig11_synthetic_lle.png   synthetic keypoints of one frame (object and hand both placed uniformly) and the LLE and PCA
                          of 1000 such frames coloured by hand-object distance (Section 3.4)
fig12_arm_embedding.png   LLE of moving-object exploration frames: contact / no-contact training frames and the
                          paper's contact sphere; held-out frames (placements never seen) coloured by the true
                          hand-object distance; their closeness against that distance with its Spearman (Section 3.5)
fig13_planned_motion.png  a held-out placement: snapshots of the arm following the DP plan made before moving from
                          the map predicted out of one frame, and that map against the ground truth (Section 3.3)
tables_arm.md             Tables 1-2 in the paper's format from the benchmark JSON (run the benchmark first)
Everything is computed here with the plain modules and the benchmark's seeds (the same code the nodes run).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import spearmanr  # noqa: E402

from mm_bringup.bench.arm_task import (COMPARE_PARAMS, LEARNER_PARAMS, PLACEMENT_SEED, PLAN_PARAMS,  # noqa: E402
                                       SCENE_ROWS, SCENE_SEED, TEST_SEED, TRAIN_SEED, choose_task, execute_plan,
                                       truth_move_maps)
from mm_bringup.arm_evaluation import evaluate_collision_prediction  # noqa: E402
from mm_manifold.arm_learning import ArmStateLearner  # noqa: E402
from mm_manifold.embedding import ImageEmbedding, format_confusion, synthetic_keypoint_frames  # noqa: E402
from mm_manifold.keypoints import KeypointExtractor, NearestImputer  # noqa: E402
from mm_planner.value_iteration import DPPlanner, JointGrid  # noqa: E402
from mm_sim.arm_motion import JointMotion  # noqa: E402


def fig11(out: Path) -> None:
    X, dist = synthetic_keypoint_frames(1000, move_object=True, random_state=0)
    Xf = NearestImputer().fit(X).transform(X)
    fig = plt.figure(figsize=(17, 4.4))
    ax = fig.add_subplot(1, 4, 1)
    pts = X[0].reshape(-1, 2)
    for sl, colour, label in ((slice(0, 10), 'tab:red', 'object'), (slice(10, 20), 'tab:blue', 'hand'),
                              (slice(20, 25), 'grey', 'background')):
        ax.scatter(pts[sl, 0], pts[sl, 1], c=colour, s=18, label=label)
    ax.set_xlim(0, 400), ax.set_ylim(400, 0), ax.set_aspect('equal')
    ax.set_title('(a) virtual keypoints of one frame\n(object and hand uniform, 10 % removed)', fontsize=9)
    ax.legend(fontsize=8, loc='lower right')
    for k, method in enumerate(('lle', 'pca')):
        Y = ImageEmbedding(3, 20, method, lle_method='standard', random_state=0).fit_transform(Xf)
        rho = [abs(spearmanr(Y[:, i], dist)[0]) for i in range(3)]
        best = int(np.argmax(rho))
        ax = fig.add_subplot(1, 4, 2 + 2 * k, projection='3d') if method == 'lle' else fig.add_subplot(1, 4, 4)
        if method == 'lle':
            sc = ax.scatter(Y[:, 0], Y[:, 1], Y[:, 2], c=dist, cmap='viridis', s=4)
            ax.set_title(f'(b) LLE (3-D) of 1000 frames\nbest axis Y{best + 1}: |Spearman| {rho[best]:.2f}',
                         fontsize=9)
            fig.colorbar(sc, ax=ax, shrink=0.6, label='hand-object distance [px]')
            ax2 = fig.add_subplot(1, 4, 3)
            ax2.scatter(Y[:, best], dist, c=dist, cmap='viridis', s=4)
            ax2.set_xlabel(f'LLE Y{best + 1}'), ax2.set_ylabel('hand-object distance [px]')
            ax2.set_title('LLE axis against the distance', fontsize=9)
        else:
            ax.scatter(Y[:, best], dist, c=dist, cmap='viridis', s=4)
            ax.set_xlabel(f'PCA axis {best + 1}'), ax.set_ylabel('hand-object distance [px]')
            ax.set_title(f'PCA, best axis: |Spearman| {rho[best]:.2f}', fontsize=9)
    fig.tight_layout()
    fig.savefig(out / 'fig11_synthetic_lle.png', dpi=110)
    plt.close(fig)


def fig12(out: Path, ev) -> None:
    learner, test = ev['_learner'], ev['_test']
    emb, sphere, Y_test_all = ev['_lle_sphere_model']
    Y, c = emb.embedding_[:, :3], learner.train_contact_      # the first three axes of a possibly 4-D embedding
    Y_test = Y_test_all[:, :3]
    d_test, c_test = test['distance'], test['contact']
    close_test = sphere.closeness(Y_test_all)
    rho = spearmanr(close_test, d_test)[0]
    flat = Y.shape[1] < 3                       # a 2-D embedding (the contact-point vector): plain axes, a circle
    fig = plt.figure(figsize=(17, 5.2))
    ax = fig.add_subplot(1, 3, 1, **({} if flat else dict(projection='3d')))
    ax.scatter(*Y[~c].T, s=3, c='tab:blue', alpha=0.25, label='no contact (training)')
    ax.scatter(*Y[c].T, s=8, c='tab:red', marker='x', alpha=0.6, label='contact (training)')
    if flat:
        t = np.linspace(0, 2 * np.pi, 100)
        ax.plot(*(sphere.centre_[:2, None] + sphere.radius_ * np.stack([np.cos(t), np.sin(t)])), 'k-',
                linewidth=0.8)
        ax.set_aspect('equal')
    else:
        u, v = np.mgrid[0:2 * np.pi:24j, 0:np.pi:12j]
        unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1) * sphere.radius_
        pts = unit + sphere.centre_[:3]              # the sphere's projection onto these axes
        ax.plot_wireframe(pts[..., 0], pts[..., 1], pts[..., 2], color='k', linewidth=0.3, alpha=0.5)
    r = ev['lle_sphere']
    ax.set_title(f'LLE ({emb.embedding_.shape[1]}-D{"" if flat else ", axes 1-3"}) of {len(Y)} exploration frames '
                 f'(object re-placed every {ev["replace_every"]})\n'
                 f'paper\'s sphere: held-out TPR {r["tpr"]:.2f} / FPR {r["fpr"]:.2f}', fontsize=9)
    ax.legend(fontsize=7, loc='upper left')
    ax = fig.add_subplot(1, 3, 2, **({} if flat else dict(projection='3d')))
    sc = ax.scatter(*Y_test.T, c=d_test, cmap='viridis_r', s=8)
    ax.scatter(*Y_test[c_test].T, s=30, facecolors='none', edgecolors='r', linewidths=0.6, label='contact')
    fig.colorbar(sc, ax=ax, shrink=0.6, label='true hand-object distance [px]')
    ax.set_title(f'{len(Y_test)} held-out frames ({ev["test_placements"]} placements never seen), '
                 'out of sample', fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 3, 3)
    ax.scatter(d_test[~c_test], close_test[~c_test], s=8, c='navy', marker='x', label='no contact')
    ax.scatter(d_test[c_test], close_test[c_test], s=8, c='darkred', marker='x', label='contact')
    ax.axhline(0.0, color='k', linewidth=0.8, label='sphere surface (closeness 0)')
    ax.axvline(ev['_model'].contact_distance, color='grey', linestyle='--', linewidth=0.8, label='contact distance')
    ax.set_xlabel('true hand-object distance [px] (not seen by the robot)')
    ax.set_ylabel('closeness to the contact sphere')
    ax.set_title(f'held-out frames: Spearman(closeness, distance) = {rho:.2f}', fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / 'fig12_arm_embedding.png', dpi=110)
    plt.close(fig)


def fig13(out: Path, ev) -> None:
    """The benchmark's planning before moving (its kept PLAN_PARAMS learner, whole-arm touch) on one held-out
    placement."""
    model = ev['_model']
    learner = ArmStateLearner(model.joint_limits, **PLAN_PARAMS).fit(ev['_kps_train'], ev['_train']['joints'],
                                                                     ev['_train']['any_contact'])
    grid = JointGrid(*learner.joint_limits, *learner.grid_shape)
    rng = np.random.default_rng(PLACEMENT_SEED)
    task = None
    while task is None:
        model.set_object_position(model.random_object_position(rng))
        truth, _ = truth_move_maps(model, grid)
        task = choose_task(model, grid, truth, rng)
    pred = learner.predict_collision_map(KeypointExtractor()(model.render(grid.centre(task[0]))))
    planner = DPPlanner(grid, clearance_reward=0.0)
    planner.update_collision(pred['collision'], pred['closeness'])
    run = execute_plan(model, grid, planner, task[0], task[1], JointMotion(model))
    traj = run['trajectory']
    picks = np.unique(np.linspace(0, len(traj) - 1, 5).round().astype(int))
    fig, axes = plt.subplots(1, len(picks) + 2, figsize=(3.1 * (len(picks) + 2), 3.6))
    hand = np.array([model.hand_position(q) for q in traj])
    for ax, k in zip(axes, picks):
        ax.imshow(model.render(traj[k]))
        ax.plot(hand[:k + 1, 0], hand[:k + 1, 1], 'y-', linewidth=1.5)
        ax.set_title(f'({list(picks).index(k) + 1}) step {k}', fontsize=9)
        ax.axis('off')
    cells = np.array([grid.cell_of(q) for q in traj])
    for ax, m, title in ((axes[-2], pred['collision'], 'predicted map (1 frame, before moving)'),
                         (axes[-1], truth, 'ground truth (any arm part)')):
        ax.imshow(m, cmap='Reds', origin='upper', vmin=0, vmax=1.5)
        ax.plot(cells[:, 1], cells[:, 0], 'b.-')
        ax.plot(task[0][1], task[0][0], 'go', label='start')
        ax.plot(task[1][1], task[1][0], 'k*', markersize=10, label='goal')
        ax.set_xlabel('shoulder_pitch cell'), ax.set_ylabel('shoulder_roll cell')
        ax.set_title(title, fontsize=9)
    axes[-1].legend(fontsize=7)
    wrong = int((pred['collision'] != truth).sum())
    fig.suptitle(f"held-out placement: {'reached' if run['reached'] else 'NOT reached'}, "
                 f"{'CONTACT' if run['contact'] else 'no contact'}; {wrong}/96 map cells wrong", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / 'fig13_planned_motion.png', dpi=100)
    plt.close(fig)


def tables(out: Path, bench_json: Path) -> None:
    """Tables 1-2 in the paper's layout (counts and percentages) from the benchmark JSON."""
    keys = (('lle_sphere', "Table 1 (the paper's method): LLE embedding, contact sphere"),
            ('lle_best', 'Table 1, best boundary: LLE embedding, region model chosen by cross-validation'),
            ('pca_sphere', "Table 2 (the paper's method): PCA embedding, contact sphere"),
            ('pca_best', 'Table 2, best boundary: PCA embedding, region model chosen by cross-validation'),
            ('raw_sphere', 'No embedding: contact sphere in the keypoint vector space'),
            ('raw_knn', 'No embedding: k-nearest-neighbour vote on the keypoint vector'),
            ('disc', "No embedding: the contact-point vector's own disc ||d|| < r (fitted with the vector)"),
            ('geometry', "No embedding: the learned object placed where the frame shows it, against the robot's "
                         "segments with per-segment contact distances (the planning vector's learner)"))
    b = json.loads(bench_json.read_text())
    for name in COMPARE_PARAMS:
        p = b.get(f'{name}_params') or {}
        vector = (f"{name} vector ({p.get('representation')}, {p.get('vector_width')} values, "
                  f"{p.get('n_components')}-D, LLE {p.get('lle_method')})")
        keys += ((f'{name}_lle_sphere', f"For comparison, {vector}: LLE, contact sphere"),
                 (f'{name}_lle_best', f'For comparison, {vector}: LLE, region model chosen by cross-validation'),
                 (f'{name}_pca_sphere', f'For comparison, {vector}: PCA, contact sphere'))
    text = ['# Arm collision prediction (paper Tables 1-2)', '',
            f"Source: {bench_json}. Test frames: {b['eval_n_test']} from {b['eval_test_placements']} object "
            f"placements never seen in training ({b['eval_test_contact']} with contact, "
            f"{b['eval_n_test'] - b['eval_test_contact']} without); training: {b['eval_n_train']} exploration "
            f"frames from {b['eval_train_placements']} placements ({b['eval_train_contact']} with contact). "
            f"Vector: {b['eval_representation']} (from the keypoint positions), {b['eval_vector_width']} values; "
            f"{b['eval_n_components']}-D embeddings, LLE method {b['learner_params']['lle_method']}.", '',
            'n_neighbors, the radius / threshold and (best rows) the region model were chosen by 5-fold '
            'cross-validation on the training frames only; the same test frames score every row.', '']
    for m, title in keys:
        if f'{m}_tp' not in b:
            continue
        k = {x: b.get(f'{m}_{x}') for x in ('tp', 'fn', 'fp', 'tn', 'region', 'n_neighbors', 'C')}
        detail = ', '.join(f'{x} {k[x]}' for x in ('region', 'n_neighbors', 'C') if k.get(x) is not None)
        text += [f'## {title}', ''] + ([f'({detail})', ''] if detail else []) + \
            ['```', format_confusion(k), '```', '']
    text += ['Paper (real images): LLE 95/115 (82.6 %) collisions recognised, 111/617 (18.0 %) false alarms; '
             'PCA 63/115 (54.8 %), 132/617 (21.4 %).', '']
    if b.get('scenes_rows'):
        text += held_out_scene_table(b)
    (out / 'tables_arm.md').write_text('\n'.join(text))


def held_out_scene_table(b: dict) -> list:
    """Markdown lines: the main rows on every held-out scene (TPR / FPR) and the scenes meeting the targets."""
    rows = SCENE_ROWS
    text = ['## The same rows on held-out scenes', '',
            'Same placements and frames, other backgrounds, object textures and arm looks (scenes no tuning script '
            'or test uses). TPR / FPR per scene:', '',
            '| scene | ' + ' | '.join(rows) + ' |', '|---' * (len(rows) + 1) + '|']
    for r in b['scenes_rows']:
        cells = ([r['error']] + [''] * (len(rows) - 1) if 'error' in r else
                 [f"{r[k]['tpr']:.3f} / {r[k]['fpr']:.3f}" for k in rows])
        text.append(f"| {r['scene']} | " + ' | '.join(cells) + ' |')
    text.append('| mean | ' + ' | '.join(f"{b[f'scenes_{k}']['mean_tpr']:.3f} / {b[f'scenes_{k}']['mean_fpr']:.3f}"
                                         if f'scenes_{k}' in b else '' for k in rows) + ' |')
    t = b['scenes_targets']
    n = len(b['scenes_rows'])
    text += ['', f"Scenes meeting the targets: LLE sphere (TPR >= {t['sphere'][0]}, FPR <= {t['sphere'][1]}) "
             f"{b['scenes_lle_sphere_meeting_target']} of {n}, PCA sphere {b['scenes_pca_sphere_meeting_target']}; "
             f"best boundary (>= {t['best'][0]}, <= {t['best'][1]}) LLE {b['scenes_lle_best_meeting_target']} of "
             f"{n}, PCA {b['scenes_pca_best_meeting_target']}, the vector's own disc "
             f"{b.get('scenes_disc_meeting_target', '-')}.", '']
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--output', default='results/figures')
    parser.add_argument('--bench', default='results/arm_task.json')
    args = parser.parse_args(argv)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    fig11(out)
    print('[figures_arm] fig11 written', flush=True)
    ev = evaluate_collision_prediction(1000, 300, SCENE_SEED, TRAIN_SEED, TEST_SEED, learner_params=LEARNER_PARAMS)
    fig12(out, ev)
    print('[figures_arm] fig12 written', flush=True)
    fig13(out, ev)
    print('[figures_arm] fig13 written', flush=True)
    if Path(args.bench).is_file():
        tables(out, Path(args.bench))
        print(f'[figures_arm] tables written to {out / "tables_arm.md"}', flush=True)
    else:
        print(f'[figures_arm] no {args.bench}: run the benchmark first for the tables', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
