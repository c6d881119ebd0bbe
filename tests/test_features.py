import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.core.errors import ConfigError
from reloc_service.core.features import (
    FeatureConf,
    capped,
    compute_at,
    detect_sift,
    extract,
    match_ratio,
)
from reloc_service.core.retain_best import retain_best


@pytest.fixture(scope="module")
def image():
    return cv2.resize(skimage.data.camera(), (320, 240))


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_extract_and_self_match(image, kind):
    feats = extract(image, FeatureConf(kind, 500))
    assert 50 < len(feats) <= 500
    assert feats.descriptors.dtype == np.uint8 and feats.descriptors.shape[1] == (
        128 if kind == "sift" else 32)
    # Matching against a permuted copy of itself recovers the permutation.
    perm = np.random.default_rng(0).permutation(len(feats))
    q, t, d = match_ratio(feats.descriptors, feats.descriptors[perm])
    assert len(q) > 0.8 * len(feats)
    assert np.all(perm[t] == q)
    assert np.all(d < 1e-2)


def test_ratio_test_rejects_ambiguous():
    rng = np.random.default_rng(1)
    train = rng.normal(size=(2, 128)).astype(np.float32)
    train[1] = train[0] + 1e-3  # two near-identical candidates: ambiguous
    q, _, _ = match_ratio(train[:1] + 1e-2, train)
    assert len(q) == 0


def test_hamming_matches_brute_force():
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, size=(40, 32), dtype=np.uint8)
    b = rng.integers(0, 256, size=(300, 32), dtype=np.uint8)
    b[:40] = a
    b[:40, 0] ^= 1  # one bit away
    q, t, d = match_ratio(a, b)
    ref = cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)[1][:, 0]
    assert np.array_equal(t, ref[q]) and np.all(d == 1)


def test_compute_at_given_positions(image):
    pts = np.array([[100.0, 100.0], [150.0, 120.0], [1.0, 1.0]])
    feats, origin = compute_at(image, "sift", pts)
    assert set(origin) <= {0, 1, 2} and 0 in origin and 1 in origin
    assert np.allclose(feats.keypoints_px, pts[origin])


