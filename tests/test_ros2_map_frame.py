"""The map frame owned by the ROS 2 bridge: ``map_from_odom`` per odometry session from
relocalizations (reloc_service/service/ros2/map_frame.py), the keyframe rule scaled by the
scene depth (keyframe_rule.py), and over real Zenoh, driven as a drone node would
(tests/ros2_standin.py): keyframes checked by relocalization, a VIO restart in a shifted frame,
``map -> odom`` on /tf, the mapping SetBool service and the lost flag."""
# ruff: noqa: E402

from __future__ import annotations

import logging

import numpy as np
import pytest
from ros2_standin import (
    HASH,
    call_set_bool,
    parse_attachment,
    read_tf,
    subscribe_tf,
)
from ros2_support import (
    body_from_cam,
    counts,
    drone_built_map,
    pngs,
    pose,
    pose_error,
    publish_frame,
    relocalize,
    settle,
    stamp,
)
from service_support import wait_until

from reloc_service.core.errors import ConfigError
from reloc_service.core.geometry import invert, pose_from_tum, se3_exp, se3_log
from reloc_service.service.app import Service
from reloc_service.service.ros2 import types as ros
from reloc_service.service.ros2.conf import Ros2Conf
from reloc_service.service.ros2.keyframe_rule import KeyframeRule, Rule, median_scene_depth
from reloc_service.service.ros2.map_frame import (
    MapFrame,
    MapFrameConf,
    Sample,
    State,
    Verdict,
    mahalanobis2,
    sample_of,
)

#: The VIO restarted in a frame turned 90 deg about z and shifted 2 m: odom2_from_map.
ODOM2_FROM_MAP = pose(90.0, (2.0, 0.5, 0.0))
COV_RELOC = np.diag(np.square([0.01, 0.01, 0.01, 0.002, 0.002, 0.002]))
COV_ODOM = np.diag(np.square([0.02, 0.02, 0.02, 0.003, 0.003, 0.003]))


def noisy(world_from_cam: np.ndarray, covariance: np.ndarray, rng) -> np.ndarray:
    return world_from_cam @ se3_exp(rng.multivariate_normal(np.zeros(6), covariance))


def draw_sample(map_from_odom: np.ndarray, rng, odom_from_cam: np.ndarray | None = None
                ) -> Sample:
    odom_from_cam = pose(30.0, (1.0, -0.5, 1.2)) if odom_from_cam is None else odom_from_cam
    map_from_cam = map_from_odom @ odom_from_cam
    return sample_of(noisy(map_from_cam, COV_RELOC, rng), COV_RELOC,
                     noisy(odom_from_cam, COV_ODOM, rng), COV_ODOM)


# -- map_frame.py -----------------------------------------------------------------------------

def test_a_sample_composes_the_poses_and_its_covariance_is_the_sampled_one():
    """``map_from_cam @ inv(odom_from_cam)`` with ``Ad(odom_from_cam) (S_map + S_odom) Ad^T``:
    the covariance of 1500 noisy samples (as log residuals) matches it."""
    rng = np.random.default_rng(0)
    truth = invert(ODOM2_FROM_MAP)
    draws = [draw_sample(truth, rng) for _ in range(1500)]
    residuals = np.array([se3_log(invert(truth) @ s.map_from_odom) for s in draws])
    empirical = np.cov(residuals.T)
    predicted = draws[0].covariance
    np.testing.assert_allclose(np.sqrt(np.diag(empirical)), np.sqrt(np.diag(predicted)),
                               rtol=0.1)
    exact = sample_of(truth @ pose(30.0, (1.0, -0.5, 1.2)), COV_RELOC,
                      pose(30.0, (1.0, -0.5, 1.2)), COV_ODOM)
    np.testing.assert_allclose(exact.map_from_odom, truth, atol=1e-12)


