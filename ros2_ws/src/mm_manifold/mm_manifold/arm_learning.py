"""The arm's learned state, all in one object: keypoint vectors -> LLE (and PCA) -> contact region -> collision map
on the joint grid, with saving and loading without pickle (paper Sections 3.2, 3.3, 3.5). No rclpy here.

Inputs per training frame are what the robot has: its SIFT keypoints, its own joint angles and its touch sensor.
The contact region in the LLE space is the paper's sphere (centre = mean of the contact frames), the Mahalanobis
ellipsoid or a quadric fitted by logistic regression (mm_manifold.embedding); `region='auto'` (default) lets 5-fold
cross-validation on the training frames choose among them, and the radius (threshold) is always chosen by that
cross-validation, with the validation frames embedded out of sample as new frames are.

The collision map is what the planner needs: for each cell of the rows x cols joint grid, whether entering it is
predicted to collide. The prediction comes from the embedding, not from the touch labels directly: every training
frame gets the closeness of the contact region in the LLE space (in-sample embedding; 0 on the region's surface, 1
at its centre / a typical contact frame, negative outside), counts as "collision for planning" when its closeness is
at least -`map_margin` (a margin inflates the region for planning only, because the planner's moves sweep whole
cells while the region is fitted for the best TPR - FPR on single frames), and a cell is marked as collision when at
least `cell_collision_fraction` of its frames count as collision. Frames are assigned to the cell
that contains their joint angles; a cell holding fewer than `cell_min_frames` frames takes the nearest frames (joint
distance in units of the cell size) up to that number, so sparsely explored cells still get a prediction. The cell's
closeness is the largest closeness of those frames (the most contact-like view seen there). The planner uses it to
keep clear of the region (mm_planner.value_iteration.clearance_rewards): a cell the object only partly covers often
has no contact frame and too few frames near the region to be marked, but its closeness is still high. That map is
only meaningful while the object stayed put during exploration.

The object moves between placements (paper 3.1: its position "differed irrelevantly to the configuration of the robot
arm"), so the learner also learns which keypoint labels are the robot's own: a label whose image position the joint
readings predict (linear regression on the products of cos / sin of each joint, which spans the image position of
any point on a chain of revolute joints seen by an orthographic camera; R^2 >= `self_r2`) moves with the arm; a
label that moves but is not predicted by the joints (R^2 <= `external_r2`) belongs to something else that moves
(the object); labels that never move are background. Nothing tells the learner which label is which.
`representation='relative'` (default) embeds the spatial relation the paper asks for: the positions of the robot's
own labels relative to where the external labels are (their median displacement from their mean training position);
'absolute' embeds the raw labelled positions (the paper's vector). External labels hidden in a frame are taken from
the `recent_frames` frames before it. 'contact_point' embeds one 2-D offset, d = p - o - e: p = A + c1 (B - A) + c2
perp(B - A) is a virtual contact point rigid with the last link (A, B: the two farthest-apart precisely placed robot
labels that move with joint 1 and rigidly with each other, put where the joint regression puts them at the frame's
joint readings, so never hidden), o the learned object's centre (template shift, tracked over the frames in order:
labels next to the hand are left out, two agreeing labels place it (a label may stand for several of the object's
keypoints, each with its own offset; a keypoint the ratio test could not tell from a look-alike may stand in for
a label in that agreement), a lone label confirms the estimate or - with
`object_labels` 1 - re-places it, a frame without one keeps the last estimate; `_object_track`) and e an image
offset. (c1, c2, e) come from least squares of ||p - o - e|| over the touch frames, then a class-balanced logistic
fit of (r - ||d||) / s, refitted without the touch frames it puts more than 2 s outside the disc (their object
estimate is wrong; the contact regions in the embeddings are fitted without them too, `region_frames_`): contact
depends on the hand relative to the object only, and the other vectors carry every arm label, which spreads the
contact frames into a slab across poses. `lle_metric` 'local' keeps the disc ||d|| < r round in the LLE space
(mm_manifold.embedding.ImageEmbedding), where sklearn's unit-covariance coordinates squeeze it into an ellipse.

`predict_collision_map(frame, recent)` plans before moving, for an object placement never seen (the paper's
"prediction of robot's hand in the image space"): for a fine lattice of joint vectors over the grid it synthesises
the keypoint vector the camera would see there - the robot's labels where the joint regression puts them, the
others as seen in the current frame (hidden ones from the recent frames) - embeds it out of sample and applies the
contact region. A cell is marked as collision when any lattice point at its centre or on the moves to its
neighbours' centres - its half of them - is predicted in contact (closeness >= `map_threshold`; the union over the
cross makes a low threshold block far too much). The map also says which moves between cell centres touch a
predicted contact (`blocked_moves`): a cell whose move to one side touches the object can still be crossed the other
way, which the per-cell map forbids and which opens the narrow passages next to the object; on the keypoint-distance
route such a move must also keep `move_clearance` px of predicted clearance, because a single move has none of the
half-cell slack the per-cell cross gives. The robot only learns the contact its touch sensor reports: with a touch sensor on
the hand alone (the paper's label) the map cannot know where the links would hit the object; arm_sim's whole-arm
contact sense (what a real arm feels through its joint torques) is the label image_embedding uses by default.

`map_method='keypoint_distance'` is the other route to the same map (mm_bringup.tune_arm_map / tune_arm_reach compare
them), which reads the image geometry the learner already has instead of the embedding. The object is what moves
rigidly but not with the joints: external labels whose mutual offsets stay within `object_tolerance` px form rigid
groups, and a group whose common shift moves by at least `min_motion` px (median over frames, so a static label
that is sometimes mismatched does not count) is an object. Its template (each label's position relative to the
group's shift) is fitted on the exploration frames, so a frame that shows any two of its labels in agreement places
the whole object, hidden keypoints included: the arm hides the object's keypoints in the very frames that carry the
contact label, which made distances to the keypoints a frame happens to show useless. The robot's segments - pairs
of its labels that keep their distance (`rigid_tolerance`), i.e. lie on one rigid part, among the labels the joint
regression places within `rigid_tolerance` px (median over the frames that show them) - are predicted at each
lattice joint vector, and each segment has its own contact distance to the object's centre (the template's mean),
learned from the touch labels: the `margin_quantile` of that segment's distances over the no-contact frames (near
zero: the largest distance the object's centre came to it without contact), at most the largest distance over the
contact frames. Per segment, because the keypoints sit at different depths inside different parts (deep in the
hand, near the axis of the links); a single distance for all of them blocked a third of the free cells.
"""
from __future__ import annotations

import json
import os
import tempfile
import warnings
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from sklearn.decomposition import PCA
from sklearn.manifold import LocallyLinearEmbedding
from sklearn.neighbors import NearestNeighbors
from threadpoolctl import threadpool_limits

from mm_manifold.embedding import (LLE_METRICS, REGION_MODELS, ContactQuadric, ContactSphere, ImageEmbedding,
                                   fit_contact_model, quadratic_features, select_contact_model)
from mm_manifold.keypoints import FrameKeypoints, KeypointVectorizer, MeanImputer, NearestImputer

FORMAT_VERSION = 12                # 10: object_modes (several template offsets per object label); 11: region_frames;
                                   # 12: object_match_distance
MISPLACED_SOFTNESSES = 2.0         # a touch frame this many softnesses outside the contact disc has a wrong object
MAX_OBJECT_MODES = 3               # template offsets learned per object label (label_modes)
AMBIGUOUS_PER_LABEL = 2            # look-alike keypoints an object label may stand for in one frame (_object_track)
REPRESENTATIONS = ('relative', 'absolute', 'contact_point')
OBJECT_SOURCES = ('frame', 'recent', 'stale', 'mean')   # where the contact-point vector's object estimate came from
MAP_METHODS = ('keypoint_distance', 'embedding')
UNPLACED_POLICIES = ('embedding', 'block')      # keypoint-distance map of a frame that does not place the object
STATIC, SELF, EXTERNAL, UNCLEAR = 0, 1, 2, 3     # label roles
_VECTORIZER_PARAMS = ('n_labels', 'max_features', 'scale', 'match_ratio', 'max_pixel_shift', 'n_frame_neighbors',
                      'min_frame_fraction', 'exemplar_spacing', 'imputation', 'n_impute_neighbors', 'max_fit_frames',
                      'random_state', 'global_match_ratio')


class ModelFileError(RuntimeError):
    """A saved model that cannot be read (missing, corrupt, or of another format)."""


def cell_indices(joints: np.ndarray, joint_limits: np.ndarray, shape) -> np.ndarray:
    """(n, 2) integer (row, col) of the joint-grid cell holding each joint vector (outside: nearest border cell)."""
    lim = np.asarray(joint_limits, dtype=float)
    step = (lim[:, 1] - lim[:, 0]) / np.asarray(shape, dtype=float)
    idx = np.floor((np.asarray(joints, dtype=float) - lim[:, 0]) / step).astype(int)
    return np.clip(idx, 0, np.asarray(shape) - 1)


def cell_map(joints: np.ndarray, predicted: np.ndarray, closeness: np.ndarray, joint_limits, shape=(8, 12),
             min_frames: int = 3, fraction: float = 0.1):
    """Per-cell collision (bool) and closeness (float) from per-frame predictions (see the module docstring)."""
    joints = np.asarray(joints, dtype=float)
    predicted = np.asarray(predicted, dtype=bool)
    closeness = np.asarray(closeness, dtype=float)
    lim = np.asarray(joint_limits, dtype=float)
    rows, cols = shape
    step = (lim[:, 1] - lim[:, 0]) / np.array([rows, cols], float)
    cells = cell_indices(joints, lim, shape)
    tree = cKDTree(joints / step)
    collision = np.zeros((rows, cols), bool)
    close = np.full((rows, cols), -np.inf)
    k_min = min(int(min_frames), len(joints))
    for r in range(rows):
        for c in range(cols):
            members = np.flatnonzero((cells[:, 0] == r) & (cells[:, 1] == c))
            if len(members) < k_min:
                centre = (lim[:, 0] + (np.array([r, c]) + 0.5) * step) / step
                _, nearest = tree.query(centre, k=k_min)
                members = np.unique(np.r_[members, np.atleast_1d(nearest)])[:max(k_min, len(members))]
            collision[r, c] = predicted[members].mean() >= fraction
            close[r, c] = closeness[members].max()
    return collision, close


