import threading

import numpy as np
import pytest

from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import GeometryError, MapError
from reloc_service.core.frame import Features, Frame, Keyframe
from reloc_service.core.geometry import se3_exp
from reloc_service.core.map import KeyframeMap

CAM = PinholeCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def make_keyframe(kf_id, n=10, landmark_ids=None, seed=0):
    rng = np.random.default_rng(seed + kf_id)
    image = rng.integers(0, 255, size=(48, 64), dtype=np.uint8)
    feats = Features.create("sift", rng.uniform(0, 60, size=(n, 2)),
                            rng.normal(size=(n, 128)).astype(np.float32))
    if landmark_ids is not None:
        pts = np.where(np.asarray(landmark_ids)[:, None] >= 0, rng.normal(size=(n, 3)), np.nan)
        feats = Features.create("sift", feats.keypoints_px, feats.descriptors,
                                landmark_ids=landmark_ids, points_world=pts)
    pose = se3_exp(np.concatenate([rng.normal(size=3), 0.1 * rng.normal(size=3)]))
    return Keyframe(image=image, camera=CAM, features={"sift": feats}, id=kf_id, world_from_cam=pose)


def test_add_remove_and_version():
    kmap = KeyframeMap()
    assert kmap.version == 0
    kmap.add_keyframe(make_keyframe(0))
    kmap.add_keyframe(make_keyframe(1))
    assert len(kmap) == 2 and kmap.version == 2
    kmap.remove_keyframe(0)
    assert 0 not in kmap and kmap.version == 3
    with pytest.raises(MapError, match="not in the map"):
        kmap.remove_keyframe(0)


def test_landmarks_follow_observations():
    kmap = KeyframeMap()
    kmap.add_keyframe(make_keyframe(0))
    kmap.add_keyframe(make_keyframe(1))
    ids = kmap.add_landmarks("sift", np.zeros((2, 3)), [[(0, 1), (1, 2)], [(0, 3)]])
    state = kmap.snapshot()
    assert len(state.landmarks) == 2
    assert state.keyframe(0).features["sift"].landmark_ids[1] == ids[0]
    assert state.keyframe(1).features["sift"].landmark_ids[2] == ids[0]
    # Removing keyframe 0 keeps landmark 0 (still seen by 1) and drops landmark 1.
    kmap.remove_keyframe(0)
    state = kmap.snapshot()
    assert set(state.landmarks) == {ids[0]}
    assert state.landmarks[ids[0]].observations == frozenset({(1, "sift", 2)})


def test_given_landmarks_and_replace():
    kmap = KeyframeMap()
    lm = np.full(10, -1)
    lm[:3] = [7, 8, 9]
    kmap.add_keyframe(make_keyframe(0, landmark_ids=lm))
    assert set(kmap.snapshot().landmarks) == {7, 8, 9}
    # Replacing keyframe 0 with one without landmarks drops them.
    kmap.add_keyframe(make_keyframe(0))
    assert len(kmap.snapshot().landmarks) == 0
    # New landmarks never reuse a given id.
    kmap.add_keyframe(make_keyframe(1, landmark_ids=lm))
    new = kmap.add_landmarks("sift", np.zeros((1, 3)), [[(0, 5)]])
    assert new[0] > 9


def test_add_observations_extends_tracks():
    kmap = KeyframeMap()
    kmap.add_keyframe(make_keyframe(0))
    kmap.add_keyframe(make_keyframe(1))
    (lm,) = kmap.add_landmarks("sift", [[1.0, 2.0, 3.0]], [[(0, 0)]])
    assert kmap.add_observations("sift", [(lm, 1, 4), (lm, 1, 4), (999, 1, 5)]) == 1
    f1 = kmap.snapshot().keyframe(1).features["sift"]
    assert f1.landmark_ids[4] == lm and np.allclose(f1.points_world[4], [1, 2, 3])


def test_snapshot_is_consistent_while_writing():
    kmap = KeyframeMap()
    kmap.add_keyframe(make_keyframe(0))
    snap = kmap.snapshot()
    stop = threading.Event()

    def writer():
        i = 1
        while not stop.is_set() and i < 200:
            kmap.add_keyframe(make_keyframe(i))
            i += 1

    t = threading.Thread(target=writer)
    t.start()
    for _ in range(200):
        s = kmap.snapshot()
        assert len(s.keyframes) == s.version  # one keyframe per version in this test
    stop.set()
    t.join()
    assert list(snap.keyframes) == [0] and snap.version == 1