def test_agreement_is_a_chi_square_gate_on_the_summed_covariances():
    """Right samples agree at the gate's confidence (0.999); a 90 deg / 2 m jump never does."""
    rng = np.random.default_rng(1)
    truth = invert(ODOM2_FROM_MAP)
    conf = MapFrameConf()
    assert conf.gate == pytest.approx(22.4577, abs=1e-3)   # chi2.ppf(0.999, 6)
    pairs = [(draw_sample(truth, rng), draw_sample(truth, rng)) for _ in range(600)]
    agree = np.mean([mahalanobis2(a, b) <= conf.gate for a, b in pairs])
    assert 0.99 <= agree <= 1.0
    jumped = draw_sample(np.eye(4), rng)
    assert mahalanobis2(pairs[0][0], jumped) > 1e4


def test_first_session_of_an_empty_map_defines_the_map_frame():
    frame = MapFrame(defines_map=True)
    assert frame.state is State.UNANCHORED        # no odometry yet
    assert not frame.on_odometry("odom", 1.0, np.eye(4))
    session, estimate = frame.current()
    assert frame.state is State.ANCHORED and frame.defining and session == 0
    assert estimate is not None and np.array_equal(estimate.map_from_odom, np.eye(4))
    rng = np.random.default_rng(2)
    assert frame.add_sample(draw_sample(np.eye(4), rng), 0) is Verdict.AGREES
    assert np.array_equal(frame.current()[1].map_from_odom, np.eye(4))  # never moved


def test_a_disagreement_starts_a_session_that_k_agreeing_samples_anchor():
    rng = np.random.default_rng(3)
    frame = MapFrame(MapFrameConf(anchor_samples=3), defines_map=True)
    frame.on_odometry("odom", 1.0, np.eye(4))
    truth = invert(ODOM2_FROM_MAP)    # the VIO restarted: map_from_odom is no longer identity
    views = [pose(10.0 * i, (0.3 * i, 0.2, 1.0)) for i in range(6)]
    assert frame.add_sample(draw_sample(truth, rng, views[0]), 0) is Verdict.DISAGREES
    assert frame.state is State.UNANCHORED and frame.session == 1
    assert "disagrees with map_from_odom by" in frame.last_event
    # the odometry itself did not reset (same epoch): its next samples re-anchor the session
    assert frame.add_sample(draw_sample(truth, rng, views[1]), 0) is Verdict.PENDING
    assert frame.add_sample(draw_sample(truth, rng, views[2]), 0) is Verdict.ANCHORED
    _, estimate = frame.current()
    metres, degrees = pose_error(estimate.map_from_odom, truth)
    assert metres < 0.05 and degrees < 2.0
    assert frame.add_sample(draw_sample(truth, rng, views[3]), 0) is Verdict.AGREES
    assert frame.status()["state"] == "anchored" and frame.status()["map_from_odom"]
    frame.on_odometry("vio2", 2.0, np.eye(4))       # an odometry reset: older samples are stale
    assert frame.epoch == 1 and frame.add_sample(draw_sample(truth, rng), 0) is Verdict.IGNORED


def test_an_outlier_restarts_the_anchoring_run():
    rng = np.random.default_rng(4)
    frame = MapFrame(MapFrameConf(anchor_samples=2))
    frame.on_odometry("odom", 1.0, np.eye(4))
    assert frame.state is State.UNANCHORED          # a map that was not empty: not defined
    truth = invert(ODOM2_FROM_MAP)
    assert frame.add_sample(draw_sample(truth, rng), 0) is Verdict.PENDING
    assert frame.add_sample(draw_sample(np.eye(4), rng), 0) is Verdict.PENDING   # restarts
    assert frame.counts["anchor_runs_restarted"] == 1
    assert frame.add_sample(draw_sample(truth, rng), 0) is Verdict.PENDING       # restarts
    assert frame.add_sample(draw_sample(truth, rng), 0) is Verdict.ANCHORED


@pytest.mark.parametrize(("frame_id", "t", "odom_from_body", "reason"), [
    ("vio2", 1.1, np.eye(4), "frame id changed"),
    ("odom", 0.5, np.eye(4), "time went back"),
    ("odom", 1.1, pose(0.0, (3.0, 0.0, 0.0)), "jumped 3.00 m in 0.100 s"),
    ("odom", 1.1, pose(90.0, (0.0, 0.0, 0.0)), "turned 90.0 deg"),
])
def test_an_odometry_reset_begins_a_new_session(frame_id, t, odom_from_body, reason):
    frame = MapFrame(defines_map=True)
    frame.on_odometry("odom", 1.0, np.eye(4))
    assert frame.state is State.ANCHORED
    assert frame.on_odometry(frame_id, t, odom_from_body)
    assert frame.state is State.UNANCHORED and frame.session == 1 and reason in frame.last_event
    assert not frame.defining


