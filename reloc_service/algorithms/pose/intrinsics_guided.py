"""The intrinsics test of a pose grown by guided matching, judged on the matches found
without the pose as well as on all of them.

Guided matching (:mod:`.guided`) looks for each landmark the pose predicts visible in a
window around its projection through the given camera. Under a wrong focal and a wrong pose
that explain the image's centre, a repeated texture offers look-alike keypoints near where
that camera projects the outer landmarks: they join as inliers, and the joint estimate of
pose and focal (:mod:`.intrinsics`) then finds the given focal again. Such matches were
selected by the hypothesis under test, so they can confirm the given intrinsics but cannot
be evidence against a wrong camera. The matches found without the pose (the ratio test over
the candidates' landmarks) were not: the same test is run on them alone, from the grown
pose, and the intrinsics pass only where both tests pass (each at the false-refusal rate,
:attr:`.intrinsics.IntrinsicsCheck.passed`). Where the unguided matches are too few
to test (fewer than 8 inliers), the whole set's test decides alone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from .intrinsics import IntrinsicsCheck

IntArray = npt.NDArray[np.int64]

#: A pose solver's intrinsics test (:func:`.pnp._check_intrinsics` bound to its fit): on all
#: its correspondences, or with ``rows=`` on those alone; options such as ``focal_starts``
#: pass through.
IntrinsicsTest = Callable[..., IntrinsicsCheck | None]


def unguided_positions(query_idx: IntArray, pool_rows: IntArray, seed_query_idx: IntArray,
                       seed_pool_rows: IntArray) -> IntArray:
    """(U,) ascending positions of the correspondences (``query_idx``, ``pool_rows``), both
    (N,), that are also seed correspondences (``seed_query_idx``, ``seed_pool_rows``, (S,):
    found without a pose): the same query keypoint matched to the same landmark."""
    query_idx, pool_rows = np.asarray(query_idx, np.int64), np.asarray(pool_rows, np.int64)
    seed_q, seed_rows = np.asarray(seed_query_idx, np.int64), np.asarray(seed_pool_rows, np.int64)
    if len(query_idx) == 0 or len(seed_q) == 0:
        return np.zeros(0, np.int64)
    width = int(max(pool_rows.max(initial=0), seed_rows.max(initial=0))) + 2
    # One integer per pair (rows of -1, a landmark the pool lacks, shifted to 0).
    pairs = query_idx * width + (pool_rows + 1)
    seeds = seed_q * width + (seed_rows + 1)
    return np.flatnonzero(np.isin(pairs, seeds[seed_rows >= 0])).astype(np.int64)


def with_unguided_test(test: IntrinsicsTest | None, unguided: IntArray) -> IntrinsicsTest | None:
    """``test`` that also runs on the correspondences ``unguided`` alone (positions among the
    solver's correspondences) and attaches that check as
    :attr:`.intrinsics.IntrinsicsCheck.unguided`; None where ``test`` is (not testing)."""
    if test is None:
        return None
    rows = np.sort(np.asarray(unguided, np.int64))

    def run(**options: Any) -> IntrinsicsCheck | None:
        check = test(**options)
        if check is None or len(rows) == 0:
            return check
        alone = test(rows=rows, **options)
        return check if alone is None else dataclasses.replace(check, unguided=alone)

    return run
