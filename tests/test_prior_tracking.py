"""Localization with a prior: a prior pose with its covariance is tracked first (landmarks
projected with the prior, matched in covariance windows, PnP, the shared verification); a
wrong prior gives the right pose from the full method or a refusal."""

from __future__ import annotations

import numpy as np
import pytest
from reloc_client import protocol as P
from reloc_client.protocol import ErrorCode, ProtocolError

from reloc_service.algorithms.relocalizers.base import Prior
from reloc_service.algorithms.relocalizers.factory import create_relocalizer, create_tracker
from reloc_service.algorithms.relocalizers.tracking import TRACK, TrackingRelocalizer
from reloc_service.algorithms.relocalizers.tracking_fallback import relocalize_with_prior
from reloc_service.core.errors import ConfigError
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_covariance_from_sigmas, pose_error, se3_exp
from reloc_service.core.map import KeyframeMap
from reloc_service.engine import Engine

#: A VIO's prior: 5 cm and 2 degrees, 1 sigma per axis.
SIGMA_M, SIGMA_RAD = 0.05, np.deg2rad(2.0)
COVARIANCE = pose_covariance_from_sigmas(SIGMA_M, SIGMA_RAD)


def _map_of(state) -> KeyframeMap:
    kmap = KeyframeMap()
    kmap.replace_state(state)
    return kmap


def _perturbed(pose, rng, sigma_m=SIGMA_M, sigma_rad=SIGMA_RAD):
    """``pose @ exp(xi)`` with xi drawn from the stated covariance (a right perturbation)."""
    xi = np.concatenate([rng.normal(0, sigma_m, 3), rng.normal(0, sigma_rad, 3)])
    return pose @ se3_exp(xi)


def _query(scene, i):
    return Frame(scene.query_images[i], scene.camera)


def test_a_good_prior_is_answered_by_tracking(synthetic_scene, synthetic_map):
    tracker = create_tracker(_map_of(synthetic_map))
    rng = np.random.default_rng(0)
    for i, gt in enumerate(synthetic_scene.query_poses):
        prior = Prior(_perturbed(gt, rng), covariance=COVARIANCE)
        result = tracker.relocalize(_query(synthetic_scene, i), prior=prior)
        assert result.ok, result.reason
        assert result.method == TRACK
        dt, dr = pose_error(result.world_from_cam, gt)
        assert dt < 0.03 and dr < np.deg2rad(1.0)
        assert result.covariance is not None and result.inliers >= 10


def test_tracking_answers_first_and_the_method_falls_back(synthetic_scene, synthetic_map):
    kmap = _map_of(synthetic_map)
    method = create_relocalizer("sbi+p3p", kmap)
    method.train()
    tracker = create_tracker(kmap)
    gt = synthetic_scene.query_poses[1]
    tracked = relocalize_with_prior(method, tracker, _query(synthetic_scene, 1),
                                    prior=Prior(_perturbed(gt, np.random.default_rng(1)),
                                                covariance=COVARIANCE))
    assert tracked.ok and tracked.method == TRACK
    # Without a covariance the method answers, as before.
    plain = relocalize_with_prior(method, tracker, _query(synthetic_scene, 1),
                                  prior=Prior(gt, radius_m=5.0))
    assert plain.ok and plain.method == "sbi+p3p"


@pytest.mark.parametrize("offset", ["2m", "30deg"])
def test_a_wrong_prior_gives_the_right_pose_or_a_refusal(synthetic_scene, synthetic_map,
                                                         offset):
    kmap = _map_of(synthetic_map)
    method = create_relocalizer("sbi+p3p", kmap)
    method.train()
    tracker = create_tracker(kmap)
    gt = synthetic_scene.query_poses[0]
    if offset == "2m":
        wrong = gt.copy()
        wrong[:3, 3] += np.array([2.0, 0.0, 0.0])
    else:
        wrong = gt @ se3_exp([0, 0, 0, 0, np.deg2rad(30.0), 0])
    prior = Prior(wrong, covariance=COVARIANCE)
    alone = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert not alone.ok  # nothing near the wrong prior verifies
    result = relocalize_with_prior(method, tracker, _query(synthetic_scene, 0), prior=prior)
    if result.ok:
        assert result.method == "sbi+p3p"
        assert pose_error(result.world_from_cam, gt)[0] < 0.05
    else:
        assert result.reason.startswith("track: ")



