"""Which rows of each keyframe's features a snapshot keeps: every keypoint's, or only those
that carry a landmark (``StoredParts.descriptors == "landmarks"``), and the landmarks'
observations renumbered to the kept rows.

An observation names its keypoint by its row in the keyframe's features of its kind; dropping
the rows without a landmark moves every later row up, so each observation's keypoint becomes
its rank among the kept rows. A keyframe stored so is marked in the manifest, loads marked
(:data:`..core.landmark_rows.LANDMARK_ROWS_ONLY`) and stays so at later saves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from ..core.frame import Features, Keyframe
from ..core.landmark_rows import holds_landmark_rows_only
from ..core.landmark_table import LandmarkColumns

#: "per-landmark" keeps the rows "landmarks" keeps, with one descriptor a landmark (its first
#: row's; "per-landmark-medoid": its rows' medoid) (:mod:`.landmark_descriptors`)
ROW_MODES = ("all", "landmarks", "per-landmark", "per-landmark-medoid")
#: The row modes that store one descriptor a landmark
SHARED_MODES = ("per-landmark", "per-landmark-medoid")

#: (keyframe id, kind) -> mask of the rows kept (None: every row kept)
RowMasks = dict[tuple[int, str], npt.NDArray[np.bool_] | None]


def row_masks(keyframes: Sequence[Keyframe], mode: str,
              kept_ids: npt.NDArray[np.int64] | None = None) -> RowMasks:
    """The rows a snapshot keeps of each keyframe's features under ``mode``: with
    ``"landmarks"`` (or ``"per-landmark"``) the keypoints with a landmark (None where that is
    every row), of the landmarks ``kept_ids`` (ascending) only when given (a summary map:
    :mod:`.landmark_summary`). A keyframe without any landmark of a kind keeps all its
    keypoints of that kind: it is not mapped yet (a map's first keyframe, one whose
    neighbours are still to come), and the keyframes that will see its keypoints make their
    landmarks from them."""
    masks: RowMasks = {}
    for kf in keyframes:
        for kind in kf.features:
            keep = None
            if mode != "all":
                ids = _landmark_ids(kf.features, kind)
                mapped = ids >= 0
                keep = mapped if kept_ids is None else _is_kept(ids, kept_ids)
                keep = None if keep.all() or not mapped.any() else keep
            masks[(kf.id, kind)] = keep
    return masks


def _is_kept(ids: npt.NDArray[np.integer], kept_ids: npt.NDArray[np.int64]
             ) -> npt.NDArray[np.bool_]:
    """(N,) whether each id is one of ``kept_ids`` (ascending; -1 never is)."""
    if len(kept_ids) == 0:
        return np.zeros(len(ids), bool)
    pos = np.clip(np.searchsorted(kept_ids, ids), 0, len(kept_ids) - 1)
    return (kept_ids[pos] == ids) & (ids >= 0)


def landmark_rows_only(keyframes: Sequence[Keyframe], masks: RowMasks) -> list[bool]:
    """Per keyframe, whether its stored features hold landmark keypoints only: rows dropped
    now, or at the save it was loaded from (its mark, set by the load: a keyframe held in
    full is not marked by a save that stores a part of it)."""
    return [holds_landmark_rows_only(kf)
            or any(masks.get((kf.id, kind)) is not None for kind in kf.features)
            for kf in keyframes]


def kept_count(masks: RowMasks, kf_id: int, kind: str, count: int) -> int:
    keep = masks.get((kf_id, kind))
    return count if keep is None else int(keep.sum())


def _landmark_ids(features: Mapping[str, Features], kind: str) -> npt.NDArray[np.integer]:
    """``kind``'s landmark ids without building a loaded keyframe's features (a
    :class:`.feature_columns.LazyFeatures` gives its stored rows)."""
    stored = getattr(features, "stored", None)
    rows = stored(kind) if stored is not None else None
    return np.asarray(rows["landmark_ids"]) if rows is not None else features[kind].landmark_ids


def renumber_observations(columns: LandmarkColumns, masks: RowMasks) -> LandmarkColumns:
    """``columns`` with each observation's keypoint renumbered to its rank among its
    keyframe's kept rows of its kind (unchanged when every row is kept)."""
    dropped = {key: keep for key, keep in masks.items() if keep is not None}
    if not dropped or len(columns.obs_keypoint) == 0:
        return columns
    kind_index = {k: i for i, k in enumerate(columns.kinds)}
    stride = len(columns.kinds) + 1
    obs_key = (np.asarray(columns.obs_keyframe, np.int64) * stride
               + np.asarray(columns.obs_kind, np.int64))
    order = np.argsort(obs_key, kind="stable")   # each (keyframe, kind)'s observations a slice
    sorted_key = obs_key[order]
    keypoints = np.array(columns.obs_keypoint, np.int64)
    for (kf_id, kind), keep in dropped.items():
        if kind not in kind_index:
            continue
        key = kf_id * stride + kind_index[kind]
        sel = order[np.searchsorted(sorted_key, key):np.searchsorted(sorted_key, key, "right")]
        rank = np.cumsum(keep) - 1
        old = keypoints[sel]
        assert keep[old].all(), "an observed keypoint carries its landmark"
        keypoints[sel] = rank[old]
    return dataclasses.replace(columns, obs_keypoint=keypoints)


def keep_rows(columns: dict[str, np.ndarray], masks: Sequence[npt.NDArray[np.bool_] | None],
              counts: Sequence[int]) -> dict[str, np.ndarray]:
    """Concatenated feature ``columns`` (parts of ``counts`` rows, in order) cut to the rows
    each part's mask keeps."""
    if all(m is None for m in masks):
        return columns
    keep = np.concatenate([np.ones(n, bool) if m is None else m
                           for m, n in zip(masks, counts, strict=True)])
    return {name: column[keep] for name, column in columns.items()}
