"""The keyframe map: keyframes, landmarks with their observations, and a version counter.

Landmarks live in a :class:`~.landmark_table.LandmarkTable` (:mod:`.landmark_table`): columns
of ids, points, depth sigmas and CSR observations (memory-mapped when loaded from a snapshot)
plus a small copy-on-write overlay of the landmarks changed since, so a map of 500k landmarks
holds no 500k Python objects and a change copies only what it touches.

A writer publishes a new immutable :class:`MapState` (copy on write); readers call
:meth:`KeyframeMap.snapshot` once and see one consistent map for as long as they hold it,
however many keyframes arrive meanwhile. One writer at a time: the map takes no lock (the
engine's writer mutex serialises its builder, see :mod:`reloc_service.engine`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from .errors import MapError
from .frame import Features, Keyframe
from .geometry import check_pose_covariance
from .landmark_table import Landmark, LandmarkEditor, LandmarkTable

Array = npt.NDArray[np.float64]

@dataclass(frozen=True)
class MapState:
    """An immutable view of the map at one version. ``landmarks`` is a
    :class:`LandmarkTable` (a plain mapping given here is converted).
    ``default_pose_covariance`` (6, 6) is the covariance of a keyframe put without one (the
    map's configuration); None: such keyframes are taken as exact. ``calibration_covariance``
    (2, 2) is how well the map's camera calibration is known (relative focal, radial pixels
    at the farthest image corner: :class:`.mapping.MappingConf`), what a relocalized pose
    states it owes to the calibration; None: the pose finders' own prior."""

    keyframes: Mapping[int, Keyframe] = field(default_factory=lambda: MappingProxyType({}))
    landmarks: LandmarkTable = field(default_factory=LandmarkTable)
    version: int = 0
    next_landmark_id: int = 0
    default_pose_covariance: Array | None = field(default=None, compare=False)
    calibration_covariance: Array | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.landmarks, LandmarkTable):
            object.__setattr__(self, "landmarks", LandmarkTable.from_mapping(self.landmarks))

    def keyframe(self, kf_id: int) -> Keyframe:
        """The keyframe ``kf_id``; MapError if it is not in the map."""
        try:
            return self.keyframes[kf_id]
        except KeyError:
            raise MapError(f"no keyframe {kf_id} in the map") from None

    def keyframe_ids(self) -> list[int]:
        """Keyframe ids in ascending order."""
        return sorted(self.keyframes)

    def pose_covariances(self, kf_ids: Iterable[int]) -> Array:
        """(K, 6, 6) covariances of the poses of keyframes ``kf_ids``: each keyframe's own,
        else :attr:`default_pose_covariance`, else zeros (exact)."""
        default = (np.zeros((6, 6)) if self.default_pose_covariance is None
                   else self.default_pose_covariance)
        covs = [self.keyframes[k].pose_covariance for k in kf_ids]
        return np.array([default if c is None else c for c in covs]).reshape(-1, 6, 6)

    def positions_world(self, kf_ids: Iterable[int] | None = None) -> Array:
        """(K, 3) camera centres of ``kf_ids`` (default: all, ascending id)."""
        ids = self.keyframe_ids() if kf_ids is None else list(kf_ids)
        if not ids:
            return np.zeros((0, 3))
        return np.stack([self.keyframes[i].world_from_cam[:3, 3] for i in ids])

    def nearest_keyframes(self, world_from_cam: Array, count: int, max_view_angle_deg: float,
                          *, exclude: int | None = None) -> list[int]:
        """Up to ``count`` keyframe ids (not ``exclude``), nearest centre to
        ``world_from_cam``'s first, among those whose optical axis is within
        ``max_view_angle_deg`` of its optical axis (keyframes that see what it sees)."""
        ids = [k for k in self.keyframe_ids() if k != exclude]
        if not ids or count <= 0:
            return []
        poses = np.stack([self.keyframes[k].world_from_cam for k in ids])
        angle = np.arccos(np.clip(poses[:, :3, 2] @ world_from_cam[:3, 2], -1.0, 1.0))
        dist = np.linalg.norm(poses[:, :3, 3] - world_from_cam[:3, 3], axis=1)
        ok = np.flatnonzero(angle <= np.deg2rad(max_view_angle_deg))
        return [ids[i] for i in ok[np.argsort(dist[ok], kind="stable")][:count]]

    def landmark_points(self, landmark_ids: npt.ArrayLike) -> Array:
        """(L, 3) world points of ``landmark_ids`` (vectorised; KeyError on an unknown id)."""
        return self.landmarks.points(landmark_ids)

    def landmark_sigmas(self, landmark_ids: npt.ArrayLike, default: float = 0.0) -> Array:
        """(L,) depth sigmas of ``landmark_ids``; ``default`` where an id is not a landmark."""
        return self.landmarks.sigmas(landmark_ids, default)

    def landmark_count(self, kind: str | None = None) -> int:
        """Number of landmarks (observed through ``kind`` features, if given)."""
        if kind is None:
            return len(self.landmarks)
        cols = self.landmarks.columns()
        if kind not in cols.kinds:
            return 0
        hit = cols.obs_kind == cols.kinds.index(kind)
        owner = np.repeat(np.arange(len(cols)), np.diff(cols.obs_offsets))
        return int(np.count_nonzero(np.bincount(owner[hit], minlength=len(cols))))


