"""Query keypoints for the ferns classifier: DoG extrema (SIFT's detector, like the landmarks'
keypoints) or FAST corners, strongest first, one per location."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def detect_keypoints(image: npt.NDArray[np.uint8], detector: str, max_keypoints: int) -> Array:
    """(N, 2) distinct keypoint pixels of a query: SIFT (DoG extrema, no descriptor) or FAST,
    the strongest ``max_keypoints``."""
    if detector == "sift":
        kps = cv2.SIFT.create().detect(image, None)  # all, then the strongest distinct ones
    else:
        fast = cv2.FastFeatureDetector.create(threshold=15, nonmaxSuppression=True)
        kps = fast.detect(image, None)
    return strongest_distinct(list(kps), max_keypoints)


def strongest_distinct(kps: list[cv2.KeyPoint], max_keypoints: int) -> Array:
    """(N, 2) pixels of the strongest ``max_keypoints`` of ``kps``, one per location."""
    if not kps:
        return np.zeros((0, 2))
    pts = np.asarray(cv2.KeyPoint.convert(kps), np.float64).reshape(-1, 2)
    response = np.fromiter((k.response for k in kps), np.float64, len(kps))
    order = np.argsort(-response, kind="stable")
    pts = pts[order]
    # SIFT repeats a location for each dominant orientation: keep the first (strongest).
    _, first = np.unique(np.rint(pts).astype(np.int64), axis=0, return_index=True)
    return pts[np.sort(first)][:max_keypoints]
