"""Random exploration of the arm's joint space before learning (paper Section 3.1: "random arm motion"). No rclpy.

The explorer picks joint targets and keeps one until the arm is there (or `max_steps_per_target` steps passed), so
the camera sees straight sweeps across the joint box. Contact with the object is rare under uniform targets, and
the contact sphere needs contact samples, so - as the robot feels contact on its hand - a share `contact_share` of
the targets is drawn around joint configurations where contact was felt before (Gaussian, `spread` rad). The
explorer only uses the robot's own joint angles and touch sensor.
"""
from __future__ import annotations

from typing import List, Optional, Sequence

import numpy as np


class ArmExplorer:
    """Parameters: joint_limits ((lo0, hi0), (lo1, hi1)) [rad], contact_share, spread [rad], tolerance [rad]
    (target reached), max_steps_per_target, max_contact_memory, random_state.
    State: target_, n_targets_, contact_joints_ (configurations where contact was felt)."""

    def __init__(self, joint_limits, contact_share: float = 0.25, spread: float = 0.08, tolerance: float = 0.02,
                 max_steps_per_target: int = 30, max_contact_memory: int = 500, random_state: Optional[int] = 0):
        lim = np.asarray(joint_limits, dtype=float)
        if lim.shape != (2, 2) or not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
            raise ValueError('joint_limits must be ((lo0, hi0), (lo1, hi1)) with finite lo < hi')
        if not 0.0 <= contact_share <= 1.0 or spread < 0 or tolerance <= 0 or max_steps_per_target < 1:
            raise ValueError('0 <= contact_share <= 1, spread >= 0, tolerance > 0, max_steps_per_target >= 1')
        self.joint_limits = lim
        self.contact_share = float(contact_share)
        self.spread = float(spread)
        self.tolerance = float(tolerance)
        self.max_steps_per_target = int(max_steps_per_target)
        self.max_contact_memory = int(max_contact_memory)
        self.random_state = random_state
        self._rng = np.random.default_rng(random_state)
        self.target_: Optional[np.ndarray] = None
        self.n_targets_ = 0
        self.contact_joints_: List[np.ndarray] = []
        self._steps_on_target = 0

    def _new_target(self) -> np.ndarray:
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        if self.contact_joints_ and self._rng.random() < self.contact_share:
            centre = self.contact_joints_[int(self._rng.integers(len(self.contact_joints_)))]
            t = centre + self._rng.normal(0.0, self.spread, 2)
        else:
            t = lo + (hi - lo) * self._rng.random(2)
        self.n_targets_ += 1
        self._steps_on_target = 0
        return np.clip(t, lo, hi)

    def next_command(self, joints: Sequence[float], contact: bool) -> np.ndarray:
        """Joint target to command after observing `joints` and the touch sensor of the last step."""
        q = np.asarray(joints, dtype=float).reshape(-1)
        if q.shape != (2,) or not np.all(np.isfinite(q)):
            raise ValueError('expected 2 finite joint values')
        if contact:
            self.contact_joints_.append(q.copy())
            if len(self.contact_joints_) > self.max_contact_memory:
                self.contact_joints_.pop(int(self._rng.integers(len(self.contact_joints_))))
        self._steps_on_target += 1
        if (self.target_ is None or np.max(np.abs(q - self.target_)) <= self.tolerance
                or self._steps_on_target > self.max_steps_per_target):
            self.target_ = self._new_target()
        return self.target_.copy()