class KeyframeMap:
    """A versioned keyframe map (copy on write; see module docstring).

    Readers need no lock: :meth:`snapshot` returns the last published state, which never
    changes, and publishing is one attribute store. Writers are NOT thread-safe: each one reads
    the current state, copies and publishes it, so two concurrent writers would lose one's
    change. Only one thread may write at a time (the engine's writer mutex guarantees it)."""

    def __init__(self, *, default_pose_covariance: npt.ArrayLike | None = None,
                 calibration_covariance: npt.ArrayLike | None = None) -> None:
        self._default_pose_covariance = (
            None if default_pose_covariance is None
            else check_pose_covariance(default_pose_covariance, name="default_pose_covariance"))
        self._calibration_covariance = (
            None if calibration_covariance is None
            else _check_calibration_covariance(calibration_covariance))
        self._state = MapState(default_pose_covariance=self._default_pose_covariance,
                               calibration_covariance=self._calibration_covariance)

    # -- readers -------------------------------------------------------------------------------
    def snapshot(self) -> MapState:
        """The current immutable state; cheap (no copy)."""
        return self._state

    @property
    def version(self) -> int:
        return self._state.version

    def __len__(self) -> int:
        return len(self._state.keyframes)

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._state.keyframes

    # -- writers -------------------------------------------------------------------------------
    def add_keyframe(self, keyframe: Keyframe) -> MapState:
        """Add ``keyframe``, or replace the keyframe with the same id (its old observations and
        the landmarks left without any are removed first). Keypoints that already carry a
        landmark id and a 3D point (as SVO sends them) register that landmark: an id unknown to
        the map creates it, a known one gains an observation."""
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        if keyframe.id in keyframes:
            _drop_observations(keyframes.pop(keyframe.id), landmarks)
        keyframes[keyframe.id] = keyframe
        next_id = self._state.next_landmark_id
        for kind, feats in keyframe.features.items():
            given_next = _register_given_landmarks(keyframe.id, kind, feats, landmarks)
            next_id = max(next_id, given_next)
        return self._publish(keyframes, landmarks, next_id)

    def remove_keyframe(self, kf_id: int) -> MapState:
        """Remove keyframe ``kf_id`` and its observations; landmarks left with no observation
        are removed. MapError if the id is unknown."""
        keyframes = dict(self._state.keyframes)
        if kf_id not in keyframes:
            raise MapError(f"cannot remove keyframe {kf_id}: not in the map")
        landmarks = self._state.landmarks.editor()
        _drop_observations(keyframes.pop(kf_id), landmarks)
        return self._publish(keyframes, landmarks, self._state.next_landmark_id)

    def add_landmarks(self, kind: str, points_world: npt.ArrayLike,
                      observations: Iterable[Iterable[tuple[int, int]]], *,
                      depth_sigmas_m: npt.ArrayLike | None = None) -> list[int]:
        """Create landmarks at ``points_world`` (L, 3), each observed by the given
        ``(keyframe id, keypoint index)`` pairs of features ``kind``, with their depth
        uncertainty (L,) if known; the keyframes' features are updated to point at them.
        Returns the new landmark ids. A keypoint that already has a landmark keeps it (that
        observation is skipped)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        obs_lists = [list(o) for o in observations]
        if len(obs_lists) != len(pts):
            raise MapError(f"add_landmarks: {len(pts)} points but {len(obs_lists)} "
                           "observation lists")
        sigmas = (np.zeros(len(pts)) if depth_sigmas_m is None
                  else np.asarray(depth_sigmas_m, dtype=np.float64).reshape(-1))
        if len(sigmas) != len(pts) or not np.all(np.isfinite(sigmas) & (sigmas >= 0)):
            raise MapError(f"add_landmarks: expected {len(pts)} finite depth sigmas >= 0")
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        next_id = self._state.next_landmark_id
        updates: dict[int, list[tuple[int, int, Array]]] = {}
        new_ids: list[int] = []
        taken: set[tuple[int, int]] = set()
        for point, obs, sigma in zip(pts, obs_lists, sigmas.tolist(), strict=True):
            fresh = [(k, i) for k, i in obs if k in keyframes and (k, i) not in taken
                     and keyframes[k].features[kind].landmark_ids[i] < 0]
            taken.update(fresh)
            if not fresh:
                continue
            lm_id = next_id
            next_id += 1
            landmarks[lm_id] = Landmark(lm_id, point.copy(),
                                        frozenset((k, kind, int(i)) for k, i in fresh),
                                        sigma)
            for k, i in fresh:
                updates.setdefault(k, []).append((int(i), lm_id, point))
            new_ids.append(lm_id)
        _apply_updates(keyframes, kind, updates)
        self._publish(keyframes, landmarks, next_id)
        return new_ids

    def add_observations(self, kind: str, triples: Iterable[tuple[int, int, int]]) -> int:
        """Attach keypoints to existing landmarks: ``(landmark id, keyframe id, keypoint index)``.
        Keypoints that already have a landmark, unknown landmarks or keyframes are skipped.
        Returns the number of observations added."""
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        updates: dict[int, list[tuple[int, int, Array]]] = {}
        taken: set[tuple[int, int]] = set()
        for lm_id, k, i in triples:
            if lm_id not in landmarks or k not in keyframes or (k, i) in taken:
                continue
            if keyframes[k].features[kind].landmark_ids[i] >= 0:
                continue
            taken.add((k, i))
            lm = landmarks[lm_id]
            landmarks[lm_id] = replace(lm, observations=lm.observations | {(k, kind, int(i))})
            updates.setdefault(k, []).append((int(i), lm_id, lm.point_world))
        _apply_updates(keyframes, kind, updates)
        self._publish(keyframes, landmarks, self._state.next_landmark_id)
        return len(taken)

    def move_landmarks(self, landmark_ids: npt.ArrayLike, points_world: npt.ArrayLike) -> MapState:
        """Move landmarks to new world points (L, 3), in the landmarks and in the features of
        the keyframes observing them (after a re-refinement with more observations)."""
        ids = np.asarray(landmark_ids, dtype=np.int64).ravel()
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if len(ids) != len(pts):
            raise MapError(f"move_landmarks: {len(ids)} ids but {len(pts)} points")
        if len(ids) == 0:
            return self._state
        order = np.argsort(ids)
        ids, pts = ids[order], pts[order]
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        observers: set[int] = set()
        for lm_id, point in zip(ids.tolist(), pts, strict=True):
            lm = landmarks[lm_id]
            landmarks[lm_id] = replace(lm, point_world=point.copy())
            observers.update(o[0] for o in lm.observations)
        for k in observers:
            keyframes[k] = _with_moved_points(keyframes[k], ids, pts)
        return self._publish(keyframes, landmarks, self._state.next_landmark_id)

    def replace_state(self, state: MapState) -> None:
        """Install a whole state (used when loading a saved map), under this map's default
        pose covariance and calibration covariance (configuration, not part of what was
        saved)."""
        self._state = replace(state, default_pose_covariance=self._default_pose_covariance,
                              calibration_covariance=self._calibration_covariance)

    def set_default_pose_covariance(self, covariance: npt.ArrayLike | None) -> MapState:
        """Take ``covariance`` (6, 6) as the pose covariance of keyframes put without one
        (None: exact) from now on, the current state's included (same version: the map's
        content is unchanged); returns that state."""
        self._default_pose_covariance = (
            None if covariance is None
            else check_pose_covariance(covariance, name="default_pose_covariance"))
        self._state = replace(self._state, default_pose_covariance=self._default_pose_covariance)
        return self._state

    def _publish(self, keyframes: dict[int, Keyframe], landmarks: LandmarkEditor,
                 next_landmark_id: int) -> MapState:
        self._state = MapState(MappingProxyType(keyframes), landmarks.commit(),
                               self._state.version + 1, next_landmark_id,
                               self._default_pose_covariance, self._calibration_covariance)
        return self._state


def _check_calibration_covariance(covariance: npt.ArrayLike) -> Array:
    """A calibration covariance: (2, 2), finite, symmetric, positive semi-definite; else
    MapError saying so."""
    out = np.asarray(covariance, np.float64)
    if (out.shape != (2, 2) or not np.isfinite(out).all() or not np.allclose(out, out.T)
            or np.linalg.eigvalsh(out).min() < 0):
        raise MapError(f"calibration_covariance: expected a finite, symmetric, positive "
                       f"semi-definite 2x2 matrix, got {out.tolist()!r}")
    return out


def _drop_observations(keyframe: Keyframe, landmarks: LandmarkEditor) -> None:
    """Remove ``keyframe``'s observations from ``landmarks`` (in place); drop emptied ones."""
    for kind, feats in keyframe.features.items():
        for idx in np.flatnonzero(feats.landmark_ids >= 0):
            lm_id = int(feats.landmark_ids[idx])
            lm = landmarks.get(lm_id)
            if lm is None:
                continue
            remaining = lm.observations - {(keyframe.id, kind, int(idx))}
            if remaining:
                landmarks[lm_id] = replace(lm, observations=remaining)
            else:
                del landmarks[lm_id]


