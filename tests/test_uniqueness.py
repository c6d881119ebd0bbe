"""A verified pose must be the only good explanation of the query: hypotheses compared by the
query keypoints each explains (McNemar), repeated textures answered where the rest of the image
decides and refused as ambiguous where nothing does."""

from __future__ import annotations

import numpy as np
import pytest
from reloc_client.result import RelocResult

from reloc_service.algorithms.pose.base import PoseEstimate, Support
from reloc_service.algorithms.pose.guided import project_into
from reloc_service.algorithms.pose.support import explained_keypoints
from reloc_service.algorithms.relocalizers.base import INTRINSICS_REFUSAL
from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.algorithms.relocalizers.uniqueness import (
    choose,
    compare,
    fits_consensus,
    refusing_rival,
    same_solution,
    solutions,
)
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.features import FeatureConf, extract
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_error
from reloc_service.tools.synth.planar import (
    downward_pose,
    keyframe_grid,
    planar_scene,
    texture_mosaic,
)

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


def support(keypoints: list[int] | range) -> Support:
    kp = np.array(sorted(keypoints), np.int64)
    return Support(kp, kp + 1000, len(kp))


def test_only_the_keypoints_one_hypothesis_explains_decide() -> None:
    shared = range(500)
    c = compare(support([*shared, *range(1000, 1040)]), support([*shared, *range(2000, 2010)]))
    assert (c.only_first, c.only_second) == (40, 10)
    assert c.p_first < 1e-4 < 0.5 < c.p_second    # 40 of 50: the first explains more
    even = compare(support([*shared, *range(1000, 1012)]), support([*shared, *range(2000, 2010)]))
    assert even.p_first > 0.1 and even.p_second > 0.1
    same = compare(support(shared), support(shared))
    assert (same.only_first, same.only_second, same.p_first) == (0, 0, 1.0)


def estimate(world_from_cam: np.ndarray, points: np.ndarray) -> PoseEstimate:
    px, _ = project_into(CAMERA, world_from_cam, points)
    return PoseEstimate(world_from_cam=world_from_cam, keyframe_ids=[], num_matches=len(px),
                        inliers=len(px), inlier_px=px, inlier_points_world=points,
                        inlier_threshold_px=5.0, image_size=CAMERA.size)


def test_a_pose_millimetres_away_is_the_same_solution_a_shifted_copy_is_not() -> None:
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200),
                              np.zeros(200)])
    a = estimate(downward_pose(0.0, 0.0, 1.0), points)
    near = estimate(downward_pose(0.002, 0.0, 1.0), points)
    shifted = estimate(downward_pose(0.6, 0.0, 1.0), points + [0.6, 0.0, 0.0])  # a copy
    assert fits_consensus(a, near.world_from_cam, CAMERA) == 1.0
    assert same_solution(a, near, CAMERA)
    assert fits_consensus(a, shifted.world_from_cam, CAMERA) < 0.1
    assert not same_solution(a, shifted, CAMERA)
    assert solutions([a, shifted, near], CAMERA, lambda x, y: False) == [[0, 2], [1]]
    bare = PoseEstimate(world_from_cam=a.world_from_cam, keyframe_ids=[])  # no inliers known
    assert same_solution(a, bare, CAMERA) is None and fits_consensus(bare, a.world_from_cam,
                                                                      CAMERA) is None
    assert solutions([a, bare], CAMERA, lambda x, y: True) == [[0, 1]]
    assert solutions([a, bare], CAMERA, lambda x, y: False) == [[0], [1]]


def test_poses_apart_by_less_than_their_covariances_allow_are_one_solution() -> None:
    """Two estimates of one place 4 cm apart (from different keyframes of a real map) fit
    few of each other's inliers, yet with 3 cm position sigmas they are one solution; with
    3 mm sigmas they are two, and a copy 60 cm away is two under either."""
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200),
                              np.zeros(200)])
    a = estimate(downward_pose(0.0, 0.0, 1.0), points)
    b = estimate(downward_pose(0.04, 0.0, 1.0), points)
    copy = estimate(downward_pose(0.6, 0.0, 1.0), points + [0.6, 0.0, 0.0])
    assert fits_consensus(a, b.world_from_cam, CAMERA) < 0.5
    for est in (a, b, copy):
        est.covariance = np.diag([0.03**2] * 3 + [np.radians(1.0)**2] * 3)
    assert same_solution(a, b, CAMERA) and not same_solution(a, copy, CAMERA)
    for est in (a, b, copy):
        est.covariance = np.diag([0.003**2] * 3 + [np.radians(0.1)**2] * 3)
    assert not same_solution(a, b, CAMERA) and not same_solution(a, copy, CAMERA)


