"""Vectors of labelled SIFT keypoint positions from camera frames (paper Section 3.2). No rclpy here.

LLE needs one fixed-length vector per image, but SIFT gives an unordered, varying set of keypoints, and a keypoint
on the moving arm changes its descriptor as the links rotate. The paper labels keypoints with a self-organising map
whose topology comes from image-pixel similarity: keypoints of images that look alike are matched, and labels that
meet through such neighbour images are merged into one label per physical point.

We keep that idea but replace the SOM with an explicit, deterministic track builder:

1. Each training frame gives SIFT keypoints (positions, unit-norm descriptors) and a small grey thumbnail.
2. Frames are linked to their `n_frame_neighbors` most similar frames by thumbnail distance (the SOM's
   pixel-level topology): between similar images the arm moved little, so its keypoints moved at most
   `max_pixel_shift` pixels and kept nearly the same descriptor.
3. Keypoints of linked frames are matched (mutual nearest descriptor within `max_pixel_shift`, Lowe ratio
   `match_ratio`); matches are merged into tracks with union-find, best matches first, refusing any merge that would
   put two keypoints of one frame in the same track (that is how a chain of small drifts is kept from gluing two
   physical points together).
   A rigid part that does not rotate but jumps between frames (an object re-placed while the robot explores) keeps
   its descriptors but moves farther than `max_pixel_shift`; so keypoints of linked frames are also matched
   anywhere in the image when the match is very distinctive (ratio `global_match_ratio` against every other
   keypoint of the other frame), neither keypoint found a match nearby and another such match of the two frames
   moved by the same shift (within RIGID_SHIFT_TOLERANCE px), which joins the object's tracks across its placements.
4. Tracks seen in at least `min_frame_fraction` of the frames become labels (the `n_labels` most frequent ones).

Why not a SOM: a SOM needs a map size and a learning schedule, and its labels depend on the presentation order;
tracks over the image-similarity graph give the same "merge labels through neighbouring images" with one pass,
reproducible results and a direct confidence (the track length).

For new frames a label is found by matching each keypoint against label exemplars (mean descriptor of a label per
image cell of size `exemplar_spacing`), again restricted to exemplars within `max_pixel_shift`, with the ratio test
against the best exemplar of any other label. Unmatched labels are NaN; `fill_missing` imputes them from the nearest
training vectors measured on the observed coordinates (or with the training mean).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import List, Optional, Sequence, Union

import cv2
import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

THUMBNAIL_SIZE = 24
RIGID_SHIFT_TOLERANCE = 3.0     # px, far matches of one rigid jump agree this closely


@dataclass
class FrameKeypoints:
    """SIFT keypoints of one frame: positions (k, 2) in full-resolution pixels (x, y), unit-norm descriptors
    (k, 128) float32, and a THUMBNAIL_SIZE^2 grey thumbnail (float32 in [0, 1]) used to find similar frames."""

    positions: np.ndarray
    descriptors: np.ndarray
    thumbnail: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)


def _as_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f'expected a uint8 image, got dtype {img.dtype}')
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    if img.ndim == 2:
        return img
    raise ValueError(f'expected an (H, W), (H, W, 1) or (H, W, 3) image, got shape {img.shape}')


class KeypointExtractor:
    """SIFT on a down-scaled grey image (scale 0.5 keeps a 400x400 frame well under 20 ms and drops the
    single-pixel detail that does not repeat between frames). Keeps the `max_features` strongest keypoints.

    `opencv_threads` (default 1) is passed to cv2.setNumThreads when the extractor is made - a process-wide OpenCV
    setting: on a 200x200 working image SIFT is faster on one thread than with OpenCV's pool (measured 7.2 vs
    9.3 ms per frame on 2 idle cores, 14 vs 20 ms on busy ones), and the callers (the image_embedding node, the
    benchmark) run their own threads next to it. None leaves OpenCV's setting alone."""

    def __init__(self, max_features: int = 300, scale: float = 0.5, contrast_threshold: float = 0.04,
                 opencv_threads: Optional[int] = 1):
        if max_features < 1 or not 0.1 <= scale <= 2.0 or contrast_threshold <= 0:
            raise ValueError('max_features >= 1, 0.1 <= scale <= 2 and contrast_threshold > 0 are required')
        self.max_features = int(max_features)
        self.scale = float(scale)
        self.contrast_threshold = float(contrast_threshold)
        self.opencv_threads = opencv_threads
        if opencv_threads is not None:
            cv2.setNumThreads(int(opencv_threads))
        self._sift = cv2.SIFT_create(nfeatures=self.max_features, contrastThreshold=self.contrast_threshold)

    def __call__(self, image: np.ndarray) -> FrameKeypoints:
        gray = _as_gray(image)
        small = gray if self.scale == 1.0 else cv2.resize(gray, None, fx=self.scale, fy=self.scale,
                                                          interpolation=cv2.INTER_AREA)
        kps, desc = self._sift.detectAndCompute(small, None)
        thumb = cv2.resize(gray, (THUMBNAIL_SIZE, THUMBNAIL_SIZE), interpolation=cv2.INTER_AREA)
        thumb = thumb.astype(np.float32) / 255.0
        if desc is None or len(kps) == 0:
            return FrameKeypoints(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), thumb)
        pos = np.array([k.pt for k in kps], np.float32) / self.scale
        desc = desc.astype(np.float32)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-6)
        return FrameKeypoints(pos, desc, thumb)

    # SIFT objects are not picklable; keep the extractor usable in copies.
    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop('_sift', None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._sift = cv2.SIFT_create(nfeatures=self.max_features, contrastThreshold=self.contrast_threshold)


def extract_keypoints(image: np.ndarray, max_features: int = 300, scale: float = 0.5) -> FrameKeypoints:
    """Keypoints of one image (convenience; reuse a KeypointExtractor for many images)."""
    return KeypointExtractor(max_features=max_features, scale=scale)(image)


class _UnionFind:
    def __init__(self, n: int, frame_of: np.ndarray):
        self.parent = np.arange(n)
        self.frames = [{int(f)} for f in frame_of]

    def find(self, a: int) -> int:
        root = a
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[a] != root:
            self.parent[a], a = root, self.parent[a]
        return root

    def union_if_disjoint(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return True
        fa, fb = self.frames[ra], self.frames[rb]
        if not fa.isdisjoint(fb):
            return False
        if len(fa) < len(fb):
            ra, rb, fa, fb = rb, ra, fb, fa
        self.parent[rb] = ra
        fa |= fb
        self.frames[rb] = set()
        return True


def _match_pair(a: FrameKeypoints, b: FrameKeypoints, max_shift: float, ratio: float):
    """Mutual-nearest descriptor matches within max_shift pixels passing the ratio test: (ia, ib, ratio)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    d2 = 2.0 - 2.0 * (a.descriptors @ b.descriptors.T)
    dx = a.positions[:, 0:1] - b.positions[:, 0][None, :]
    dy = a.positions[:, 1:2] - b.positions[:, 1][None, :]
    d2[dx * dx + dy * dy > max_shift * max_shift] = np.inf
    best_b = np.argmin(d2, axis=1)
    best_a = np.argmin(d2, axis=0)
    rows = np.arange(len(a))
    d1 = d2[rows, best_b].copy()
    d2[rows, best_b] = np.inf
    second = d2.min(axis=1)
    ok = (best_a[best_b] == rows) & np.isfinite(d1)
    r = np.zeros(len(a))
    fin = np.isfinite(second)      # a unique candidate in the window counts as ratio 0
    r[fin] = np.sqrt(np.maximum(d1[fin], 0.0) / np.maximum(second[fin], 1e-12))
    ok &= r < ratio
    return rows[ok], best_b[ok], r[ok]


class NearestImputer:
    """Fill NaNs of a vector with the mean of the `n_neighbors` nearest training vectors that observe that entry.

    Distance between a vector and a training vector uses only the coordinates observed in both:
        d^2 = sum_common (x - t)^2 / sum_common var_j
    i.e. the squared difference relative to how much those coordinates vary in training. Unlike a plain mean over
    the common coordinates (sklearn's nan-Euclidean), coordinates that never move (background keypoints) add to
    neither sum, so they cannot make a donor look close just because it shares many of them. Labelled keypoints
    move rigidly with their part, so the neighbours' value is a far better guess than the column mean (checked in
    the tests)."""

    def __init__(self, n_neighbors: int = 5):
        if n_neighbors < 1:
            raise ValueError('n_neighbors must be >= 1')
        self.n_neighbors = int(n_neighbors)

    def fit(self, X: np.ndarray) -> 'NearestImputer':
        X = np.asarray(X, dtype=float)
        if X.ndim != 2:
            raise ValueError('X must be 2-D')
        self.observed_ = np.isfinite(X)
        self.values_ = np.where(self.observed_, X, 0.0)
        cnt = np.maximum(self.observed_.sum(0), 1)
        self.mean_ = self.values_.sum(0) / cnt
        self.var_ = np.where(self.observed_, (self.values_ - self.mean_) ** 2, 0.0).sum(0) / cnt + 1e-6
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        X = np.array(X, dtype=float, ndmin=2)
        if X.shape[1] != self.values_.shape[1]:
            raise ValueError(f'expected {self.values_.shape[1]} columns, got {X.shape[1]}')
        out = X.copy()
        obs_t = self.observed_.astype(float)
        sq_t = self.values_ ** 2
        for i in np.flatnonzero(~np.isfinite(X).all(axis=1)):
            x = X[i]
            o = np.isfinite(x)
            of = o.astype(float)
            xv = np.where(o, x, 0.0)
            # sum over common coords of (t - x)^2 = t^2 - 2 t x + x^2 (each only where both are observed)
            ssd = sq_t @ of - 2.0 * self.values_ @ xv + obs_t @ (xv ** 2)
            scale = obs_t @ (self.var_ * of)
            dist = np.where(scale > 0, np.maximum(ssd, 0.0) / np.maximum(scale, 1e-12), np.inf)
            order = np.argsort(dist, kind='stable')
            miss = ~o
            obs_sorted = self.observed_[order][:, miss]
            take = obs_sorted & (np.cumsum(obs_sorted, axis=0) <= self.n_neighbors)
            cnt = take.sum(0)
            vals = (self.values_[order][:, miss] * take).sum(0)
            out[i, miss] = np.where(cnt > 0, vals / np.maximum(cnt, 1), self.mean_[miss])
        return out


class MeanImputer:
    """Fill NaNs with the training column mean (the baseline of the imputation check)."""

    def fit(self, X: np.ndarray) -> 'MeanImputer':
        X = np.asarray(X, dtype=float)
        obs = np.isfinite(X)
        self.mean_ = np.where(obs.any(0), np.where(obs, X, 0.0).sum(0) / np.maximum(obs.sum(0), 1), 0.0)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        X = np.array(X, dtype=float, ndmin=2)
        return np.where(np.isfinite(X), X, self.mean_[None, :])


Frame = Union[np.ndarray, FrameKeypoints]


class KeypointVectorizer:
    """Fixed-length vectors of labelled SIFT keypoint positions (see the module docstring for the method).

    Parameters: n_labels (maximum number of labels; vector length is 2 * n_labels_), max_features and scale of the
    SIFT extractor, match_ratio (Lowe ratio), max_pixel_shift [px] between matched keypoints of similar frames and
    between a keypoint and a label exemplar, n_frame_neighbors (image-similarity graph degree), min_frame_fraction
    (a label must be seen in this share of the training frames), exemplar_spacing [px] (None: max_pixel_shift / 2),
    imputation ('nearest' or 'mean'), n_impute_neighbors, max_fit_frames (random subset for labelling; the rest
    is still vectorised), random_state, global_match_ratio (Lowe ratio of matches anywhere in the image; None: off).
    Learned attributes: n_labels_, label_counts_ (training frames per label), label_positions_ (mean position),
    exemplar_positions_, exemplar_descriptors_, exemplar_labels_, training_vectors_ (with NaN), imputer_,
    n_frames_seen_.
    """

    def __init__(self, n_labels: int = 200, max_features: int = 300, scale: float = 0.5, match_ratio: float = 0.8,
                 max_pixel_shift: float = 30.0, n_frame_neighbors: int = 6, min_frame_fraction: float = 0.2,
                 exemplar_spacing: Optional[float] = None, imputation: str = 'nearest', n_impute_neighbors: int = 5,
                 max_fit_frames: int = 3000, random_state: Optional[int] = 0,
                 global_match_ratio: Optional[float] = 0.5):
        if global_match_ratio is not None and not 0.0 < global_match_ratio <= 1.0:
            raise ValueError('global_match_ratio must be in (0, 1] or None (no matches beyond max_pixel_shift)')
        if n_labels < 1 or not 0.0 < match_ratio <= 1.0 or max_pixel_shift <= 0 or n_frame_neighbors < 1:
            raise ValueError('n_labels >= 1, 0 < match_ratio <= 1, max_pixel_shift > 0, n_frame_neighbors >= 1')
        if not 0.0 <= min_frame_fraction <= 1.0:
            raise ValueError('min_frame_fraction must be in [0, 1]')
        if imputation not in ('nearest', 'mean'):
            raise ValueError("imputation must be 'nearest' or 'mean'")
        self.n_labels = int(n_labels)
        self.max_features = max_features
        self.scale = scale
        self.match_ratio = float(match_ratio)
        self.max_pixel_shift = float(max_pixel_shift)
        self.n_frame_neighbors = int(n_frame_neighbors)
        self.min_frame_fraction = float(min_frame_fraction)
        self.exemplar_spacing = exemplar_spacing
        self.imputation = imputation
        self.n_impute_neighbors = int(n_impute_neighbors)
        self.max_fit_frames = int(max_fit_frames)
        self.random_state = random_state
        self.global_match_ratio = global_match_ratio
        self.extractor = KeypointExtractor(max_features=max_features, scale=scale)

    # --- per-frame helpers --------------------------------------------------------------------------------
    def extract(self, image: np.ndarray) -> FrameKeypoints:
        """Keypoints of one image with this vectoriser's extractor settings (for nodes: call per image)."""
        return self.extractor(image)

    def _keypoints(self, frames) -> List[FrameKeypoints]:
        """Accept one image, one FrameKeypoints, a (n, H, W[, C]) stack or a sequence of images / keypoints."""
        if isinstance(frames, FrameKeypoints) or (isinstance(frames, np.ndarray) and frames.ndim in (2, 3)):
            frames = [frames]
        return [f if isinstance(f, FrameKeypoints) else self.extractor(f) for f in frames]

    # --- fitting ------------------------------------------------------------------------------------------
    def fit(self, frames: Sequence[Frame]) -> 'KeypointVectorizer':
        # The matrices here are small (a few hundred keypoints); a multi-threaded BLAS only adds hand-off cost
        # (and stalls badly when the cores are busy), so keep BLAS single-threaded while fitting.
        with threadpool_limits(1, user_api='blas'):
            return self._fit(frames)

    def _fit(self, frames: Sequence[Frame]) -> 'KeypointVectorizer':
        kps = self._keypoints(frames)
        n = len(kps)
        if n < 2:
            raise ValueError('at least 2 training frames are needed')
        rng = np.random.default_rng(self.random_state)
        fit_idx = np.arange(n) if n <= self.max_fit_frames else np.sort(rng.choice(n, self.max_fit_frames, False))
        fit_kps = [kps[i] for i in fit_idx]
        labels_per_frame = self._build_tracks(fit_kps)
        self._build_exemplars(fit_kps, labels_per_frame)
        self.n_frames_seen_ = n
        self.training_vectors_ = self.transform(kps)
        self.imputer_ = (NearestImputer(self.n_impute_neighbors) if self.imputation == 'nearest'
                         else MeanImputer()).fit(self.training_vectors_)
        return self

    def _frame_graph(self, kps: List[FrameKeypoints]) -> np.ndarray:
        """Pairs (i, j), i < j, of frames among each other's n_frame_neighbors most similar thumbnails."""
        T = np.stack([k.thumbnail.ravel() for k in kps]).astype(np.float64)
        sq = (T ** 2).sum(1)
        d = sq[:, None] + sq[None, :] - 2.0 * T @ T.T
        np.fill_diagonal(d, np.inf)
        k = min(self.n_frame_neighbors, len(kps) - 1)
        nn = np.argpartition(d, k - 1, axis=1)[:, :k]
        pairs = np.stack([np.repeat(np.arange(len(kps)), k), nn.ravel()], axis=1)
        pairs = np.sort(pairs, axis=1)
        return np.unique(pairs, axis=0)

    def _build_tracks(self, kps: List[FrameKeypoints]) -> List[np.ndarray]:
        offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
        frame_of = np.repeat(np.arange(len(kps)), np.diff(offsets))
        ea, eb, er = [], [], []
        for i, j in self._frame_graph(kps):
            ia, ib, r = _match_pair(kps[i], kps[j], self.max_pixel_shift, self.match_ratio)
            if self.global_match_ratio is not None:
                ga, gb, gr = _match_pair(kps[i], kps[j], np.inf, self.global_match_ratio)
                shift = kps[j].positions[gb] - kps[i].positions[ga]
                far = (np.linalg.norm(shift, axis=1) > self.max_pixel_shift) & ~np.isin(ga, ia) & ~np.isin(gb, ib)
                # a part that jumped without turning moves all its keypoints alike: keep a far match only if another
                # far match of the pair shifted the same way (look-alike points of a turning part do not)
                agree = np.linalg.norm(shift[:, None] - shift[None], axis=2) < RIGID_SHIFT_TOLERANCE
                far &= (agree & far[None, :]).sum(axis=1) >= 2
                ia, ib, r = np.r_[ia, ga[far]], np.r_[ib, gb[far]], np.r_[r, gr[far]]
            ea.append(ia + offsets[i])
            eb.append(ib + offsets[j])
            er.append(r)
        ea, eb, er = (np.concatenate(v) if v else np.zeros(0) for v in (ea, eb, er))
        uf = _UnionFind(int(offsets[-1]), frame_of)
        for k in np.argsort(er, kind='stable'):
            uf.union_if_disjoint(int(ea[k]), int(eb[k]))
        roots = np.array([uf.find(a) for a in range(int(offsets[-1]))], dtype=int)
        counts = np.bincount(roots, minlength=len(roots)) if len(roots) else np.zeros(0, int)
        min_count = max(3, int(np.ceil(self.min_frame_fraction * len(kps))))
        candidates = np.flatnonzero(counts >= min_count)
        candidates = candidates[np.argsort(-counts[candidates], kind='stable')][:self.n_labels]
        if len(candidates) == 0:
            raise ValueError('no keypoint was tracked through enough frames; are the training frames related?')
        label_of_root = np.full(len(roots), -1, int)
        label_of_root[candidates] = np.arange(len(candidates))
        labels = label_of_root[roots]
        self.n_labels_ = len(candidates)
        self.label_counts_ = counts[candidates]
        return [labels[offsets[f]:offsets[f + 1]] for f in range(len(kps))]

    def _build_exemplars(self, kps: List[FrameKeypoints], labels_per_frame: List[np.ndarray]) -> None:
        spacing = self.exemplar_spacing if self.exemplar_spacing is not None else self.max_pixel_shift / 2.0
        pos = np.concatenate([k.positions for k in kps])
        desc = np.concatenate([k.descriptors for k in kps])
        lab = np.concatenate(labels_per_frame)
        keep = lab >= 0
        pos, desc, lab = pos[keep], desc[keep], lab[keep]
        cell = np.floor(pos / spacing).astype(np.int64)
        key = (lab.astype(np.int64) * 100003 + cell[:, 0]) * 100003 + cell[:, 1]
        _, inv = np.unique(key, return_inverse=True)
        m = inv.max() + 1
        cnt = np.bincount(inv, minlength=m).astype(float)
        ex_pos = np.stack([np.bincount(inv, pos[:, d], m) for d in range(2)], 1) / cnt[:, None]
        # per-exemplar descriptor sums (np.add.at is slow; a stable sort keeps the summation order, so the sums are
        # the same as np.add.at's)
        order = np.argsort(inv, kind='stable')
        starts = np.flatnonzero(np.r_[True, np.diff(inv[order]) != 0])
        ex_desc = np.add.reduceat(desc[order].astype(np.float64), starts, axis=0)
        ex_desc /= np.maximum(np.linalg.norm(ex_desc, axis=1, keepdims=True), 1e-9)
        ex_lab = np.zeros(m, int)
        ex_lab[inv] = lab
        self.exemplar_positions_ = ex_pos.astype(np.float32)
        self.exemplar_descriptors_ = ex_desc.astype(np.float32)
        self.exemplar_labels_ = ex_lab
        self._exemplar_tree = cKDTree(self.exemplar_positions_)
        self.label_positions_ = np.stack([np.bincount(lab, pos[:, d], self.n_labels_) for d in range(2)], 1) / \
            np.maximum(np.bincount(lab, minlength=self.n_labels_), 1)[:, None]

    # --- vectorising --------------------------------------------------------------------------------------
    def _candidate_pairs(self, frame: FrameKeypoints):
        """(keypoint index, exemplar index, squared descriptor distance) of every exemplar within max_pixel_shift of
        each keypoint (KD-tree on exemplar positions, so the cost does not grow with the image area), sorted by
        keypoint, then distance."""
        near = self._exemplar_tree.query_ball_point(frame.positions, self.max_pixel_shift)
        lengths = np.fromiter((len(n) for n in near), int, len(frame))
        qi = np.repeat(np.arange(len(frame)), lengths)
        ej = np.fromiter(itertools.chain.from_iterable(near), int, int(lengths.sum()))
        d2 = 2.0 - 2.0 * np.einsum('ij,ij->i', frame.descriptors[qi], self.exemplar_descriptors_[ej])
        order = np.lexsort((d2, qi))
        return qi[order], ej[order], d2[order]

    def assign_labels(self, frame: FrameKeypoints) -> np.ndarray:
        """Label index per keypoint (-1: not matched); each label goes to at most one keypoint (the best match).

        Candidates are the exemplars within max_pixel_shift; a keypoint takes the label of its nearest candidate
        descriptor if that is `match_ratio` closer than the nearest candidate of any other label."""
        self._check_fitted()
        k = len(frame)
        out = np.full(k, -1, int)
        if k == 0:
            return out
        qi, ej, d2 = self._candidate_pairs(frame)
        if not len(qi):
            return out
        first = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
        kq = qi[first]
        best_d = d2[first]
        best_lab = self.exemplar_labels_[ej[first]]
        lab_of_pair = self.exemplar_labels_[ej]
        group = np.repeat(np.arange(len(first)), np.diff(np.r_[first, len(qi)]))
        other = np.where(lab_of_pair != best_lab[group], d2, np.inf)
        second = np.minimum.reduceat(other, first)
        ok = (best_d < (self.match_ratio ** 2) * second) | ~np.isfinite(second)
        cand = np.flatnonzero(ok)
        cand = cand[np.argsort(best_d[cand], kind='stable')]
        taken = np.zeros(self.n_labels_, bool)
        for c in cand:       # one keypoint per label: the closest descriptor wins
            lab = best_lab[c]
            if not taken[lab]:
                taken[lab] = True
                out[kq[c]] = lab
        return out

    def near_best_matches(self, frame: FrameKeypoints, labels: Sequence[int], per_label: int):
        """Keypoints that may be labels[j] although the ratio test cannot tell them from another label (a look-alike
        elsewhere in the scene): those whose nearest exemplar of labels[j] within max_pixel_shift is at most
        1 / match_ratio^2 times as far (squared descriptor distance) as their nearest exemplar of any label. Returns
        positions (J, per_label, 2) and squared descriptor distances (J, per_label), the closest first, NaN / inf
        where fewer; the caller decides which to believe (ArmStateLearner checks them against each other)."""
        self._check_fitted()
        labels = np.asarray(labels, dtype=int)
        pos = np.full((len(labels), per_label, 2), np.nan)
        dist = np.full((len(labels), per_label), np.inf)
        if len(frame) == 0 or not len(labels):
            return pos, dist
        qi, ej, d2 = self._candidate_pairs(frame)
        if not len(qi):
            return pos, dist
        best = np.full(len(frame), np.inf)
        np.minimum.at(best, qi, d2)
        slot = np.full(self.n_labels_, -1, int)
        slot[labels] = np.arange(len(labels))
        j = slot[self.exemplar_labels_[ej]]
        keep = (j >= 0) & (d2 <= best[qi] / self.match_ratio ** 2)
        qi, j, d2 = qi[keep], j[keep], d2[keep]
        order = np.lexsort((d2, j))                           # per label, the closest first
        qi, j, d2 = qi[order], j[order], d2[order]
        _, first = np.unique(j * len(frame) + qi, return_index=True)   # a keypoint once per label (its closest)
        first = np.sort(first)
        qi, j, d2 = qi[first], j[first], d2[first]
        rank = np.arange(len(j)) - np.searchsorted(j, j)      # position within its label's run
        use = rank < per_label
        pos[j[use], rank[use]] = frame.positions[qi[use]]
        dist[j[use], rank[use]] = d2[use]
        return pos, dist

    def vectorize(self, frame: Frame) -> np.ndarray:
        """(2 * n_labels_,) vector [x0, y0, x1, y1, ...] with NaN where a label was not matched."""
        kp = frame if isinstance(frame, FrameKeypoints) else self.extractor(frame)
        lab = self.assign_labels(kp)
        v = np.full((self.n_labels_, 2), np.nan)
        m = lab >= 0
        v[lab[m]] = kp.positions[m]
        return v.ravel()

    def transform(self, frames: Sequence[Frame]) -> np.ndarray:
        """(n, 2 * n_labels_) labelled keypoint positions with NaN where unmatched (see fill_missing)."""
        self._check_fitted()
        kps = self._keypoints(frames)
        if not kps:
            return np.zeros((0, 2 * self.n_labels_))
        with threadpool_limits(1, user_api='blas'):
            return np.stack([self.vectorize(k) for k in kps])

    def fill_missing(self, X: np.ndarray) -> np.ndarray:
        """Impute NaN entries with the fitted imputer ('nearest' training vectors or the 'mean')."""
        self._check_fitted()
        return self.imputer_.transform(X)

    def fit_transform(self, frames: Sequence[Frame]) -> np.ndarray:
        self.fit(frames)
        return self.training_vectors_.copy()

    def _check_fitted(self) -> None:
        if not hasattr(self, 'exemplar_labels_'):
            raise RuntimeError('KeypointVectorizer is not fitted')
