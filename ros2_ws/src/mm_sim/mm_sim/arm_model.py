"""Two-joint planar arm seen by a fixed camera, with an object and a static background (paper Section 3.1). No rclpy.

The paper moves NAO's shoulder roll and shoulder pitch while the other joints are fixed, so the arm moves in a plane
perpendicular to the camera's optical axis. Here that plane *is* the image plane: a 400x400 RGB frame, pixel
coordinates (x right, y down). The shoulder sits near the bottom centre; joint 0 ("shoulder_roll") is the absolute
angle of the upper link and joint 1 ("shoulder_pitch") the angle of the forearm relative to the upper link, both
measured like atan2(dy, dx) in image coordinates (so -pi/2 points straight up). The default limits make the hand sweep
the upper part of the image, where the object is placed.

Every part carries a high-contrast random texture (blobs and stripes of random colours) generated once from
`random_state`, so SIFT finds stable keypoints on the hand, the links, the object and the background, and a frame is
a pure function of (seed, joints). Rendering is fast: the background and object are drawn once; per frame only the
three arm patches are warped (cv2.warpAffine into their bounding boxes) and alpha-composited.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np
from mm_common.robot_description import planar_chain_urdf

JOINT_NAMES = ('shoulder_roll', 'shoulder_pitch')
# URDF lengths are metres; the simulated arm lives in the image plane, so 1 px is written as 1 mm.
PX_TO_URDF = 1e-3


def _random_texture(rng: np.random.Generator, height: int, width: int, n_blobs: Optional[int] = None,
                    disc: bool = False) -> np.ndarray:
    """A high-contrast texture: coloured base, a few stripes and blobs of several sizes (SIFT responds to blobs).

    Blob radii span 3-9 px so DoG extrema appear at a few scales even on a half-resolution image (keypoints are
    extracted at scale 0.5 for speed); colours are far from the base so the contrast survives rotation. With
    `disc`, blobs are placed inside the inscribed disc (they would be cut off by the disc mask otherwise). A light
    blur removes the pixel-level aliasing that would give unstable, tiny keypoints."""
    base = rng.integers(70, 186, size=3)
    img = np.empty((height, width, 3), np.uint8)
    img[:] = base
    area = height * width
    for _ in range(max(1, area // 1500)):      # a few stripes for corners / elongated structure
        c = tuple(int(v) for v in np.where(base > 127, rng.integers(0, 50, 3), rng.integers(205, 256, 3)))
        p0 = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        p1 = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.line(img, p0, p1, c, int(rng.integers(2, 4)), cv2.LINE_AA)
    n = n_blobs if n_blobs is not None else max(4, area // 180)
    cx, cy, rad = (width - 1) / 2.0, (height - 1) / 2.0, min(width, height) / 2.0
    for _ in range(n):
        dark = rng.random() < 0.5
        c = tuple(int(v) for v in (rng.integers(0, 60, 3) if dark else rng.integers(195, 256, 3)))
        r = int(rng.integers(3, 10))
        if disc:
            ang, rr = rng.uniform(0, 2 * math.pi), (rad - r - 1) * math.sqrt(rng.random())
            centre = (int(round(cx + rr * math.cos(ang))), int(round(cy + rr * math.sin(ang))))
        else:
            centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        if rng.random() < 0.7:
            cv2.circle(img, centre, r, c, -1, cv2.LINE_AA)
        else:
            cv2.rectangle(img, (centre[0] - r, centre[1] - r // 2), (centre[0] + r, centre[1] + r // 2), c, -1)
    return cv2.GaussianBlur(img, (0, 0), 0.8)


def _disc_alpha(size: int, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    c = (size - 1) / 2.0
    d = np.sqrt((xx - c) ** 2 + (yy - c) ** 2)
    return np.clip(radius + 0.5 - d, 0.0, 1.0).astype(np.float32)


class ArmModel:
    """Planar 2-link arm, a graspable object and background shapes, rendered as a camera image.

    Parameters: image_size [px], shoulder (x, y) [px], link_lengths and link_widths [px], hand_radius and
    object_radius [px], joint_limits ((lo0, hi0), (lo1, hi1)) [rad], n_background shapes, object_position (x, y) or
    None for a random reachable place, contact_margin [px] added to the contact distance, random_state (textures,
    layout and object place).
    Attributes after construction: object_position_ (x, y), static_background_ (background shapes only),
    background_ (static background with the object drawn at object_position_), textures.
    """

    def __init__(self, image_size: int = 400, shoulder: Tuple[float, float] = (200.0, 330.0),
                 link_lengths: Tuple[float, float] = (110.0, 90.0), link_widths: Tuple[float, float] = (24.0, 20.0),
                 hand_radius: float = 18.0, object_radius: float = 20.0,
                 joint_limits: Tuple[Tuple[float, float], Tuple[float, float]] = ((-3.2, -0.8), (0.0, 2.2)),
                 n_background: int = 3, object_position: Optional[Tuple[float, float]] = None,
                 contact_margin: float = 0.0, random_state: Optional[int] = 0):
        limits = np.asarray(joint_limits, dtype=float)
        if limits.shape != (2, 2) or not np.all(np.isfinite(limits)) or np.any(limits[:, 0] >= limits[:, 1]):
            raise ValueError('joint_limits must be ((lo0, hi0), (lo1, hi1)) with finite lo < hi')
        if image_size < 64 or min(link_lengths) <= 0 or min(link_widths) <= 0 or hand_radius <= 0 or object_radius <= 0:
            raise ValueError('image_size >= 64 and positive link lengths, widths and radii are required')
        self.image_size = int(image_size)
        self.shoulder = np.asarray(shoulder, dtype=float)
        self.link_lengths = tuple(float(v) for v in link_lengths)
        self.link_widths = tuple(float(v) for v in link_widths)
        self.hand_radius = float(hand_radius)
        self.object_radius = float(object_radius)
        self.joint_limits = limits
        self.n_background = int(n_background)
        self.contact_margin = float(contact_margin)
        self.random_state = random_state
        rng = np.random.default_rng(random_state)
        # Textured patches of the moving parts: RGB + alpha (float), drawn with their anchor at patch (0, h/2).
        self._links = []
        for length, width in zip(self.link_lengths, self.link_widths):
            h, w = int(round(width)), int(round(length + width / 2))
            rgb = _random_texture(rng, h, w)
            alpha = np.ones((h, w), np.float32)
            self._links.append((rgb, alpha))
        size = int(2 * math.ceil(self.hand_radius) + 3)
        hand = _random_texture(rng, size, size, n_blobs=9, disc=True)
        self._hand = (hand, _disc_alpha(size, self.hand_radius))
        # The object's texture is made once; the object can be moved later (set_object_position) without
        # changing the background or any texture, as the paper varies the object's place between frames.
        # (Drawn from the generator after the background, so a seed gives the same scene as before objects moved.)
        self.object_position_ = (self._place_object(rng) if object_position is None
                                 else np.asarray(object_position, dtype=float))
        self.static_background_ = self._make_background(rng)
        d = int(2 * math.ceil(self.object_radius) + 3)
        self._object = (_random_texture(rng, d, d, n_blobs=10, disc=True), _disc_alpha(d, self.object_radius))
        self.set_object_position(self.object_position_)

    # --- the object ---------------------------------------------------------------------------------------------
    def set_object_position(self, position: Sequence[float]) -> None:
        """Move the object to image point `position` (x, y) [px]; raises ValueError if it leaves the image."""
        p = np.asarray(position, dtype=float).reshape(-1)
        if p.shape != (2,) or not np.all(np.isfinite(p)):
            raise ValueError('object position must be 2 finite pixel coordinates (x, y)')
        r = self.object_radius
        if np.any(p < r) or np.any(p > self.image_size - r):
            raise ValueError(f'object at {p.tolist()} would leave the {self.image_size} px image')
        self.object_position_ = p
        frame = self.static_background_.copy()
        tex, alpha = self._object
        c = (alpha.shape[0] - 1) / 2.0
        self._blit(frame, tex, alpha, p, 0.0, anchor=(c, c))
        self.background_ = frame

    def random_object_position(self, rng: np.random.Generator) -> np.ndarray:
        """A random object place where the hand can touch the object from every side (see _place_object)."""
        return self._place_object(rng)

    # --- kinematics -------------------------------------------------------------------------------------------
    def validate_joints(self, joints: Sequence[float]) -> np.ndarray:
        """Return joints as a float array of shape (2,); raise ValueError on wrong size or non-finite values."""
        q = np.asarray(joints, dtype=float).reshape(-1)
        if q.shape != (2,):
            raise ValueError(f'expected 2 joint values ({", ".join(JOINT_NAMES)}), got {q.size}')
        if not np.all(np.isfinite(q)):
            raise ValueError('joint values must be finite')
        return q

    def robot_description(self, max_joint_speed: float) -> str:
        """URDF of the arm (joint limits, link lengths, speed limit [rad/s]) for arm/robot_description."""
        joints = [(name, lo, hi, length * PX_TO_URDF)
                  for name, (lo, hi), length in zip(JOINT_NAMES, self.joint_limits, self.link_lengths)]
        return planar_chain_urdf('mm_planar_arm', joints, max_joint_speed, unit_note='the arm moves in the camera '
                                 'image plane: lengths are image pixels x 1e-3 (1 px -> 1 mm)')

    def clip_joints(self, joints: Sequence[float]) -> np.ndarray:
        """Validated joints clipped to the limits (a position controller saturates at the joint stops)."""
        q = self.validate_joints(joints)
        return np.clip(q, self.joint_limits[:, 0], self.joint_limits[:, 1])

    def within_limits(self, joints: Sequence[float]) -> bool:
        q = self.validate_joints(joints)
        return bool(np.all(q >= self.joint_limits[:, 0]) and np.all(q <= self.joint_limits[:, 1]))

    def sample_joints(self, n: int, rng: Optional[np.random.Generator] = None) -> np.ndarray:
        """n joint vectors uniform inside the limits."""
        rng = rng if rng is not None else np.random.default_rng()
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        return lo + (hi - lo) * rng.random((int(n), 2))

    def link_points(self, joints: Sequence[float]) -> np.ndarray:
        """(3, 2) image points: shoulder, elbow, hand centre."""
        q = self.validate_joints(joints)
        a0, a1 = q[0], q[0] + q[1]
        elbow = self.shoulder + self.link_lengths[0] * np.array([math.cos(a0), math.sin(a0)])
        hand = elbow + self.link_lengths[1] * np.array([math.cos(a1), math.sin(a1)])
        return np.stack([self.shoulder, elbow, hand])

    def inverse_kinematics(self, point: Sequence[float]) -> Optional[np.ndarray]:
        """Joints that put the hand centre at an image point, or None when it is out of reach or outside the limits.
        Within the default limits (joint 1 >= 0) the elbow bends one way only, so the solution is unique."""
        d = np.asarray(point, dtype=float) - self.shoulder
        l1, l2 = self.link_lengths
        r2 = float(d @ d)
        c = (r2 - l1 * l1 - l2 * l2) / (2 * l1 * l2)
        if not -1.0 <= c <= 1.0:
            return None
        for q1 in (math.acos(c), -math.acos(c)):
            q0 = math.atan2(d[1], d[0]) - math.atan2(l2 * math.sin(q1), l1 + l2 * math.cos(q1))
            for wrap in (0.0, 2 * math.pi, -2 * math.pi):
                q = np.array([q0 + wrap, q1])
                if np.all(q >= self.joint_limits[:, 0]) and np.all(q <= self.joint_limits[:, 1]):
                    return q
        return None

    def hand_position(self, joints: Sequence[float]) -> np.ndarray:
        return self.link_points(joints)[2]

    def hand_object_distance(self, joints: Sequence[float]) -> float:
        """Ground-truth distance between hand and object centres [px] (evaluation only)."""
        return float(np.linalg.norm(self.hand_position(joints) - self.object_position_))

    @property
    def contact_distance(self) -> float:
        """Centre distance below which the hand disc overlaps the object disc."""
        return self.hand_radius + self.object_radius + self.contact_margin

    def in_contact(self, joints: Sequence[float]) -> bool:
        """The hand touches (overlaps) the object."""
        return self.hand_object_distance(joints) < self.contact_distance

    def link_points_many(self, joints: np.ndarray) -> np.ndarray:
        """(N, 3, 2) image points (shoulder, elbow, hand centre) of N joint vectors (N, 2)."""
        q = np.asarray(joints, dtype=float)
        if q.ndim != 2 or q.shape[1] != 2 or not np.all(np.isfinite(q)):
            raise ValueError('joints must be finite, of shape (N, 2)')
        a0, a1 = q[:, 0], q[:, 0] + q[:, 1]
        elbow = self.shoulder + self.link_lengths[0] * np.stack([np.cos(a0), np.sin(a0)], 1)
        hand = elbow + self.link_lengths[1] * np.stack([np.cos(a1), np.sin(a1)], 1)
        return np.stack([np.broadcast_to(self.shoulder, elbow.shape), elbow, hand], 1)

    def part_clearances(self, joints, object_position: Optional[Sequence[float]] = None) -> np.ndarray:
        """Surface gap [px] between the object and each arm part (upper link, forearm, hand) for a joint vector (2,)
        or many (N, 2): shape (3,) or (N, 3); negative = overlap. Links are capsules of their width around the joint
        segment (as link_collides_object); the hand gap is measured to contact_distance (as in_contact). With
        `object_position`, the gaps to an object there instead of at object_position_ (to check a place first)."""
        obj = self.object_position_ if object_position is None else np.asarray(object_position, dtype=float)
        q = np.asarray(joints, dtype=float)
        pts = self.link_points_many(q.reshape(-1, 2) if q.ndim == 1 else q)
        shoulder, elbow, hand = pts[:, 0], pts[:, 1], pts[:, 2]
        gaps = np.stack([
            _points_segments_distance(obj, shoulder, elbow) - self.link_widths[0] / 2,
            _points_segments_distance(obj, elbow, hand) - self.link_widths[1] / 2,
            np.linalg.norm(hand - obj, axis=1) - self.hand_radius - self.contact_margin,
        ], 1) - self.object_radius
        return gaps[0] if q.ndim == 1 else gaps

    def link_collides_object(self, joints: Sequence[float]) -> bool:
        """One of the two links (not the hand) overlaps the object."""
        pts = self.link_points(joints)
        for i in range(2):
            if _point_segment_distance(self.object_position_, pts[i], pts[i + 1]) < \
                    self.link_widths[i] / 2 + self.object_radius:
                return True
        return False

    # --- rendering --------------------------------------------------------------------------------------------
    def render(self, joints: Sequence[float]) -> np.ndarray:
        """(H, W, 3) uint8 RGB frame for the joint vector; deterministic for a given model."""
        pts = self.link_points(joints)
        frame = self.background_.copy()
        for i, (rgb, alpha) in enumerate(self._links):
            angle = math.atan2(*(pts[i + 1] - pts[i])[::-1])
            # link patch anchor: left end, mid height, so the patch starts at the joint and overlaps the next one
            self._blit(frame, rgb, alpha, pts[i], angle, anchor=(self.link_widths[i] / 4, rgb.shape[0] / 2.0))
        rgb, alpha = self._hand
        c = (rgb.shape[1] - 1) / 2.0
        angle = math.atan2(*(pts[2] - pts[1])[::-1])
        self._blit(frame, rgb, alpha, pts[2], angle, anchor=(c, c))
        return frame

    def _blit(self, frame: np.ndarray, rgb: np.ndarray, alpha: np.ndarray, at: np.ndarray, angle: float,
              anchor: Tuple[float, float]) -> None:
        """Rotate a patch by `angle` about its `anchor`, put the anchor at image point `at`, alpha-composite."""
        h, w = alpha.shape
        ca, sa = math.cos(angle), math.sin(angle)
        rot = np.array([[ca, -sa], [sa, ca]])
        t = at - rot @ np.asarray(anchor, float)
        corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], float) @ rot.T + t
        x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 1
        size = self.image_size
        x0c, y0c, x1c, y1c = max(x0, 0), max(y0, 0), min(x1, size), min(y1, size)
        if x0c >= x1c or y0c >= y1c:
            return
        m = np.hstack([rot, (t - [x0c, y0c])[:, None]])
        dsize = (x1c - x0c, y1c - y0c)
        patch = cv2.warpAffine(rgb, m, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        a = cv2.warpAffine(alpha, m, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        roi = frame[y0c:y1c, x0c:x1c]
        a3 = a[:, :, None]
        roi[:] = (patch * a3 + roi * (1.0 - a3) + 0.5).astype(np.uint8)

    # --- construction helpers -------------------------------------------------------------------------------
    def _place_object(self, rng: np.random.Generator) -> np.ndarray:
        """A random place inside the image where the hand can touch the object from every side: the whole contact
        circle around it is reachable, so "in contact" is a full disc of hand positions (not one cut by a joint
        limit) and reaching past the object is possible."""
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        margin = self.object_radius + 8
        ring = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        for _ in range(10000):
            q = lo + (hi - lo) * (0.1 + 0.8 * rng.random(2))
            p = self.hand_position(q)
            if np.linalg.norm(p - self.shoulder) < 0.55 * sum(self.link_lengths):
                continue
            if np.any(p < margin) or np.any(p > self.image_size - margin):
                continue
            around = p + (self.contact_distance + 6.0) * np.stack([np.cos(ring), np.sin(ring)], 1)
            if all(self.inverse_kinematics(a) is not None for a in around):
                return p
        raise ValueError('no object position with a reachable contact circle inside the image; check the geometry')

    def _make_background(self, rng: np.random.Generator) -> np.ndarray:
        size = self.image_size
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
        g0, g1 = rng.uniform(90, 150, 3), rng.uniform(90, 150, 3)
        bg = (g0 * (1 - yy[..., None]) + g1 * yy[..., None] + 10 * np.sin(6.0 * xx)[..., None])
        bg = bg.astype(np.uint8)
        # Static textured shapes away from the object (they stay put while the arm moves in front of them).
        placed = []
        for _ in range(self.n_background):
            for _attempt in range(200):
                w, h = int(rng.integers(36, 64)), int(rng.integers(36, 64))
                x, y = int(rng.integers(5, size - w - 5)), int(rng.integers(5, size - h - 5))
                centre = np.array([x + w / 2, y + h / 2])
                if np.linalg.norm(centre - self.object_position_) < self.object_radius + max(w, h) / 2 + 15:
                    continue
                if any(abs(x + w / 2 - px - pw / 2) < (w + pw) / 2 + 5
                       and abs(y + h / 2 - py - ph / 2) < (h + ph) / 2 + 5 for px, py, pw, ph in placed):
                    continue
                break
            placed.append((x, y, w, h))
            tex = _random_texture(rng, h, w)
            if rng.random() < 0.5:
                mask = np.zeros((h, w), np.uint8)
                cv2.ellipse(mask, (w // 2, h // 2), (w // 2 - 1, h // 2 - 1), 0, 0, 360, 255, -1)
            else:
                mask = np.full((h, w), 255, np.uint8)
            roi = bg[y:y + h, x:x + w]
            roi[mask > 0] = tex[mask > 0]
        return bg


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def _points_segments_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from point p (2,) to each segment a[i] -> b[i] (N, 2)."""
    ab, ap = b - a, p - a
    t = np.clip(np.einsum('ij,ij->i', ap, ab) / np.maximum(np.einsum('ij,ij->i', ab, ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