def test_the_hypothesis_that_beats_every_other_wins_else_ambiguous() -> None:
    points = np.zeros((4, 3)) + [0.0, 0.0, 0.0]
    ests = [estimate(downward_pose(x, 0.0, 1.0), points) for x in (0.0, 1.2, 2.4)]
    base = range(300)
    strong = support([*base, *range(1000, 1100)])
    weak1, weak2 = support([*base, *range(2000, 2010)]), support([*base, *range(3000, 3005)])
    assert choose(ests, [weak1, strong, weak2], alpha=0.01).index == 1
    tie = choose(ests, [support([*base, *range(1000, 1010)]), support([*base, *range(2000, 2012)]),
                        weak2], alpha=0.01)
    assert tie.index is None
    assert tie.reason.startswith("ambiguous: 3 different poses") and "1.20 m" in tie.reason


def test_a_refused_copy_the_answer_does_not_out_explain_refuses_the_query() -> None:
    """A hypothesis whose intrinsics test refused the camera is weighed as a rival: the
    answer stands where it explains significantly more keypoints, else the refusal does
    (saying which pose and by how much); the answer's own place is no rival."""
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200),
                              np.zeros(200)])
    answer = estimate(downward_pose(0.0, 0.0, 1.0), points)
    copy = estimate(downward_pose(0.6, 0.0, 1.0), points + [0.6, 0.0, 0.0])
    near = estimate(downward_pose(0.002, 0.0, 1.0), points)
    refusal = RelocResult.failure("bow+p3p", f"{INTRINSICS_REFUSAL}: focal 870.0 px "
                                  "estimated, 1000.0 given (p = 1.0e-09)")
    base = range(300)
    supports = {id(answer): support([*base, *range(1000, 1100)]),
                id(copy): support([*base, *range(2000, 2010)]),
                id(near): support(base)}
    kw = dict(camera=CAMERA, support=lambda e: supports[id(e)], close=lambda x, y: False,
              alpha=0.01)
    assert refusing_rival(answer, [(refusal, copy), (refusal, near)], **kw) is None
    supports[id(copy)] = support([*base, *range(2000, 2090)])  # 100 vs 90: no clear winner
    found = refusing_rival(answer, [(refusal, near), (refusal, copy)], **kw)
    assert found is not None and found[1] is copy
    assert found[2].startswith(INTRINSICS_REFUSAL) and "0.60 m" in found[2]
    assert "100 vs 90 query keypoints" in found[2]
    supports[id(copy)] = None  # cannot be compared: the answer cannot vouch for itself
    assert refusing_rival(answer, [(refusal, copy)], **kw) is not None
    assert refusing_rival(answer, [], **kw) is None


def repeated_texture() -> np.ndarray:
    """The mosaic with its top-right photograph replaced by the top-left one: one picture in
    two places, 2 m apart (as two copies of a poster)."""
    tex = texture_mosaic().copy()
    tex[:512, 1024:] = tex[:512, :512]
    return tex


@pytest.fixture(scope="module")
def repeated_scene():
    poses = keyframe_grid(5, 3, extent=(2.0, 1.0), height=0.8)
    return planar_scene(poses, camera=CAMERA, max_features=800, texture=repeated_texture())


def relocalizer(scene):
    # One keyframe per group and every keyframe heard: both copies' groups verify.
    return create_relocalizer("sbi+p3p", scene.map,
                              options={"multi": {"num_candidates": 1, "max_groups": 15}})