def test_frame_validation():
    with pytest.raises(GeometryError, match="does not match"):
        Frame(image=np.zeros((10, 10), np.uint8), camera=CAM)
    with pytest.raises(GeometryError, match="uint8"):
        Frame(image=np.zeros((48, 64), np.float32), camera=CAM)
    with pytest.raises(MapError, match="non-negative"):
        Keyframe(image=np.zeros((48, 64), np.uint8), camera=CAM, id=-3)
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(GeometryError, match="non-finite"):
        Keyframe(image=np.zeros((48, 64), np.uint8), camera=CAM, id=1, world_from_cam=bad)


def test_small_blurry_image_is_zero_mean():
    f = Frame(image=np.random.default_rng(0).integers(0, 255, (48, 64), dtype=np.uint8), camera=CAM)
    sbi = f.small_blurry_image()
    assert sbi.shape == (30, 40) and abs(float(sbi.mean())) < 1e-3


def test_depth_sigmas_follow_landmarks_through_updates():
    kmap = KeyframeMap()
    for k in range(2):
        kmap.add_keyframe(make_keyframe(k))
    ids = kmap.add_landmarks("sift", [[0, 0, 2.0], [1, 0, 3.0]], [[(0, 0)], [(0, 1)]],
                             depth_sigmas_m=[0.05, 0.4])
    kmap.add_observations("sift", [(ids[0], 1, 0)])
    kmap.move_landmarks([ids[1]], [[1.0, 0.1, 3.1]])
    state = kmap.snapshot()
    assert [state.landmarks[i].depth_sigma_m for i in ids] == [0.05, 0.4]
    with pytest.raises(MapError):
        kmap.add_landmarks("sift", [[0, 0, 1.0]], [[(1, 2)]], depth_sigmas_m=[float("nan")])


