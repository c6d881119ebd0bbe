"""One stored descriptor per landmark (``keyframe_descriptors = "per-landmark"``): the rows of a
landmark read its first row's descriptor unless theirs differs from it beyond descriptor noise
(then they keep their own), the map loads and saves again unchanged, a shared column or
own-row mask of the wrong length is refused by name, and format-7 and 8 snapshots still
load."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from stored_maps import V6_MAP, V7_MAP, V8_MAP

from reloc_service.core import distributions
from reloc_service.core.errors import StorageError
from reloc_service.core.map import MapState
from reloc_service.storage.keyframe_parts import EVERYTHING, StoredParts
from reloc_service.storage.landmark_descriptors import (
    OWN_FALSE_ALARM,
    OWN_ROWS,
    SHARED_DESCRIPTORS,
    first_rows,
    noise_threshold,
    own_and_reference,
    own_rows,
    shared_index,
)
from reloc_service.storage.packed_columns import DELTA_PACKED, packed_file, unpack
from reloc_service.storage.snapshot import (
    SHARED_FORMAT_VERSION,
    load_map,
    save_map,
)
from reloc_service.storage.snapshot_files import current_snapshot
from reloc_service.storage.snapshot_format import OWN_ROWS_FORMAT_VERSION

PER_LANDMARK = StoredParts(descriptors="per-landmark")


def test_shared_index_gives_each_row_its_landmarks_first_row():
    ids = np.array([5, -1, 3, 5, 3, -1, 7, 5])
    assert first_rows(ids).tolist() == [True, True, True, False, False, True, True, False]
    # stored rows: 5, -1, 3, -1, 7 -> ranks 0..4
    assert shared_index(ids).tolist() == [0, 1, 2, 0, 2, 3, 4, 0]
    assert shared_index(np.zeros(0, np.int64)).tolist() == []
    assert shared_index(np.full(3, -1)).tolist() == [0, 1, 2]


def test_shared_index_agrees_with_a_sort_on_random_ids():
    ids = np.random.default_rng(0).integers(-1, 500, 5000)
    has = np.flatnonzero(ids >= 0)
    _, at, inverse = np.unique(ids[has], return_index=True, return_inverse=True)
    first = ids < 0
    first[has[at]] = True
    rank = np.cumsum(first) - 1
    expected = rank.copy()
    expected[has] = rank[has[at]][inverse]
    assert np.array_equal(first_rows(ids), first)
    assert np.array_equal(shared_index(ids), expected)


def test_own_rows_take_their_own_rank_and_others_their_landmarks_first_rows():
    ids = np.array([5, -1, 3, 5, 3, -1, 7, 5])
    own = np.array([False, False, False, False, True, False, False, True])
    assert first_rows(ids, own).tolist() == [True, True, True, False, True, True, True, True]
    # stored rows: 5, -1, 3, 3 (own), -1, 7, 5 (own) -> ranks 0..6
    assert shared_index(ids, own).tolist() == [0, 1, 2, 0, 3, 4, 5, 6]


def _assert_own_are(own, far, later):
    """Every ``far`` row keeps its own; of the other ``later`` rows (noise alone), no more
    than the false-alarm rate allows (its binomial's 99.9 % quantile)."""
    assert own[far].all()
    noise = np.setdiff1d(later, far)
    assert own[noise].sum() <= distributions.binom.ppf(0.999, len(noise), OWN_FALSE_ALARM)
    assert not own[np.setdiff1d(np.arange(len(own)), later)].any()   # first rows never


def test_binary_rows_beyond_the_binomial_quantile_keep_their_own():
    """ORB: 200 landmarks of 3 rows each; later rows flip 10% of their 256 bits (noise) or,
    for every tenth landmark, 40% (another patch): those and only those keep their own."""
    rng = np.random.default_rng(1)
    first = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    ids = np.repeat(np.arange(200), 3)
    desc = first[ids].copy()
    later = np.flatnonzero(np.arange(600) % 3 != 0)
    far = later[ids[later] % 10 == 0]
    for rows, p in ((later, 0.1), (far, 0.4)):
        flips = np.packbits(rng.random((len(rows), 256)) < p, axis=1)
        desc[rows] = first[ids[rows]] ^ flips
    own = own_rows(desc, ids)
    _assert_own_are(own, far, later)
    # the threshold: the binomial's quantile at the median's bit-flip rate
    distances = np.unpackbits(desc[later] ^ first[ids[later]], axis=1).sum(1)
    median = float(np.median(distances))
    assert noise_threshold(distances.astype(float), desc) == distributions.binom.ppf(
        1 - OWN_FALSE_ALARM, 256, median / 256)


def test_real_rows_beyond_the_chi_square_quantile_keep_their_own():
    """SIFT-like (128 values): Gaussian noise of one level on later rows, of five on every
    tenth landmark's; a row identical to its landmark's first row never keeps its own."""
    rng = np.random.default_rng(2)
    first = rng.uniform(40, 200, (300, 128))
    ids = np.repeat(np.arange(300), 2)
    desc = first[ids].copy()
    later = np.arange(1, 600, 2)
    sigma = np.where(ids[later] % 10 == 0, 5.0, 1.0)
    desc[later] += rng.normal(0, 1, (len(later), 128)) * sigma[:, None]
    desc = np.clip(np.round(desc), 0, 255).astype(np.uint8)
    own = own_rows(desc, ids)
    _assert_own_are(own, later[ids[later] % 10 == 0], later)
    desc[later] = desc[later - 1]
    assert not own_rows(desc, ids).any()


def _rows_in_snapshot_order(state: MapState, kind: str):
    """(keyframe id, Features) of ``kind`` in the order a snapshot concatenates them."""
    return [(k, kf.features[kind]) for k, kf in state.keyframes.items() if kind in kf.features]


def test_per_landmark_descriptors_round_trip(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path / "full", parts=StoredParts(descriptors="landmarks"))
    snap = save_map(synthetic_map, tmp_path / "shared", parts=PER_LANDMARK)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == OWN_ROWS_FORMAT_VERSION == 9
    assert f"features/sift.{SHARED_DESCRIPTORS}.npy" in manifest["files"]
    assert "features/sift.descriptors.npy" not in manifest["files"]
    rows = _rows_in_snapshot_order(synthetic_map, "sift")
    ids = np.concatenate([f.landmark_ids[f.landmark_ids >= 0] for _, f in rows])
    own = own_rows(np.concatenate([f.descriptors[f.landmark_ids >= 0] for _, f in rows]), ids)
    assert 0 < own.sum() < len(own) / 2   # some keep their own, most share
    loaded, _ = load_map(tmp_path / "shared")
    first: dict[int, np.ndarray] = {}   # landmark id -> descriptor of its first row
    observed = 0
    for k, feats in rows:
        got = loaded.keyframes[k].features["sift"]
        has = feats.landmark_ids >= 0
        assert np.array_equal(got.landmark_ids, feats.landmark_ids[has])
        assert np.array_equal(got.keypoints_px, feats.keypoints_px[has])
        for lm, desc, mine in zip(feats.landmark_ids[has], got.descriptors,
                                  feats.descriptors[has], strict=True):
            expected = first.setdefault(int(lm), mine)
            assert np.array_equal(desc, mine if own[observed] else expected)
            observed += 1
    assert observed > len(first) + own.sum()   # some landmark's descriptor shared
    full = current_snapshot(tmp_path / "full") / "features" / "sift.descriptors.npy"
    shared = snap / "features" / f"sift.{SHARED_DESCRIPTORS}.npy"
    assert shared.stat().st_size < (full.stat().st_size * (len(first) + own.sum()) / observed
                                    + 1024)
    # saved again (rows copied as stored, then as built): the same shared column
    again = save_map(loaded, tmp_path / "again", parts=PER_LANDMARK)
    assert (again / shared.relative_to(snap)).read_bytes() == shared.read_bytes()
    for kf in loaded.keyframes.values():
        kf.features["sift"]   # noqa: B018 (built now)
    thrice = save_map(loaded, tmp_path / "thrice", parts=PER_LANDMARK)
    assert (thrice / shared.relative_to(snap)).read_bytes() == shared.read_bytes()


def _rewrite(snapshot: Path, relpath: str, data: bytes) -> None:
    """Replace a snapshot file and its manifest entry (size and checksum agree again)."""
    (snapshot / relpath).write_bytes(data)
    manifest_path = snapshot / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["files"][relpath] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest_path.write_text(json.dumps(manifest))


def test_a_shared_column_of_the_wrong_length_is_refused_by_name(tmp_path, synthetic_map):
    snap = save_map(synthetic_map, tmp_path, parts=PER_LANDMARK)
    rel = f"features/sift.{SHARED_DESCRIPTORS}.npy"
    column = np.load(snap / rel)
    import io
    buf = io.BytesIO()
    np.save(buf, column[:-1])
    _rewrite(snap, rel, buf.getvalue())
    with pytest.raises(StorageError, match=rf"sift\.{SHARED_DESCRIPTORS}: {len(column) - 1} "
                                           rf"rows, expected {len(column)}"):
        load_map(tmp_path)


def test_an_own_row_mask_of_the_wrong_length_is_refused_by_name(tmp_path, synthetic_map):
    snap = save_map(synthetic_map, tmp_path, parts=PER_LANDMARK)
    rel = next(f for f in json.loads((snap / "manifest.json").read_text())["files"]
               if f.startswith(f"features/sift.{OWN_ROWS}."))
    mask = unpack((snap / rel).read_bytes(), rel, delta=rel.endswith(DELTA_PACKED))
    assert mask.any() and len(mask) > 1
    shorter, data = packed_file(f"features/sift.{OWN_ROWS}", mask[:-1])
    assert shorter == rel   # the same packing: the manifest entry is rewritten in place
    _rewrite(snap, rel, data)
    with pytest.raises(StorageError, match=r"sift.*expected one row per keypoint"):
        load_map(tmp_path)


def test_a_damaged_shared_column_is_refused_by_name(tmp_path, synthetic_map):
    snap = save_map(synthetic_map, tmp_path, parts=PER_LANDMARK)
    path = snap / "features" / f"sift.{SHARED_DESCRIPTORS}.npy"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=rf"sift\.{SHARED_DESCRIPTORS}\.npy: checksum"):
        load_map(tmp_path)