def test_any_prior_gives_a_right_pose_or_a_refusal_never_an_error(synthetic_scene,
                                                                   synthetic_map):
    """Priors off by 1 mm to 10 m and 0.01 to 100 deg that state 0.3 mm to 30 m and 0.001 to
    100 deg (a VIO that is right, drifted or reset, and says so or not): tracking first, then
    the method, answer each near the truth or refuse; nothing raises."""
    kmap = _map_of(synthetic_map)
    method = create_relocalizer("sbi+p3p", kmap)
    method.train()
    tracker = create_tracker(kmap)
    rng = np.random.default_rng(11)
    answered = 0
    for _ in range(24):
        i = int(rng.integers(len(synthetic_scene.query_poses)))
        gt = synthetic_scene.query_poses[i]
        xi = rng.normal(size=6)
        xi[:3] *= 10 ** rng.uniform(-3, 1) / np.linalg.norm(xi[:3])
        xi[3:] *= np.deg2rad(10 ** rng.uniform(-2, 2)) / np.linalg.norm(xi[3:])
        covariance = pose_covariance_from_sigmas(10 ** rng.uniform(-3.5, 1.5),
                                                 np.deg2rad(10 ** rng.uniform(-3, 2)))
        result = relocalize_with_prior(method, tracker, _query(synthetic_scene, i),
                                       prior=Prior(gt @ se3_exp(xi), covariance=covariance))
        if result.ok:
            answered += 1
            dt, dr = pose_error(result.world_from_cam, gt)
            assert dt < 0.05 and dr < np.deg2rad(5.0), (dt, np.rad2deg(dr), result.method)
    assert answered > 0

def test_a_huge_covariance_leaves_the_query_to_the_method(synthetic_scene, synthetic_map):
    tracker = create_tracker(_map_of(synthetic_map))
    gt = synthetic_scene.query_poses[2]
    result = tracker.relocalize(_query(synthetic_scene, 2),
                                prior=Prior(gt, covariance=pose_covariance_from_sigmas(1.0, 0.5)))
    assert not result.ok and "prior too uncertain to track" in result.reason


def test_no_covariance_no_tracking(synthetic_scene, synthetic_map):
    tracker = create_tracker(_map_of(synthetic_map))
    result = tracker.relocalize(_query(synthetic_scene, 0),
                                prior=Prior(synthetic_scene.query_poses[0], radius_m=1.0))
    assert not result.ok and "no prior with a covariance" in result.reason


def test_engine_tracks_a_prior_with_a_covariance(synthetic_scene):
    engine = Engine()
    for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                          synthetic_scene.keyframe_poses, strict=True)):
        engine.add_keyframe(i, image, synthetic_scene.camera, pose)
    engine.train(["sbi+p3p"])
    gt = synthetic_scene.query_poses[0]
    prior = Prior(_perturbed(gt, np.random.default_rng(3)), covariance=COVARIANCE)
    result = engine.relocalize(_query(synthetic_scene, 0), method="sbi+p3p", prior=prior)
    assert result.ok and result.method == TRACK
    assert pose_error(result.world_from_cam, gt)[0] < 0.03


@pytest.mark.parametrize(("matrix", "problem"), [
    (np.eye(5), "shape|36 numbers"),
    (np.diag([1.0, 1, 1, 1, 1, np.nan]), "NaN or infinite|finite number"),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1), "not symmetric"),
    (np.diag([1.0, 1, 1, 1, 1, -1]), "not positive semi-definite"),
])
def test_covariance_validation(matrix, problem):
    with pytest.raises(ConfigError, match=problem):
        Prior(np.eye(4), covariance=matrix)
    pose = P.WirePose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    wire_prior = {"world_from_cam": pose.to_wire(),
                  "covariance": np.asarray(matrix, float).reshape(-1).tolist()}
    with pytest.raises(ProtocolError, match=problem) as err:
        P.Prior.from_wire(wire_prior, "relocalize.prior")
    assert err.value.code == ErrorCode.BAD_VALUE
    with pytest.raises(ConfigError, match="radius_m"):
        Prior(np.eye(4), radius_m=-1.0)


def test_a_prior_needs_a_radius_or_a_covariance():
    pose = P.WirePose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    with pytest.raises(ProtocolError, match="'radius_m'.*'covariance'") as err:
        P.Prior.from_wire({"world_from_cam": pose.to_wire()}, "relocalize.prior")
    assert err.value.code == ErrorCode.MISSING_FIELD
    with pytest.raises(ProtocolError, match="'radius_m'.*'covariance'"):
        P.Prior(pose)


def test_protocol_round_trip_of_a_prior_with_a_covariance():
    pose = P.WirePose((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))
    image = P.WireImage(P.ImageFormat.MONO8, 4, 2, bytes(8))
    camera = P.WireCamera("pinhole", 4, 2, 2.0, 2.0, 1.5, 0.5)
    for prior in (P.Prior(pose, 3.0), P.Prior(pose, covariance=tuple(COVARIANCE.reshape(-1))),
                  P.Prior(pose, 1.5, tuple(COVARIANCE.reshape(-1)))):
        msg = P.RelocalizeRequest(image, camera=camera, prior=prior)
        back = P.RelocalizeRequest.decode(msg.encode())
        assert back.prior == prior
        if prior.covariance is not None:
            assert np.allclose(np.reshape(back.prior.covariance, (6, 6)), COVARIANCE)
        else:
            assert "covariance" not in prior.to_wire()  # an older service still reads it


