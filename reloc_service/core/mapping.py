"""Incremental map building: features of every configured kind for each posed keyframe, then
landmarks triangulated against its overlapping neighbours only (or lifted from its depth map).

Also :func:`landmark_errors`, the accuracy of a built map against a dataset's depth maps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from .cameras import Camera
from .errors import ConfigError, GeometryError
from .features import FEATURE_KINDS, FeatureConf, compute_at, extract
from .frame import EncodedImage, Features, Keyframe, check_grey_image
from .geometry import pose_covariance_from_sigmas
from .landmarks import lift_pixels, sample_depth, triangulate_keyframe
from .map import KeyframeMap, MapState
from .plugins import make_conf
from .triangulation import TriangulationConf, TriangulationStats

Array = npt.NDArray[np.float64]

#: A detected keypoint closer than this to a given (SVO) keypoint is dropped: the given one
#: carries the landmark, a second keypoint there would only make a duplicate.
GIVEN_KEYPOINT_RADIUS_PX = 2.0
#: The value of ``MappingConf.keyframe_position_sigma_m`` / ``..._rotation_sigma_deg`` that
#: has the map measure them.
AUTO = "auto"
#: Strongest keypoints kept per keyframe for a kind ``MappingConf.max_features`` does not name.
DEFAULT_MAX_FEATURES = 2000


@dataclass(frozen=True)
class MappingConf:
    """How keyframes become map content."""

    #: Feature kinds extracted for every keyframe (the engine adds what its methods need).
    feature_kinds: tuple[str, ...] = ("sift",)
    #: Strongest keypoints kept per keyframe: one number for every kind, or a table kind ->
    #: number (a kind it does not name keeps :data:`DEFAULT_MAX_FEATURES`).
    max_features: int | Mapping[str, int] = DEFAULT_MAX_FEATURES
    #: Keyframes a new keyframe is matched against: the nearest posed keyframes by centre
    #: distance whose optical axis is within ``max_view_angle_deg`` of the new one's.
    neighbours: int = 5
    max_view_angle_deg: float = 60.0
    triangulation: TriangulationConf = field(default_factory=TriangulationConf)
    #: 1-sigma error of a keyframe pose put without a covariance, per axis: position
    #: (metres) and rotation (degrees). The poses a drone puts come from its visual-inertial
    #: odometry, whose per-frame noise against its own smoothed trajectory is a few
    #: centimetres and a few tenths of a degree (the ground-truth systems of the real sets
    #: are no better: TUM's motion capture 1-3 cm and 0.3-0.7 deg, KinectFusion 2-6 px); a
    #: relocalized pose cannot be more accurate than the poses its landmarks were placed
    #: with. 0 takes such keyframes as exact. ``"auto"`` (both) measures it from the map
    #: itself when its methods are trained or it is loaded, as the keyframes' disagreement
    #: with their landmarks re-triangulated without them
    #: (:mod:`~reloc_service.algorithms.pose.keyframe_disagreement`): about 0 for exact
    #: (rendered) poses, but blind to an error the keyframes share (a drift between passes,
    #: a ground truth's own bias), and it adds seconds to a training and a load; so the
    #: stated noise above is the default.
    keyframe_position_sigma_m: float | str = 0.02
    keyframe_rotation_sigma_deg: float | str = 0.5
    #: How well the map's camera calibration is known, 1 sigma: the focal, relative, and the
    #: radial distortion, as the pixels it moves the image's farthest corner. A relocalized
    #: pose whose query claims this camera states what that uncertainty does to it
    #: (:mod:`~reloc_service.algorithms.pose.intrinsics_marginal`); it changes no answer
    #: (the intrinsics test allows its own ``[options.p3p]`` prior). The default is a
    #: routine checkerboard calibration's; 0 takes the calibration as exact (a rendered
    #: dataset, a camera calibrated much better than routine).
    calibration_focal_sigma_rel: float = 0.005
    calibration_radial_sigma_px: float = 2.0

    def __post_init__(self) -> None:
        if isinstance(self.triangulation, Mapping):   # a nested config table
            object.__setattr__(self, "triangulation", make_conf(
                TriangulationConf, self.triangulation, owner="mapping.triangulation"))
        if not isinstance(self.triangulation, TriangulationConf):
            raise ConfigError(f"mapping.triangulation: expected a table of triangulation "
                              f"options, got {self.triangulation!r}")
        unknown = [k for k in self.feature_kinds if k not in FEATURE_KINDS]
        if unknown or not self.feature_kinds:
            raise ConfigError(f"mapping.feature_kinds: expected some of {FEATURE_KINDS}, got "
                              f"{list(self.feature_kinds)}")
        object.__setattr__(self, "max_features", _check_max_features(self.max_features))
        if self.neighbours < 0:
            raise ConfigError(f"mapping.neighbours must be >= 0, got {self.neighbours}")
        if not 0 < self.max_view_angle_deg <= 180:
            raise ConfigError(f"mapping.max_view_angle_deg must be in (0, 180], got "
                              f"{self.max_view_angle_deg}")
        _check_keyframe_sigmas(self.keyframe_position_sigma_m, self.keyframe_rotation_sigma_deg)
        numbers: tuple[str, ...] = ("calibration_focal_sigma_rel", "calibration_radial_sigma_px")
        if not self.keyframe_sigma_auto:
            numbers += ("keyframe_position_sigma_m", "keyframe_rotation_sigma_deg")
        for name in numbers:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                    math.isfinite(value) and value >= 0):
                raise ConfigError(f"mapping.{name}: expected a finite number >= 0, got "
                                  f"{value!r}")

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None) -> MappingConf:
        """From a config table; a nested ``triangulation`` table sets :class:`TriangulationConf`."""
        return make_conf(cls, options, owner="mapping")

    @property
    def keyframe_sigma_auto(self) -> bool:
        """Whether the keyframe pose sigmas are measured from the map (``"auto"``)."""
        return self.keyframe_position_sigma_m == AUTO

    def default_pose_covariance(self) -> Array | None:
        """(6, 6) covariance of a keyframe pose put without one (twist (rho, omega)):
        ``keyframe_position_sigma_m`` and ``keyframe_rotation_sigma_deg`` on each axis,
        independent; None where they are ``"auto"`` (measured once the map is built)."""
        if self.keyframe_sigma_auto:
            return None
        return pose_covariance_from_sigmas(float(self.keyframe_position_sigma_m),
                                           math.radians(float(self.keyframe_rotation_sigma_deg)))

    def calibration_covariance(self) -> Array:
        """(2, 2) covariance of the calibration's error ``theta = (a, b)`` (relative focal,
        radial pixels at the farthest image corner; :mod:`~reloc_service.algorithms.pose.
        intrinsics`): ``calibration_focal_sigma_rel`` and ``calibration_radial_sigma_px``,
        independent."""
        return np.diag([self.calibration_focal_sigma_rel**2,
                        self.calibration_radial_sigma_px**2]).astype(np.float64)

    def features_for(self, kind: str) -> int:
        """Strongest keypoints of ``kind`` kept per keyframe."""
        if isinstance(self.max_features, int):
            return self.max_features
        return self.max_features.get(kind, DEFAULT_MAX_FEATURES)

    def with_kinds(self, kinds: Sequence[str]) -> MappingConf:
        """This configuration extracting ``kinds`` too (order kept, no duplicates)."""
        merged = tuple(dict.fromkeys([*self.feature_kinds, *kinds]))
        return dataclasses.replace(self, feature_kinds=merged)


def _check_keyframe_sigmas(position: object, rotation: object) -> None:
    """``mapping.keyframe_position_sigma_m`` and ``..._rotation_sigma_deg``: both ``"auto"``
    or both numbers (checked further by the caller); else ConfigError saying so."""
    if (position == AUTO) != (rotation == AUTO):
        raise ConfigError(f"mapping.keyframe_position_sigma_m and keyframe_rotation_sigma_deg: "
                          f"expected both {AUTO!r} or both numbers, got {position!r} and "
                          f"{rotation!r}")
    for name, value in (("keyframe_position_sigma_m", position),
                        ("keyframe_rotation_sigma_deg", rotation)):
        if isinstance(value, str) and value != AUTO:
            raise ConfigError(f"mapping.{name}: expected {AUTO!r} or a finite number >= 0, "
                              f"got {value!r}")


def _check_max_features(value: object) -> int | Mapping[str, int]:
    """``mapping.max_features`` validated: a positive integer, or a table of feature kinds to
    positive integers (returned read-only)."""
    def positive(v: object) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v > 0

    if isinstance(value, Mapping):
        unknown = sorted(str(k) for k in value if k not in FEATURE_KINDS)
        if unknown:
            raise ConfigError(f"mapping.max_features: unknown feature kind(s) {unknown}; "
                              f"expected some of {list(FEATURE_KINDS)}")
        bad = {k: v for k, v in value.items() if not positive(v)}
        if bad:
            raise ConfigError(f"mapping.max_features: expected a positive integer per kind, "
                              f"got {bad}")
        return MappingProxyType(dict(value))
    if not positive(value):
        raise ConfigError(f"mapping.max_features: expected a positive integer or a table "
                          f"kind -> positive integer (e.g. {{sift = 2000, orb = 1000}}), got "
                          f"{value!r}")
    return value  # type: ignore[return-value]


def select_neighbours(state: MapState, keyframe: Keyframe, count: int, max_view_angle_deg: float
                      ) -> list[int]:
    """Up to ``count`` keyframe ids of ``state`` (not ``keyframe`` itself), nearest centre
    first, among those whose optical axis is within ``max_view_angle_deg`` of ``keyframe``'s."""
    return state.nearest_keyframes(keyframe.world_from_cam, count, max_view_angle_deg,
                                   exclude=keyframe.id)