def test_motion_within_the_vehicle_limits_is_no_reset():
    frame = MapFrame(defines_map=True)
    frame.on_odometry("odom", 1.0, np.eye(4))
    assert not frame.on_odometry("odom", 1.1, pose(5.0, (1.0, 0.0, 0.0)))   # 10 m/s, 50 deg/s
    assert not frame.on_odometry("odom", 200.0, pose(90.0, (9.0, 0.0, 0.0)))  # after a pause
    assert frame.state is State.ANCHORED


def test_lost_reads_lost_and_ignores_samples():
    frame = MapFrame(defines_map=True)
    frame.on_odometry("odom", 1.0, np.eye(4))
    frame.set_lost(True)
    assert frame.state is State.LOST
    assert frame.add_sample(draw_sample(ODOM2_FROM_MAP, np.random.default_rng(5)), 0) \
        is Verdict.IGNORED
    frame.set_lost(False)
    assert frame.state is State.ANCHORED


# -- keyframe_rule.py ------------------------------------------------------------------------

def test_the_overlap_rule_scales_with_the_scene_depth():
    rule = KeyframeRule(Rule.OVERLAP, overlap_fraction=0.12, default_depth_m=2.0,
                        min_angle_deg=15.0)
    kf = np.eye(4)
    assert rule.radius_m(None) == pytest.approx(0.24) and rule.radius_m(30.0) == pytest.approx(3.6)
    moved = pose(0.0, (1.0, 0.0, 0.0))
    assert rule.is_new(moved, [(kf, 2.0)])            # 1 m in a room: a new view
    assert not rule.is_new(moved, [(kf, 30.0)])       # 1 m under a field 30 m away: the same
    assert rule.is_new(pose(20.0, (0.0, 0.0, 0.0)), [(kf, 30.0)])   # turned
    metres = KeyframeRule(Rule.DISTANCE, min_distance_m=0.15, min_angle_deg=15.0)
    assert metres.is_new(pose(0.0, (0.2, 0, 0)), [(kf, 30.0)])      # depth ignored
    assert rule.nearest_depth(moved, [(kf, None), (pose(0.0, (5.0, 0, 0)), 7.0)]) == 7.0


def test_the_distance_rule_is_metres_or_angle():
    from reloc_service.core.geometry import look_at

    rule = KeyframeRule(Rule.DISTANCE, min_distance_m=0.1, min_angle_deg=10.0)
    first = look_at((0, 0, 1), (0, 2, 1))
    assert rule.is_new(first, [])
    assert not rule.is_new(look_at((0.05, 0, 1), (0.05, 2, 1)), [(first, None)])
    assert rule.is_new(look_at((0.15, 0, 1), (0.15, 2, 1)), [(first, None)])   # moved
    assert rule.is_new(look_at((0, 0, 1), (0.6, 2, 1)), [(first, None)])       # turned 17 deg


def test_scene_depth_of_a_keyframe_is_the_median_depth_of_its_map_points(synthetic_map,
                                                                         synthetic_scene):
    """The mapped synthetic room: each keyframe's depth from its triangulated map points is
    within 5 % of the median rendered (true) depth at the pixels of the keypoints that observe
    them (the depth of what the keyframe's features see, as SVO's average feature depth)."""
    for kf_id, kf in synthetic_map.keyframes.items():
        depth = median_scene_depth(kf)
        rendered = synthetic_scene.keyframe_depths[kf_id]
        pixels = np.concatenate([f.keypoints_px[f.landmark_ids >= 0]
                                 for f in kf.features.values()])
        cols, rows = np.rint(pixels).astype(int).T
        truth = float(np.nanmedian(rendered[rows, cols]))
        assert depth is not None and abs(depth - truth) < 0.05 * truth, (kf_id, depth, truth)