def _register_given_landmarks(kf_id: int, kind: str, feats: Features,
                              landmarks: LandmarkEditor) -> int:
    """Register landmarks that arrive with a keyframe; returns the next free landmark id."""
    next_id = 0
    for idx in np.flatnonzero(feats.landmark_ids >= 0):
        lm_id = int(feats.landmark_ids[idx])
        obs = (kf_id, kind, int(idx))
        lm = landmarks.get(lm_id)
        if lm is None:
            point = feats.points_world[idx]
            if not np.all(np.isfinite(point)):
                raise MapError(f"keyframe {kf_id}: landmark {lm_id} has no finite 3D point")
            landmarks[lm_id] = Landmark(lm_id, point.copy(), frozenset({obs}))
        else:
            landmarks[lm_id] = replace(lm, observations=lm.observations | {obs})
        next_id = max(next_id, lm_id + 1)
    return next_id


def _with_moved_points(keyframe: Keyframe, sorted_ids: npt.NDArray[np.int64],
                       points_world: Array) -> Keyframe:
    """``keyframe`` with the points of landmarks ``sorted_ids`` replaced by ``points_world``."""
    for kind, feats in keyframe.features.items():
        idx = np.flatnonzero(np.isin(feats.landmark_ids, sorted_ids))
        if len(idx):
            pos = np.searchsorted(sorted_ids, feats.landmark_ids[idx])
            keyframe = keyframe.with_features(
                kind, feats.with_landmarks(idx, feats.landmark_ids[idx], points_world[pos]))
    return keyframe


def _apply_updates(keyframes: dict[int, Keyframe], kind: str,
                   updates: dict[int, list[tuple[int, int, Array]]]) -> None:
    """Write landmark ids and points into the keyframes' features (new keyframe objects)."""
    for k, rows in updates.items():
        idx = [r[0] for r in rows]
        ids = [r[1] for r in rows]
        pts = np.stack([r[2] for r in rows])
        kf = keyframes[k]
        keyframes[k] = kf.with_features(kind, kf.features[kind].with_landmarks(idx, ids, pts))
