"""Joint position control of the simulated arm: one simulator step toward a commanded target. No rclpy here.

A position-controlled joint pair (ros2_control's forward position controller on a real robot) does not jump to the
target: per step of `dt` it moves along the straight joint-space line toward the (clipped) target, at most
`max_joint_speed * dt` rad in either joint. The hand's touch sensor fires if the hand touches the object anywhere
along that motion, not only at the end of the step (a fast move must not pass through the object unnoticed), so
contact is checked on sub-steps of at most `contact_resolution` rad.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np


def move_towards(current: Sequence[float], target: Sequence[float], max_step: float,
                 limits: np.ndarray) -> np.ndarray:
    """Joints after one step: straight toward `target` (clipped to `limits`), at most `max_step` rad per joint."""
    q = np.asarray(current, dtype=float)
    t = np.clip(np.asarray(target, dtype=float), limits[:, 0], limits[:, 1])
    d = t - q
    largest = float(np.max(np.abs(d)))
    if largest <= max_step or largest == 0.0:
        return t
    return q + d * (max_step / largest)


def swept_contact(model, start: Sequence[float], end: Sequence[float], resolution: float = 0.02) -> bool:
    """True if the hand touches the object anywhere on the straight joint-space segment start -> end."""
    return sweep(model, start, end, resolution).hand_contact


PART_NAMES = ('upper_link', 'forearm', 'hand')


@dataclass(frozen=True)
class Sweep:
    """What happened between the arm and the object along one straight joint-space motion (ends included)."""
    part_contact: Tuple[bool, bool, bool]        # per part of PART_NAMES: overlapped the object at some sub-step
    min_part_clearance: Tuple[float, float, float]   # smallest surface gap of each part [px]; < 0 = overlap
    min_hand_object_distance: float              # smallest hand-object centre distance [px]

    @property
    def hand_contact(self) -> bool:
        return self.part_contact[2]

    @property
    def any_contact(self) -> bool:
        return any(self.part_contact)

    @property
    def min_clearance(self) -> float:
        return min(self.min_part_clearance)

    @property
    def contact_parts(self) -> List[str]:
        return [name for name, hit in zip(PART_NAMES, self.part_contact) if hit]


def sweep(model, start: Sequence[float], end: Sequence[float], resolution: float = 0.02) -> Sweep:
    """Contact and clearance of every arm part along start -> end, on sub-steps of at most `resolution` rad."""
    a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    n = max(1, int(np.ceil(float(np.max(np.abs(b - a))) / max(resolution, 1e-6))))
    qs = a + (b - a) * (np.arange(n + 1) / n)[:, None]
    smallest = model.part_clearances(qs).min(axis=0)
    # the hand's gap is its centre distance less contact_distance (ArmModel.part_clearances)
    return Sweep(part_contact=tuple(bool(v < 0.0) for v in smallest),
                 min_part_clearance=tuple(float(v) for v in smallest),
                 min_hand_object_distance=float(smallest[2] + model.contact_distance))


class JointMotion:
    """Steps the arm toward commanded targets: `step(q, target) -> (new q, contact during the step)`."""

    def __init__(self, model, max_joint_speed: float = 4.0, dt: float = 0.1, contact_resolution: float = 0.02):
        if max_joint_speed <= 0 or dt <= 0 or contact_resolution <= 0:
            raise ValueError('max_joint_speed, dt and contact_resolution must be positive')
        self.model = model
        self.max_joint_speed = float(max_joint_speed)
        self.dt = float(dt)
        self.contact_resolution = float(contact_resolution)

    @property
    def max_step(self) -> float:
        return self.max_joint_speed * self.dt

    def step(self, current: Sequence[float], target: Sequence[float]) -> Tuple[np.ndarray, bool]:
        q = move_towards(current, target, self.max_step, self.model.joint_limits)
        return q, swept_contact(self.model, current, q, self.contact_resolution)