def _given_features(image: npt.NDArray[np.uint8], kind: str, keypoints_px: Array,
                    landmark_ids: npt.NDArray[np.int64], points_world: Array) -> Features:
    """Descriptors computed at given keypoints, carrying their landmark ids and points."""
    feats, origin = compute_at(image, kind, keypoints_px)
    return dataclasses.replace(feats, landmark_ids=landmark_ids[origin].copy(),
                               points_world=points_world[origin].copy())


def _concat(first: Features, second: Features, keep: npt.NDArray[np.bool_]) -> Features:
    """``first`` followed by ``second[keep]`` (same kind)."""
    return Features(
        kind=first.kind,
        keypoints_px=np.concatenate([first.keypoints_px, second.keypoints_px[keep]]),
        levels=np.concatenate([first.levels, second.levels[keep]]),
        sizes=np.concatenate([first.sizes, second.sizes[keep]]),
        angles=np.concatenate([first.angles, second.angles[keep]]),
        descriptors=np.concatenate([first.descriptors,
                                    second.descriptors[keep].astype(first.descriptors.dtype)]),
        landmark_ids=np.concatenate([first.landmark_ids, second.landmark_ids[keep]]),
        points_world=np.concatenate([first.points_world, second.points_world[keep]]))


@dataclass(frozen=True, eq=False)
class GivenFeatures:
    """Keypoints that arrive with a keyframe (SVO): (N, 2) pixels, (N,) landmark ids (-1: none)
    and (N, 3) world points (NaN where no landmark)."""

    keypoints_px: Array
    landmark_ids: npt.NDArray[np.int64]
    points_world: Array

    @classmethod
    def check(cls, keypoints_px: npt.ArrayLike | None, landmark_ids: npt.ArrayLike | None,
              points_world: npt.ArrayLike | None) -> GivenFeatures | None:
        """Validated given features, or None when no keypoints are given."""
        if keypoints_px is None:
            if landmark_ids is not None or points_world is not None:
                raise GeometryError("given_landmark_ids/given_points_world need given_keypoints_px")
            return None
        kp = np.asarray(keypoints_px, dtype=np.float64)
        if kp.ndim != 2 or kp.shape[1] != 2 or not np.all(np.isfinite(kp)):
            raise GeometryError(f"given_keypoints_px: expected finite (N, 2), got shape {kp.shape}")
        n = len(kp)
        ids = np.full(n, -1, np.int64) if landmark_ids is None else np.asarray(landmark_ids)
        if ids.shape != (n,) or not np.issubdtype(ids.dtype, np.integer):
            raise GeometryError(f"given_landmark_ids: expected ({n},) integers, got "
                                f"{ids.shape} {ids.dtype}")
        pts = (np.full((n, 3), np.nan) if points_world is None
               else np.asarray(points_world, np.float64))
        if pts.shape != (n, 3):
            raise GeometryError(f"given_points_world: expected ({n}, 3), got {pts.shape}")
        missing = (ids >= 0) & ~np.isfinite(pts).all(axis=1)
        if missing.any():
            raise GeometryError(f"given_points_world: {int(missing.sum())} keypoint(s) with a "
                                f"landmark id have no finite 3D point (first: index "
                                f"{int(np.flatnonzero(missing)[0])})")
        return cls(kp, ids.astype(np.int64), pts)