def test_track_is_a_registered_method(synthetic_scene, synthetic_map):
    from reloc_service.algorithms.relocalizers.factory import list_methods
    from reloc_service.algorithms.relocalizers.tracking import TrackingRelocalizer

    track = create_relocalizer("track", _map_of(synthetic_map),
                               options={"track": {"gate_probability": 0.95}})
    assert isinstance(track, TrackingRelocalizer) and track.conf.gate_probability == 0.95
    assert TRACK in {m["method"] for m in list_methods()}
    with pytest.raises(ConfigError, match="gate_probability"):
        create_relocalizer("track", _map_of(synthetic_map),
                           options={"track": {"gate_probability": 1.5}})


def test_a_tight_prior_leaves_the_intrinsics_test_fewer_focal_starts(
        synthetic_scene, synthetic_map, monkeypatch):
    from reloc_service.algorithms.pose import pnp
    from reloc_service.algorithms.pose.intrinsics import FOCAL_STARTS

    # Record the starts each intrinsics test is given; the test itself runs unchanged.
    starts: list[tuple[float, ...]] = []
    real = pnp.check_intrinsics

    def recording(*args, **kwargs):
        starts.append(tuple(kwargs.get("focal_starts", FOCAL_STARTS)))
        return real(*args, **kwargs)

    monkeypatch.setattr(pnp, "check_intrinsics", recording)
    tracker = create_tracker(_map_of(synthetic_map))
    gt = synthetic_scene.query_poses[0]
    prior = Prior(_perturbed(gt, np.random.default_rng(3)), covariance=COVARIANCE)
    result = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert result.ok, result.reason
    # The back wall is about 2 m away: a 5 cm prior admits focal errors of about 12 %, so
    # the starts at 0.66, 0.76, 1.32 and 1.52 cannot yield a pose inside its gate.
    assert starts and len(starts[-1]) < len(FOCAL_STARTS)
    assert set(starts[-1]) <= set(FOCAL_STARTS) and 1.15 in starts[-1]
    # Without a prior the method's test starts from every focal, as before.
    starts.clear()
    method = create_relocalizer("sbi+p3p", _map_of(synthetic_map))
    method.train()
    assert method.relocalize(_query(synthetic_scene, 0)).ok
    assert starts and all(s == FOCAL_STARTS for s in starts)



def _stated_uncertain(state, sigma_m=0.01, sigma_deg=0.3):
    """``state`` with every keyframe's pose stated accurate to ``sigma_m`` / ``sigma_deg``."""
    import dataclasses

    return dataclasses.replace(state, default_pose_covariance=pose_covariance_from_sigmas(
        sigma_m, np.deg2rad(sigma_deg)))


def test_landmarks_of_keyframes_with_pose_errors_are_less_certain(synthetic_scene, synthetic_map):
    from reloc_service.algorithms.pose.landmark_pool import LandmarkPool
    from reloc_service.algorithms.relocalizers.tracking_local_map import landmark_uncertainty

    near = synthetic_map.nearest_keyframes(synthetic_scene.query_poses[0], 10, 60.0)
    keyframes = [synthetic_map.keyframes[k] for k in near]
    pool = LandmarkPool.gather(keyframes, "sift")
    exact = landmark_uncertainty(pool, synthetic_map, near, keyframes).depth_sigmas_m
    uncertain = landmark_uncertainty(pool, _stated_uncertain(synthetic_map), near,
                                      keyframes).depth_sigmas_m
    finite = np.isfinite(exact) & (exact > 0)
    assert finite.sum() > 20
    # 0.3 deg at the scene's focal is several pixels against the keypoints' half pixel.
    assert np.all(uncertain[finite] > 3.0 * exact[finite])


def test_a_good_prior_is_still_tracked_on_a_map_of_uncertain_keyframes(synthetic_scene,
                                                                      synthetic_map):
    tracker = create_tracker(_map_of(_stated_uncertain(synthetic_map)))
    rng = np.random.default_rng(0)
    answered = 0
    for i, gt in enumerate(synthetic_scene.query_poses):
        prior = Prior(_perturbed(gt, rng), covariance=COVARIANCE)
        result = tracker.relocalize(_query(synthetic_scene, i), prior=prior)
        if result.ok:
            answered += 1
            dt, dr = pose_error(result.world_from_cam, gt)
            assert dt < 0.03 and dr < np.deg2rad(1.0)
    assert answered >= len(synthetic_scene.query_poses) - 1


