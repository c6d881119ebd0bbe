"""Tests of the bag-of-words place finder (vocabulary tree, tf-idf, L1 scoring)."""

from __future__ import annotations

import cv2
import msgpack
import numpy as np
import pytest
import skimage.data

from reloc_service.algorithms.place.base import create_place_finder
from reloc_service.algorithms.place.bow import BagOfWords
from reloc_service.algorithms.place.vocabulary import VocabularyTree, sized_branching
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError, NotTrainedError, StorageError
from reloc_service.core.features import FeatureConf, extract
from reloc_service.core.frame import Frame, Keyframe
from reloc_service.core.map import KeyframeMap

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
PHOTOS = ("camera", "astronaut", "coffee", "chelsea", "brick", "grass", "gravel", "rocket",
          "moon", "coins")
MAX_FEATURES = 500


def _grey(name: str) -> np.ndarray:
    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return img


def _views() -> list[np.ndarray]:
    """Two 640x480 views per photo: the whole photo and a zoomed crop of its left part."""
    views = []
    for name in PHOTOS:
        g = _grey(name)
        h, w = g.shape
        views.append(cv2.resize(g, (640, 480), interpolation=cv2.INTER_AREA))
        crop = g[h // 4:h // 4 + h // 2, w // 8:w // 8 + w // 2]
        views.append(cv2.resize(crop, (640, 480), interpolation=cv2.INTER_LINEAR))
    return views


def _rotated(image: np.ndarray, angle_deg: float = 90.0, scale: float = 1.15) -> np.ndarray:
    """The image turned in plane about its centre and slightly zoomed (a drone's yaw)."""
    m = cv2.getRotationMatrix2D((319.5, 239.5), angle_deg, scale)
    return cv2.warpAffine(image, m, (640, 480))


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    return _views()


@pytest.fixture(scope="module")
def sift_keyframes(images) -> list[Keyframe]:
    return _keyframes(images, "sift")


def _keyframes(images: list[np.ndarray], kind: str) -> list[Keyframe]:
    return [Keyframe(image=im, camera=CAMERA, id=i, world_from_cam=np.eye(4),
                     features={kind: extract(im, FeatureConf(kind, MAX_FEATURES))})
            for i, im in enumerate(images)]


def _finder(keyframes: list[Keyframe], **options) -> tuple[BagOfWords, KeyframeMap]:
    kmap = KeyframeMap()
    for kf in keyframes:
        kmap.add_keyframe(kf)
    finder = create_place_finder({"name": "bow", "max_features": MAX_FEATURES, **options}, kmap)
    assert isinstance(finder, BagOfWords)
    return finder, kmap


def _query(image: np.ndarray) -> Frame:
    return Frame(image=_rotated(image), camera=CAMERA)


def _sbi_best(keyframes: list[Keyframe], query: Frame) -> int:
    """PTAM's place finder (zero-mean SSD of small blurry images), for comparison."""
    q = query.small_blurry_image()
    return int(np.argmin([((kf.small_blurry_image() - q) ** 2).sum() for kf in keyframes]))


@pytest.fixture(scope="module")
def trained(sift_keyframes) -> BagOfWords:
    finder, _ = _finder(sift_keyframes)
    finder.train()
    return finder


@pytest.mark.parametrize("target", [0, 3, 7, 12])
def test_rotated_scaled_view_ranks_its_keyframe_first(trained, sift_keyframes, images, target):
    query = _query(images[target])
    candidates = trained.find_places(query, 5)
    assert candidates[0].keyframe_id == target
    assert candidates[0].score > 1.5 * candidates[1].score
    assert all(a.score >= b.score for a, b in zip(candidates, candidates[1:], strict=False))
    # The small blurry image is not rotation invariant: it picks another keyframe.
    assert _sbi_best(sift_keyframes, query) != target


def test_query_features_are_stored_for_the_pose_finder(trained, images):
    query = _query(images[2])
    trained.find_places(query, 1)
    assert "sift" in query.features and len(query.features["sift"]) > 100


@pytest.mark.parametrize("target", [0, 7])
def test_half_size_query_features_are_reused_not_extracted_again(trained, images, target):
    """With ``query_scale`` 0.5 the finder quantises the half-size SIFT a chain's earlier
    step left on the query (the same object, no full-size extraction) against the
    keyframes' full-size words, and still finds the rotated view's keyframe."""
    half = FeatureConf("sift", 1000, scale=0.5)
    finder = BagOfWords(trained.map, BagOfWords.Conf(max_features=1000, query_scale=0.5))
    finder._install(trained.vocabulary)   # the same words, the keyframes indexed again
    query = _query(images[target])
    cached = query.features[half.key] = extract(query.image, half)
    candidates = finder.find_places(query, 5)
    assert candidates[0].keyframe_id == target
    assert query.features[half.key] is cached and "sift" not in query.features
    assert finder.feature_confs() == {"sift@0.5": half}


def test_allowed_restricts_candidates(trained, images):
    query = _query(images[3])
    candidates = trained.find_places(query, 10, allowed={1, 5, 9})
    assert candidates and {c.keyframe_id for c in candidates} <= {1, 5, 9}


def test_add_after_training_uses_existing_vocabulary(sift_keyframes, images):
    finder, kmap = _finder(sift_keyframes[:-1])
    finder.train()
    vocabulary = finder.vocabulary
    new = sift_keyframes[-1]
    kmap.add_keyframe(new)
    finder.add_keyframe(new)
    assert finder.vocabulary is vocabulary
    assert finder.indexed_keyframe_ids() == [kf.id for kf in sift_keyframes]
    assert finder.find_places(_query(images[new.id]), 1)[0].keyframe_id == new.id


def test_remove_really_removes(sift_keyframes, images):
    finder, kmap = _finder(sift_keyframes)
    finder.train()
    target = 7
    query = _query(images[target])
    before = finder.find_places(query, len(sift_keyframes))
    assert before[0].keyframe_id == target
    kmap.remove_keyframe(target)
    finder.remove_keyframe(sift_keyframes[target])
    after = finder.find_places(query, len(sift_keyframes))
    assert target not in [c.keyframe_id for c in after]
    assert target not in finder.indexed_keyframe_ids()
    # idf follows the smaller database: the remaining scores change.
    scores_before = {c.keyframe_id: c.score for c in before}
    assert any(abs(scores_before[c.keyframe_id] - c.score) > 1e-9 for c in after)
    # Adding it back restores the original ranking and scores.
    kmap.add_keyframe(sift_keyframes[target])
    finder.add_keyframe(sift_keyframes[target])
    again = finder.find_places(query, len(sift_keyframes))
    assert [(c.keyframe_id, round(c.score, 9)) for c in again] == \
           [(c.keyframe_id, round(c.score, 9)) for c in before]


def test_state_round_trip_through_msgpack(trained, sift_keyframes, images):
    blob = msgpack.packb(trained.state(), use_bin_type=True)
    restored, _ = _finder(sift_keyframes)
    restored.load_state(msgpack.unpackb(blob, raw=False))
    assert restored.trained
    query = _query(images[5])
    assert restored.find_places(query, 5) == trained.find_places(query, 5)


def test_load_state_reconciles_with_the_map(trained, sift_keyframes):
    state = trained.state()
    restored, _ = _finder(sift_keyframes[:10])
    restored.load_state(state)
    assert restored.indexed_keyframe_ids() == list(range(10))


def test_load_state_refuses_other_kind_and_damage(trained, sift_keyframes):
    state = trained.state()
    orb, _ = _finder(sift_keyframes, kind="orb")
    with pytest.raises(StorageError, match="sift"):
        orb.load_state(state)
    damaged = dict(state, indptr=state["indptr"][:-8])
    with pytest.raises(StorageError):
        _finder(sift_keyframes)[0].load_state(damaged)


def test_untrained_finder_refuses_until_trained(sift_keyframes, images):
    finder, kmap = _finder(sift_keyframes[:5], depth=3)
    assert not finder.trained and finder.state() is None
    with pytest.raises(NotTrainedError, match="train"):
        finder.find_places(_query(images[4]), 1)
    # Keyframes that arrive before training are picked up by train() from the map.
    kmap.add_keyframe(sift_keyframes[5])
    finder.add_keyframe(sift_keyframes[5])
    finder.train()
    assert finder.trained and finder.indexed_keyframe_ids() == list(range(6))
    assert finder.find_places(_query(images[5]), 1)[0].keyframe_id == 5


def test_subsampled_training_is_seeded_and_still_ranks(sift_keyframes, images):
    trees = []
    for _ in range(2):
        finder, _ = _finder(sift_keyframes, max_train_descriptors=1500, depth=3)
        finder.train()
        trees.append(finder.vocabulary)
    first, second = trees
    assert all(np.array_equal(a, b) for a, b in zip(first.centres, second.centres, strict=True))
    assert finder.find_places(_query(images[3]), 1)[0].keyframe_id == 3


def test_empty_map_gives_no_candidates(images):
    finder, _ = _finder([])
    assert finder.find_places(Frame(image=images[0], camera=CAMERA), 3) == []
    assert not finder.trained


def test_keyframes_without_features_are_described_on_the_fly(images):
    kfs = [Keyframe(image=im, camera=CAMERA, id=i) for i, im in enumerate(images[:6])]
    finder, _ = _finder(kfs, depth=3)
    finder.train()
    assert finder.indexed_keyframe_ids() == list(range(6))
    assert finder.find_places(_query(images[2]), 1)[0].keyframe_id == 2


def test_orb_variant_finds_rotated_view(images):
    keyframes = _keyframes(images, "orb")
    finder, _ = _finder(keyframes, kind="orb")
    assert finder.required_features == frozenset({"orb"})
    finder.train()
    assert finder.vocabulary is not None and finder.vocabulary.dtype == np.uint8
    for target in (0, 7, 12):
        assert finder.find_places(_query(images[target]), 3)[0].keyframe_id == target


def test_tree_separates_float_blobs():
    rng = np.random.default_rng(0)
    centres = rng.normal(0, 50, (4, 16)).astype(np.float32)
    labels = rng.integers(0, 4, 800)
    x = centres[labels] + rng.normal(0, 1, (800, 16)).astype(np.float32)
    tree = VocabularyTree.build(x, branching=4, depth=1, iterations=5, rng=np.random.default_rng(0))
    words = tree.quantise(x)
    # One word per blob, the same for all its members.
    assert tree.n_words == 4
    assert all(len(np.unique(words[labels == b])) == 1 for b in range(4))
    assert len(np.unique(words)) == 4


def test_tree_k_majority_recovers_binary_prototypes():
    rng = np.random.default_rng(1)
    prototypes = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    labels = rng.integers(0, 3, 600)
    bits = np.unpackbits(prototypes[labels], axis=1)
    flips = (rng.random(bits.shape) < 0.05).astype(np.uint8)  # 5 % bit noise
    x = np.packbits(bits ^ flips, axis=1)
    tree = VocabularyTree.build(x, branching=3, depth=1, iterations=5, rng=np.random.default_rng(0))
    words = tree.quantise(x)
    assert all(len(np.unique(words[labels == b])) == 1 for b in range(3))
    # The majority of noisy copies is the prototype itself.
    found = {bytes(c) for c in tree.centres[0][0]}
    assert found == {bytes(p) for p in prototypes}


def test_deep_tree_on_few_descriptors_and_consistent_quantisation():
    rng = np.random.default_rng(2)
    x = rng.normal(0, 1, (37, 8)).astype(np.float32)
    tree = VocabularyTree.build(x, branching=3, depth=5, iterations=3, rng=np.random.default_rng(0))
    words = tree.quantise(x)
    assert 1 <= tree.n_words <= 37 and words.max() < tree.n_words
    assert np.array_equal(words, tree.quantise(x.copy()))  # deterministic
    assert VocabularyTree.from_state(tree.to_state()).quantise(x).tolist() == words.tolist()


@pytest.mark.parametrize(("n", "expected"), [
    (200_000, 10),      # the training cap: 10^4 leaves of 20, the fixed tree
    (10_000_000, 10),   # never above the configured branching
    (199_999, 9),       # 10^4 leaves would hold fewer than 20 each
    (131_220, 9), (131_219, 8),   # 9^4 * 20 = 131,220
    (30_000, 6),        # 6^4 = 1,296 leaves of 23
    (0, 2), (100, 2),   # never below a binary split
])
def test_sized_branching_keeps_the_count_per_leaf(n, expected):
    k = sized_branching(n, depth=4, max_branching=10, leaf_descriptors=20)
    assert k == expected
    assert k == 2 or k ** 4 * 20 <= n < (k + 1) ** 4 * 20 or k == 10


def test_sized_branching_rejects_a_zero_count():
    with pytest.raises(ValueError, match="leaf_descriptors >= 1"):
        sized_branching(1000, depth=4, max_branching=10, leaf_descriptors=0)


def test_sized_vocabulary_follows_the_map_and_still_ranks(sift_keyframes, images):
    fixed, _ = _finder(sift_keyframes)
    sized, _ = _finder(sift_keyframes, leaf_descriptors=20)
    fixed.train()
    sized.train()
    n = sum(len(kf.features["sift"]) for kf in sift_keyframes)   # 20 views, up to 500 each
    k = sized_branching(n, depth=4, max_branching=10, leaf_descriptors=20)
    assert sized.vocabulary is not None and fixed.vocabulary is not None
    assert sized.vocabulary.branching == k < fixed.vocabulary.branching == 10
    assert sized.vocabulary.n_words <= k ** 4 <= n / 20
    assert len(msgpack.packb(sized.state())) < len(msgpack.packb(fixed.state())) / 4
    for target in (0, 3, 7, 12):
        assert sized.find_places(_query(images[target]), 1)[0].keyframe_id == target
    restored, _ = _finder(sift_keyframes)   # a reader of any configuration reads the tree
    restored.load_state(msgpack.unpackb(msgpack.packb(sized.state())))
    assert restored.vocabulary is not None and restored.vocabulary.branching == k


def test_config_errors():
    kmap = KeyframeMap()
    with pytest.raises(ConfigError, match="leaf_descriptors >= 0"):
        create_place_finder({"name": "bow", "leaf_descriptors": -1}, kmap)
    with pytest.raises(ConfigError, match="kind"):
        create_place_finder({"name": "bow", "kind": "surf"}, kmap)
    with pytest.raises(ConfigError, match="branching"):
        create_place_finder({"name": "bow", "branching": 1}, kmap)
    with pytest.raises(ConfigError, match="unknown option"):
        create_place_finder({"name": "bow", "vocabulary_size": 3}, kmap)
    for scale in (0.0, 1.5):
        with pytest.raises(ConfigError, match="query_scale in"):
            create_place_finder({"name": "bow", "query_scale": scale}, kmap)


def test_float_centres_are_stored_as_float16_and_older_float32_states_still_load(
        trained, sift_keyframes, images):
    tree = trained._tree
    state = tree.to_state()
    assert state["dtype"] == "float32" and state["stored_dtype"] == "float16"
    float32_bytes = sum(c.nbytes for c in tree.centres)
    assert sum(len(level["centres"]) for level in state["levels"]) == float32_bytes // 2
    restored = VocabularyTree.from_state(state)
    assert all(np.abs(a - b).max() <= 0.0625 for a, b in zip(restored.centres, tree.centres,
                                                            strict=True))
    # a state written before float16 storage: centres in their own dtype, no stored_dtype
    old = dict(state, levels=[dict(level, centres=np.ascontiguousarray(c).tobytes())
                              for level, c in zip(state["levels"], tree.centres, strict=True)])
    del old["stored_dtype"]
    assert all(np.array_equal(a, b) for a, b in zip(VocabularyTree.from_state(old).centres,
                                                    tree.centres, strict=True))


def test_uint8_centres_halve_the_stored_vocabulary_and_stay_within_half_a_unit(
        trained, sift_keyframes, images):
    """``centres="uint8"``: SIFT means rounded to SIFT's integer values, half float16's bytes;
    read back as float32 by the reader of float16 centres, and the loaded finder saved again
    stores the same bytes and answers as the first load does."""
    small = trained.state(centres="uint8")
    assert small["tree"]["stored_dtype"] == "uint8"

    def centre_bytes(state):
        return sum(len(level["centres"]) for level in state["tree"]["levels"])

    assert 2 * centre_bytes(small) == centre_bytes(trained.state())
    restored, _ = _finder(sift_keyframes)
    restored.load_state(msgpack.unpackb(msgpack.packb(small, use_bin_type=True), raw=False))
    for held, read in zip(trained.vocabulary.centres, restored.vocabulary.centres, strict=True):
        assert read.dtype == np.float32 and np.abs(read - held).max() <= 0.5
        assert np.array_equal(read, np.rint(held))
    again = restored.state(centres="uint8")
    assert again["tree"] == small["tree"]
    twice, _ = _finder(sift_keyframes)
    twice.load_state(again)
    query = _query(images[5])
    assert twice.find_places(query, 5) == restored.find_places(query, 5)
    assert restored.find_places(query, 1)[0].keyframe_id == 5


def test_uint8_centres_apply_only_to_centres_on_sift_s_value_range():
    """Float descriptors outside 0-255 keep float16 centres; an unknown setting is refused."""
    rng = np.random.default_rng(0)
    tree = VocabularyTree.build(rng.normal(0.0, 1.0, (300, 8)).astype(np.float32),
                                branching=3, depth=2, iterations=2, rng=rng)
    assert tree.to_state(centres="uint8")["stored_dtype"] == "float16"
    with pytest.raises(ValueError, match="'float16' or 'uint8'"):
        tree.to_state(centres="int4")