def test_config_checks_the_map_frame_keys():
    with pytest.raises(ConfigError, match="keyframe_rule"):
        Ros2Conf(keyframe_rule="metres")
    with pytest.raises(ConfigError, match="anchor_confidence"):
        Ros2Conf(anchor_confidence=1.5)
    with pytest.raises(ConfigError, match="anchor_samples"):
        Ros2Conf(anchor_samples=0)
    assert Ros2Conf().keyframe_rule == "overlap"


def test_tf_and_set_bool_carry_their_official_type_hashes():
    assert ros.type_hash(ros.TF_MESSAGE) == HASH["tf2_msgs/msg/TFMessage"]
    assert ros.type_hash(ros.TF_MESSAGE).startswith("RIHS01_e369d0f0")
    assert ros.type_hash(ros.TF_MESSAGE).endswith("020f087")
    assert ros.type_hash(ros.SET_BOOL) == HASH["std_srvs/srv/SetBool"]


# -- over Zenoh, as a drone node ---------------------------------------------------------------


def new_views(scene) -> list[tuple[np.ndarray, bytes]]:
    """Views the map has no keyframe at (each keyframe's pose 30 cm forward or up), rendered."""
    poses = []
    for i, kf in enumerate(scene.keyframe_poses):
        p = kf.copy()
        p[:3, 3] += (0.0, 0.3, 0.0) if i % 2 == 0 else (0.0, 0.0, 0.3)
        poses.append(p)
    return [(p, png) for p, png in zip(poses, pngs([scene.render(p)[0] for p in poses]),
                                       strict=True)]


@pytest.fixture(scope="module")
def mapped(synthetic_scene):
    """A service whose map "room" was built by a drone from the 6 synthetic keyframes (the
    first session: its odometry frame ``odom`` is the map frame), the drone, and new views.
    The overlap rule at 10 % of the depth, 2 m assumed until the map knows it: the keyframes,
    25 cm apart, are each a new view whatever their depth (1.24 to 2.11 m: 12 to 21 cm)."""
    with drone_built_map(synthetic_scene, subscribe_tf, keyframe_rule="overlap",
                         keyframe_overlap_fraction=FRACTION,
                         keyframe_default_depth_m=DEFAULT_DEPTH_M) as (service, drone, tf):
        yield service, drone, tf, new_views(synthetic_scene)


FRACTION, DEFAULT_DEPTH_M = 0.1, 2.0


def keyframe_count(service: Service) -> int:
    return len(service.maps["room"].map_state().keyframes)


def wait_count(service: Service, name: str, before: int) -> None:
    wait_until(lambda: int(counts(service).get(name, "0")) > before, timeout=60)
    service.wait_idle()


def count_of(service: Service, name: str) -> int:
    return int(counts(service).get(name, "0"))


def test_the_keyframe_distance_follows_the_scene_depth_the_map_knows(mapped, synthetic_scene):
    """A keyframe's radius is 10 % of the depth of its map points, not of the assumed 2 m: a
    camera between the two radii behind keyframe 2 is judged by the known one."""
    service, drone, _tf, _views = mapped
    state = service.maps["room"].map_state()
    depth = median_scene_depth(state.keyframes[2])
    assert depth is not None
    known, assumed = FRACTION * depth, FRACTION * DEFAULT_DEPTH_M
    assert abs(known - assumed) > 0.02
    behind = synthetic_scene.keyframe_poses[2].copy()
    behind[:3, 3] -= behind[:3, 2] * 0.5 * (known + assumed)   # back along the optical axis
    [png] = pngs([synthetic_scene.render(behind)[0]])
    before, images = keyframe_count(service), service.ros2.counters["images"]
    odometry = service.ros2.counters["odometry"]
    publish_frame(drone, 105.0, "odom", behind, png)
    settle(service, images + 1, odometry + 1)
    # farther than the known radius: a new keyframe; nearer: none (the assumed depth would
    # have said the opposite)
    assert keyframe_count(service) == before + (1 if known < assumed else 0), (known, assumed)