class MapBuilder:
    """Adds posed keyframes to a :class:`KeyframeMap` and triangulates their landmarks
    incrementally. Not thread-safe: one writer at a time (the engine holds its writer mutex)."""

    def __init__(self, kmap: KeyframeMap, conf: MappingConf | None = None) -> None:
        self.map = kmap
        self.conf = conf or MappingConf()
        #: Statistics of the last :meth:`add_keyframe`, per feature kind.
        self.last_stats: dict[str, TriangulationStats] = {}

    def add_keyframe(self, kf_id: int, image: npt.ArrayLike | EncodedImage, camera: Camera,
                     world_from_cam: Array,
                     *, depth: npt.ArrayLike | None = None, timestamp: float | None = None,
                     given_keypoints_px: npt.ArrayLike | None = None,
                     given_landmark_ids: npt.ArrayLike | None = None,
                     given_points_world: npt.ArrayLike | None = None,
                     pose_covariance: npt.ArrayLike | None = None) -> Keyframe:
        """Extract features, add the keyframe (replacing one with the same id), triangulate
        against its neighbours; returns the keyframe as the map now holds it. An
        :class:`EncodedImage` ``image`` (the JPEG or PNG a client sent) is decoded here and
        kept as it is, to be saved without re-encoding. ``pose_covariance``: see
        :class:`~.frame.Keyframe` (None: the map's default applies)."""
        encoded = image if isinstance(image, EncodedImage) else None
        grey = check_grey_image(image.decode() if isinstance(image, EncodedImage) else image,
                                camera)
        given = GivenFeatures.check(given_keypoints_px, given_landmark_ids, given_points_world)
        depth_m = None if depth is None else np.asarray(depth, dtype=np.float32)
        features = {kind: self._features(grey, kind, given) for kind in self.conf.feature_kinds}
        keyframe = Keyframe(image=grey, camera=camera, features=features, id=kf_id,
                            world_from_cam=world_from_cam, timestamp=timestamp, depth=depth_m,
                            encoded=encoded,
                            pose_covariance=None if pose_covariance is None
                            else np.asarray(pose_covariance, np.float64))
        self.map.add_keyframe(keyframe)
        self._triangulate(keyframe, self.conf.feature_kinds)
        return self.map.snapshot().keyframe(keyframe.id)

    def remove_keyframe(self, kf_id: int) -> Keyframe:
        """Remove keyframe ``kf_id`` (its observations, and landmarks left unobserved);
        returns the keyframe removed. MapError if unknown."""
        keyframe = self.map.snapshot().keyframe(kf_id)
        self.map.remove_keyframe(kf_id)
        return keyframe

    def add_feature_kinds(self, kinds: Sequence[str]) -> list[int]:
        """Configure ``kinds`` too, and extract and triangulate them for every keyframe of the
        map that lacks them (in id order, each against its neighbours); returns the ids of
        the keyframes updated."""
        self.conf = self.conf.with_kinds(kinds)
        updated = []
        for kf_id in self.map.snapshot().keyframe_ids():
            kf = self.map.snapshot().keyframe(kf_id)
            missing = [k for k in self.conf.feature_kinds if k not in kf.features]
            if not missing:
                continue
            for kind in missing:
                kf = kf.with_features(kind, self._features(kf.image, kind, None))
            self.map.add_keyframe(kf)
            self._triangulate(kf, missing)
            updated.append(kf_id)
        return updated

    def _features(self, image: npt.NDArray[np.uint8], kind: str, given: GivenFeatures | None
                  ) -> Features:
        detected = extract(image, FeatureConf(kind, self.conf.features_for(kind)))
        if given is None or len(given.keypoints_px) == 0:
            return detected
        supplied = _given_features(image, kind, given.keypoints_px, given.landmark_ids,
                                   given.points_world)
        keep = np.ones(len(detected), bool)
        if len(supplied) and len(detected):
            dist, _ = cKDTree(supplied.keypoints_px).query(detected.keypoints_px)
            keep = dist > GIVEN_KEYPOINT_RADIUS_PX
        return _concat(supplied, detected, keep)

    def _triangulate(self, keyframe: Keyframe, kinds: Sequence[str]) -> None:
        state = self.map.snapshot()
        neighbours = select_neighbours(state, keyframe, self.conf.neighbours,
                                       self.conf.max_view_angle_deg)
        self.last_stats = {kind: triangulate_keyframe(self.map, keyframe.id, neighbours, kind,
                                                      self.conf.triangulation)
                           for kind in kinds}


