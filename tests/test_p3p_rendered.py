"""P3P pose finder on rendered images of a textured plane with a small map: poses found and
refused, features extracted once, guided growth, support searched once per pose, and the
solves the first pool and a known pose spare."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.place.base import PlaceCandidate
from reloc_service.algorithms.pose.base import PoseEstimate, create_pose_finder
from reloc_service.algorithms.relocalizers.base import (
    VerifyConf,
    note_map_calibration,
    result_from_estimate,
)
from reloc_service.core import features as feature_lib
from reloc_service.core.cameras import camera_from_dict
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_error, se3_exp
from reloc_service.tools.synth.planar import PlanarScene, planar_scene, query_pose


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    camera = camera_from_dict({"model": "pinhole", "width": 320, "height": 240, "fx": 250.0,
                               "fy": 250.0, "cx": 159.5, "cy": 119.5})
    from reloc_service.tools.synth.planar import keyframe_grid

    return planar_scene(keyframe_grid(3, 2), kinds=("sift", "orb"), camera=camera,
                        max_features=1000)


def candidates_near(scene: PlanarScene, world_from_cam: np.ndarray, k: int) -> list[PlaceCandidate]:
    state = scene.map.snapshot()
    ids = state.keyframe_ids()
    dist = np.linalg.norm(state.positions_world(ids) - world_from_cam[:3, 3], axis=1)
    return [PlaceCandidate(ids[i], -float(dist[i])) for i in np.argsort(dist)[:k]]


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_find_pose_on_rendered_images(scene, kind, monkeypatch):
    finder = create_pose_finder({"name": "p3p", "kind": kind, "max_features": 1000})
    gt = query_pose(0)
    query = Frame(scene.render(gt), scene.camera)
    calls = []
    real_extract = feature_lib.extract
    monkeypatch.setattr(feature_lib, "extract",
                        lambda *a, **k: calls.append(1) or real_extract(*a, **k))
    state = scene.map.snapshot()
    est = finder.find_pose(query, candidates_near(scene, gt, 3), state)
    assert est is not None and est.inliers >= 50
    dt, dr = pose_error(est.world_from_cam, gt)
    assert dt < 0.01 and np.degrees(dr) < 0.5
    assert set(est.keyframe_ids) <= {c.keyframe_id for c in candidates_near(scene, gt, 3)}
    assert {"features", "match", "solve"} <= est.timings.keys()
    # The relocalizer notes whether the query claims the map's calibration (it does here),
    # which a planar view that cannot check the intrinsics needs to be trusted.
    note_map_calibration(est, query.camera, state)
    assert result_from_estimate(est, VerifyConf(), method="p3p", map_version=0, timings={}).ok
    finder.find_pose(query, candidates_near(scene, gt, 2), state)
    assert len(calls) == 1 and kind in query.features  # extracted once, cached on the query


def test_find_pose_without_enough_matches_is_refused(scene):
    finder = create_pose_finder({"name": "p3p"})
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 255, (240, 320)).astype(np.uint8)
    state = scene.map.snapshot()
    est = finder.find_pose(Frame(noise, scene.camera), candidates_near(scene, query_pose(0), 3),
                           state)
    result = result_from_estimate(est, VerifyConf(), method="p3p", map_version=0, timings={})
    assert not result.ok and result.reason
    assert finder.find_pose(Frame(noise, scene.camera), [PlaceCandidate(999, 0.0)], state) is None


def test_guided_matching_grows_a_weak_first_pose(scene):
    import cv2

    gt = query_pose(0)
    blurred = cv2.GaussianBlur(scene.render(gt), (0, 0), 1.5)
    dark = np.clip(blurred.astype(np.float64) * 0.5 + 20, 0, 255).astype(np.uint8)
    state, cands = scene.map.snapshot(), candidates_near(scene, gt, 3)
    plain = create_pose_finder({"name": "p3p", "guided": False}).find_pose(
        Frame(dark, scene.camera), cands, state)
    grown = create_pose_finder({"name": "p3p"}).find_pose(Frame(dark, scene.camera), cands, state)
    assert plain.inliers < 50 and grown.inliers > plain.inliers
    assert grown.unguided_evidence == (plain.num_matches, plain.inliers)
    assert pose_error(grown.world_from_cam, gt)[0] < 0.02
    assert "guided" in grown.timings


def test_support_is_searched_once_per_pose_and_map_state(scene):
    """The repetition search and the uniqueness check ask for one pose's support: the second
    answer is the first's, equal to a fresh search; another pose searches anew."""
    from reloc_service.algorithms.pose.support import explained_keypoints

    finder = create_pose_finder({"name": "p3p"})
    gt = query_pose(0)
    query = Frame(scene.render(gt), scene.camera)
    state = scene.map.snapshot()
    est = finder.find_pose(query, candidates_near(scene, gt, 3), state)
    first = finder.support(query, est.world_from_cam, state)
    assert first is not None and len(first) > 50
    assert finder.support(query, est.world_from_cam.copy(), state) is first
    (key, _), = finder.feature_confs().items()
    fresh = explained_keypoints(query.features[key], query.camera, est.world_from_cam, state,
                                "sift", radius_px=2.0 * finder.conf.max_reproj_error_px)
    assert np.array_equal(fresh.keypoints, first.keypoints) and fresh.predicted == first.predicted
    moved = est.world_from_cam @ se3_exp(np.random.default_rng(1).normal(0.0, 0.01, 6))
    assert finder.support(query, moved, state) is not first