def test_landmark_table_copy_on_write_matches_a_dict(monkeypatch):
    """The columnar table behaves like the dict of Landmark objects it replaces, through
    overlay changes and compactions (forced often here), and old tables never change."""
    from reloc_service.core import landmark_table
    from reloc_service.core.landmark_table import Landmark, LandmarkTable

    monkeypatch.setattr(landmark_table, "COMPACT_MIN_OVERLAY", 5)
    rng = np.random.default_rng(0)
    model: dict[int, Landmark] = {}
    table = LandmarkTable()
    history = []
    for step in range(60):
        changes: dict[int, Landmark | None] = {}
        for _ in range(int(rng.integers(1, 6))):
            lm_id = int(rng.integers(0, 40))
            if lm_id in model and rng.random() < 0.3:
                changes[lm_id] = None
            else:
                obs = frozenset((int(rng.integers(0, 9)), str(rng.choice(["sift", "orb"])),
                                 int(rng.integers(0, 99))) for _ in range(int(rng.integers(1, 4))))
                changes[lm_id] = Landmark(lm_id, rng.normal(size=3), obs, float(rng.random()))
        history.append((table, dict(model)))
        table = table.evolve(changes)
        for k, v in changes.items():
            if v is None:
                model.pop(k, None)
            else:
                model[k] = v
        for t, m in [(table, model), history[step // 2]]:
            assert len(t) == len(m) and sorted(t) == sorted(m)
            ids = np.array(sorted(m), np.int64)
            if len(ids):
                assert np.array_equal(t.points(ids), np.stack([m[i].point_world for i in ids]))
                assert np.array_equal(t.sigmas(ids), [m[i].depth_sigma_m for i in ids])
            for i in range(40):
                assert (i in t) == (i in m) and t.contains([i])[0] == (i in m)
                if i in m:
                    assert t[i].observations == m[i].observations
            assert t.sigmas([99], default=-1.0).tolist() == [-1.0]
            query = rng.integers(0, 45, int(rng.integers(0, 30)))  # repeats, non-landmarks
            votes: dict[int, int] = {}
            for i in set(query.tolist()) & set(m):
                for kf in {o[0] for o in m[i].observations}:
                    votes[kf] = votes.get(kf, 0) + 1
            kf_ids, counts = t.observing_keyframes(query)
            assert dict(zip(kf_ids.tolist(), counts.tolist(), strict=True)) == votes
            assert kf_ids.tolist() == sorted(votes)


def test_encoded_image_decodes_on_first_use_and_checks_its_size():
    """A keyframe holding a PNG decodes it when its pixels are first read (the same pixels),
    stays encoded through with_features, and a PNG of the wrong size or not a PNG is refused."""
    import cv2

    from reloc_service.core.frame import EncodedImage

    img = np.random.default_rng(3).integers(0, 256, (48, 64)).astype(np.uint8)
    png = cv2.imencode(".png", img)[1].tobytes()
    kf = Keyframe(image=EncodedImage(png), camera=CAM, id=4)
    feats = Features.create("sift", np.zeros((0, 2)), np.zeros((0, 128), np.uint8))
    copy = kf.with_features("sift", feats)
    assert isinstance(kf.image_source, EncodedImage) and isinstance(copy.image_source, EncodedImage)
    assert np.array_equal(kf.image, img) and isinstance(kf.image_source, EncodedImage)
    assert np.array_equal(copy.small_blurry_image(), Frame(img, CAM).small_blurry_image())
    query = Frame(EncodedImage(png), CAM)             # a query keeps its pixels once decoded
    assert np.array_equal(query.image, img) and isinstance(query.image_source, np.ndarray)
    small = cv2.imencode(".png", img[:24, :32])[1].tobytes()
    with pytest.raises(GeometryError, match="32x24 does not match the camera's 64x48"):
        Keyframe(image=EncodedImage(small), camera=CAM, id=5)
    with pytest.raises(GeometryError, match="expected a PNG"):
        EncodedImage(b"not a png at all, just some bytes")


def test_keyframes_keep_images_encoded_and_share_recent_pixels():
    """A keyframe given its pixels and the encoded image they decode from holds only the
    encoded one; its next readers get those pixels (no decode), read-only, until the bounded
    cache of recently decoded images drops them, then decode the same pixels again."""
    import cv2

    from reloc_service.core.frame import RECENT_PIXELS, EncodedImage, RecentPixels

    img = np.random.default_rng(4).integers(0, 256, (48, 64)).astype(np.uint8)
    png = cv2.imencode(".png", img)[1].tobytes()
    pixels = EncodedImage(png).decode().copy()       # decoded elsewhere (as the service does)
    encoded = EncodedImage(png)
    kf = Keyframe(image=pixels, camera=CAM, id=1, encoded=encoded)
    assert kf.image_source is encoded and kf.encoded is encoded
    shared = kf.image
    assert np.shares_memory(shared, pixels) and kf.image is shared  # the pixels given: no decode
    with pytest.raises(ValueError, match="read-only"):
        kf.image[0, 0] = 1
    assert pixels.flags.writeable                     # the caller's array is left as it was
    # a bounded LRU: the least recently read drops out first
    cache = RecentPixels(max_bytes=2 * img.nbytes)
    images = [EncodedImage(cv2.imencode(".png", img)[1].tobytes()) for _ in range(3)]
    for e in images[:2]:
        cache.put(e, img)
    assert cache.get(images[0]) is img                 # now the most recent
    cache.put(images[2], img)
    assert cache.get(images[1]) is None and cache.get(images[0]) is img and len(cache) == 2
    cache.put(EncodedImage(cv2.imencode(".png", img)[1].tobytes()), np.zeros((200, 200), np.uint8))
    assert len(cache) == 2                             # larger than the budget: not kept
    # after the process-wide cache forgot them, the keyframe decodes the same pixels again
    for _ in range(RECENT_PIXELS.max_bytes // img.nbytes + 1):
        other = EncodedImage(cv2.imencode(".png", img)[1].tobytes())
        other.decode()
    assert RECENT_PIXELS.get(encoded) is None
    again = kf.image
    assert not np.shares_memory(again, pixels) and np.array_equal(again, img)
    with pytest.raises(GeometryError, match=r"pixels of \(4, 4\) uint8, expected \(48, 64\)"):
        encoded.remember(np.zeros((4, 4), np.uint8))


def test_keyframe_pose_covariance_is_checked_and_the_map_default_fills_in():
    cov = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])
    kf = make_keyframe(0)
    with_cov = Keyframe(image=kf.image, camera=kf.camera, id=1, world_from_cam=np.eye(4),
                        pose_covariance=cov)
    np.testing.assert_array_equal(with_cov.pose_covariance, cov)
    with pytest.raises(GeometryError, match="keyframe 2 pose_covariance: .*not symmetric"):
        bad = cov.copy()
        bad[0, 1] = 1e-5
        Keyframe(image=kf.image, camera=kf.camera, id=2, world_from_cam=np.eye(4),
                 pose_covariance=bad)
    default = np.eye(6) * 4e-4
    kmap = KeyframeMap(default_pose_covariance=default)
    kmap.add_keyframe(kf)
    kmap.add_keyframe(with_cov)
    covs = kmap.snapshot().pose_covariances([0, 1])
    np.testing.assert_array_equal(covs[0], default)      # put without one: the default
    np.testing.assert_array_equal(covs[1], cov)
    other = KeyframeMap()                                 # no default: exact
    other.add_keyframe(kf)
    np.testing.assert_array_equal(other.snapshot().pose_covariances([0])[0], np.zeros((6, 6)))
    kmap.replace_state(other.snapshot())                  # a loaded state takes this map's
    np.testing.assert_array_equal(kmap.snapshot().pose_covariances([0])[0], default)