def test_a_copy_elsewhere_verifies_too_but_the_rest_of_the_image_picks_the_true_pose(
        repeated_scene) -> None:
    gt = downward_pose(-0.75, -0.5, 0.8)  # the left copy and the photograph right of it
    result = relocalizer(repeated_scene).relocalize(Frame(repeated_scene.render(gt), CAMERA),
                                                    hypotheses=15)
    assert result.ok, result.reason
    assert pose_error(result.world_from_cam, gt)[0] < 0.02
    far = [h for h in result.hypotheses if pose_error(h.world_from_cam, gt)[0] > 1.0]
    assert far, "the copy's group should verify on its own"


def test_a_view_of_one_copy_only_is_ambiguous(repeated_scene) -> None:
    gt = downward_pose(-1.0, -0.5, 0.45)  # nothing but the repeated photograph
    result = relocalizer(repeated_scene).relocalize(Frame(repeated_scene.render(gt), CAMERA))
    assert not result.ok
    assert result.reason.startswith("ambiguous"), result.reason
    off = create_relocalizer("sbi+p3p", repeated_scene.map,
                             options={"multi": {"num_candidates": 1, "max_groups": 15,
                                                "unique": False}})
    assert off.relocalize(Frame(repeated_scene.render(gt), CAMERA)).ok  # the old behaviour


def test_support_counts_the_keypoints_the_local_map_explains(repeated_scene) -> None:
    from reloc_service.core import features as feature_lib

    gt = downward_pose(-0.75, -0.5, 0.8)
    image = repeated_scene.render(gt)
    feats = feature_lib.extract(image, feature_lib.FeatureConf(kind="sift", max_features=800))
    state = repeated_scene.map.snapshot()
    right = explained_keypoints(feats, CAMERA, gt, state, "sift", radius_px=10.0)
    copy = explained_keypoints(feats, CAMERA, downward_pose(1.25, -0.5, 0.8), state, "sift",
                               radius_px=10.0)
    assert len(right) > 0.3 * len(feats) and right.predicted > len(right)
    assert np.all(np.diff(right.keypoints) > 0)
    assert compare(right, copy).p_first < 1e-3


def test_ferns_refuse_a_view_of_one_copy_and_answer_the_view_beside_it(repeated_scene) -> None:
    fast = dict(num_ferns=40, num_tests=10, num_warps=25, workers=2, partition="select")
    ferns = create_relocalizer("ferns", repeated_scene.map, options={"ferns": fast})
    ferns.train()
    copy_only = Frame(repeated_scene.render(downward_pose(-1.0, -0.5, 0.6)), CAMERA)
    refused = ferns.relocalize(copy_only)
    assert not refused.ok and refused.reason.startswith("ambiguous"), refused.reason
    gt = downward_pose(-0.75, -0.5, 0.8)
    answered = ferns.relocalize(Frame(repeated_scene.render(gt), CAMERA))
    assert answered.ok, answered.reason
    assert pose_error(answered.world_from_cam, gt)[0] < 0.02
    first_only = create_relocalizer("ferns", repeated_scene.map,
                                    options={"ferns": {**fast, "competitors": 0}})
    first_only.train()
    assert first_only.relocalize(copy_only).ok   # the first verified pose, as before


def test_ferns_weigh_the_pose_of_a_copy_against_the_true_place_elsewhere(repeated_scene) -> None:
    """Classified against the landmarks of the keyframes near the right copy only (a prior
    around it), the query of the left copy and the photograph beside it verifies one pose:
    the copy's. Ferns' own hypotheses show no other, but the keypoints that pose leaves
    unexplained point to the true place (a repetition alternative, as a multi step weighs
    its own), whose pose explains more of the image: it answers, not the copy's."""
    from reloc_service.algorithms.relocalizers.base import Prior

    ferns = create_relocalizer("ferns", repeated_scene.map, options={"ferns": dict(
        num_ferns=40, num_tests=10, num_warps=25, workers=2, partition="select")})
    ferns.train()
    gt, copy_pose = downward_pose(-0.75, -0.5, 0.8), downward_pose(1.25, -0.5, 0.8)
    near_copy = Prior(copy_pose, radius_m=0.8)   # keyframes at x >= 0.5, the truth's 1.75 m away
    query = Frame(repeated_scene.render(gt), CAMERA)
    result = ferns.relocalize(query, prior=near_copy)
    assert result.ok, result.reason
    assert pose_error(result.world_from_cam, gt)[0] < 0.02, (
        f"answered {pose_error(result.world_from_cam, gt)[0]:.2f} m from the truth")
    # The weighing's SIFT features were capped from ferns' detection: extract's features.
    weighed, extracted = query.features["sift"], extract(query.image, FeatureConf("sift", 2000))
    assert np.array_equal(weighed.keypoints_px, extracted.keypoints_px)
    assert np.array_equal(weighed.descriptors, extracted.descriptors)
    unweighed = create_relocalizer("ferns", repeated_scene.map, options={"ferns": dict(
        num_ferns=40, num_tests=10, num_warps=25, workers=2, partition="select",
        competitors=0)})
    unweighed.train()
    copy = unweighed.relocalize(Frame(repeated_scene.render(gt), CAMERA), prior=near_copy)
    assert copy.ok and pose_error(copy.world_from_cam, copy_pose)[0] < 0.1  # the first pose