def test_a_format_7_snapshot_loads_the_same_and_saves_as_format_8_or_9(tmp_path):
    manifest = json.loads((V7_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 7
    v7, _ = load_map(V7_MAP)
    v6, _ = load_map(V6_MAP)
    assert v7.keyframe_ids() == v6.keyframe_ids()
    for k in v6.keyframe_ids():
        for kind, feats in v6.keyframes[k].features.items():
            got = v7.keyframes[k].features[kind]
            assert np.array_equal(got.descriptors, feats.descriptors)
            assert np.array_equal(got.keypoints_px, feats.keypoints_px)
            assert np.array_equal(got.landmark_ids, feats.landmark_ids)
    assert sorted(v7.landmarks) == sorted(v6.landmarks)
    save_map(v7, tmp_path / "full", parts=EVERYTHING)
    save_map(v7, tmp_path / "shared", parts=PER_LANDMARK)
    for name in ("full", "shared"):
        snap = current_snapshot(tmp_path / name)
        written = json.loads((snap / "manifest.json").read_text())
        # only a snapshot that shares descriptors needs format 8's reader, and only one
        # where a row keeps its own format 9's
        own = any(OWN_ROWS in f for f in written["files"])
        assert written["format_version"] == (7 if name == "full" else 9 if own else 8)
        again, _ = load_map(tmp_path / name)
        assert sorted(again.landmarks) == sorted(v7.landmarks)


def test_a_format_8_snapshot_loads_its_shared_descriptors_and_saves_again(tmp_path):
    manifest = json.loads((V8_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == SHARED_FORMAT_VERSION == 8
    assert not any(OWN_ROWS in f for f in manifest["files"])
    v8, _ = load_map(V8_MAP)
    v7, _ = load_map(V7_MAP)
    assert v8.keyframe_ids() == v7.keyframe_ids()
    first: dict[tuple[str, int], np.ndarray] = {}
    for k in v7.keyframe_ids():
        for kind, feats in v7.keyframes[k].features.items():
            got = v8.keyframes[k].features[kind]
            has = feats.landmark_ids >= 0
            assert np.array_equal(got.keypoints_px, feats.keypoints_px[has])
            for lm, desc, mine in zip(feats.landmark_ids[has], got.descriptors,
                                      feats.descriptors[has], strict=True):
                assert np.array_equal(desc, first.setdefault((kind, int(lm)), mine))
    # every row of a landmark reads one descriptor: saved again, none keeps its own
    snap = save_map(v8, tmp_path, parts=PER_LANDMARK)
    again = json.loads((snap / "manifest.json").read_text())
    assert again["format_version"] == 8
    for name in manifest["files"]:
        if name.endswith(".angles.npy"):   # read by nothing: no longer stored
            assert not (snap / name).exists()
        elif name.startswith("features/"):
            assert (snap / name).read_bytes() == (V8_MAP / "snapshots/000001" / name).read_bytes()


def _brute_medoid(desc: np.ndarray, rows: np.ndarray, binary: bool) -> int:
    """The row of ``rows`` with least summed distance to the others (earliest on a tie)."""
    if binary:
        d = np.array([[np.unpackbits(desc[a] ^ desc[b]).sum() for b in rows] for a in rows])
    else:
        g = desc[rows].astype(np.float64)
        d = np.sqrt(((g[:, None, :] - g[None, :, :]) ** 2).sum(-1))
    return int(rows[np.argmin(d.sum(1))])


@pytest.mark.parametrize("binary", [False, True])
def test_medoid_reference_is_the_rows_medoid_unless_the_first_row_is_beyond_noise(binary):
    """Landmarks of 1 to 6 rows, shuffled in row order: each row's reference is its
    landmark's medoid (brute force), the first row for one or two rows, and the first row
    where that differs from the medoid beyond the noise threshold; the own rows differ from
    their reference beyond it, and a row that is its landmark's reference is never own."""
    rng = np.random.default_rng(5)
    sizes = rng.integers(1, 7, 300)
    ids = rng.permutation(np.repeat(np.arange(300), sizes))
    if binary:
        centre = rng.integers(0, 256, (300, 32), dtype=np.uint8)
        p = np.where(rng.random(len(ids)) < 0.05, 0.4, 0.08)
        desc = centre[ids] ^ np.packbits(rng.random((len(ids), 256)) < p[:, None], axis=1)
    else:
        centre = rng.uniform(40, 200, (300, 128))
        sigma = np.where(rng.random(len(ids)) < 0.05, 6.0, 1.5)
        desc = np.clip(np.round(centre[ids] + rng.normal(0, 1, (len(ids), 128))
                                * sigma[:, None]), 0, 255).astype(np.uint8)
    own, reference = own_and_reference(desc, ids, medoid=True)
    plain_own, plain_ref = own_and_reference(desc, ids)
    assert np.array_equal(plain_own, own_rows(desc, ids))
    moved = 0
    for lm in range(300):
        rows = np.flatnonzero(ids == lm)
        assert (plain_ref[rows] == rows[0]).all()
        medoid = _brute_medoid(desc, rows, binary) if len(rows) >= 3 else int(rows[0])
        ref = int(reference[rows[0]])
        assert (reference[rows] == ref).all()
        assert ref in (medoid, int(rows[0]))
        moved += ref != rows[0]
        assert not own[ref] and not own[rows[0]]
    assert moved > 50   # most landmarks of 3+ rows share their medoid's descriptor
    assert own.sum() < plain_own.sum() + 5   # rows read a central view: no more keep their own


def test_per_landmark_medoid_descriptors_round_trip(tmp_path, synthetic_map):
    """Each row reads its own descriptor or its landmark's medoid's (an observed row's), the
    snapshot has the format and files of ``"per-landmark"`` (older readers read it), and a
    loaded map saved again, before and after its features are built, stores the same."""
    medoid_parts = StoredParts(descriptors="per-landmark-medoid")
    snap = save_map(synthetic_map, tmp_path / "medoid", parts=medoid_parts)
    plain = save_map(synthetic_map, tmp_path / "plain", parts=PER_LANDMARK)
    files = json.loads((snap / "manifest.json").read_text())
    assert files["format_version"] == json.loads(
        (plain / "manifest.json").read_text())["format_version"]
    assert sorted(files["files"]) == sorted(json.loads(
        (plain / "manifest.json").read_text())["files"])
    rows = _rows_in_snapshot_order(synthetic_map, "sift")
    ids = np.concatenate([f.landmark_ids[f.landmark_ids >= 0] for _, f in rows])
    desc = np.concatenate([f.descriptors[f.landmark_ids >= 0] for _, f in rows])
    own, reference = own_and_reference(desc, ids, medoid=True)
    assert (reference[ids >= 0] != np.flatnonzero(ids >= 0)).any()
    loaded, _ = load_map(tmp_path / "medoid")
    got = np.concatenate([loaded.keyframes[k].features["sift"].descriptors for k, _ in rows])
    expected = np.where(own[:, None], desc, desc[reference])
    assert np.array_equal(got, expected)
    shared = snap / "features" / f"sift.{SHARED_DESCRIPTORS}.npy"
    again = save_map(loaded, tmp_path / "again", parts=medoid_parts)
    assert (again / shared.relative_to(snap)).read_bytes() == shared.read_bytes()
    for kf in loaded.keyframes.values():
        kf.features["sift"]   # noqa: B018 (built now)
    thrice = save_map(loaded, tmp_path / "thrice", parts=medoid_parts)
    assert (thrice / shared.relative_to(snap)).read_bytes() == shared.read_bytes()
