"""Learning nodes of mm: grid-based sensor manifold, Jacobians and virtual sensor space (Section 2); SIFT keypoint vectors, LLE/PCA embedding and collision sphere (Section 3)."""