def test_set_bool_pauses_and_resumes_mapping(mapped):
    service, drone, _tf, views = mapped
    [(success, message, att)] = call_set_bool(drone, "/reloc/room/mapping", False, seq=1)
    assert success and "mapping paused" in message and parse_attachment(att) == (1, drone.gid)
    assert counts(service)["mapping"] == "paused"
    before, paused = keyframe_count(service), count_of(service, "mapping_paused")
    world_from_cam, png = views[0]
    publish_frame(drone, 110.0, "odom", world_from_cam, png)
    wait_count(service, "mapping_paused", paused)
    assert keyframe_count(service) == before        # a new view, but mapping is paused
    [(success, message, _)] = call_set_bool(drone, "/reloc/room/mapping", True, seq=2)
    assert success and "mapping resumed" in message
    agreed = count_of(service, "mapping_samples_agrees")
    publish_frame(drone, 111.0, "odom", world_from_cam, png)
    wait_count(service, "mapping_samples_agrees", agreed)   # relocalized first, and agrees
    wait_until(lambda: keyframe_count(service) == before + 1)
    newest = service.maps["room"].map_state().keyframes[max(
        service.maps["room"].map_state().keyframes)]
    assert np.allclose(newest.world_from_cam, world_from_cam, atol=1e-6)   # identity frame


def test_lost_pauses_mapping(mapped):
    service, drone, _tf, views = mapped
    drone.publish("/reloc/room/lost", "std_msgs/msg/Bool", ros.type_hash(ros.BOOL),
                  b"\x00\x01\x00\x00\x01")
    wait_until(lambda: counts(service)["state"] == "lost")
    before, paused = keyframe_count(service), count_of(service, "mapping_paused_lost")
    world_from_cam, png = views[1]
    publish_frame(drone, 120.0, "odom", world_from_cam, png)
    wait_count(service, "mapping_paused_lost", paused)
    assert keyframe_count(service) == before
    drone.publish("/reloc/room/lost", "std_msgs/msg/Bool", ros.type_hash(ros.BOOL),
                  b"\x00\x01\x00\x00\x00")
    wait_until(lambda: counts(service)["state"] == "anchored")
    publish_frame(drone, 121.0, "odom", world_from_cam, png)
    wait_until(lambda: keyframe_count(service) == before + 1, timeout=60)


