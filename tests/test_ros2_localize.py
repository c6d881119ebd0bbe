"""``[ros2] localize_every_n`` over real Zenoh, driven as a drone node would
(tests/ros2_standin.py): while the VIO tracks and the map frame is anchored, every Nth image
is localized with the odometry's pose in the map frame as the query's prior (its covariance
the odometry's plus ``map_from_odom``'s), and the pose is published; nothing while lost; a
prior far off gives the right pose or none, never one near the prior."""

from __future__ import annotations

import queue

import numpy as np
import pytest
from ros2_standin import read_pose
from ros2_support import (
    body_from_cam,
    drone_built_map,
    pngs,
    pose_error,
    publish_frame,
    settle,
    stamp,
)
from service_support import wait_until

from reloc_service.core.errors import ConfigError
from reloc_service.service.ros2 import types as ros
from reloc_service.service.ros2.conf import Ros2Conf

EVERY_N = 3


@pytest.fixture(scope="module")
def tracking(synthetic_scene):
    """A map a drone built from the 6 keyframes (its odometry frame: the map frame, anchored
    from the start), ``localize_every_n = 3``; views 2 cm beside each keyframe (the keyframe
    rule skips them), rendered."""
    with drone_built_map(synthetic_scene, localize_every_n=EVERY_N) as (service, drone, _):
        settle(service, 6)
        quiet(service, drone)
        views = []
        for world_from_cam in synthetic_scene.keyframe_poses:
            beside = world_from_cam.copy()
            beside[:3, 3] += (0.02, 0.0, 0.0)
            views.append(beside)
        yield service, drone, list(zip(views, pngs([synthetic_scene.render(v)[0]
                                                    for v in views]), strict=True))


def drain(poses: queue.Queue) -> list:
    out = []
    while True:
        try:
            out.append(read_pose(poses.get(timeout=1.0)[0]))
        except queue.Empty:
            return out


def fly(service, drone, frames, t0: float) -> None:
    """Publish each (odom_from_cam, png) with its odometry, 0.1 s apart from ``t0``, each
    once the bridge took the one before (as a camera's frames come, not in one burst: a
    selected image whose odometry has not come yet is replaced by the next selected one), and
    wait until every localization they asked for was answered."""
    counters = service.ros2.counters
    images = counters["images"]
    for i, (odom_from_cam, png) in enumerate(frames):
        taken = counters["images"], counters["odometry"]
        publish_frame(drone, t0 + 0.1 * i, "odom", odom_from_cam, png)
        wait_until(lambda taken=taken: counters["images"] > taken[0]
                   and counters["odometry"] > taken[1])
    settle(service, images + len(frames))


def localizations(service) -> int:
    counters, _ = service.ros2.node("room").status.snapshot()
    return counters.get("localize_ok", 0) + counters.get("localize_failed", 0)


def quiet(service, drone) -> None:
    """Until every localization submitted so far was answered (the map's own images are
    counted too), then drop the poses published meanwhile."""
    wait_until(lambda: localizations(service) == service.ros2.counters["localize_submitted"],
               timeout=60)
    drain(drone.poses)


def test_every_nth_image_while_tracking_is_localized_from_the_odometry_prior(tracking):
    """Six images (two runs of three): exactly two localized, published with their images'
    stamps within 2 cm / 1 deg of the truth; by tracking in the prior's windows where the
    tracked pose is known better than the prior in every direction, else by the chain. The
    odometry here is sharp (1-3 cm, 0.2-0.4 deg), so one of the two views' tracked poses is
    not (along one direction) and the chain answers it: at least one is tracked."""
    service, drone, views = tracking
    quiet(service, drone)
    tracked, done = service.ros2.counters["tracked_poses"], localizations(service)
    fly(service, drone, views, 200.0)
    wait_until(lambda: localizations(service) == done + 2, timeout=60)
    readings = drain(drone.poses)
    assert len(readings) == 2
    assert tracked + 1 <= service.ros2.counters["tracked_poses"] <= tracked + 2
    truth = {stamp(200.0 + 0.1 * i): world_from_cam for i, (world_from_cam, _) in
             enumerate(views)}
    for reading in readings:
        assert reading.stamp in truth and reading.frame_id == "map"
        world_from_body = truth[reading.stamp] @ np.linalg.inv(body_from_cam())
        metres, degrees = pose_error(reading.map_from_body, world_from_body)
        assert metres < 0.02 and degrees < 1.0, (metres, degrees)
        assert np.all(np.linalg.eigvalsh(reading.covariance) > 0)


def test_nothing_is_localized_while_the_vio_is_lost(tracking):
    service, drone, views = tracking
    quiet(service, drone)
    submitted = service.ros2.counters["localize_submitted"]
    drone.publish("/reloc/room/lost", "std_msgs/msg/Bool", ros.type_hash(ros.BOOL),
                  b"\x00\x01\x00\x00\x01")
    wait_until(lambda: service.ros2.node("room").lost)
    try:
        fly(service, drone, views, 300.0)
        assert service.ros2.counters["localize_submitted"] == submitted
    finally:
        drone.publish("/reloc/room/lost", "std_msgs/msg/Bool", ros.type_hash(ros.BOOL),
                      b"\x00\x01\x00\x00\x00")
        wait_until(lambda: not service.ros2.node("room").lost)


def test_a_prior_two_metres_off_never_gives_a_pose_near_it(tracking):
    """Odometry 2 m off the truth (a VIO that drifted, the map frame not yet told) on the
    image selected for localization: the tracking windows find nothing; the full method
    answers with the true pose or refuses. The drifted frame is the first one selected, so
    no keyframe probe of an earlier drifted frame can show the map frame the jump first."""
    service, drone, views = tracking
    quiet(service, drone)
    done, tracked = localizations(service), service.ros2.counters["tracked_poses"]
    unanchored = service.ros2.counters["localize_unanchored"]
    taken = service.ros2.node("room").localize._images % EVERY_N
    lead = views[:EVERY_N - 1 - taken]          # on the truth: selected none
    fly(service, drone, lead, 400.0)
    world_from_cam, png = views[len(lead)]
    t = 401.0 + 0.1 * len(lead)                 # 2 m in over a second: drift, not a reset
    fly(service, drone, [(world_from_cam @ _shift(2.0), png)], t)
    wait_until(lambda: localizations(service) - done
               + service.ros2.counters["localize_unanchored"] - unanchored == 1, timeout=60)
    assert localizations(service) == done + 1   # localized with the drifted prior
    assert service.ros2.counters["tracked_poses"] == tracked
    for reading in drain(drone.poses):
        assert reading.stamp == stamp(t)
        world_from_body = world_from_cam @ np.linalg.inv(body_from_cam())
        metres, _ = pose_error(reading.map_from_body, world_from_body)
        assert metres < 0.05, metres


def test_config_checks_localize_every_n():
    assert Ros2Conf().localize_every_n == 0           # off by default
    assert Ros2Conf(localize_every_n=5).localize_every_n == 5
    with pytest.raises(ConfigError, match="localize_every_n: expected an integer >= 0"):
        Ros2Conf(localize_every_n=-1)


def _shift(metres: float) -> np.ndarray:
    out = np.eye(4)
    out[0, 3] = metres
    return out