# -- accuracy against ground truth ------------------------------------------------------------

class _DepthDataset(Protocol):
    map_entries: Sequence[Any]

    def load_truth_depth(self, entry: Any) -> npt.NDArray[np.float32] | None: ...


def first_observations(state: MapState, kind: str | None = None
                       ) -> dict[int, tuple[npt.NDArray[np.int64], Array]]:
    """For each keyframe id: the landmarks whose first observation (lowest keyframe id) it
    holds, as (landmark ids (M,), keypoint pixels (M, 2))."""
    kf_parts, lm_parts, px_parts = [], [], []
    for kf_id, kf in state.keyframes.items():
        for k, feats in kf.features.items():
            if kind is None or k == kind:
                idx = np.flatnonzero(feats.has_landmark)
                kf_parts.append(np.full(len(idx), kf_id, np.int64))
                lm_parts.append(feats.landmark_ids[idx])
                px_parts.append(feats.keypoints_px[idx])
    if not kf_parts:
        return {}
    kf_ids, lm_ids = np.concatenate(kf_parts), np.concatenate(lm_parts)
    px = np.concatenate(px_parts)
    order = np.lexsort((kf_ids, lm_ids))
    _, first = np.unique(lm_ids[order], return_index=True)
    sel = order[first]
    return {int(k): (lm_ids[sel][kf_ids[sel] == k], px[sel][kf_ids[sel] == k])
            for k in np.unique(kf_ids[sel])}


