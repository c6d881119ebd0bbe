"""The peer ``reloc bench`` compares against: the relocalization a user would write with plain
OpenCV, given the same map (keyframes whose SIFT keypoints carry landmarks).

    JPEG -> cv2.imdecode -> SIFT detectAndCompute -> cv2.BFMatcher(NORM_L2).knnMatch(k=2)
    against the landmark descriptors of EVERY keyframe (one train set per keyframe, added
    with ``BFMatcher.add``) -> Lowe ratio test -> cv2.solvePnPRansac (OpenCV defaults) ->
    accept if at least ``min_inliers`` inliers.

(One train set per keyframe is also what makes big maps possible at all: OpenCV refuses a
single train set of 2^18 descriptors or more.)

No place finder, no pooling of landmarks across keyframes, no verification beyond the inlier
count: that is the point of the comparison. With ``dedupe`` the user keeps one descriptor per
landmark (the first keyframe's), which a careful user would do, since the same landmark seen
by several keyframes otherwise fails the ratio test against itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.geometry import invert
from ...core.map import MapState

Array = npt.NDArray[np.float64]

#: Lowe's ratio, as in our matcher and in the SIFT paper.
RATIO = 0.8
#: A user accepts a pose with at least this many RANSAC inliers (a common hand-picked gate).
MIN_INLIERS = 20


@dataclass(frozen=True, eq=False)
class PlainMap:
    """The map as the plain pipeline sees it: (M, 128) float32 SIFT descriptors of every
    keyframe's keypoints that carry a landmark, with their (M, 3) landmark points (world)."""

    descriptors: npt.NDArray[np.float32]
    points_world: Array
    landmark_ids: npt.NDArray[np.int64]
    #: (K + 1,) row where each keyframe's descriptors start (and the total), in id order.
    starts: npt.NDArray[np.int64]

    @classmethod
    def from_state(cls, state: MapState, *, kind: str = "sift", dedupe: bool = False
                   ) -> PlainMap:
        """Stack the landmark observations of every keyframe of ``state`` (one row per
        observation; with ``dedupe`` one row per landmark, the lowest keyframe id's)."""
        desc, points, ids, rows = [], [], [], []
        for row, kf_id in enumerate(state.keyframe_ids()):
            feats = state.keyframes[kf_id].features.get(kind)
            if feats is None:
                continue
            has = feats.landmark_ids >= 0
            desc.append(feats.descriptors[has])
            points.append(feats.points_world[has])
            ids.append(feats.landmark_ids[has])
            rows.append(np.full(int(has.sum()), row, np.int64))
        if not desc:
            return cls(np.zeros((0, 128), np.float32), np.zeros((0, 3)), np.zeros(0, np.int64),
                       np.zeros(len(state.keyframes) + 1, np.int64))
        all_desc = np.ascontiguousarray(np.concatenate(desc), dtype=np.float32)
        all_pts, all_ids, all_rows = (np.concatenate(points), np.concatenate(ids),
                                      np.concatenate(rows))
        if dedupe:
            _, first = np.unique(all_ids, return_index=True)
            keep = np.sort(first)  # rows stay grouped by keyframe
            all_desc, all_pts, all_ids, all_rows = (all_desc[keep], all_pts[keep], all_ids[keep],
                                                    all_rows[keep])
        starts = np.searchsorted(all_rows, np.arange(len(state.keyframes) + 1))
        return cls(all_desc, all_pts, all_ids, starts.astype(np.int64))

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def keyframes(self) -> int:
        return len(self.starts) - 1

    def per_keyframe(self, min_rows: int = 2
                     ) -> tuple[list[npt.NDArray[np.float32]], npt.NDArray[np.int64]]:
        """The descriptors of each keyframe that has some (views), and the first row of each.

        A keyframe with fewer than ``min_rows`` descriptors (the k of ``knnMatch``) shares the
        set of the next keyframe (the previous one at the end): OpenCV's
        ``BFMatcher.knnMatch`` over a collection returns garbage image and train indices for
        every query descriptor as soon as one train set holds fewer than k rows (seen with
        OpenCV 5.0.0). Sets stay contiguous row ranges, so ``start + trainIdx`` holds."""
        nonempty = np.flatnonzero(np.diff(self.starts) > 0)
        firsts = [int(self.starts[k]) for k in nonempty]
        merged: list[int] = []
        for first in firsts:
            if not merged or first - merged[-1] >= min_rows:
                merged.append(first)
        if len(merged) > 1 and len(self) - merged[-1] < min_rows:
            merged.pop()
        return ([self.descriptors[a:b] for a, b in zip(merged, [*merged[1:], len(self)],
                                                       strict=True)],
                np.asarray(merged, np.int64))