def cross_max(hit: np.ndarray, value: np.ndarray, shape, resolution: int):
    """Per grid cell, over the lattice points of its centre row and column out to its borders (where the arm goes
    while it is in the cell: standing at the centre, or on its half of a move to a neighbour's centre; the other
    half belongs to the neighbour, so a move between two free cells is free): any `hit` (bool) and the largest
    `value`. The lattice has `resolution` points per cell side, edges included ((rows * res + 1, cols * res + 1)).
    (Reaching to the neighbours' centres instead grows every obstacle by a cell and cut the free paths.)"""
    rows, cols = shape
    s, h = int(resolution), int(resolution) // 2
    if hit.shape != (rows * s + 1, cols * s + 1) or value.shape != hit.shape:
        raise ValueError('lattice does not match the grid shape and resolution')
    out_hit = np.zeros((rows, cols), bool)
    out_val = np.full((rows, cols), -np.inf)
    for r in range(rows):
        for c in range(cols):
            i, j = r * s + h, c * s + h
            i0, i1 = i - h, i + h
            j0, j1 = j - h, j + h
            cross_hit = np.r_[hit[i, j0:j1 + 1], hit[i0:i1 + 1, j]]
            cross_val = np.r_[value[i, j0:j1 + 1], value[i0:i1 + 1, j]]
            out_hit[r, c] = cross_hit.any()
            out_val[r, c] = cross_val.max()
    return out_hit, out_val


# Moves between adjacent cells, in the order of mm_planner.value_iteration.MOVES (CollisionMap.blocked_moves).
GRID_MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))


def move_hits(hit: np.ndarray, shape, resolution: int) -> np.ndarray:
    """(4, rows, cols) bool: whether any lattice point on the straight move from each cell's centre to its
    neighbour's centre (GRID_MOVES order; both centres included) is a `hit`; moves off the grid count as hit.
    Lattice as in cross_max."""
    rows, cols = shape
    s, h = int(resolution), int(resolution) // 2
    if hit.shape != (rows * s + 1, cols * s + 1):
        raise ValueError('lattice does not match the grid shape and resolution')
    out = np.ones((len(GRID_MOVES), rows, cols), bool)
    for k, (dr, dc) in enumerate(GRID_MOVES):
        for r in range(max(0, -dr), rows - max(0, dr)):
            for c in range(max(0, -dc), cols - max(0, dc)):
                i, j = r * s + h, c * s + h
                steps = np.arange(s + 1)
                out[k, r, c] = hit[i + dr * steps, j + dc * steps].any()
    return out


def joint_features(joints: np.ndarray) -> np.ndarray:
    """(n, 3^d) products of (1, cos q_j, sin q_j) over the d joints: the image position of a point on a chain of
    revolute joints (orthographic view) is linear in these, whatever the link lengths."""
    q = np.atleast_2d(np.asarray(joints, dtype=float))
    basis = [np.ones(len(q))]
    for j in range(q.shape[1]):
        basis = [b * f for b in basis for f in (np.ones(len(q)), np.cos(q[:, j]), np.sin(q[:, j]))]
    return np.stack(basis, 1)


def rigid_pairs(P: np.ndarray, tolerance: float) -> np.ndarray:
    """(K, 2) index pairs (i <= j, (i, i) included) of the labels in P (n, S, 2) whose mutual image distance varies by
    at most `tolerance` px (standard deviation over the n poses): labels on one rigid part. The segment between two
    of them lies on that part (a link's outline is convex), which fills the gaps between sparse keypoints."""
    n_labels = P.shape[1]
    i, j = np.triu_indices(n_labels)
    d = np.linalg.norm(P[:, i] - P[:, j], axis=2)
    return np.stack([i, j], 1)[d.std(axis=0) <= tolerance]