def landmark_errors(kmap_state: MapState, dataset: _DepthDataset, *, kind: str | None = None,
                    entries: Mapping[int, Any] | None = None, max_depth_jump: float = 0.03,
                    return_range: bool = False) -> Array | tuple[Array, Array]:
    """Distance (metres, (L,)) of each landmark to its ground truth: the pixel of its first
    observation lifted with the dataset's ground-truth depth map of that keyframe (its sensor
    depth map where it has no ground truth). Keyframe ids index
    ``dataset.map_entries`` unless ``entries`` maps them. Landmarks whose ground truth is
    unknown (no depth map, no depth or a depth discontinuity at the pixel) are left out.
    With ``return_range``, also the range (L,) from the first observing camera to the
    ground-truth point."""
    errors, ranges = [], []
    for kf_id, (lm_ids, px) in first_observations(kmap_state, kind).items():
        entry = entries[kf_id] if entries is not None else dataset.map_entries[kf_id]
        depth = dataset.load_truth_depth(entry)
        if depth is None:
            continue
        kf = kmap_state.keyframes[kf_id]
        z, valid = sample_depth(depth, px, max_jump=max_depth_jump)
        truth = lift_pixels(kf.camera, kf.world_from_cam, px[valid], z[valid])
        errors.append(np.linalg.norm(kmap_state.landmark_points(lm_ids[valid]) - truth, axis=1))
        ranges.append(np.linalg.norm(truth - kf.position_world, axis=1))
    err = np.concatenate(errors) if errors else np.zeros(0)
    rng = np.concatenate(ranges) if ranges else np.zeros(0)
    return (err, rng) if return_range else err