@dataclass
class PlainResult:
    """One answer of the plain pipeline: ``world_from_cam`` (None when refused), counts and
    seconds per stage (decode, features, match, solve)."""

    world_from_cam: Array | None
    matches: int
    inliers: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.world_from_cam is not None


def opencv_distortion(camera: Camera) -> npt.NDArray[np.float64] | None:
    """OpenCV's distortion coefficients for ``camera`` (None for a pinhole); ValueError for a
    model OpenCV's solvePnP cannot take (fisheye, FOV)."""
    model = camera.model
    if model == "pinhole":
        return None
    if model == "radtan":
        return np.asarray(camera.distortion, np.float64)
    raise ValueError(f"the plain OpenCV pipeline takes pinhole or radtan cameras; got {model!r}")


class PlainOpenCVPipeline:
    """The plain OpenCV relocalizer over a :class:`PlainMap` (see module docstring)."""

    def __init__(self, plain_map: PlainMap, camera: Camera, *, max_features: int = 2000,
                 ratio: float = RATIO, min_inliers: int = MIN_INLIERS) -> None:
        self.map = plain_map
        self.camera = camera
        self.K = camera.K
        self.dist = opencv_distortion(camera)
        self.max_features = max_features
        self.ratio = ratio
        self.min_inliers = min_inliers
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        train_sets, self._set_starts = plain_map.per_keyframe()
        if train_sets:
            self.matcher.add(train_sets)

    def relocalize_jpeg(self, jpeg: bytes) -> PlainResult:
        """Decode ``jpeg`` and relocalize it."""
        start = time.perf_counter()
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError("the query does not decode as an image")
        decoded = time.perf_counter() - start
        result = self.relocalize(np.asarray(image, np.uint8))
        result.timings["decode"] = decoded
        return result

    def relocalize(self, image: npt.NDArray[np.uint8]) -> PlainResult:
        """``world_from_cam`` of a grey (H, W) query, or a refusal with the counts."""
        timings: dict[str, float] = {}
        t = time.perf_counter()
        keypoints, desc = cv2.SIFT.create(nfeatures=self.max_features).detectAndCompute(image,
                                                                                        None)
        timings["features"] = time.perf_counter() - t
        t = time.perf_counter()
        pixels, points = self._match(list(keypoints), desc)
        timings["match"] = time.perf_counter() - t
        t = time.perf_counter()
        world_from_cam, inliers = self._solve(pixels, points)
        timings["solve"] = time.perf_counter() - t
        return PlainResult(world_from_cam, len(pixels), inliers, timings)

    def _match(self, keypoints: list[cv2.KeyPoint], desc: npt.NDArray[Any] | None
               ) -> tuple[Array, Array]:
        """Ratio-test matches of the query to every map descriptor: (M, 2) pixels and (M, 3)
        world points."""
        if desc is None or len(desc) == 0 or len(self.map) < 2:
            return np.zeros((0, 2)), np.zeros((0, 3))
        pairs = self.matcher.knnMatch(desc, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < self.ratio * p[1].distance]
        q = np.fromiter((m.queryIdx for m in good), np.int64, len(good))
        t = np.fromiter((self._set_starts[m.imgIdx] + m.trainIdx for m in good), np.int64,
                        len(good))
        pixels = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
        return pixels[q], self.map.points_world[t]

    def _solve(self, pixels: Array, points: Array) -> tuple[Array | None, int]:
        """``cv2.solvePnPRansac`` with OpenCV's default settings (100 iterations, 8 px,
        confidence 0.99, iterative refinement)."""
        if len(pixels) < 4:
            return None, 0
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(points, pixels, self.K, self.dist)
        count = 0 if inliers is None else len(inliers)
        if not ok or count < self.min_inliers:
            return None, count
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = cv2.Rodrigues(rvec)[0]
        cam_from_world[:3, 3] = tvec.ravel()
        return invert(cam_from_world), count
