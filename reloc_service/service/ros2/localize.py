"""Localization with a prior while tracking: ``[ros2] localize_every_n``.

While the VIO tracks (the lost flag not set) and the map frame is anchored (``map_from_odom``
known), every Nth image is localized with a prior: the odometry pose of the image's stamp in
the map frame, ``map_from_odom @ odom_from_body @ body_from_cam``, with its covariance (the
odometry's, or the map's default keyframe covariance where the odometry gives none, plus
``map_from_odom``'s: :meth:`.mapping.Mapping.camera_covariance`). The service then matches the
landmarks that prior predicts visible in windows its covariance sets, and runs its full method
only where that does not verify (algorithms/relocalizers/tracking.py). The pose is published
as a Trigger answer's is and is one more ``map_from_odom`` sample.

The odometry of an image's stamp often arrives after the image (VIO lags the camera): the
selected image waits for it, until odometry stamped later than the pairing tolerance shows it
will not come. Everything here runs on the bridge's one ordered worker.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from reloc_client import protocol as wire

from . import convert

Array = npt.NDArray[np.float64]


class TrackedNode(Protocol):
    """What the localization needs of its map node (:class:`.bridge.MapNode`)."""

    bridge: Any
    conf: Any                           # Ros2Conf
    map_name: str
    lost: bool
    odometry: convert.StampedPoses
    mapping: Any                        # mapping.Mapping
    body_from_cam: Array


class PriorLocalization:
    """Every ``localize_every_n``-th image while tracking, localized with the odometry's prior
    (see module docstring); ``submit(image, prior)`` relocalizes and publishes."""

    def __init__(self, node: TrackedNode, submit: Callable[[Any, wire.Prior], None]) -> None:
        self.node = node
        self.every_n = int(node.conf.localize_every_n)
        self._submit = submit
        self._images = 0
        self._waiting: Any = None       # the selected image waiting for its odometry

    def on_image(self, latest: Any) -> None:
        """Count an image taken while tracking; the Nth waits for its odometry."""
        if not self.every_n or self.node.lost:
            return
        self._images += 1
        if self._images % self.every_n == 0:
            self._waiting = latest     # a newer selection replaces one still waiting
            self.retry()

    def retry(self) -> None:
        """Submit the waiting image once the odometry of its stamp is known (after each
        odometry message); drop it when that odometry will not come or VIO is lost."""
        latest = self._waiting
        if latest is None:
            return
        node, tolerance = self.node, self.node.conf.max_stamp_difference_s
        stamp = convert.stamp_seconds(latest.stamp)
        paired = node.odometry.nearest_with_covariance(stamp, tolerance)
        if paired is None and node.odometry.newest() <= stamp + tolerance:
            return
        self._waiting = None
        if node.lost:
            return
        if paired is None:
            node.bridge.count("localize_unpaired")
            return
        prior = self.prior_of(*paired)
        if prior is None:
            node.bridge.count("localize_unanchored")
            return
        node.bridge.count("localize_submitted")
        self._submit(latest, prior)

    def prior_of(self, odom_from_body: Array, ros_covariance: Array | None) -> wire.Prior | None:
        """The camera's pose in the map frame from the odometry, with its covariance; None
        while the map frame is not anchored or no covariance is known."""
        mapping = self.node.mapping
        _, estimate = mapping.frame.current()
        if estimate is None:
            return None
        covariance = mapping.camera_covariance(ros_covariance, odom_from_body, estimate)
        if covariance is None:
            covariance = self._default_covariance()
        if covariance is None:
            return None
        map_from_cam = estimate.map_from_odom @ odom_from_body @ self.node.body_from_cam
        return wire.Prior(world_from_cam=wire.WirePose.from_matrix(map_from_cam),
                          covariance=tuple(float(v) for v in np.ravel(covariance)))

    def _default_covariance(self) -> Array | None:
        """The map's default keyframe covariance (odometry without one, a map frame defined
        by its own session without an uncertainty of its own)."""
        rt = self.node.bridge.host.maps.get(self.node.map_name)
        return None if rt is None else rt.map_state().default_pose_covariance