def _counted_orb_finder(scene, monkeypatch):
    """An ORB p3p finder matching the best candidate's landmarks first, whose whole group is
    always matched after (``guided_below_inliers`` out of reach), with the real PnP solve
    counted: (finder, ground-truth pose, state, candidates, the solves' sizes)."""
    import reloc_service.algorithms.pose.p3p as p3p

    gt = query_pose(0)
    state, cands = scene.map.snapshot(), candidates_near(scene, gt, 3)
    finder = create_pose_finder({"name": "p3p", "kind": "orb", "max_features": 1000,
                                 "first_pool_keyframes": 1, "guided_below_inliers": 100_000})
    solves: list[int] = []
    real_solve = p3p.solve_pnp_indexed
    monkeypatch.setattr(p3p, "solve_pnp_indexed",
                        lambda px, *a, **k: solves.append(len(px)) or real_solve(px, *a, **k))
    return finder, gt, state, cands, solves


def test_a_first_pool_with_too_few_matches_to_be_kept_is_not_solved(scene, monkeypatch):
    """A first pool whose pose would be set aside for the whole group's (fewer inliers than
    ``guided_below_inliers``) is not solved when it has fewer matches than that: the estimate
    is the one solving it would give, with one solve fewer."""
    import reloc_service.algorithms.pose.p3p as p3p

    finder, gt, state, cands, solves = _counted_orb_finder(scene, monkeypatch)
    skipped = finder.find_pose(Frame(scene.render(gt), scene.camera), cands, state)
    n_skipped = len(solves)
    real_match_and_solve = p3p.P3PPoseFinder._match_and_solve
    monkeypatch.setattr(p3p.P3PPoseFinder, "_match_and_solve",
                        lambda self, *a, solve_from=0, **k: real_match_and_solve(self, *a, **k))
    solves.clear()
    solved = finder.find_pose(Frame(scene.render(gt), scene.camera), cands, state)
    assert len(solves) == n_skipped + 1 and solves[0] < 100_000  # the first pool's, set aside
    assert skipped is not None and solved is not None and skipped.inliers == solved.inliers > 0
    np.testing.assert_array_equal(skipped.world_from_cam, solved.world_from_cam)
    np.testing.assert_array_equal(skipped.inlier_landmark_ids, solved.inlier_landmark_ids)
    assert skipped.num_matches == solved.num_matches


def test_a_pose_the_caller_knows_is_returned_at_once(scene, monkeypatch):
    """``known`` recognising the first pool's pose ends the search there (one solve, no whole
    group, no guided matching); recognising nothing, the search runs in full to the pose it
    gives without ``known``."""
    finder, gt, state, cands, solves = _counted_orb_finder(scene, monkeypatch)

    def found(known):
        solves.clear()
        est = finder.find_pose_deferred(Frame(scene.render(gt), scene.camera), cands, state,
                                        known=known)
        assert est is not None
        return est, len(solves)

    asked: list[PoseEstimate] = []
    early, n_early = found(lambda est: asked.append(est) or True)
    full, n_full = found(None)
    refused, n_refused = found(lambda est: False)
    assert n_early == 1 and asked == [early] and early.keyframe_ids == [cands[0].keyframe_id]
    assert "guided" not in early.timings and "guided" in full.timings
    assert n_refused == n_full + 1  # the first pool solved to be asked about, then as without
    np.testing.assert_array_equal(refused.world_from_cam, full.world_from_cam)
    assert refused.inliers == full.inliers > early.inliers
