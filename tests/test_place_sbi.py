"""The small-blurry-image place finder (thesis 3.1.1): ranking, add/remove, restriction."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.place.base import create_place_finder
from reloc_service.algorithms.place.sbi import SmallBlurryImageFinder
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError
from reloc_service.core.frame import Frame, Keyframe
from reloc_service.core.map import KeyframeMap
from reloc_service.tools.synth.planar import PlanarScene, downward_pose, texture_mosaic

CAMERA = PinholeCamera(width=160, height=120, fx=125.0, fy=125.0, cx=79.5, cy=59.5)


@pytest.fixture(scope="module")
def plane() -> PlanarScene:
    return PlanarScene(texture_mosaic(), 1.0 / 512, CAMERA, KeyframeMap())


def make_map(plane: PlanarScene, n: int, seed: int = 0) -> tuple[KeyframeMap, list[np.ndarray]]:
    """``n`` keyframes (no features) looking down at random places of the textured plane."""
    rng = np.random.default_rng(seed)
    kmap = KeyframeMap()
    poses = [downward_pose(*rng.uniform([-1.0, -0.6, 0.9], [1.0, 0.6, 1.5]),
                           yaw=rng.uniform(-np.pi, np.pi)) for _ in range(n)]
    for i, pose in enumerate(poses):
        kmap.add_keyframe(Keyframe(image=plane.render(pose), camera=CAMERA, id=i,
                                   world_from_cam=pose))
    return kmap, poses


def brute_force_scores(finder: SmallBlurryImageFinder, kmap: KeyframeMap, query: Frame
                       ) -> dict[int, float]:
    q = finder.thumbnail(query).astype(np.float64)
    return {i: -float(((finder.thumbnail(kf).astype(np.float64) - q) ** 2).sum())
            for i, kf in kmap.snapshot().keyframes.items()}


def test_near_duplicate_ranks_first(plane):
    kmap, poses = make_map(plane, 30)
    finder = create_place_finder({"name": "sbi"}, kmap)
    rng = np.random.default_rng(1)
    for target in (3, 17, 29):
        moved = poses[target].copy()
        moved[:3, 3] += [0.02, -0.01, 0.0]  # 2 cm sideways
        image = plane.render(moved)
        noisy = np.clip(image + rng.normal(0, 6, image.shape) + 20, 0, 255).astype(np.uint8)
        found = finder.find_places(Frame(noisy, CAMERA), 3)
        assert found[0].keyframe_id == target
        assert found[0].score >= found[1].score >= found[2].score


def test_exposure_change_does_not_move_the_ranking(plane):
    """Gain and offset (an exposure change) leave the normalised thumbnails unchanged: the
    darkened or brightened keyframe image still scores as itself (SSD 0, NCC 1)."""
    kmap, poses = make_map(plane, 30)
    finder = create_place_finder({"name": "sbi"}, kmap)
    for target, gain, offset in ((4, 0.45, 0.0), (11, 1.5, -30.0), (22, 0.7, 25.0)):
        image = plane.render(poses[target]).astype(np.float64)
        exposed = np.clip(gain * image + offset, 0, 255).astype(np.uint8)
        found = finder.find_places(Frame(exposed, CAMERA), 2)
        assert found[0].keyframe_id == target and found[0].score > -0.02


def test_scores_match_brute_force_ssd(plane):
    kmap, poses = make_map(plane, 12)
    finder = create_place_finder({"name": "sbi"}, kmap)
    query = Frame(plane.render(downward_pose(0.1, 0.2, 1.1, yaw=0.4)), CAMERA)
    expected = brute_force_scores(finder, kmap, query)
    found = finder.find_places(query, 12)
    assert [c.keyframe_id for c in found] == sorted(expected, key=lambda i: -expected[i])
    for c in found:
        assert c.score == pytest.approx(expected[c.keyframe_id], rel=1e-4, abs=1e-5)


def test_removed_keyframes_are_never_returned_and_index_stays_consistent(plane):
    kmap, poses = make_map(plane, 20)
    finder = create_place_finder({"name": "sbi"}, kmap)
    rng = np.random.default_rng(2)
    removed: set[int] = set()
    for kf_id in rng.permutation(20)[:9]:  # swap-removes from the middle and the end
        kf = kmap.snapshot().keyframe(int(kf_id))
        kmap.remove_keyframe(int(kf_id))
        finder.remove_keyframe(kf)
        removed.add(int(kf_id))
    # Re-add one removed keyframe under a new id, and replace an existing one.
    kf = Keyframe(image=plane.render(poses[5]), camera=CAMERA, id=100, world_from_cam=poses[5])
    kmap.add_keyframe(kf)
    finder.add_keyframe(kf)
    assert len(finder) == len(kmap) == 12
    for target in removed:
        found = finder.find_places(Frame(plane.render(poses[target]), CAMERA), 50)
        ids = {c.keyframe_id for c in found}
        assert not ids & removed
        assert ids == set(kmap.snapshot().keyframes)
    query = Frame(plane.render(poses[5]), CAMERA)
    expected = brute_force_scores(finder, kmap, query)
    got = {c.keyframe_id: c.score for c in finder.find_places(query, 50)}
    assert got.keys() == expected.keys()
    for i in got:
        assert got[i] == pytest.approx(expected[i], rel=1e-4, abs=1.0)


def test_allowed_restricts_candidates(plane):
    kmap, poses = make_map(plane, 15)
    finder = create_place_finder({"name": "sbi"}, kmap)
    query = Frame(plane.render(poses[4]), CAMERA)
    assert finder.find_places(query, 1)[0].keyframe_id == 4
    found = finder.find_places(query, 10, allowed={1, 2, 9})
    assert {c.keyframe_id for c in found} == {1, 2, 9}
    assert finder.find_places(query, 10, allowed=set()) == []


def test_indexes_existing_map_and_handles_empty_and_re_adding(plane):
    kmap, poses = make_map(plane, 4)
    finder = create_place_finder({"name": "sbi"}, kmap)
    assert len(finder) == 4
    for kf in kmap.snapshot().keyframes.values():  # the caller telling again is harmless
        finder.add_keyframe(kf)
    assert len(finder) == 4
    empty = create_place_finder({"name": "sbi"}, KeyframeMap())
    assert empty.find_places(Frame(plane.render(poses[0]), CAMERA), 5) == []
    many = make_map(plane, 40, seed=3)[0]  # grows beyond the initial capacity
    assert len(create_place_finder({"name": "sbi"}, many)) == 40


def test_unknown_or_invalid_options_raise():
    with pytest.raises(ConfigError, match="unknown option"):
        create_place_finder({"name": "sbi", "sigma": 2.0}, KeyframeMap())
    with pytest.raises(ConfigError):
        create_place_finder({"name": "sbi", "width": 0}, KeyframeMap())