def segment_point_distances(P: np.ndarray, pairs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, K) image distance [px] from each segment `pairs` of the robot's points P (n, S, 2) to the nearest of
    `points` (n, M, 2) (NaN points = unknown; inf where none is known)."""
    A, B = P[:, pairs[:, 0]], P[:, pairs[:, 1]]                    # (n, K, 2)
    AB = B - A
    length2 = np.maximum(np.einsum('nkc,nkc->nk', AB, AB), 1e-12)
    best = np.full(A.shape[:2], np.inf)
    for m in range(points.shape[1]):
        o = points[:, m]
        seen = np.isfinite(o[:, 0])
        if not seen.any():
            continue
        AO = o[seen, None, :] - A[seen]
        t = np.clip(np.einsum('nkc,nkc->nk', AO, AB[seen]) / length2[seen], 0.0, 1.0)
        best[seen] = np.minimum(best[seen], np.linalg.norm(AO - t[..., None] * AB[seen], axis=2))
    return best


def fit_template(P: np.ndarray, iterations: int = 3) -> np.ndarray:
    """(G, 2) positions of a rigid group's labels relative to its shift, from their positions P (n, G, 2; NaN where
    unseen): alternately the shift of each frame (median over its labels) and each label's mean relative position, so
    a label seen only at some of the object's places is not biased towards them."""
    with np.errstate(invalid='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)           # frames or labels never seen -> NaN
        template = np.nanmean(P, axis=0)
        for _ in range(iterations):
            shift = np.nanmedian(P - template[None], axis=1)
            template = np.nanmean(P - shift[:, None], axis=0)
    return template


def fit_contact_disc(rel: np.ndarray, M: np.ndarray, contact: np.ndarray, fit: np.ndarray) -> np.ndarray:
    """theta = (c1, c2, e1, e2, r, log s) of the contact-point vector d = rel + M c - e (rel (n, 2) = A - o, M (n, 2, 2)
    the link frame; module docstring) from the frames `fit` (n,) bool with touch labels `contact` (n,): (1) least
    squares of d = 0 over the touch frames, (2) a class-balanced logistic fit of (r - ||d||) / s, (3) refitted without
    the touch frames it puts more than MISPLACED_SOFTNESSES s outside the disc. A touch frame there placed the object
    wrongly (touch means the hand is at it): a few such frames (objects 75-117 px off on diagnosis scene 21) pulled
    the radius from 47 to 59 px. Refits until none is left (3 were enough on diagnosis scenes 21-32; 10 bound the
    loop)."""
    from scipy.optimize import minimize
    use = contact & fit
    Mc = np.concatenate([M[use], np.broadcast_to(-np.eye(2), (int(use.sum()), 2, 2))], axis=2).reshape(-1, 4)
    ce = np.linalg.lstsq(Mc, -rel[use].reshape(-1), rcond=None)[0]

    def dist(theta, sel):
        return np.linalg.norm(rel[sel] + np.einsum('nij,j->ni', M[sel], theta[:2]) - theta[2:4], axis=1)

    def solve(sel, start):
        y = contact[sel]
        w = np.where(y, 0.5 / y.mean(), 0.5 / (1.0 - y.mean()))

        def loss(theta):
            z = (theta[4] - dist(theta, sel)) / np.exp(theta[5])
            return float(np.sum(w * np.logaddexp(0.0, np.where(y, -z, z))) / len(y))
        res = minimize(loss, start, method='Nelder-Mead', options=dict(maxiter=4000, xatol=1e-5, fatol=1e-7))
        return res.x if np.all(np.isfinite(res.x)) and res.fun <= loss(start) else start

    d0 = dist(np.r_[ce, 0.0, 0.0], fit)
    theta = solve(fit, np.r_[ce, 0.5 * float(np.median(d0[contact[fit]]) + np.median(d0[~contact[fit]])), np.log(5.0)])
    everything = np.ones(len(fit), bool)
    for _ in range(10):
        far = contact & fit & (dist(theta, everything) > theta[4] + MISPLACED_SOFTNESSES * np.exp(theta[5]))
        if not far.any() or (contact & fit & ~far).sum() < 2:
            break
        fit = fit & ~far
        theta = solve(fit, theta)
    return theta


def label_modes(P: np.ndarray, template: np.ndarray, tolerance: float, max_modes: int = 3,
                min_share: float = 0.1, min_frames: int = 5) -> np.ndarray:
    """(G, max_modes, 2) offsets of each label of a rigid group from the group's shift, most frequent first, NaN where
    a label has fewer modes; P (n, G, 2) the labels' positions (NaN unseen), `template` (G, 2) from fit_template.
    One label may stand for several physical keypoints of the object (SIFT's look-alikes, joined into one track): on
    diagnosis scene 30 one label's single template offset lay 25 px from every place it was seen, between two of
    them. A label's offset is measured in the frames where the other labels agree on the shift (within 2 x
    `tolerance` px; one other label for a group of two), clustered greedily (radius 2 x `tolerance`, the densest
    first), and a cluster holding at least `min_share` of them and `min_frames` frames is a mode. Done twice, the
    second time with every label's main mode as its template (a template between two modes misleads the others)."""
    n, G = P.shape[:2]
    radius = 2.0 * tolerance
    modes = np.full((G, max_modes, 2), np.nan)
    with np.errstate(invalid='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        for _ in range(2):
            implied = P - template[None]                                    # (n, G, 2) shift each label implies
            for j in range(G):
                others = implied[:, np.arange(G) != j]
                shift = np.nanmedian(others, axis=1)
                agree = (np.linalg.norm(others - shift[:, None], axis=2) <= radius).sum(axis=1)
                ok = (agree >= min(2, G - 1)) & np.isfinite(P[:, j, 0])
                offsets = P[ok, j] - shift[ok]
                need = max(min_frames, min_share * len(offsets))
                free = np.ones(len(offsets), bool)
                found = []
                while len(found) < max_modes and free.sum() >= need:
                    pts = offsets[free]
                    close = np.linalg.norm(pts[:, None] - pts[None], axis=2) <= radius
                    members = close[np.argmax(close.sum(axis=1))]
                    if members.sum() < need:
                        break
                    mode = np.median(pts[members], axis=0)
                    found.append(mode)
                    free &= np.linalg.norm(offsets - mode, axis=1) > radius
                modes[j] = np.nan
                modes[j, :max(len(found), 1)] = found if found else [template[j]]
            template = modes[:, 0].copy()
    return modes


def group_shifts(P: np.ndarray, template: np.ndarray, tolerance: float) -> np.ndarray:
    """(n, 2) shift of a rigid group in each frame from its labels' positions P (n, G, 2): the median offset from the
    template, kept only where at least two labels agree with it within 2 x `tolerance` px (NaN otherwise: one label
    alone may be a mismatch)."""
    with np.errstate(invalid='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        rel = P - template[None]
        shift = np.nanmedian(rel, axis=1)
        agree = (np.linalg.norm(rel - shift[:, None], axis=2) <= 2.0 * tolerance).sum(axis=1)
    shift[agree < 2] = np.nan
    return shift


def rigid_groups(P: np.ndarray, tolerance: float, min_motion: float, min_frames: int = 20) -> list:
    """Groups (arrays of indices into P's labels) of labels that move together rigidly - the spread (1.4826 x median
    absolute deviation) of their mutual offset within `tolerance` px over the frames that see both - and whose common
    shift moves by at least `min_motion` px (median distance from its median): the objects. P (n, L, 2), NaN unseen."""
    n_labels = P.shape[1]
    rigid = np.zeros((n_labels, n_labels), bool)
    for i in range(n_labels):
        for j in range(i + 1, n_labels):
            d = P[:, i] - P[:, j]
            d = d[np.isfinite(d[:, 0])]
            if len(d) >= min_frames:
                spread = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
                rigid[i, j] = rigid[j, i] = float(np.hypot(*spread)) <= tolerance
    _, component = connected_components(coo_matrix(rigid), directed=False)
    groups = []
    for g in np.unique(component):
        members = np.flatnonzero(component == g)
        if len(members) < 2:
            continue
        shift = group_shifts(P[:, members], fit_template(P[:, members]), tolerance)
        shift = shift[np.isfinite(shift[:, 0])]
        motion = np.median(np.linalg.norm(shift - np.median(shift, axis=0), axis=1)) if len(shift) else 0.0
        if len(shift) >= min_frames and motion >= min_motion:
            groups.append(members)
    return groups


def label_roles(raw: np.ndarray, joints: np.ndarray, min_motion: float = 3.0, self_r2: float = 0.9,
                external_r2: float = 0.3, min_frames: int = 20):
    """Role of each keypoint label (STATIC, SELF, EXTERNAL, UNCLEAR) from raw labelled positions (n, 2L, NaN where
    unseen) and the joint readings: returns (roles (L,), joint regression coefficients (L, 3^d, 2), R^2 (L,),
    motion (L,) = RMS distance of the label from its mean position [px])."""
    n_labels = raw.shape[1] // 2
    P = raw.reshape(len(raw), n_labels, 2)
    phi = joint_features(joints)
    roles = np.full(n_labels, UNCLEAR, int)
    coef = np.zeros((n_labels, phi.shape[1], 2))
    r2 = np.zeros(n_labels)
    motion = np.zeros(n_labels)
    for label in range(n_labels):
        seen = np.isfinite(P[:, label, 0])
        if seen.sum() < max(min_frames, phi.shape[1] + 2):
            continue
        Y = P[seen, label]
        spread = ((Y - Y.mean(0)) ** 2).sum()
        motion[label] = float(np.sqrt(spread / len(Y)))
        if motion[label] < min_motion:
            roles[label] = STATIC
            continue
        coef[label] = np.linalg.lstsq(phi[seen], Y, rcond=None)[0]
        r2[label] = 1.0 - float(((Y - phi[seen] @ coef[label]) ** 2).sum()) / max(spread, 1e-12)
        roles[label] = SELF if r2[label] >= self_r2 else EXTERNAL if r2[label] <= external_r2 else UNCLEAR
    return roles, coef, r2, motion


class ArmStateLearner:
    """Learn the arm's image state from frames and predict collisions (module docstring).

    Parameters: joint_limits ((lo0, hi0), (lo1, hi1)) [rad], the robot's joint box from its description (no
    default: a robot constant has no place in learning code); n_components (LLE and PCA dimensions), n_neighbors
    (LLE), lle_method, region ('auto', or one of 'sphere' (the paper's), 'ellipsoid', 'quadric'), grid_shape (rows,
    cols), cell_min_frames,
    cell_collision_fraction, map_margin, vectorizer_params (dict for KeypointVectorizer), random_state, n_folds
    (cross-validation of the region), representation ('relative', 'absolute' or 'contact_point'; the last needs the
    joint readings in transform / frame_vectors and n_components <= 2), object_labels (contact_point: 2 = a frame
    places the object when two of its labels agree, 1 = a single label will do), self_r2 and external_r2 (label
    roles), min_motion [px] (below: a static label), recent_frames (how many preceding frames may stand in for a
    hidden external label), map_resolution (lattice points per cell side in predict_collision_map; even),
    map_threshold (closeness at or above which predict_collision_map counts a lattice point as contact; chosen by
    mm_bringup.tune_arm), move_clearance [px] (keypoint_distance: the predicted clearance a move between cell centres
    must keep to count as free in blocked_moves; chosen by mm_bringup.tune_arm_reach), lle_metric ('unit' or
    'local': ImageEmbedding's scaling of the LLE coordinates; 'local' keeps the input's neighbour distances),
    hand_exclusion, track_gate [px], object_modes and object_match_distance (contact_point's object track:
    _object_track; 0 leaves the look-alike matches out).
    Learned attributes: vectorizer_, label_roles_, joint_coef_ (joint regression of every label), label_r2_,
    label_motion_, label_mean_ (mean training position of every label), lle_, pca_, region_ and
    pca_region_ (ContactSphere or ContactQuadric), selection_ and pca_selection_ (the cross-validated choice: model, C,
    threshold, cv_tpr, cv_fpr), imputer_ (for the embedded vectors), train_vectors_ (imputed), train_joints_,
    train_contact_, train_stamps_ (int ns, or -1), region_frames_ (bool per training frame: those the contact
    region is fitted to; contact_point leaves out the touch frames its disc puts far outside), train_predicted_
    and train_closeness_ (LLE region, in-sample), collision_map_ (rows, cols) bool and closeness_map_ (rows, cols)
    over the exploration frames; contact_point only (None otherwise): contact_labels_ (A, B label ids),
    contact_coef_ (c1, c2), contact_offset_ (e), contact_radius_ and contact_softness_ [px] (the logistic fit),
    contact_object_ (object group used), object_mean_ (training mean of its centre), object_modes_
    (k, MAX_OBJECT_MODES, 2) offsets of the object's labels (label_modes),
    train_object_source_ (index into OBJECT_SOURCES per training frame).
    """

    def __init__(self, joint_limits, n_components: int = 3, n_neighbors: int = 20, lle_method: str = 'standard',
                 region: str = 'auto', grid_shape=(8, 12),
                 cell_min_frames: int = 3, cell_collision_fraction: float = 0.1, map_margin: float = 0.1,
                 vectorizer_params: Optional[Dict] = None, random_state: Optional[int] = 0, n_folds: int = 5,
                 representation: str = 'relative', self_r2: float = 0.9, external_r2: float = 0.3,
                 min_motion: float = 10.0, recent_frames: int = 5, map_resolution: int = 4,
                 map_threshold: float = 0.25, map_method: str = 'embedding', rigid_tolerance: float = 2.0,
                 object_tolerance: float = 3.0, margin_quantile: float = 0.01, unplaced_object: str = 'embedding',
                 move_clearance: float = 3.0, object_labels: int = 2, lle_metric: str = 'unit',
                 hand_exclusion: float = 15.0, track_gate: float = 25.0, object_modes: int = 2,
                 object_match_distance: float = 0.2):
        lim = np.asarray(joint_limits, dtype=float)
        if lim.shape != (2, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
            raise ValueError('joint_limits must be ((lo0, hi0), (lo1, hi1)) with finite lo < hi')
        if len(grid_shape) != 2 or min(grid_shape) < 1:
            raise ValueError('grid_shape must be (rows >= 1, cols >= 1)')
        if cell_min_frames < 1 or not 0.0 < cell_collision_fraction <= 1.0:
            raise ValueError('cell_min_frames >= 1 and 0 < cell_collision_fraction <= 1 are required')
        if region != 'auto' and region not in REGION_MODELS:
            raise ValueError(f"region must be 'auto' or one of {REGION_MODELS}")
        if n_folds < 2:
            raise ValueError('n_folds must be >= 2')
        if representation not in REPRESENTATIONS:
            raise ValueError(f'representation must be one of {REPRESENTATIONS}')
        if not 0.0 <= external_r2 < self_r2 <= 1.0 or min_motion < 0 or recent_frames < 0:
            raise ValueError('0 <= external_r2 < self_r2 <= 1, min_motion >= 0 and recent_frames >= 0 are required')
        if not -10.0 < map_threshold < 10.0:
            raise ValueError('map_threshold must be in (-10, 10)')
        if map_resolution < 2 or map_resolution % 2:
            raise ValueError('map_resolution must be even and >= 2 (the lattice must hold the cell centres)')
        if map_method not in MAP_METHODS:
            raise ValueError(f'map_method must be one of {MAP_METHODS}')
        if not (0.0 <= rigid_tolerance < 100.0 and 0.0 < object_tolerance < 100.0 and 0.0 <= margin_quantile <= 0.5):
            raise ValueError('0 <= rigid_tolerance < 100, 0 < object_tolerance < 100 and 0 <= margin_quantile <= 0.5 '
                             'are required')
        if unplaced_object not in UNPLACED_POLICIES:
            raise ValueError(f'unplaced_object must be one of {UNPLACED_POLICIES}')
        if not 0.0 <= move_clearance < 100.0:
            raise ValueError('move_clearance must be in [0, 100) px')
        if object_labels not in (1, 2):
            raise ValueError('object_labels must be 1 or 2')
        if not (0.0 <= hand_exclusion < 100.0 and 0.0 < track_gate < 1000.0):
            raise ValueError('hand_exclusion must be in [0, 100) px and track_gate in (0, 1000) px')
        if object_modes not in range(1, MAX_OBJECT_MODES + 1):
            raise ValueError(f'object_modes must be 1 ... {MAX_OBJECT_MODES}')
        if not 0.0 <= object_match_distance <= 4.0:
            raise ValueError('object_match_distance must be in [0, 4] (squared distance of unit descriptors)')
        if lle_metric not in LLE_METRICS:
            raise ValueError(f'lle_metric must be one of {LLE_METRICS}')
        if representation == 'contact_point' and n_components > 2:
            raise ValueError('contact_point embeds a 2-D vector: n_components must be <= 2')
        unknown = set(vectorizer_params or {}) - set(_VECTORIZER_PARAMS)
        if unknown:
            raise ValueError(f'unknown vectorizer parameters: {sorted(unknown)}')
        self.n_components = int(n_components)
        self.n_neighbors = int(n_neighbors)
        self.lle_method = lle_method
        self.region = region
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self.joint_limits = lim
        self.cell_min_frames = int(cell_min_frames)
        self.cell_collision_fraction = float(cell_collision_fraction)
        if not 0.0 <= map_margin < 10.0:
            raise ValueError('map_margin must be in [0, 10)')
        self.map_margin = float(map_margin)
        self.vectorizer_params = dict(vectorizer_params or {})
        self.random_state = random_state
        self.n_folds = int(n_folds)
        self.representation = representation
        self.self_r2 = float(self_r2)
        self.external_r2 = float(external_r2)
        self.min_motion = float(min_motion)
        self.recent_frames = int(recent_frames)
        self.map_resolution = int(map_resolution)
        self.map_threshold = float(map_threshold)
        self.map_method = map_method
        self.rigid_tolerance = float(rigid_tolerance)
        self.object_tolerance = float(object_tolerance)
        self.margin_quantile = float(margin_quantile)
        self.unplaced_object = unplaced_object
        self.move_clearance = float(move_clearance)
        self.object_labels = int(object_labels)
        self.lle_metric = lle_metric
        self.hand_exclusion = float(hand_exclusion)
        self.track_gate = float(track_gate)
        self.object_modes = int(object_modes)
        self.object_match_distance = float(object_match_distance)

    def get_params(self) -> Dict[str, object]:
        """The constructor's parameters (JSON-able), as saved with the model."""
        return dict(n_components=self.n_components, n_neighbors=self.n_neighbors, lle_method=self.lle_method,
                    region=self.region, grid_shape=list(self.grid_shape), joint_limits=self.joint_limits.tolist(),
                    cell_min_frames=self.cell_min_frames, cell_collision_fraction=self.cell_collision_fraction,
                    map_margin=self.map_margin, random_state=self.random_state, n_folds=self.n_folds,
                    representation=self.representation, self_r2=self.self_r2, external_r2=self.external_r2,
                    min_motion=self.min_motion, recent_frames=self.recent_frames,
                    map_resolution=self.map_resolution, map_threshold=self.map_threshold, map_method=self.map_method,
                    rigid_tolerance=self.rigid_tolerance, object_tolerance=self.object_tolerance,
                    margin_quantile=self.margin_quantile, unplaced_object=self.unplaced_object,
                    move_clearance=self.move_clearance, object_labels=self.object_labels,
                    lle_metric=self.lle_metric, hand_exclusion=self.hand_exclusion, track_gate=self.track_gate,
                    object_modes=self.object_modes, object_match_distance=self.object_match_distance)

    # --- fitting ------------------------------------------------------------------------------------------
    def fit(self, keypoints: Sequence[FrameKeypoints], joints, contact, stamps=None) -> 'ArmStateLearner':
        """Learn from exploration frames in the order they were taken (a hidden external label is taken from the
        frames before it): SIFT keypoints, joint readings and touch-sensor readings per frame."""
        joints = np.asarray(joints, dtype=float).reshape(-1, 2)
        contact = np.asarray(contact, dtype=bool).ravel()
        if not len(keypoints) == len(joints) == len(contact):
            raise ValueError('keypoints, joints and contact must have the same length')
        if not np.all(np.isfinite(joints)):
            raise ValueError('joints must be finite')
        if contact.sum() < 4 or (~contact).sum() < 4:
            raise ValueError(f'need at least 4 contact and 4 no-contact frames, got {int(contact.sum())} and '
                             f'{int((~contact).sum())}')
        with threadpool_limits(1, user_api='blas'):
            vec = KeypointVectorizer(**{'random_state': self.random_state, **self.vectorizer_params})
            vec.fit(list(keypoints))
            raw = vec.training_vectors_
            self.vectorizer_ = vec
            self._learn_roles(raw, joints)
            self._fit_object_geometry(raw, joints, contact)
            look_alikes = self._fit_contact_point(raw, joints, contact, keypoints)
            V = self._raw_vectors(raw, joints, look_alikes)
            self.imputer_ = NearestImputer(vec.n_impute_neighbors).fit(V)
            X = self.imputer_.transform(V)
        use = self.region_frames_
        # every fold needs two frames of each class: fewer folds while contact frames are scarce
        folds = max(2, min(self.n_folds, int((contact & use).sum()) // 2, int((~contact & use).sum()) // 2))
        models = REGION_MODELS if self.region == 'auto' else (self.region,)
        fitted = {}
        for method in ('lle', 'pca'):
            sel = select_contact_model(X, contact, method, self.n_components, (self.n_neighbors,), models,
                                       n_folds=folds, embedding_params=self._embedding_params(method),
                                       random_state=self.random_state, region_frames=use)['best']
            emb, region = fit_contact_model(X, contact, sel, method, self.n_components,
                                            self._embedding_params(method), self.random_state, region_frames=use)
            fitted[method] = (emb, region, sel)
        self.lle_, self.region_, self.selection_ = fitted['lle']
        self.pca_, self.pca_region_, self.pca_selection_ = fitted['pca']
        self.train_vectors_ = X
        self.train_joints_ = joints.copy()
        self.train_contact_ = contact.copy()
        self.train_stamps_ = (np.full(len(joints), -1, np.int64) if stamps is None
                              else np.asarray(stamps, dtype=np.int64).ravel())
        if len(self.train_stamps_) != len(joints):
            raise ValueError('stamps must have one entry per frame')
        self.__dict__.pop('_lle_tree', None)
        self._update_map()
        return self

    def _learn_roles(self, raw: np.ndarray, joints: np.ndarray) -> None:
        self.label_roles_, self.joint_coef_, self.label_r2_, self.label_motion_ = label_roles(
            raw, joints, self.min_motion, self.self_r2, self.external_r2)
        P = raw.reshape(len(raw), -1, 2)
        seen = np.isfinite(P[:, :, 0])
        self.label_mean_ = np.where(seen.any(0)[:, None],
                                    np.nansum(P, axis=0) / np.maximum(seen.sum(0), 1)[:, None], np.nan)
        if self.representation != 'absolute' and not np.any(self.label_roles_ == SELF):
            raise ValueError(f'no keypoint label follows the joint readings; cannot build the {self.representation} '
                             'vector')

    def _fit_object_geometry(self, raw: np.ndarray, joints: np.ndarray, contact: np.ndarray) -> None:
        """The keypoint-distance contact model (module docstring): rigid pairs of the robot's labels (over a lattice
        of the joint range, from the joint regression alone), the objects' label groups and templates, and each
        segment's contact distance to the objects' centres."""
        lattice = np.stack(np.meshgrid(*[np.linspace(lo, hi, 15) for lo, hi in self.joint_limits],
                                       indexing='ij'), -1).reshape(-1, 2)
        P = raw.reshape(len(raw), -1, 2)
        # Only labels the joints place precisely outline the robot: a label SIFT sometimes matches elsewhere on the
        # arm passes the regression's R^2 test yet lands 5-20 px off, and a segment through it blocked cells whose
        # true clearance was 20-100 px.
        precise = np.flatnonzero(self._label_residuals(P, joints) <= self.rigid_tolerance)
        pairs = rigid_pairs(self._robot_points(lattice)[:, precise], self.rigid_tolerance)
        self.rigid_pairs_ = precise[pairs].reshape(-1, 2)
        external = self.external_labels_
        self.object_group_ = np.full(P.shape[1], -1, int)
        self.object_template_ = np.full((P.shape[1], 2), np.nan)
        for g, members in enumerate(rigid_groups(P[:, external], self.object_tolerance, self.min_motion)):
            labels = external[members]
            self.object_group_[labels] = g
            self.object_template_[labels] = fit_template(P[:, labels])
        centres = self._object_centres(P)                                       # (n, G, 2)
        # a frame counts where it places every object: a hidden one could be the one touched
        known = (np.isfinite(centres[:, :, 0]).all(axis=1) if centres.shape[1] else np.zeros(len(P), bool))
        self.segment_margins_ = np.zeros(len(self.rigid_pairs_))
        if (known & contact).any() and (known & ~contact).any() and len(self.rigid_pairs_):
            D = segment_point_distances(self._robot_points(joints[known]), self.rigid_pairs_, centres[known])
            hit = contact[known]
            cap = float(D[hit].min(axis=1).max())
            self.segment_margins_ = np.minimum(np.quantile(D[~hit], self.margin_quantile, axis=0), cap)
        self.object_frames_ = int(known.sum())

    _CONTACT_ATTRS = ('contact_labels_', 'contact_coef_', 'contact_offset_', 'contact_radius_', 'contact_softness_',
                      'contact_object_', 'object_mean_', 'object_modes_', 'train_object_source_')

    def _fit_contact_point(self, raw: np.ndarray, joints: np.ndarray, contact: np.ndarray, keypoints):
        """The contact-point vector's parameters (module docstring), from the training frames only; returns the
        training frames' look-alike matches (_look_alikes; None for the other vectors)."""
        for name in self._CONTACT_ATTRS:
            setattr(self, name, None)
        self.region_frames_ = np.ones(len(contact), bool)
        if self.representation != 'contact_point':
            return None
        P = raw.reshape(len(raw), -1, 2)
        if not self.n_objects_:
            raise ValueError('contact_point needs a learned object: no rigid group of external labels moves')
        centres = self._object_centres(P)
        self.contact_object_ = int(np.argmax(np.isfinite(centres[:, :, 0]).sum(axis=0)))   # the most often placed
        # last link: robot labels that joint 1 moves, placed precisely, rigid with each other; A, B farthest apart
        lattice = np.stack(np.meshgrid(*[np.linspace(lo, hi, 15) for lo, hi in self.joint_limits],
                                       indexing='ij'), -1).reshape(-1, 2)
        R0 = self._robot_points(lattice)
        step = 0.05
        moves = np.median(np.linalg.norm(self._robot_points(lattice + [0.0, step]) - R0, axis=2), axis=0) / step
        on_link = (moves > 0.2 * moves.max()) & (self._label_residuals(P, joints) <= self.rigid_tolerance)
        pairs = self.rigid_pairs_[(self.rigid_pairs_[:, 0] != self.rigid_pairs_[:, 1])
                                  & on_link[self.rigid_pairs_[:, 0]] & on_link[self.rigid_pairs_[:, 1]]]
        if not len(pairs):
            raise ValueError('contact_point needs two precisely placed robot labels rigid on the last link')
        span = np.median(np.linalg.norm(R0[:, pairs[:, 0]] - R0[:, pairs[:, 1]], axis=2), axis=0)
        self.contact_labels_ = self.self_labels_[pairs[int(np.argmax(span))]]
        labels = np.flatnonzero(self.object_group_ == self.contact_object_)
        self.object_modes_ = label_modes(P[:, labels], self.object_template_[labels], self.object_tolerance,
                                         MAX_OBJECT_MODES)
        self.object_mean_ = np.zeros(2)          # placeholder for the track below
        placed = np.isfinite(centres[:, self.contact_object_, 0])
        if placed.any():
            self.object_mean_ = centres[placed, self.contact_object_].mean(axis=0)
        look_alikes = self._look_alikes(keypoints)
        o, source = self._object_track(P, joints, look_alikes)
        self.train_object_source_ = source
        A, M = self._link_frame(joints)
        fit = source <= 1                         # the frame or one just before places the object
        if (contact & fit).sum() < 2 or (~contact & fit).sum() < 2:
            raise ValueError('contact_point needs touch and no-touch frames that place the object')
        theta = fit_contact_disc(A - o, M, contact, fit)
        self.contact_coef_, self.contact_offset_ = theta[:2].copy(), theta[2:4].copy()
        self.contact_radius_, self.contact_softness_ = float(theta[4]), float(np.exp(theta[5]))
        # the contact region is fitted without the touch frames the disc puts far outside it: their object
        # estimate is wrong, so their vector says nothing about where contact lies (they are still embedded)
        far = np.linalg.norm(self._contact_vectors(joints, o), axis=1) > (
            self.contact_radius_ + MISPLACED_SOFTNESSES * self.contact_softness_)
        self.region_frames_ = ~(contact & far)
        return look_alikes

    def _look_alikes(self, keypoints: Sequence[FrameKeypoints]):
        """Per frame, the keypoints each label of the tracked object may be although the ratio test could not tell
        them from a look-alike (KeypointVectorizer.near_best_matches): positions (n, k, AMBIGUOUS_PER_LABEL, 2) and
        squared descriptor distances (n, k, AMBIGUOUS_PER_LABEL). On the benchmark scene the object often lies on a
        background shape whose corners look like its own; its labels then lose the ratio test in every frame.
        None while `object_match_distance` is 0: the track would not use them."""
        if self.object_match_distance <= 0:
            return None
        labels = np.flatnonzero(self.object_group_ == self.contact_object_)
        matches = [self.vectorizer_.near_best_matches(k, labels, AMBIGUOUS_PER_LABEL) for k in keypoints]
        if not matches:
            shape = (0, len(labels), AMBIGUOUS_PER_LABEL)
            return np.zeros(shape + (2,)), np.zeros(shape)
        return np.stack([m[0] for m in matches]), np.stack([m[1] for m in matches])

    def _link_frame(self, joints: np.ndarray):
        """A (n, 2) and M (n, 2, 2) = [B - A, perp(B - A)] of the last link at `joints`, from the joint regression."""
        ia, ib = np.searchsorted(self.self_labels_, self.contact_labels_)
        R = self._robot_points(np.asarray(joints, dtype=float).reshape(-1, 2))
        A, u = R[:, ia], R[:, ib] - R[:, ia]
        return A, np.stack([u, np.stack([-u[:, 1], u[:, 0]], axis=1)], axis=2)

    def _object_track(self, P: np.ndarray, joints: Optional[np.ndarray] = None, look_alikes=None):
        """Object estimate for frames P (n, L, 2) taken in this order: (centres (n, 2), source (n,) index into
        OBJECT_SOURCES). A sequential estimate, because the arm hides the object's keypoints in the very frames
        that matter. Each object label the frame shows implies a centre per offset it has (its position minus the
        offset; the first `object_modes` of object_modes_, from label_modes);
        a label within `hand_exclusion` px of where the joint regression puts one of the robot's labels at the
        frame's `joints` (n, 2; a NaN row or None: unknown) is left out: SIFT there mostly matched the hand (on
        non-benchmark scenes 21-32, 84 % of object labels within 3 px of a robot label were > 15 px off the object
        against 4 % beyond 15 px). Where implied centres of two labels agree (2 x `object_tolerance`) the frame
        places the object at the median of the centres agreeing with the one most labels agree with ('frame');
        `look_alikes` (_look_alikes of the same frames, or None) add the centres their keypoints within
        `object_match_distance` imply to that vote, never to the lone-label step below (two look-alikes of the
        wrong shape rarely agree where the template says; one always agrees with itself). With `object_labels` 1 a
        frame placing none keeps the previous estimate if one of its centres lies within `track_gate` px of it,
        else it takes the median of its labels' main-offset centres: the object was re-placed
        ('frame' either way). A frame that shows no object label keeps the previous estimate ('recent' within
        `recent_frames`, else 'stale'); before any, the training mean ('mean'). The defaults of `hand_exclusion`,
        `track_gate`, `object_modes` and `object_match_distance` are mm_bringup.tune_arm's 'track' choice (15 px,
        25 px, 2, 0.2: held-out frames > 8 px off 0.58 %, against 2.9 % without look-alikes at 20 px / 8 px / 3)."""
        labels = np.flatnonzero(self.object_group_ == self.contact_object_)
        modes = self.object_modes_[:, :self.object_modes]                       # (k, m, 2)
        Q = P[:, labels].copy()
        if joints is not None:
            q = np.asarray(joints, dtype=float).reshape(-1, 2)
            known = np.flatnonzero(np.isfinite(q).all(axis=1))
            if len(known) and self.hand_exclusion > 0:
                R = self._robot_points(q[known])                                  # (m, S, 2)
                with np.errstate(invalid='ignore'):
                    gap = np.linalg.norm(Q[known][:, :, None] - R[:, None], axis=3).min(axis=2)   # (m, k)
                near = np.zeros(Q.shape[:2], bool)
                near[known] = gap <= self.hand_exclusion
                Q[near] = np.nan
        # every centre a seen label implies, one per mode of that label: (n, k, m, 2)
        implied = Q[:, :, None] - modes[None] + modes[:, 0].mean(axis=0)
        owner = np.broadcast_to(np.arange(len(labels))[:, None], modes.shape[:2]).ravel()
        main = np.broadcast_to(np.arange(modes.shape[1]) == 0, modes.shape[:2]).ravel()
        # the same for the look-alike keypoints: (n, k, c, m, 2), owner per (k, c, m)
        alike = np.full((len(P), len(labels), 0, modes.shape[1], 2), np.nan)
        if look_alikes is not None and self.object_match_distance > 0:
            A = np.where((look_alikes[1] <= self.object_match_distance)[..., None], look_alikes[0], np.nan)
            if joints is not None and len(known) and self.hand_exclusion > 0:
                with np.errstate(invalid='ignore'):
                    gap = np.linalg.norm(A[known][:, :, :, None] - R[:, None, None], axis=4).min(axis=3)
                A[known] = np.where((gap <= self.hand_exclusion)[..., None], np.nan, A[known])
            alike = A[:, :, :, None] - modes[None, :, None] + modes[:, 0].mean(axis=0)
        alike_owner = np.broadcast_to(np.arange(len(labels))[:, None, None], alike.shape[1:4]).ravel()
        radius = 2.0 * self.object_tolerance
        est = np.empty((len(P), 2))
        source = np.zeros(len(P), int)
        last = None                                  # (estimate, index of the newest frame that placed it)
        for i in range(len(P)):
            cand = implied[i].reshape(-1, 2)
            ok = np.isfinite(cand[:, 0])
            cand, who, primary = cand[ok], owner[ok], main[ok]
            extra = alike[i].reshape(-1, 2)
            ok = np.isfinite(extra[:, 0])
            voters, voter = np.concatenate([cand, extra[ok]]), np.concatenate([who, alike_owner[ok]])
            placed = None
            if len(np.unique(voter)) >= 2:
                # the candidate that the most labels agree with (one candidate per label), then the tightest
                gap = np.linalg.norm(voters[:, None] - voters[None], axis=2)
                close = gap <= radius
                votes = np.array([len(np.unique(voter[c])) for c in close])
                if votes.max() >= 2:
                    best = np.lexsort((np.where(close, gap, 0.0).sum(axis=1), -votes))[0]
                    keep = []                        # per agreeing label, its candidate nearest the best
                    for w in np.unique(voter[close[best]]):
                        mine = np.flatnonzero(close[best] & (voter == w))
                        keep.append(mine[np.argmin(gap[best, mine])])
                    placed = np.median(voters[keep], axis=0)
            if placed is not None:
                last = (placed, i)
            elif self.object_labels == 1 and len(cand):
                moved = last is None or np.linalg.norm(cand - last[0], axis=1).min() > self.track_gate
                last = (np.median(cand[primary], axis=0), i) if moved else (last[0], i)
            if last is None:
                est[i], source[i] = self.object_mean_, 3
            else:
                age = i - last[1]
                est[i], source[i] = last[0], (0 if age == 0 else 1 if age <= self.recent_frames else 2)
        return est, source

    def _newest_object(self, raw: np.ndarray, frame: FrameKeypoints, recent: Sequence[FrameKeypoints], joints=None):
        """Object estimate (2,) and its source index of `frame` (its vector `raw`, already computed by the caller)
        after the frames `recent` (oldest first); `joints`: the frame's joint readings, if known."""
        frames = list(recent) + [frame]
        q = np.full((len(frames), 2), np.nan)
        if joints is not None:
            q[-1] = np.asarray(joints, dtype=float).reshape(2)
        P = np.array([self.vectorizer_.vectorize(r) for r in recent] + [raw]).reshape(len(frames), -1, 2)
        est, source = self._object_track(P, q, self._look_alikes(frames))
        return est[-1], int(source[-1])

    def object_track(self, keypoints: Sequence[FrameKeypoints], joints=None):
        """contact_point: the object estimate of frames taken in this order, (centres (n, 2), sources (n,) names
        from OBJECT_SOURCES; anything but 'frame' means the frame itself did not place the object); `joints`
        (n, 2): the frames' joint readings, if known (_object_track)."""
        if self.contact_labels_ is None:
            raise RuntimeError("object_track needs representation='contact_point'")
        raw = self.vectorizer_.transform(list(keypoints))
        est, source = self._object_track(raw.reshape(len(raw), -1, 2), joints, self._look_alikes(keypoints))
        return est, np.array(OBJECT_SOURCES)[source]

    def _contact_vectors(self, joints: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """(n, 2) d = p - o - e at the joint readings for object centres o (n, 2)."""
        A, M = self._link_frame(joints)
        return A + np.einsum('nij,j->ni', M, self.contact_coef_) - centres - self.contact_offset_

    def _label_residuals(self, P: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Median distance [px] between each robot label's seen positions in frames P (n, L, 2) and where the joint
        regression puts it (inf for a label never seen)."""
        predicted = self._robot_points(joints)
        seen = P[:, self.self_labels_]
        error = np.linalg.norm(predicted - seen, axis=2)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)           # a label never seen -> NaN
            median = np.nanmedian(error, axis=0)
        return np.where(np.isfinite(median), median, np.inf)

    @property
    def n_objects_(self) -> int:
        return int(self.object_group_.max()) + 1 if len(self.object_group_) else 0

    def _object_centres(self, P: np.ndarray) -> np.ndarray:
        """(n, G, 2) image position of each object's centre (its template's mean) in frames P (n, L, 2), NaN where
        the frame does not place it."""
        out = np.full((len(P), self.n_objects_, 2), np.nan)
        for g in range(self.n_objects_):
            labels = np.flatnonzero(self.object_group_ == g)
            template = self.object_template_[labels]
            out[:, g] = group_shifts(P[:, labels], template, self.object_tolerance) + template.mean(axis=0)
        return out

    def object_centres(self, frame: FrameKeypoints, recent: Sequence[FrameKeypoints] = ()) -> np.ndarray:
        """(G, 2) centre of each learned object as `frame` places it (an object it does not place: from the newest
        of `recent` (oldest first) that does; NaN if none does)."""
        out = np.full((self.n_objects_, 2), np.nan)
        for f in [frame] + list(recent)[::-1][:self.recent_frames]:
            hole = ~np.isfinite(out[:, 0])
            if not hole.any():
                break
            seen = self._object_centres(self.vectorizer_.vectorize(f).reshape(1, -1, 2))[0]
            out[hole] = seen[hole]
        return out

    def _robot_points(self, joints: np.ndarray) -> np.ndarray:
        """(n, S, 2) image positions of the robot's own labels where the joint regression puts them."""
        return np.einsum('nf,lfc->nlc', joint_features(joints), self.joint_coef_[self.self_labels_])

    def _embedding_params(self, method: str) -> Dict:
        return dict(lle_method=self.lle_method, lle_metric=self.lle_metric) if method == 'lle' else {}

    # --- vectors --------------------------------------------------------------------------------------------
    @property
    def self_labels_(self) -> np.ndarray:
        return np.flatnonzero(self.label_roles_ == SELF)

    @property
    def external_labels_(self) -> np.ndarray:
        return np.flatnonzero(self.label_roles_ == EXTERNAL)

    def _fill_from_recent(self, raw: np.ndarray, recent_raw: Sequence[np.ndarray]) -> np.ndarray:
        """Labels other than the robot's own that are unseen in `raw` (2L,) taken from the most recent frame of
        `recent_raw` (newest last) that saw them."""
        P = raw.reshape(-1, 2).copy()
        others = self.label_roles_ != SELF
        for r in list(recent_raw)[::-1][:self.recent_frames]:
            hole = others & ~np.isfinite(P[:, 0])
            if not hole.any():
                break
            R = r.reshape(-1, 2)
            P[hole] = R[hole]
        return P.ravel()

    def _raw_vectors(self, raw: np.ndarray, joints: Optional[np.ndarray] = None, look_alikes=None) -> np.ndarray:
        """Vectors to embed (with NaN) from raw labelled positions of frames in order (hidden external labels
        filled from the preceding frames); contact_point needs the frames' joint readings and takes their
        look-alike matches (_look_alikes)."""
        if self.representation == 'contact_point':
            if joints is None or len(np.asarray(joints).reshape(-1, 2)) != len(raw):
                raise ValueError('contact_point needs the joint readings of every frame')
            o = self._object_track(raw.reshape(len(raw), -1, 2), joints, look_alikes)[0]
            return self._contact_vectors(joints, o)
        filled = np.array([self._fill_from_recent(raw[i], raw[max(0, i - self.recent_frames):i])
                           for i in range(len(raw))]) if len(raw) else raw
        return self._vectors_of_positions(filled.reshape(len(filled), -1, 2))

    def _vectors_of_positions(self, P: np.ndarray) -> np.ndarray:
        """(n, L, 2) labelled positions (NaN where unknown) -> (n, d) vectors to embed."""
        if self.representation == 'absolute':
            return P.reshape(len(P), -1)
        ext = self.external_labels_
        if len(ext):
            with np.errstate(invalid='ignore'), warnings.catch_warnings():
                warnings.simplefilter('ignore', RuntimeWarning)     # all external labels unseen -> NaN offset
                offset = np.nanmedian(P[:, ext] - self.label_mean_[ext], axis=1)
        else:
            offset = np.zeros((len(P), 2))
        return (P[:, self.self_labels_] - offset[:, None, :]).reshape(len(P), -1)

    def frame_vectors(self, keypoints: Sequence[FrameKeypoints], joints=None) -> np.ndarray:
        """Imputed vectors (n, d) of new frames taken in this order, as embedded (for evaluation and figures);
        `joints` (n, 2): the frames' joint readings (used by contact_point only)."""
        keypoints = list(keypoints)
        raw = self.vectorizer_.transform(keypoints)
        look_alikes = self._look_alikes(keypoints) if self.representation == 'contact_point' else None
        return self.imputer_.transform(self._raw_vectors(raw, None if joints is None else np.asarray(joints, float),
                                                         look_alikes))

    def _update_map(self) -> None:
        self.train_predicted_ = self.region_.predict(self.lle_.embedding_)
        self.train_closeness_ = self.region_.closeness(self.lle_.embedding_)
        self.collision_map_, self.closeness_map_ = cell_map(
            self.train_joints_, self.train_closeness_ >= -self.map_margin, self.train_closeness_, self.joint_limits,
            self.grid_shape, self.cell_min_frames, self.cell_collision_fraction)

    @property
    def n_frames_(self) -> int:
        return len(self.train_joints_)

    # --- per-frame state ----------------------------------------------------------------------------------
    def transform(self, frame: FrameKeypoints, recent: Sequence[FrameKeypoints] = (), joints=None) -> Dict[str, object]:
        """State of one new frame: raw vector (NaN where unmatched), labelled count, LLE and PCA coordinates
        (out of sample), collision prediction and closeness of the LLE contact region, and object_source
        (contact_point: where the object estimate came from, OBJECT_SOURCES; None otherwise). `recent`: frames
        taken just before (oldest first) that may stand in for hidden external labels; `joints`: the frame's joint
        readings (contact_point needs them).

        The out-of-sample maps are those of ImageEmbedding.transform (LLE: barycentric weights of the n_neighbors
        nearest training vectors, regularised like scikit-learn's barycenter_weights; PCA: projection), computed
        here directly with a KD-tree: for one frame, scikit-learn's neighbour search costs tens of ms in thread
        start-up alone, which a per-frame node cannot afford."""
        if not hasattr(self, 'region_'):
            raise RuntimeError('ArmStateLearner is not fitted')
        raw = self.vectorizer_.vectorize(frame)
        source = None
        if self.representation == 'contact_point':
            if joints is None:
                raise ValueError('contact_point needs the joint readings of the frame')
            o, s = self._newest_object(raw, frame, recent, joints)
            v, source = self._contact_vectors(joints, o[None]), OBJECT_SOURCES[s]
        else:
            filled = self._fill_from_recent(raw, [self.vectorizer_.vectorize(r) for r in recent])
            v = self._vectors_of_positions(filled.reshape(1, -1, 2))
        x = self.imputer_.transform(v)[0]
        y = self.lle_transform(x[None])[0]
        p = self.pca_transform(x[None])[0]
        return dict(vector=raw, labelled=int(np.isfinite(raw).sum() // 2), embedding=y, pca_embedding=p,
                    collision=bool(self.region_.predict(y[None])[0]),
                    closeness=float(self.region_.closeness(y[None])[0]), object_source=source)

    def lle_transform(self, X: np.ndarray) -> np.ndarray:
        """LLE out-of-sample coordinates of imputed vectors (n, d)."""
        Z = (np.atleast_2d(X) - self.lle_.mean_) / self.lle_.scale_
        if not hasattr(self, '_lle_tree'):
            self._lle_Z = (self.train_vectors_ - self.lle_.mean_) / self.lle_.scale_
            self._lle_tree = cKDTree(self._lle_Z)
        k = min(self.n_neighbors, len(self._lle_Z))
        _, ind = self._lle_tree.query(Z, k=k)
        ind = np.asarray(ind).reshape(len(Z), k)
        D = self._lle_Z[ind] - Z[:, None, :]                    # (n, k, d)
        G = np.einsum('nkd,njd->nkj', D, D)
        trace = np.trace(G, axis1=1, axis2=2)
        G[:, np.arange(k), np.arange(k)] += np.where(trace > 0, self.lle_.reg * trace, self.lle_.reg)[:, None]
        w = np.linalg.solve(G, np.ones((len(Z), k, 1)))[:, :, 0]
        w /= w.sum(axis=1, keepdims=True)
        return np.einsum('nk,nkc->nc', w, self.lle_.embedding_[ind])

    def pca_transform(self, X: np.ndarray) -> np.ndarray:
        """PCA coordinates of imputed vectors (n, d)."""
        Z = (np.atleast_2d(X) - self.pca_.mean_) / self.pca_.scale_
        m = self.pca_.model_
        return (Z - m.mean_) @ m.components_.T

    # --- planning before moving -----------------------------------------------------------------------------
    def map_lattice(self) -> np.ndarray:
        """(R, C, 2) joint vectors of the lattice predict_collision_map evaluates: map_resolution points per cell
        side, cell edges and centres included (R = rows * map_resolution + 1)."""
        rows, cols = self.grid_shape
        s = self.map_resolution
        a = np.linspace(self.joint_limits[0, 0], self.joint_limits[0, 1], rows * s + 1)
        b = np.linspace(self.joint_limits[1, 0], self.joint_limits[1, 1], cols * s + 1)
        return np.stack(np.meshgrid(a, b, indexing='ij'), -1)

    def predict_frames(self, frame: FrameKeypoints, joints: np.ndarray, recent: Sequence[FrameKeypoints] = (),
                       method: Optional[str] = None) -> Dict[str, np.ndarray]:
        """Predicted states of the frames the camera would see with the arm at `joints` (n, 2) and everything else
        as in `frame` (hidden labels from `recent`, oldest first): the robot's labels where the joint regression
        puts them. `method` (default map_method): 'embedding' embeds the predicted vectors and applies the contact
        region (closeness >= map_threshold is contact); 'keypoint_distance' places the learned objects where the
        frames show them and compares the robot's predicted segments with their centres (closeness = largest
        1 - distance / contact distance over the segments, >= 0 is contact); where no contact distance was learned
        it falls back to 'embedding', and where the frames place no object it follows `unplaced_object`: fall back
        to 'embedding' (the paper's route), or 'block' every joint vector (objects_placed 0; the planner then
        refuses rather than trust a map that does not know where the object is). Returns dict(closeness (n,),
        collision (n,), clearance (n,) px or None, embedding (n, k) or None, external_seen (labels of the object side
        known), objects_placed (learned objects the frames place; -1 for 'embedding', 0 for 'block'), method (the
        route taken))."""
        if not hasattr(self, 'region_'):
            raise RuntimeError('ArmStateLearner is not fitted')
        method = method or self.map_method
        if method not in MAP_METHODS:
            raise ValueError(f'method must be one of {MAP_METHODS}')
        q = np.asarray(joints, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(q)):
            raise ValueError('joints must be finite')
        raw = self.vectorizer_.vectorize(frame)
        filled = self._fill_from_recent(raw, [self.vectorizer_.vectorize(r) for r in recent]).reshape(-1, 2)
        seen = int(np.isfinite(filled[self.external_labels_, 0]).sum())
        if method == 'keypoint_distance':
            centres = self.object_centres(frame, recent)
            placed = centres[np.isfinite(centres[:, 0])]
            # no contact distance learned (no contact frame placed the object): the route knows nothing to avoid
            learned = bool(len(self.rigid_pairs_) and self.segment_margins_.any())
            if len(placed) and learned:
                D = segment_point_distances(self._robot_points(q), self.rigid_pairs_,
                                            np.repeat(placed[None], len(q), axis=0))
                clearance = (D - self.segment_margins_[None]).min(axis=1)
                close = np.max(1.0 - D / np.maximum(self.segment_margins_, 1e-6)[None], axis=1)
                return dict(closeness=np.maximum(close, -1e6), collision=clearance < 0.0, clearance=clearance,
                            embedding=None, external_seen=seen, objects_placed=len(placed), method=method)
            if learned and self.unplaced_object == 'block':
                # the object is somewhere this frame does not show: any joint vector may touch it
                return dict(closeness=np.ones(len(q)), collision=np.ones(len(q), bool), clearance=None,
                            embedding=None, external_seen=seen, objects_placed=0, method=method)
        if self.representation == 'contact_point':
            o = self._newest_object(raw, frame, recent)[0]
            V = self._contact_vectors(q, np.repeat(o[None], len(q), axis=0))
        else:
            P = np.repeat(filled[None], len(q), axis=0)
            P[:, self.self_labels_] = self._robot_points(q)
            V = self._vectors_of_positions(P)
        Y = self.lle_transform(self.imputer_.transform(V))
        close = self.region_.closeness(Y)
        return dict(closeness=close, collision=close >= self.map_threshold, clearance=None, embedding=Y,
                    external_seen=seen, objects_placed=-1, method='embedding')

    def predict_collision_map(self, frame: FrameKeypoints, recent: Sequence[FrameKeypoints] = (),
                              method: Optional[str] = None) -> Dict[str, object]:
        """Collision map for the object placement seen in `frame` before moving (module docstring): dict(
        collision (rows, cols) bool, closeness (rows, cols) float (largest over the cell's cross of lattice
        points), blocked_moves (4, rows, cols) bool (move_hits: the move between two cell centres touches a
        predicted contact or, on the keypoint-distance route, keeps less than `move_clearance` px of predicted
        clearance), lattice_joints (R, C, 2), lattice_closeness (R, C), external_labels (learned count),
        external_seen (of them known in frame + recent), objects_placed, method (route taken), new_frames
        (1 + len(recent)))."""
        lattice = self.map_lattice()
        pred = self.predict_frames(frame, lattice.reshape(-1, 2), recent, method)
        close = pred['closeness'].reshape(lattice.shape[:2])
        hit = pred['collision'].reshape(lattice.shape[:2])
        collision, closeness = cross_max(hit, close, self.grid_shape, self.map_resolution)
        move_hit = hit if pred['clearance'] is None else (
            pred['clearance'].reshape(hit.shape) < self.move_clearance) | hit
        return dict(collision=collision, closeness=closeness,
                    blocked_moves=move_hits(move_hit, self.grid_shape, self.map_resolution), lattice_joints=lattice,
                    lattice_closeness=close,
                    external_labels=int(len(self.external_labels_)), external_seen=pred['external_seen'],
                    objects_placed=pred['objects_placed'], method=pred['method'], new_frames=1 + len(recent))

    # --- persistence (np.savez + JSON, no pickle) ---------------------------------------------------------
    def _contact_arrays(self) -> Dict[str, np.ndarray]:
        """The contact-point attributes as arrays (empty when representation is not contact_point)."""
        if self.contact_labels_ is None:
            return dict(contact_labels=np.zeros(0, int), contact_params=np.zeros(0),
                        object_modes=np.zeros((0, MAX_OBJECT_MODES, 2)), train_object_source=np.zeros(0, int))
        return dict(contact_labels=np.asarray(self.contact_labels_, int),
                    contact_params=np.r_[self.contact_coef_, self.contact_offset_, self.contact_radius_,
                                         self.contact_softness_, self.object_mean_, self.contact_object_],
                    object_modes=np.asarray(self.object_modes_, float),
                    train_object_source=np.asarray(self.train_object_source_, int))

    def _restore_contact(self, a: Dict[str, np.ndarray]) -> None:
        for name in self._CONTACT_ATTRS:
            setattr(self, name, None)
        labels, params = a['contact_labels'].astype(int).ravel(), a['contact_params'].astype(float).ravel()
        if (self.representation == 'contact_point') != (len(labels) > 0):
            raise ModelFileError('contact-point arrays do not match the representation')
        if not len(labels):
            return
        if len(labels) != 2 or len(params) != 9 or not np.all(np.isin(labels, self.self_labels_)):
            raise ModelFileError('contact-point arrays are malformed')
        if not np.all(np.isfinite(params)) or params[4] <= 0 or params[5] <= 0:
            raise ModelFileError('contact-point parameters must be finite with a positive radius and softness')
        self.contact_labels_ = labels
        self.contact_coef_, self.contact_offset_ = params[0:2], params[2:4]
        self.contact_radius_, self.contact_softness_ = float(params[4]), float(params[5])
        self.object_mean_, self.contact_object_ = params[6:8], int(params[8])
        if not 0 <= self.contact_object_ < self.n_objects_:
            raise ModelFileError('contact-point object is not a learned object')
        modes = a['object_modes'].astype(float)
        if (modes.shape != (int(np.sum(self.object_group_ == self.contact_object_)), MAX_OBJECT_MODES, 2)
                or not np.all(np.isfinite(modes[:, 0]))):
            raise ModelFileError("object_modes must hold a finite main mode for each of the object's labels")
        self.object_modes_ = modes
        self.train_object_source_ = a['train_object_source'].astype(int).ravel()
        if np.any((self.train_object_source_ < 0) | (self.train_object_source_ >= len(OBJECT_SOURCES))):
            raise ModelFileError('train_object_source names no object source')

    def save(self, path: os.PathLike) -> None:
        """Write the fitted model to `path` (.npz) atomically: a temp file in the same directory + os.replace."""
        path = Path(path)
        vec = self.vectorizer_
        meta = dict(format_version=FORMAT_VERSION, params=self.get_params(),
                    vectorizer_params={k: getattr(vec, k) for k in _VECTORIZER_PARAMS},
                    n_labels=int(vec.n_labels_), n_frames_seen=int(vec.n_frames_seen_),
                    selection=self.selection_, pca_selection=self.pca_selection_)
        region_arrays = {}
        for name in ('region', 'pca_region'):
            meta[name + '_state'], arrays = _region_state(getattr(self, name + '_'))
            region_arrays.update({f'{name}_{k}': v for k, v in arrays.items()})
        arrays = dict(
            meta=np.array(json.dumps(meta)),
            label_counts=vec.label_counts_, label_positions=vec.label_positions_,
            exemplar_positions=vec.exemplar_positions_, exemplar_descriptors=vec.exemplar_descriptors_,
            exemplar_labels=vec.exemplar_labels_, raw_training_vectors=vec.training_vectors_,
            lle_mean=self.lle_.mean_, lle_scale=self.lle_.scale_, lle_embedding=self.lle_.embedding_,
            lle_metric_map=self.lle_.metric_map_,
            pca_mean=self.pca_.mean_, pca_scale=self.pca_.scale_, pca_embedding=self.pca_.embedding_,
            pca_components=self.pca_.model_.components_, pca_model_mean=self.pca_.model_.mean_,
            pca_explained_variance=self.pca_.model_.explained_variance_,
            **region_arrays,
            train_vectors=self.train_vectors_, train_joints=self.train_joints_, train_contact=self.train_contact_,
            region_frames=self.region_frames_,
            train_stamps=self.train_stamps_, label_roles=self.label_roles_, joint_coef=self.joint_coef_,
            label_r2=self.label_r2_, label_motion=self.label_motion_, label_mean=self.label_mean_,
            rigid_pairs=self.rigid_pairs_, object_group=self.object_group_, object_template=self.object_template_,
            segment_margins=self.segment_margins_, object_frames=np.array(self.object_frames_),
            **self._contact_arrays(),
            imputer_vectors=np.where(self.imputer_.observed_, self.imputer_.values_, np.nan))
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + '.', suffix='.tmp', dir=path.parent)
        try:
            with os.fdopen(fd, 'wb') as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    @classmethod
    def load(cls, path: os.PathLike) -> 'ArmStateLearner':
        """Read a model written by `save`; ModelFileError if it is missing, corrupt or of another format."""
        try:
            with np.load(Path(path), allow_pickle=False) as data:
                a = {k: data[k] for k in data.files}
            meta = json.loads(str(a['meta']))
            if meta.get('format_version') != FORMAT_VERSION:
                raise ModelFileError(f'{path}: format version {meta.get("format_version")}, expected {FORMAT_VERSION}')
            params = dict(meta['params'])
            params['grid_shape'] = tuple(params['grid_shape'])
            self = cls(**params)
            self._restore(meta, a)
        except ModelFileError:
            raise
        except Exception as exc:  # zip/npy/JSON/key/shape errors all mean "this file is not a usable model"
            raise ModelFileError(f'{path}: cannot load model ({type(exc).__name__}: {exc})') from exc
        return self

    def _restore(self, meta: dict, a: Dict[str, np.ndarray]) -> None:
        vp = meta['vectorizer_params']
        vec = KeypointVectorizer(**vp)
        vec.n_labels_ = int(meta['n_labels'])
        vec.n_frames_seen_ = int(meta['n_frames_seen'])
        vec.label_counts_, vec.label_positions_ = a['label_counts'], a['label_positions']
        vec.exemplar_positions_ = a['exemplar_positions'].astype(np.float32)
        vec.exemplar_descriptors_ = a['exemplar_descriptors'].astype(np.float32)
        vec.exemplar_labels_ = a['exemplar_labels'].astype(int)
        if vec.exemplar_labels_.size and vec.exemplar_labels_.max() >= vec.n_labels_:
            raise ModelFileError('exemplar labels exceed the number of labels')
        vec._exemplar_tree = cKDTree(vec.exemplar_positions_)
        vec.training_vectors_ = a['raw_training_vectors']
        if vec.training_vectors_.shape[1] != 2 * vec.n_labels_:
            raise ModelFileError('training vectors do not match the number of labels')
        vec.imputer_ = (NearestImputer(vec.n_impute_neighbors) if vec.imputation == 'nearest'
                        else MeanImputer()).fit(vec.training_vectors_)
        self.vectorizer_ = vec
        self.label_roles_ = a['label_roles'].astype(int)
        self.joint_coef_, self.label_r2_ = a['joint_coef'], a['label_r2']
        self.label_motion_, self.label_mean_ = a['label_motion'], a['label_mean']
        if not (len(self.label_roles_) == len(self.joint_coef_) == len(self.label_mean_) == vec.n_labels_):
            raise ModelFileError('label arrays do not match the number of labels')
        self.rigid_pairs_ = a['rigid_pairs'].astype(int).reshape(-1, 2)
        self.object_group_ = a['object_group'].astype(int)
        self.object_template_ = a['object_template'].astype(float).reshape(-1, 2)
        self.segment_margins_ = a['segment_margins'].astype(float).ravel()
        self.object_frames_ = int(a['object_frames'])
        if not (len(self.object_group_) == len(self.object_template_) == vec.n_labels_
                and len(self.segment_margins_) == len(self.rigid_pairs_)):
            raise ModelFileError('object or segment arrays do not match the labels or the rigid pairs')
        if self.rigid_pairs_.size and not 0 <= self.rigid_pairs_.min() <= self.rigid_pairs_.max() < len(
                self.self_labels_):
            raise ModelFileError('rigid pairs name labels the robot does not have')
        self._restore_contact(a)
        self.imputer_ = NearestImputer(vec.n_impute_neighbors).fit(a['imputer_vectors'])
        X = a['train_vectors']
        if self.imputer_.values_.shape[1] != X.shape[1]:
            raise ModelFileError('imputer and training vectors differ in width')
        for name in ('lle', 'pca'):
            emb = ImageEmbedding(self.n_components, self.n_neighbors, name, random_state=self.random_state,
                                 **self._embedding_params(name))
            emb.mean_, emb.scale_, emb.embedding_ = a[f'{name}_mean'], a[f'{name}_scale'], a[f'{name}_embedding']
            emb.n_samples_seen_ = len(X)
            emb.metric_map_ = a['lle_metric_map'] if name == 'lle' else np.eye(self.n_components)
            if emb.metric_map_.shape != (self.n_components,) * 2 or not np.all(np.isfinite(emb.metric_map_)):
                raise ModelFileError('lle_metric_map is not a finite (n_components, n_components) matrix')
            Z = (X - emb.mean_) / emb.scale_
            if name == 'lle':
                m = LocallyLinearEmbedding(n_neighbors=self.n_neighbors, n_components=self.n_components,
                                           method=self.lle_method, eigen_solver='dense',
                                           random_state=self.random_state)
                m.nbrs_ = NearestNeighbors(n_neighbors=self.n_neighbors).fit(Z)
                m.embedding_ = emb.embedding_
            else:
                m = PCA(n_components=self.n_components, random_state=self.random_state)
                m.components_, m.mean_ = a['pca_components'], a['pca_model_mean']
                m.explained_variance_ = a['pca_explained_variance']
                m.n_components_ = self.n_components
            m.n_features_in_ = Z.shape[1]
            emb.model_ = m
            if emb.embedding_.shape != (len(X), self.n_components):
                raise ModelFileError(f'{name} embedding has shape {emb.embedding_.shape}')
            setattr(self, f'{name}_', emb)
        for name in ('region', 'pca_region'):
            arrays = {k[len(name) + 1:]: v for k, v in a.items() if k.startswith(name + '_')}
            setattr(self, name + '_', _region_from_state(meta[name + '_state'], arrays, self.random_state))
        self.selection_, self.pca_selection_ = meta['selection'], meta['pca_selection']
        self.train_vectors_ = X
        self.train_joints_ = a['train_joints']
        self.train_contact_ = a['train_contact'].astype(bool)
        self.train_stamps_ = a['train_stamps'].astype(np.int64)
        self.region_frames_ = a['region_frames'].astype(bool).ravel()
        if not (len(self.train_joints_) == len(self.train_contact_) == len(X) == len(self.train_stamps_)
                == len(self.region_frames_)):
            raise ModelFileError('training arrays have different lengths')
        self._update_map()


def _region_state(region):
    """(JSON-able parameters, arrays) of a fitted ContactSphere or ContactQuadric, for saving without pickle."""
    if isinstance(region, ContactQuadric):
        return (dict(kind='quadric', C=region.C, threshold=region.threshold_, intercept=region.intercept_,
                     depth=region.depth_),
                dict(mean=region.mean_, std=region.std_, coef=region.coef_))
    return (dict(kind='sphere' if region.metric == 'euclidean' else 'ellipsoid', radius=float(region.radius_),
                 spread=float(region.spread_)),
            dict(centre=region.centre_, whitening=region.whitening_))


def _region_from_state(meta: dict, arrays: Dict[str, np.ndarray], random_state):
    if meta['kind'] == 'quadric':
        r = ContactQuadric(C=meta['C'], threshold=meta['threshold'], random_state=random_state)
        r.mean_, r.std_, r.coef_ = arrays['mean'], arrays['std'], arrays['coef']
        if not r.mean_.shape == r.std_.shape or r.coef_.shape != quadratic_features(r.mean_[None]).shape[1:]:
            raise ModelFileError('quadric arrays do not fit together')
        r.intercept_, r.threshold_, r.depth_ = float(meta['intercept']), float(meta['threshold']), float(meta['depth'])
        return r
    if meta['kind'] not in ('sphere', 'ellipsoid'):
        raise ModelFileError(f"unknown contact region {meta['kind']!r}")
    r = ContactSphere(radius=meta['radius'], metric='euclidean' if meta['kind'] == 'sphere' else 'mahalanobis',
                      random_state=random_state)
    r.centre_, r.whitening_ = arrays['centre'], arrays['whitening']
    r.radius_, r.spread_, r.validation_ = float(meta['radius']), float(meta['spread']), None
    if r.whitening_.shape != (len(r.centre_), len(r.centre_)):
        raise ModelFileError('sphere arrays do not fit together')
    return r
