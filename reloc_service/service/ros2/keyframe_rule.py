"""The keyframe rule of a map built from odometry: SVO's, a frame is a new keyframe when its
camera is farther from every keyframe than a fraction of the scene depth that keyframe sees
(``overlap``; SVO takes 12 % of the average depth), or than fixed metres (``distance``), or
looks away from each of them by more than an angle.

Scaled by the depth, the rule keeps the image overlap between neighbouring keyframes the same
in a room (depth 2 m: a keyframe every 24 cm) and over a field seen from 30 m (every 3.6 m).
A keyframe's scene depth is the median depth of the map points it observes (or of its depth
image); until it has enough of them, the nearest keyframe's depth that is known, else the
configured default.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.frame import Keyframe
from ...core.geometry import invert, rotation_angle

Array = npt.NDArray[np.float64]

#: A median over fewer map points says little about the scene's depth (the verification of a
#: relocalization needs 10 inliers by default: a keyframe seeing fewer is barely usable).
MIN_DEPTH_POINTS = 10


class Rule(enum.StrEnum):
    OVERLAP = "overlap"      # fraction of the scene depth
    DISTANCE = "distance"    # fixed metres


def median_scene_depth(keyframe: Keyframe) -> float | None:
    """The median Z-depth (metres, camera frame) of the map points ``keyframe`` observes, or of
    its depth image where it has one; None when fewer than :data:`MIN_DEPTH_POINTS` are known."""
    if keyframe.depth is not None:
        depth = np.asarray(keyframe.depth, np.float64)
        depth = depth[np.isfinite(depth) & (depth > 0)]
        if len(depth) >= MIN_DEPTH_POINTS:
            return float(np.median(depth))
    points = [f.points_world[f.landmark_ids >= 0] for f in keyframe.features.values()]
    points_world = np.concatenate(points) if points else np.zeros((0, 3))
    points_world = points_world[np.all(np.isfinite(points_world), axis=1)]
    cam_from_world = invert(keyframe.world_from_cam)
    z = points_world @ cam_from_world[2, :3] + cam_from_world[2, 3]
    z = z[z > 0]
    return float(np.median(z)) if len(z) >= MIN_DEPTH_POINTS else None


@dataclass(frozen=True)
class KeyframeRule:
    """See module docstring. ``depth`` of a keyframe None: not known (yet)."""

    rule: Rule = Rule.OVERLAP
    overlap_fraction: float = 0.12
    default_depth_m: float = 2.0
    min_distance_m: float = 0.15
    min_angle_deg: float = 15.0

    def radius_m(self, depth_m: float | None) -> float:
        """How far a camera may be from a keyframe seeing ``depth_m`` and still be covered."""
        if self.rule is Rule.DISTANCE:
            return self.min_distance_m
        return self.overlap_fraction * (self.default_depth_m if depth_m is None else depth_m)

    def is_new(self, world_from_cam: Array,
               keyframes: list[tuple[Array, float | None]]) -> bool:
        """True when no keyframe ``(world_from_cam, scene depth)`` covers the camera: each is
        farther than its radius or turned more than ``min_angle_deg``."""
        for world_from_kf, depth in keyframes:
            distance = float(np.linalg.norm(world_from_kf[:3, 3] - world_from_cam[:3, 3]))
            if distance > self.radius_m(depth):
                continue
            angle = np.degrees(rotation_angle(world_from_kf[:3, :3].T
                                              @ world_from_cam[:3, :3]))
            if angle <= self.min_angle_deg:
                return False
        return True

    def nearest_depth(self, world_from_cam: Array,
                      keyframes: list[tuple[Array, float | None]]) -> float | None:
        """The scene depth of the nearest keyframe whose depth is known (None: none is)."""
        known = [(float(np.linalg.norm(p[:3, 3] - world_from_cam[:3, 3])), d)
                 for p, d in keyframes if d is not None]
        return min(known)[1] if known else None