def test_what_a_copys_pose_leaves_unexplained_points_to_the_true_place(repeated_scene) -> None:
    """Posed on the keyframe above the right copy only, the query of the left copy and the
    photograph beside it gets the copy's pose; the keypoints that pose does not explain
    (the photograph beside the left copy) match the landmarks of the keyframes above the
    true place, and the pose found there is an alternative within 2 cm of the truth."""
    from reloc_service.algorithms.place.base import PlaceCandidate
    from reloc_service.algorithms.pose.repetition import RepetitionConf, unexplained_matches

    gt = downward_pose(-0.75, -0.5, 0.8)
    copy_pose = downward_pose(1.25, -0.5, 0.8)
    query = Frame(repeated_scene.render(gt), CAMERA)
    finder = relocalizer(repeated_scene).pose
    state = repeated_scene.map.snapshot()
    above_copy = state.nearest_keyframes(copy_pose, 1, 60.0)
    wrong = finder.find_pose(query, [PlaceCandidate(k, 1.0) for k in above_copy], state)
    assert wrong is not None and pose_error(wrong.world_from_cam, copy_pose)[0] < 0.1

    feats = query.features["sift"]
    pool, index, _ = finder._map_pool(state)
    explained = finder.support(query, wrong.world_from_cam, state)
    rows = unexplained_matches(feats, explained.keypoints, index, RepetitionConf())
    kf_ids, votes = state.landmarks.observing_keyframes(pool.landmark_ids[rows])
    near_truth = set(state.nearest_keyframes(gt, 3, 60.0))
    assert near_truth & set(kf_ids[votes == votes.max()].tolist())
    everything = unexplained_matches(feats, np.zeros(0, np.int64), index, RepetitionConf())
    assert len(everything) > len(rows)  # explained keypoints are left out

    (there,) = finder._elsewhere(query, wrong, state, pool.landmark_ids[rows], lambda _: True)
    assert pose_error(there.world_from_cam, gt)[0] < 0.02
    alternatives = finder.alternatives(query, wrong, state)
    assert any(pose_error(a.world_from_cam, gt)[0] < 0.02 for a in alternatives)


def test_the_indexed_repetition_check_finds_the_true_place_too(repeated_scene) -> None:
    """As above with the whole-map pool searched in its index (as on a map too large to
    scan): the alternatives still hold the true pose."""
    from reloc_service.algorithms.place.base import PlaceCandidate

    gt = downward_pose(-0.75, -0.5, 0.8)
    query = Frame(repeated_scene.render(gt), CAMERA)
    finder = create_relocalizer("sbi+p3p", repeated_scene.map,
                                options={"p3p": {"repetition_exact_rows": 0}}).pose
    state = repeated_scene.map.snapshot()
    assert finder._map_pool(state)[1].tree is not None
    above_copy = state.nearest_keyframes(downward_pose(1.25, -0.5, 0.8), 1, 60.0)
    wrong = finder.find_pose(query, [PlaceCandidate(k, 1.0) for k in above_copy], state)
    alternatives = finder.alternatives(query, wrong, state)
    assert any(pose_error(a.world_from_cam, gt)[0] < 0.02 for a in alternatives)
