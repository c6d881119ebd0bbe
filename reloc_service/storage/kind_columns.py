"""The columns a snapshot stores for one feature kind (:func:`kind_columns`: narrowed where
lossless, derivable fields only where load would not derive them, as
:mod:`.feature_columns` describes) and the codebook its descriptors are saved with."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.features import level_scale_factor
from ..core.frame import Features
from ..core.landmark_table import LandmarkColumns, LandmarkTable
from .descriptor_hybrid import EXACT, EXACT_ROWS, exact_threshold, split_exact, with_exact
from .descriptor_pq import (
    CODEC_SUBSPACES,
    DESCRIPTOR_CODES,
    EXACT_CODECS,
    PQCodebook,
    descriptor_rows,
    seeded_rows,
    train_codebook,
)
from .feature_columns import (
    DERIVABLE_FIELDS,
    DERIVED_FIELD,
    EIGHTH_PIXELS,
    LEVEL_PIXELS,
    SCALE_TABLE,
    SIZE_TABLE,
    STORED_FIELDS,
    LazyFeatures,
    ids_from_observations,
    level_pixels,
    narrow,
    points_are_derived,
    sizes_by_level,
)
from .landmark_descriptors import SHARED_CODES, SHARED_DESCRIPTORS, share_descriptors
from .landmark_rows import keep_rows


def kind_columns(kind: str, owners: Sequence[tuple[int, int, Mapping[str, Features]]],
                 table: LandmarkTable, landmarks: LandmarkColumns,
                 codebook: PQCodebook | None = None,
                 keep: Sequence[npt.NDArray[np.bool_] | None] | None = None,
                 compact: bool = False, shared: bool = False,
                 medoid: bool = False) -> dict[str, np.ndarray]:
    """The columns a snapshot stores for ``kind`` (name -> array): ``owners`` are (keyframe
    id, first row, features) of every keyframe holding ``kind``, in row order; rows narrowed
    where lossless, and the derivable fields only where they are not what load derives
    (sizes from a level table, ids from ``landmarks``' observations, points from ``table``).
    With a ``codebook`` the descriptors are stored as its codes (:data:`DESCRIPTOR_CODES`);
    ``keep``: per owner, the mask of its rows stored (None: all; :mod:`.landmark_rows`);
    ``compact``: keypoints in eighths of a pixel, sizes float16; ``shared``: one
    descriptor per landmark (:mod:`.landmark_descriptors`), its rows' medoid's with
    ``medoid``. A codebook with an exact threshold also stores in full the rows its codes
    reconstruct worse than that (:mod:`.descriptor_hybrid`)."""
    # a part is the rows as a loaded snapshot stored them (never built since), or Features
    parts: list[Features | dict[str, np.ndarray]] = [
        _stored_rows(features, kind) or features[kind] for _, _, features in owners]
    codes = [_descriptor_rows(p, _codebook_of(f, kind), codebook)
             for p, (_, _, f) in zip(parts, owners, strict=True)]
    fields = [f for f in (*STORED_FIELDS, *DERIVABLE_FIELDS[:2]) if f != "descriptors"]
    if not all(points_are_derived(table, p.landmark_ids, p.points_world)
               for p in parts if isinstance(p, Features)):
        fields.append(DERIVED_FIELD)
        parts = [features[kind] for _, _, features in owners]   # every keyframe's points
    columns = {name: _concat([getattr(p, name) if isinstance(p, Features) else p[name]
                              for p in parts]) for name in fields}
    columns["descriptors" if codebook is None else DESCRIPTOR_CODES] = _concat(codes)
    exact = codebook is not None and codebook.exact_above is not None
    if exact:   # the full rows ride along through the row selection and the sharing
        columns["descriptors"] = _concat([_full_rows(p, _codebook_of(f, kind))
                                          for p, (_, _, f) in zip(parts, owners, strict=True)])
    if keep is not None:
        columns = keep_rows(columns, keep, [len(c) for c in codes])
    if shared:
        columns = share_descriptors(columns, codebook, medoid=medoid)
    if exact:
        assert codebook is not None
        full, coded = (("descriptors", DESCRIPTOR_CODES) if DESCRIPTOR_CODES in columns
                       else (SHARED_DESCRIPTORS, SHARED_CODES))
        columns.update(split_exact(columns.pop(full), columns[coded], codebook))
    sizes = sizes_by_level(columns["levels"], columns["sizes"])
    if sizes is not None:
        del columns["sizes"]
        columns[SIZE_TABLE] = sizes
    order = sorted(range(len(owners)), key=lambda i: owners[i][0])
    kf_ids = np.array([owners[i][0] for i in order], np.int64).reshape(-1)
    starts = np.array([owners[i][1] for i in order], np.int64).reshape(-1)
    ids = ids_from_observations(landmarks, kind, len(columns["landmark_ids"]), kf_ids, starts)
    if ids is not None and np.array_equal(ids, columns["landmark_ids"]):
        del columns["landmark_ids"]
    # no angles: read by nothing once extracted (a descriptor is already steered by its
    # keypoint's angle), so the answers are the same without them
    out = {name: narrow(name, column) for name, column in columns.items() if name != "angles"}
    if kind == "orb":
        found = level_pixels(out["keypoints_px"], out["levels"], level_scale_factor(kind))
        if found is not None:
            del out["keypoints_px"]
            out[LEVEL_PIXELS], out[SCALE_TABLE] = found
    if compact:   # after the exact level pixels, which ORB's keypoints take first
        _compact_keypoints(out)
    return out


def _compact_keypoints(out: dict[str, np.ndarray]) -> None:
    """Sizes float16 and float keypoints as :data:`EIGHTH_PIXELS` where they fit (in place)."""
    if "sizes" in out:
        out["sizes"] = out["sizes"].astype(np.float16)
    if "keypoints_px" in out:
        eighths = np.rint(np.asarray(out["keypoints_px"], np.float64) * 8.0)
        if len(eighths) and np.all(np.abs(eighths) <= np.iinfo(np.int16).max):  # NaN fails
            out[EIGHTH_PIXELS] = eighths.astype(np.int16)
            del out["keypoints_px"]


def codebook_for(kind: str, owners: Sequence[tuple[int, int, Mapping[str, Features]]],
                 codec: str, caches: Sequence[dict[str, Any]]) -> PQCodebook | None:
    """The codebook ``kind``'s descriptors are saved with under ``codec`` (None: in full):
    only SIFT's are coded ("pq", "pq16": :data:`CODEC_SUBSPACES`). The codebook a loaded
    snapshot's keyframes use, or an earlier save's (kept in the keyframes' ``caches``), is
    kept when it has the codec's sub-quantizers: codes are copied, never decoded and coded
    again. Else one is learnt on the map's own descriptors and put in ``caches`` (None when
    the map holds too few to learn from)."""
    subspaces = CODEC_SUBSPACES.get(codec)
    if subspaces is None or kind.split("@")[0] != "sift":
        return None
    exact = codec in EXACT_CODECS
    key = f"pq{subspaces}{'-exact' if exact else ''}:{kind}"
    for (_, _, features), cache in zip(owners, caches, strict=True):
        codebook = _codebook_of(features, kind) or cache.get(key)
        if (codebook is not None and codebook.subspaces == subspaces
                and (codebook.exact_above is not None) == exact):
            break
    else:
        codebook = train_codebook(seeded_rows([f[kind].descriptors for _, _, f in owners]),
                                  subspaces=subspaces)
        if codebook is not None and exact:
            codebook = _with_threshold(codebook, kind, owners)
    if codebook is not None:
        for cache in caches:
            cache[key] = codebook
    return codebook


def _with_threshold(codebook: PQCodebook, kind: str,
                    owners: Sequence[tuple[int, int, Mapping[str, Features]]]) -> PQCodebook:
    """``codebook`` with its exact threshold measured on the owners' landmark rows (infinite,
    no row exact, when no landmark has two rows to measure descriptor noise on)."""
    feats = [f[kind] for _, _, f in owners]
    threshold = exact_threshold([x.descriptors for x in feats], [x.landmark_ids for x in feats])
    return PQCodebook(codebook.centroids,
                      exact_above=float("inf") if threshold is None else threshold)


def _descriptor_rows(part: Features | dict[str, np.ndarray], source: PQCodebook | None,
                     target: PQCodebook | None) -> np.ndarray:
    """:func:`.descriptor_pq.descriptor_rows`, a loaded snapshot's exact rows included
    where its codes are not copied as they are."""
    if isinstance(part, dict) and EXACT_ROWS in part and (target is None or source is not target):
        full = _full_rows(part, source)
        return full if target is None else target.encode(full)
    return descriptor_rows(part, source, target)


def _full_rows(part: Features | dict[str, np.ndarray], source: PQCodebook | None
               ) -> np.ndarray:
    """A part's descriptors as held: a loaded snapshot's stored codes decoded, with the rows
    it kept exact."""
    if isinstance(part, Features):
        return np.asarray(part.descriptors)
    if DESCRIPTOR_CODES not in part:
        return np.asarray(part["descriptors"])
    assert source is not None, "coded rows come with their codebook"
    decoded = source.decode(np.asarray(part[DESCRIPTOR_CODES]))
    if EXACT_ROWS not in part:
        return decoded
    return with_exact(decoded, np.asarray(part[EXACT_ROWS], bool), np.asarray(part[EXACT]))


def _stored_rows(features: Mapping[str, Features], kind: str) -> dict[str, np.ndarray] | None:
    return features.stored(kind) if isinstance(features, LazyFeatures) else None


def _codebook_of(features: Mapping[str, Features], kind: str) -> PQCodebook | None:
    return features.codebook(kind) if isinstance(features, LazyFeatures) else None


def _concat(parts: list[np.ndarray]) -> np.ndarray:
    """Rows of ``parts`` in one array, in the widest dtype among them (empty parts may be
    1-D placeholders of a 2-D field)."""
    wide = [np.asarray(p) for p in parts if len(p)] or [np.asarray(p) for p in parts]
    dtype = np.result_type(*wide)
    return np.concatenate([np.asarray(p).reshape(len(p), *wide[0].shape[1:]).astype(dtype)
                           for p in parts])