def test_a_tracker_answers_from_its_kept_local_map_as_a_fresh_one_does(synthetic_scene,
                                                                       synthetic_map):
    kmap = _map_of(synthetic_map)
    tracker = create_tracker(kmap)
    gt = synthetic_scene.query_poses[0]
    prior = Prior(_perturbed(gt, np.random.default_rng(5)), covariance=COVARIANCE)
    first = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    again = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    fresh = create_tracker(kmap).relocalize(_query(synthetic_scene, 0), prior=prior)
    assert first.ok and again.ok and fresh.ok, (first.reason, again.reason, fresh.reason)
    for other in (again, fresh):
        assert np.array_equal(other.world_from_cam, first.world_from_cam)
        assert np.array_equal(other.covariance, first.covariance)
        assert other.inliers == first.inliers
    # A map edit pools the local map afresh: the keyframes removed give no inlier.
    gone = set(first.matched_keyframe_ids)
    for kf_id in gone:
        kmap.remove_keyframe(kf_id)
    after = tracker.relocalize(_query(synthetic_scene, 0), prior=prior)
    assert not gone & set(after.matched_keyframe_ids or [])


def test_the_regated_growth_tracks_a_good_prior_and_an_unknown_growth_is_refused(
        synthetic_scene, synthetic_map):
    tracker = create_relocalizer("track", _map_of(synthetic_map),
                                 options={"track": {"growth": "regated"}})
    gt = synthetic_scene.query_poses[2]
    prior = Prior(_perturbed(gt, np.random.default_rng(7)), covariance=COVARIANCE)
    result = tracker.relocalize(_query(synthetic_scene, 2), prior=prior)
    assert result.ok, result.reason
    dt, dr = pose_error(result.world_from_cam, gt)
    assert dt < 0.03 and dr < np.deg2rad(1.0)
    with pytest.raises(ConfigError, match="growth"):
        create_relocalizer("track", _map_of(synthetic_map), options={"track": {"growth": "x"}})


@pytest.mark.parametrize("fallback", ["sift", "sift-half"])
def test_a_fallback_kind_tracks_where_the_first_kind_refuses(synthetic_scene, synthetic_map,
                                                             fallback):
    # The map holds SIFT landmarks only: ORB tracking finds none to match and refuses.
    kmap = _map_of(synthetic_map)
    orb_only = TrackingRelocalizer(kmap, TrackingRelocalizer.Conf(kind="orb"))
    with_fallback = TrackingRelocalizer(
        kmap, TrackingRelocalizer.Conf(kind="orb", fallback=fallback))
    rng = np.random.default_rng(3)
    answered = 0
    for i, gt in enumerate(synthetic_scene.query_poses):
        prior = Prior(_perturbed(gt, rng), covariance=COVARIANCE)
        refused = orb_only.relocalize(_query(synthetic_scene, i), prior=prior)
        assert not refused.ok and "no keyframe near the prior sees" in refused.reason
        result = with_fallback.relocalize(_query(synthetic_scene, i), prior=prior)
        if result.ok:
            answered += 1
            dt, dr = pose_error(result.world_from_cam, gt)
            assert result.method == TRACK and dt < 0.03 and dr < np.deg2rad(1.0)
        else:
            # Each kind's reason, named.
            assert result.reason.startswith("orb: ") and f"; {fallback}: " in result.reason
    assert answered >= len(synthetic_scene.query_poses) - 1


def test_an_unknown_fallback_kind_is_refused():
    with pytest.raises(ConfigError, match="fallback must be one of"):
        TrackingRelocalizer.Conf(fallback="surf")


def test_a_tracked_answer_states_the_covariance_the_method_states_for_the_maps_camera(
        synthetic_scene, synthetic_map):
    """A query that claims the keyframes' own camera is answered under the map's
    calibration accuracy, as the method's steps answer it; one claiming another camera (a
    focal 0.1 % off: nothing vouches for it) with the intrinsics marginalised, wider along
    the optical axis."""
    import dataclasses

    tracker = create_tracker(_map_of(synthetic_map))
    gt = synthetic_scene.query_poses[0]
    prior = Prior(_perturbed(gt, np.random.default_rng(3)), covariance=COVARIANCE)
    camera = synthetic_scene.camera
    other = dataclasses.replace(camera, fx=camera.fx * 1.001, fy=camera.fy * 1.001)
    image = synthetic_scene.query_images[0]
    own = tracker.relocalize(Frame(image, camera), prior=prior)
    foreign = tracker.relocalize(Frame(image, other), prior=prior)
    assert own.ok and foreign.ok, (own.reason, foreign.reason)
    assert own.method == foreign.method == TRACK
    # Along the optical axis (the twist's third component), where the focal moves the pose.
    assert own.covariance[2, 2] < foreign.covariance[2, 2]
    dt, dr = pose_error(own.world_from_cam, gt)
    assert dt < 0.03 and dr < np.deg2rad(1.0)