@pytest.mark.parametrize("cap", [5000, 200, 50])
def test_sift_capped_from_its_whole_detection_is_the_extraction(image, cap):
    """Capped from every keypoint SIFT detects and describes, the features are extract's:
    the same arrays in the same order, whether the cap drops keypoints or not; the
    detection's keypoints are those SIFT's detector alone lists."""
    detection = detect_sift(image)
    assert [k.pt for k in detection.keypoints] == [
        k.pt for k in cv2.SIFT.create().detect(image, None)]
    conf = FeatureConf("sift", cap)
    want, got = extract(image, conf), capped(image, detection, conf)
    assert (len(detection.keypoints) > cap) == (cap < 5000)
    assert len(want) >= min(cap, len(detection.keypoints))
    for name in ("keypoints_px", "descriptors", "levels", "sizes", "angles"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name


@pytest.mark.parametrize("count", [1, 7, 100, 999])
def test_retain_best_orders_as_opencvs_cap(count):
    """The emulated order of OpenCV's cap is the one ``cv2.SIFT`` with ``nfeatures`` gives,
    on a photograph with more keypoints than each cap."""
    image = cv2.resize(skimage.data.astronaut()[..., 1], (512, 512))
    detected = list(cv2.SIFT.create().detect(image, None))
    capped = cv2.SIFT.create(nfeatures=count).detect(image, None)
    order = retain_best([k.response for k in detected], count)
    assert order is not None and len(detected) > count
    assert [detected[i].pt for i in order] == [k.pt for k in capped]


def test_retain_best_keeps_ties_of_the_weakest_kept():
    # Introselect (worked by hand) leaves [0, 3 | 2, 1, 4]; 2 ties the weakest kept (3).
    assert retain_best([3.0, 1.0, 2.0, 2.0, 0.5], 2) == [0, 3, 2]
    assert retain_best([1.0, 2.0], 5) == [0, 1]


def test_capped_wants_full_image_sift(image):
    with pytest.raises(ConfigError, match="SIFT features of the full image expected"):
        capped(image, detect_sift(image), FeatureConf("orb", 100))


def test_conf_errors():
    with pytest.raises(ConfigError, match="unknown"):
        FeatureConf("akaze")
    with pytest.raises(ConfigError, match="positive"):
        FeatureConf("sift", 0)


def test_sift_uint8_is_lossless_and_matches_identically(image):
    """OpenCV's SIFT values are integers 0-255 held in float32: the uint8 copy we keep is
    exact, and matching it gives the same matches and distances as the float32 original."""
    keypoints, raw = cv2.SIFT.create(nfeatures=500).detectAndCompute(image, None)
    other_kp, other = cv2.SIFT.create(nfeatures=500).detectAndCompute(
        cv2.GaussianBlur(image, (0, 0), 1.0), None)
    assert raw.dtype == np.float32 and np.array_equal(raw, np.rint(raw))
    assert raw.min() >= 0 and raw.max() <= 255
    feats = extract(image, FeatureConf("sift", 500))
    assert np.array_equal(feats.descriptors.astype(np.float32), raw)
    ours = match_ratio(feats.descriptors, other.astype(np.uint8))
    theirs = match_ratio(raw, other)
    assert len(ours[0]) > 20
    for a, b in zip(ours, theirs, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize(("n", "m", "width"), [(500, 3000, 32), (3, 2, 32), (70, 90, 12)])
def test_hamming_ratio_test_is_the_bitwise_one(n, m, width):
    """The popcount kernel gives the Hamming distances and matches that L2 on unpacked bits
    gives (the definition): same pairs, same distances, also across chunks of query rows
    and for widths that are no multiple of 8 bytes."""
    rng = np.random.default_rng(n)
    query = rng.integers(0, 256, (n, width), dtype=np.uint8)
    train = rng.integers(0, 256, (m, width), dtype=np.uint8)
    near = rng.choice(n, min(n, m) // 2, replace=False)
    flips = (rng.random((len(near), width * 8)) < 0.05).astype(np.uint8)
    train[:len(near)] = query[near] ^ np.packbits(flips, axis=1)  # true matches, a few bits off
    q, t, dist = match_ratio(query, train, ratio=0.8)
    bits_q = np.unpackbits(query, axis=1).astype(np.float64)
    bits_t = np.unpackbits(train, axis=1).astype(np.float64)
    # squared L2 of 0/1 vectors, |a|^2 + |b|^2 - 2 a.b: exact integers in float64 (not the
    # (n, m, bits) array of differences, 3 GB at 500 x 3000)
    full = (bits_q.sum(1)[:, None] + bits_t.sum(1)[None, :] - 2.0 * bits_q @ bits_t.T
            ).astype(np.int64)
    best = np.sort(full, axis=1)
    expected = np.flatnonzero(best[:, 0] < 0.8 * best[:, 1])
    assert np.array_equal(q, expected)
    assert np.array_equal(dist, best[expected, 0].astype(np.float32))
    assert np.array_equal(full[q, t], best[q, 0])
    if n == 500:
        assert len(q) >= len(near) // 2  # the planted matches pass


def test_orb_keypoints_are_level_pixels_times_the_level_scale(synthetic_scene):
    """OpenCV's ORB returns integer pixels of pyramid level l times float32(1.2f ** l): every
    keypoint of a real extraction rebuilds bit-exactly from int16 pixels (what a snapshot
    stores), and one moved by a float32 ulp does not."""
    from reloc_service.core.features import ORB_SCALE_FACTOR
    from reloc_service.storage.feature_columns import level_pixels, pixels_from_levels

    feats = extract(synthetic_scene.keyframe_images[0], FeatureConf("orb", 2000))
    keypoints = feats.keypoints_px.astype(np.float32)
    assert np.array_equal(keypoints.astype(np.float64), feats.keypoints_px)
    assert len(np.unique(feats.levels)) == 8
    found = level_pixels(keypoints, feats.levels, ORB_SCALE_FACTOR)
    assert found is not None
    pixels, table = found
    assert pixels.dtype == np.int16 and table.shape == (8, 2)
    assert np.array_equal(pixels_from_levels(pixels, feats.levels, table), keypoints)
    moved = keypoints.copy()
    i = int(np.flatnonzero(feats.levels == 5)[0])
    moved[i, 0] = np.nextafter(moved[i, 0], np.float32(1e9))
    assert level_pixels(moved, feats.levels, ORB_SCALE_FACTOR) is None


def test_sift_two_nearest_take_the_product_of_minus_two_a_to_the_bit(image):
    """The squared-L2 two nearest scale the query rows by -2 before the product, not the
    (N, M) product after it: the same distances and indices to the bit as the product scaled
    afterwards, on real SIFT descriptors, in one chunk and across several."""
    from reloc_service.core.features import _knn2_squared

    a = extract(image, FeatureConf("sift", 300)).descriptors.astype(np.float32)
    b = extract(cv2.flip(image, 1), FeatureConf("sift", 500)).descriptors.astype(np.float32)
    b = np.concatenate([b, a[::3]])   # some exact twins: distance 0 and ties broken by index
    g = (a @ b.T) * np.float32(-2.0) + (b * b).sum(1)
    i1 = g.argmin(1)
    rows = np.arange(len(a))
    d1 = g[rows, i1].copy()
    g[rows, i1] = np.inf
    i2 = g.argmin(1)
    expected_d = np.maximum(np.stack([d1, g[rows, i2]], 1) + (a * a).sum(1)[:, None], 0.0)
    for chunk in (1 << 22, 7 * len(b)):
        d, idx = _knn2_squared(a, b, chunk_elems=chunk)
        assert np.array_equal(idx, np.stack([i1, i2], 1)) and np.array_equal(d, expected_d)
    assert np.all(d[::3, 0] == 0.0)   # each of a[::3] meets its twin