def test_a_vio_restart_in_a_shifted_frame_adds_no_keyframe_in_the_wrong_frame(
        mapped, synthetic_scene):
    """The VIO restarts in frame ``odom`` again, turned 90 deg and shifted 2 m (a pause
    between, so the odometry does not jump faster than a vehicle: only relocalization can
    tell). The first keyframe candidate disagrees, mapping stops, the new session is
    re-anchored from agreeing relocalizations within 5 cm / 2 deg of the truth, /tf says
    so, keyframes resume in the map frame, and every pose asked for is right or refused."""
    service, drone, tf, views = mapped
    scene = synthetic_scene
    rt = service.maps["room"]
    truth_by_stamp = {kf.timestamp: kf.world_from_cam for kf in rt.map_state().keyframes.values()}
    before = set(rt.map_state().keyframes)
    frames = [*views[2:], *zip(scene.query_poses, pngs(scene.query_images), strict=True)]
    disagreed = count_of(service, "mapping_samples_disagrees")
    images, odometry = service.ros2.counters["images"], service.ros2.counters["odometry"]
    for i, (world_from_cam, png) in enumerate(frames):
        t = 300.0 + i
        truth_by_stamp[t] = world_from_cam
        publish_frame(drone, t, "odom", ODOM2_FROM_MAP @ world_from_cam, png)
    settle(service, images + len(frames), odometry + len(frames))
    # no keyframe in the wrong frame: every one added since sits where its image was taken
    added = [kf for k, kf in rt.map_state().keyframes.items() if k not in before]
    print(f"{len(added)} keyframes added after the restart; status {counts(service)}")
    assert len(added) >= 2          # mapping resumed once anchored
    for kf in added:
        metres, degrees = pose_error(kf.world_from_cam, truth_by_stamp[kf.timestamp])
        assert metres < 0.05 and degrees < 2.0, (kf.id, metres, degrees)
    status = counts(service)
    assert count_of(service, "mapping_samples_disagrees") == disagreed + 1
    assert (status["state"], status["session"], status["resets"]) == ("anchored", "1", "1")
    # map -> odom re-estimated: map_from_odom = inv(odom2_from_map)
    estimate = pose_from_tum(np.array(status["map_from_odom"].split(), float))
    metres, degrees = pose_error(estimate, invert(ODOM2_FROM_MAP))
    print(f"\nmap_from_odom re-estimated within {metres * 100:.2f} cm / {degrees:.2f} deg")
    assert metres < 0.05 and degrees < 2.0
    # the last /tf: map -> odom with the estimate, official hash in the key
    readings = []

    def all_arrived() -> bool:   # one publisher: Zenoh keeps its samples in order
        while not tf.empty():
            key, payload = tf.get()
            assert key.endswith("tf2_msgs::msg::dds_::TFMessage_/"
                                + HASH["tf2_msgs/msg/TFMessage"])
            readings.extend(read_tf(payload))
        return len(readings) == count_of(service, "mapping_tf_published")

    wait_until(all_arrived)
    last = readings[-1]
    assert (last.parent, last.child) == ("map", "odom")
    metres, degrees = pose_error(last.parent_from_child, invert(ODOM2_FROM_MAP))
    assert metres < 0.05 and degrees < 2.0
    # every later pose is right or refused
    for i, (png, world_from_cam) in enumerate(zip(pngs(scene.query_images), scene.query_poses,
                                                  strict=True)):
        success, message, reading = relocalize(drone, service, png, stamp(400.0 + i), 50 + i,
                                               "room")
        if success:
            metres, degrees = pose_error(reading.map_from_body,
                                         world_from_cam @ invert(body_from_cam()))
            assert metres < 0.25 and degrees < 10.0, (i, metres, degrees, message)


def test_a_new_odometry_frame_id_stops_mapping_until_anchored_again(mapped, synthetic_scene,
                                                                    caplog):
    """The VIO comes back in frame ``odom_2`` (turned -45 deg, shifted 1 m): the odometry
    itself says it is a new session, no relocalization has to disagree; the session is
    anchored from the next relocalizations and /tf names ``odom_2`` as the child."""
    service, drone, tf, _views = mapped
    scene = synthetic_scene
    odom3_from_map = pose(-45.0, (0.0, 1.0, 0.2))
    resets, disagreed = count_of(service, "resets"), count_of(service, "samples_disagreed")
    images, odometry = service.ros2.counters["images"], service.ros2.counters["odometry"]
    shots = [0, 2, 4, 5]
    caplog.set_level(logging.WARNING, logger="reloc_service.service.ros2.map_frame")
    for i, k in enumerate(shots):
        publish_frame(drone, 500.0 + i, "odom_2", odom3_from_map @ scene.keyframe_poses[k],
                      pngs([scene.keyframe_images[k]])[0])
    settle(service, images + len(shots), odometry + len(shots))
    status = counts(service)
    assert count_of(service, "resets") == resets + 1
    assert count_of(service, "samples_disagreed") == disagreed   # the odometry said so
    assert any("frame id changed from 'odom' to 'odom_2'; mapping stops" in r.getMessage()
               for r in caplog.records)
    assert (status["state"], status["odom_frame_id"]) == ("anchored", "odom_2")
    estimate = pose_from_tum(np.array(status["map_from_odom"].split(), float))
    metres, degrees = pose_error(estimate, invert(odom3_from_map))
    assert metres < 0.05 and degrees < 2.0
    readings = []

    def last_arrived() -> bool:
        while not tf.empty():
            readings.extend(read_tf(tf.get()[1]))
        return bool(readings) and readings[-1].child == "odom_2"

    wait_until(last_arrived)
    metres, degrees = pose_error(readings[-1].parent_from_child, invert(odom3_from_map))
    assert readings[-1].parent == "map" and metres < 0.05 and degrees < 2.0
