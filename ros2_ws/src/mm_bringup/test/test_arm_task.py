"""The arm benchmark's helpers: ground-truth move maps, planning before moving on held-out placements, the synthetic
check with a moving object (small sizes; the benchmark runs the full ones)."""
import numpy as np
import pytest

from mm_bringup.bench.arm_task import plan_before_moving, synthetic_check, truth_move_maps
from mm_bringup.arm_evaluation import moving_object_exploration, render_keypoints
from mm_manifold.arm_learning import ArmStateLearner
from mm_manifold.keypoints import KeypointExtractor
from mm_planner.value_iteration import JointGrid
from mm_sim.arm_model import ArmModel
from mm_sim.arm_motion import sweep


def test_truth_move_maps_follow_the_swept_contact():
    model = ArmModel(random_state=6)
    grid = JointGrid(*model.joint_limits)
    any_part, hand = truth_move_maps(model, grid)
    assert np.all(any_part[hand]) and 0 < hand.sum() <= any_part.sum() < 96
    for r, c in np.argwhere(any_part)[:5]:
        a = grid.centre((r, c))
        moves = [grid.centre((r + dr, c + dc)) for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
                 if 0 <= r + dr < grid.rows and 0 <= c + dc < grid.cols]
        assert any(sweep(model, a, b).any_contact for b in moves)
    for r, c in np.argwhere(~any_part)[:5]:
        assert not sweep(model, grid.centre((r, c)), grid.centre((r, c))).any_contact


def test_plan_before_moving_keeps_the_model_and_scores_every_cell():
    model = ArmModel(random_state=7)
    data = moving_object_exploration(model, 200, 10, rng=np.random.default_rng(7))
    ext = KeypointExtractor()
    kps = render_keypoints(model, data['joints'], data['object'], ext)
    learner = ArmStateLearner(model.joint_limits, n_folds=3).fit(kps, data['joints'], data['contact'])
    out = plan_before_moving(learner, model, n_placements=2, seed=70, extractor=ext, log=lambda *_: None)
    assert out['plan_placements'] == 2 and out['plan_new_frames_per_placement'] == 1
    for key in ('any', 'hand'):
        m = out[f'plan_map_{key}']
        assert m['tp'] + m['fn'] + m['fp'] + m['tn'] == 2 * 96
    assert out['plan_map_any']['tp'] + out['plan_map_any']['fn'] >= out['plan_map_hand']['tp'] + \
        out['plan_map_hand']['fn']
    for row in out['plan_rows']:
        assert row['paper']['reached'] in (True, False) and row['truth_blocked'] > 0


def test_synthetic_check_reports_both_embeddings():
    out = synthetic_check()
    assert out['synthetic_frames'] == 1000 and 0.08 < out['synthetic_missing_share'] < 0.12
    for method in ('lle', 'pca'):
        assert 0.0 <= out[f'synthetic_{method}_abs_spearman'] <= 1.0
        assert out[f'synthetic_{method}_abs_spearman'] == max(out[f'synthetic_{method}_abs_spearman_per_axis'])


def test_geometry_row_is_scored_by_the_named_learner():
    """The geometry row's fallback region belongs to one vector; evaluate runs it with the learner asked for."""
    from mm_bringup.arm_evaluation import evaluate_collision_prediction
    contact_point = dict(representation='contact_point', n_components=2, object_labels=1, n_folds=3)
    relative = dict(representation='relative', n_components=4, n_folds=3)
    with pytest.raises(ValueError, match='geometry_from'):
        evaluate_collision_prediction(200, 60, 5, 51, 52, learner_params=contact_point, geometry_from='relative')
    out = evaluate_collision_prediction(150, 40, 5, 51, 52, learner_params=contact_point, n_neighbors_grid=(10,),
                                        compare_params=dict(relative=relative), geometry_from='relative')
    row = out['geometry']
    assert row['vector'] == 'relative' and row['tp'] + row['fn'] + row['fp'] + row['tn'] == 40
    assert out['representation'] == 'contact_point' and out['relative_params']['representation'] == 'relative'
    disc = out['disc']              # the vector's own disc, on the same test frames
    assert disc['tp'] + disc['fn'] + disc['fp'] + disc['tn'] == 40 and disc['radius'] == out['_learner'].contact_radius_


def test_held_out_scenes_summarise_every_scene():
    """Every scene gets a row (one that cannot be fitted: its error), and the summary matches the rows."""
    from mm_bringup.bench.arm_task import BEST_TARGET, SCENE_ROWS, SPHERE_TARGET, held_out_scenes
    out = held_out_scenes((5, 6), 200, 60, KeypointExtractor())
    assert out['scenes'] == [5, 6] and len(out['scenes_rows']) == 2
    fitted = [r for r in out['scenes_rows'] if 'error' not in r]
    assert out['scenes_failed_to_fit'] == 2 - len(fitted) and fitted
    for key in SCENE_ROWS:
        tpr = [r[key]['tpr'] for r in fitted]
        assert out[f'scenes_{key}']['min_tpr'] == min(tpr)
        assert out[f'scenes_{key}']['mean_tpr'] == pytest.approx(np.mean(tpr))
    for key, (tpr, fpr) in (('lle_sphere', SPHERE_TARGET), ('lle_best', BEST_TARGET), ('disc', BEST_TARGET)):
        assert out[f'scenes_{key}_meeting_target'] == sum(r[key]['tpr'] >= tpr and r[key]['fpr'] <= fpr
                                                          for r in fitted)
