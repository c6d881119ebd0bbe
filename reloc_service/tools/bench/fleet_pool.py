"""The fleet section's figure of the repetition check on the template map: what its pool of
every landmark of the map costs to make and to search, in the index
(:mod:`reloc_service.algorithms.pose.repetition_index`) against a full scan, and how often
the two agree on the template's own queries."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...algorithms.pose.landmark_pool import LandmarkPool
from ...algorithms.pose.repetition import RepetitionConf
from ...algorithms.pose.repetition_index import IndexConf, RepetitionIndex
from ...core import features as feature_lib
from .samples import QuerySet

MB = 1024 * 1024

#: Each kind with the query features the default chain's step of that kind extracts.
KINDS = {"orb": 500, "sift": 1000}


def repetition_pool(map_dir: Path, queries: QuerySet, *, conf: IndexConf | None = None,
                    max_queries: int = 5, max_full_scans: int = 2) -> dict[str, Any]:
    """Per feature kind of the snapshot in ``map_dir``: pool rows and MB, index MB, seconds
    to gather the pool and to build the index, ms per query to search it (as many
    descriptors as the check looks up: ``max_inliers + max_unexplained``) and to scan the
    whole pool, rows scanned per descriptor, and the share of nearest neighbours and
    ratio-test matches of the full scan the index finds (up to ``max_queries`` queries,
    ``max_full_scans`` of them scanned in full). ``conf``: the index's (default: the
    check's own)."""
    from ...storage.snapshot import load_map

    state, _ = load_map(map_dir)
    keyframes = [state.keyframes[k] for k in state.keyframes]
    images = [np.asarray(cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_GRAYSCALE),
                         np.uint8) for j in queries.jpegs[:max_queries]]
    return {kind: _kind_figures(keyframes, kind, count, images, conf or IndexConf(),
                                max_full_scans)
            for kind, count in KINDS.items()}


def _kind_figures(keyframes: list[Any], kind: str, count: int,
                  images: list[npt.NDArray[np.uint8]], conf: IndexConf,
                  max_full_scans: int) -> dict[str, Any]:
    start = time.perf_counter()
    pool = LandmarkPool.gather(keyframes, kind)
    gathered = time.perf_counter()
    index = RepetitionIndex.build(pool.descriptors, conf)
    built = time.perf_counter()
    out: dict[str, Any] = {
        "rows": len(pool.landmark_ids), "indexed": index.tree is not None,
        "pool_mb": sum(a.nbytes for a in (pool.descriptors, pool.landmark_ids,
                                          pool.points_world, pool.keyframe_rows)) / MB,
        "index_mb": index.nbytes / MB, "gather_s": gathered - start,
        "index_build_s": built - gathered}
    if len(pool.landmark_ids) < 2:
        return out
    check = RepetitionConf()
    search_ms, scan_ms, scanned = [], [], []
    compared = nearest_same = ratio_full = ratio_found = 0
    for n, image in enumerate(images):
        desc = _looked_up(image, kind, count, check.max_inliers + check.max_unexplained)
        t = time.perf_counter()
        d, rows = index.nearest_two(desc)
        search_ms.append(1000 * (time.perf_counter() - t))
        scanned.append(float(index.scanned_rows(desc).mean()))
        if n >= max_full_scans:
            continue
        t = time.perf_counter()
        d_all, rows_all = feature_lib.nearest_two(desc, pool.descriptors)
        scan_ms.append(1000 * (time.perf_counter() - t))
        same = rows[:, 0] == rows_all[:, 0]
        compared += len(desc)
        matched = d_all[:, 0] < check.ratio * d_all[:, 1]
        nearest_same += int(same.sum())
        ratio_full += int(matched.sum())
        ratio_found += int((matched & same & (d[:, 0] < check.ratio * d[:, 1])).sum())
    return {**out, "search_ms_p50": float(np.median(search_ms)) if search_ms else None,
            "full_scan_ms_p50": float(np.median(scan_ms)) if scan_ms else None,
            "scanned_rows_mean": float(np.mean(scanned)) if scanned else None,
            "nearest_found": nearest_same / compared if compared else None,
            "ratio_matches_found": ratio_found / ratio_full if ratio_full else None}


def _looked_up(image: npt.NDArray[np.uint8], kind: str, count: int, size: int
               ) -> npt.NDArray[Any]:
    """``size`` descriptors of ``kind`` of the query ``image``, evenly chosen (as the check
    chooses its inliers and unexplained keypoints)."""
    feats = feature_lib.extract(image, feature_lib.FeatureConf(kind=kind, max_features=count))
    pick = np.unique(np.linspace(0, len(feats) - 1, min(size, len(feats))).astype(np.int64))
    return feats.descriptors[pick]
