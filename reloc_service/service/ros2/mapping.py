"""Keyframes from odometry, in the map frame: a map node's mapping (see :mod:`.map_frame`).

The keyframe rule (:mod:`.keyframe_rule`) selects a candidate from the images paired with
odometry. Once the map can relocalize, the candidate is relocalized first (the relocalize
pool, the same path as the Trigger service) and added only when the answer agrees with its
odometry pose mapped through ``map_from_odom``; its keyframe pose is then
``map_from_odom @ odom_from_body @ body_from_cam``, in the map frame. A disagreement stops
mapping until the new session is anchored again; unanchored, candidates are still relocalized
(as probes) to anchor it. Before the map can relocalize, the first session of an empty map adds
its keyframes unquestioned: its odometry frame is the map frame.

Mapping pauses while the VIO says it is lost and when the ``mapping`` std_srvs/SetBool service
says so. ``map -> odom`` goes out on ``/tf`` (tf2_msgs/TFMessage, REP-105) when the estimate
changes and with the images while anchored.
"""

from __future__ import annotations

import collections
import itertools
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import zenoh
from reloc_client import protocol as wire

from ...core.geometry import invert, matrix_to_quat_xyzw, se3_adjoint
from . import convert, graph
from . import types as ros
from .keyframe_rule import KeyframeRule, Rule, median_scene_depth
from .map_frame import MapFrame, MapFrameConf, Sample, Verdict, sample_of
from .trigger import stamp_text

log = logging.getLogger(__name__)

Array = npt.NDArray[np.float64]
#: How long a candidate waits for the keyframes put before it to reach the map (the writer
#: applies them in order; a refused one never arrives).
MAP_CATCH_UP_S = 5.0
#: Candidates waiting for the one being relocalized (a burst of images selected at once).
PENDING_CANDIDATES = 64


@dataclass(frozen=True)
class Candidate:
    """An image the rule selected, with its odometry."""

    image: Any                          # bridge.LatestImage
    odom_from_body: Array
    ros_covariance: Array | None        # the odometry's, ROS's convention
    epoch: int                          # the odometry's (MapFrame.epoch)
    world_from_cam: Array | None        # predicted in the map frame (None: unanchored probe)
    depth_m: float | None


class MappedNode(Protocol):
    """What the mapping needs of its map node (:class:`.bridge.MapNode`)."""

    bridge: Any
    conf: Any
    map_name: str
    body_from_cam: Array
    lost: bool
    status: Any                         # diagnostics.NodeStatus: refusals are reported there

    def put_keyframe(self, latest: Any, world_from_cam: Array,
                     pose_covariance: tuple[float, ...] | None) -> int: ...

    def keyframe_covariance(self, ros_covariance: Array | None, world_from_cam: Array,
                            world_from_body: Array) -> tuple[float, ...] | None: ...


class Mapping:
    """One map node's mapping (see module docstring)."""

    def __init__(self, node: MappedNode, camera_id: str, *, map_is_empty: bool) -> None:
        conf = node.conf
        self.node = node
        self.camera_id = camera_id
        self.enabled = True
        self.frame = MapFrame(MapFrameConf(conf.anchor_samples, conf.anchor_confidence,
                                           conf.odometry_max_speed_m_s,
                                           conf.odometry_max_turn_rate_deg_s),
                              defines_map=map_is_empty)
        self.rule = KeyframeRule(Rule(conf.keyframe_rule), conf.keyframe_overlap_fraction,
                                 conf.keyframe_default_depth_m, conf.keyframe_min_distance_m,
                                 conf.keyframe_min_angle_deg)
        self.counts: collections.Counter[str] = collections.Counter()
        #: kf id -> (world_from_cam in the map frame, scene depth or None until known)
        self.keyframes: dict[int, tuple[Array, float | None]] = {}
        self._lock = threading.RLock()
        self._queue: collections.deque[Candidate] = collections.deque(maxlen=PENDING_CANDIDATES)
        self._in_flight: Candidate | None = None
        self._probes: list[tuple[Array, float | None]] = []
        self._probe_session = -1
        self._can_relocalize = False
        self._depth_version = -1
        self._last_put: int | None = None
        self._waited_for: int | None = None
        self._tf: Any = None
        self._tf_gid = b""
        self._tf_seq = itertools.count(1)
        self._tf_last_stamp = float("-inf")
        self.service_key = ""

    # -- wiring --------------------------------------------------------------------------------
    def attach(self, tf_publisher: Any, tf_gid: bytes, service_key: str) -> None:
        self._tf, self._tf_gid, self.service_key = tf_publisher, tf_gid, service_key

    def restore(self, state: Any) -> None:
        """The map's keyframes (the rule applies to them too), with their scene depths."""
        with self._lock:
            for kf in state.keyframes.values():
                self.keyframes[kf.id] = (kf.world_from_cam, median_scene_depth(kf))

    def count(self, name: str) -> None:
        with self._lock:
            self.counts[name] += 1

    def status(self) -> dict[str, str]:
        with self._lock:
            counts = {f"mapping_{k}": str(v) for k, v in sorted(self.counts.items())}
            known = len(self.keyframes)
            waiting = len(self._queue) + (self._in_flight is not None)
        return {**self.frame.status(), "mapping": "on" if self.enabled else "paused",
                "keyframes": str(known), "candidates_waiting": str(waiting), **counts}

    @property
    def adding(self) -> bool:
        """Keyframes are added (``build_map`` and not paused by the ``mapping`` service).
        Otherwise images a keyframe apart are still relocalized as probes: they anchor the
        map frame and keep checking ``map_from_odom`` (localization on a fixed map)."""
        return self.enabled and bool(self.node.conf.build_map)

    # -- candidates (the bridge's worker) ------------------------------------------------------
    def consider(self, image: Any, odom_from_body: Array, ros_covariance: Array | None) -> None:
        """An image paired with the odometry of its stamp: maybe a keyframe (see module)."""
        odom_from_cam = odom_from_body @ self.node.body_from_cam
        epoch, estimate = self.frame.current()
        if estimate is not None:
            self._republish_tf(image.stamp, estimate)
        if self.node.lost:
            self.count("paused_lost")
            return
        if not self._map_can_relocalize():
            if self.adding and self.frame.defining and estimate is not None:
                self._add_if_new(image, odom_from_body, ros_covariance, estimate)
            else:   # a new session on a map that cannot check it: nothing may be added
                self.count("refused_cannot_check" if self.adding else "paused")
            return
        if not self.adding:
            self.count("paused")   # probes still check the map frame; nothing is added
        with self._lock:
            self._refresh_depths()
            if estimate is not None and self.adding:
                world_from_cam = estimate.map_from_odom @ odom_from_cam
                known = self._known()
                if not self.rule.is_new(world_from_cam, known):
                    return
                candidate = Candidate(image, odom_from_body, ros_covariance, epoch,
                                      world_from_cam, self.rule.nearest_depth(world_from_cam,
                                                                              known))
            else:   # probes: anchor a new session; not adding, keep checking the frame
                session = self.frame.session
                if self._probe_session != session:
                    self._probes, self._probe_session = [], session
                if not self.rule.is_new(odom_from_cam, self._probes):
                    return
                self._probes = [*self._probes[-(PENDING_CANDIDATES - 1):], (odom_from_cam, None)]
                candidate = Candidate(image, odom_from_body, ros_covariance, epoch, None, None)
            self._queue.append(candidate)
        self._pump()

    def _known(self) -> list[tuple[Array, float | None]]:
        """Keyframes and the candidates that may become one (their predicted poses)."""
        waiting = [(c.world_from_cam, c.depth_m) for c in [self._in_flight, *self._queue]
                   if c is not None and c.world_from_cam is not None]
        return [*self.keyframes.values(), *waiting]

    def _map_can_relocalize(self) -> bool:
        """The map holds ``anchor_min_keyframes`` keyframes and landmarks (remembered once
        true). Whether its methods are trained is not asked: a chain answers with the steps
        that are, and a map that cannot answer refuses candidates, which is safe."""
        if not self._can_relocalize:
            rt = self.node.bridge.host.maps.get(self.node.map_name)
            if rt is not None:
                state = rt.map_state()
                self._can_relocalize = (
                    len(state.keyframes) >= self.node.conf.anchor_min_keyframes
                    and len(state.landmarks) > 0)
        return self._can_relocalize

    def _refresh_depths(self) -> None:
        """Scene depths of keyframes that had none (their map points come with later ones)."""
        rt = self.node.bridge.host.maps.get(self.node.map_name)
        if rt is None:
            return
        state = rt.map_state()
        if state.version == self._depth_version:
            return
        self._depth_version = state.version
        for kf_id, (pose, depth) in list(self.keyframes.items()):
            if depth is None and kf_id in state.keyframes:
                self.keyframes[kf_id] = (pose, median_scene_depth(state.keyframes[kf_id]))

    def _pump(self) -> None:
        """Relocalize the next candidate of the current odometry, one at a time."""
        with self._lock:
            if self._in_flight is not None:
                return
            epoch = self.frame.epoch
            while self._queue and self._queue[0].epoch != epoch:
                self._queue.popleft()
                self.count("stale_candidates")
            if not self._queue:
                return
            candidate = self._in_flight = self._queue.popleft()
        pool = self.node.bridge.host.relocalize_pool
        if pool is None or not pool.submit(lambda queued: self._check(candidate, queued)):
            self.count("busy")
            with self._lock:
                self._in_flight = None

    # -- checking a candidate (a relocalize worker) --------------------------------------------
    def _check(self, candidate: Candidate, queued_s: float) -> None:
        try:
            self._wait_for_map()
            self._decide(candidate, self._relocalize(candidate, queued_s))
        except Exception as exc:   # a candidate never stops mapping
            self.count("errors")
            self.node.status.keyframe_refused(None, stamp_text(candidate.image.stamp),
                                              f"the candidate could not be checked: {exc}")
        finally:
            with self._lock:
                self._in_flight = None
            self._pump()

    def _wait_for_map(self) -> None:
        """Until the map holds the last keyframe put (relocalized against the map as built);
        a keyframe the writer refused (a quota) is waited for once, not by every candidate."""
        rt = self.node.bridge.host.maps.get(self.node.map_name)
        last = self._last_put
        if rt is None or last is None or last == self._waited_for:
            return
        deadline = time.monotonic() + MAP_CATCH_UP_S
        while last not in rt.map_state().keyframes and time.monotonic() < deadline:
            time.sleep(0.01)
        self._waited_for = last

    def _relocalize(self, candidate: Candidate, queued_s: float) -> tuple[Array, Array] | str:
        """(map_from_cam, its covariance) or why not."""
        host = self.node.bridge.host
        rt = host.maps.get(self.node.map_name)
        if rt is None:
            return f"map {self.node.map_name!r} is not served"
        request = wire.RelocalizeRequest(image=candidate.image.image, camera_id=self.camera_id,
                                         timestamp=convert.stamp_seconds(candidate.image.stamp))
        reply = wire.RelocalizeReply.decode(host.relocalize_payload(rt, request.encode(),
                                                                    queued_s), rt.limits)
        if reply.status is not wire.ReplyStatus.OK or reply.world_from_cam is None:
            return reply.reason or reply.status.value
        if reply.covariance is None:
            return "relocalized without a covariance: its agreement cannot be tested"
        return reply.world_from_cam.matrix(), np.reshape(reply.covariance, (6, 6))

    def _decide(self, candidate: Candidate, answer: tuple[Array, Array] | str) -> None:
        if isinstance(answer, str):
            self.count("refused_not_relocalized")
            self.node.status.keyframe_refused(None, stamp_text(candidate.image.stamp),
                                              f"the candidate did not relocalize ({answer})")
            return
        verdict, estimate = self._judge(candidate, answer)
        if verdict in (Verdict.AGREES, Verdict.ANCHORED) and estimate is not None:
            if self.adding:
                self._add_if_new(candidate.image, candidate.odom_from_body,
                                 candidate.ros_covariance, estimate)
        elif verdict is Verdict.DISAGREES:
            self.count("refused_disagrees")
            self.node.status.keyframe_refused(
                None, stamp_text(candidate.image.stamp),
                "its relocalization disagrees with its odometry through map_from_odom (a VIO "
                "reset or drift): mapping stops until the new session is anchored")

    def _judge(self, candidate: Candidate, answer: tuple[Array, Array]
               ) -> tuple[Verdict, Sample | None]:
        """The relocalization ``answer`` of ``candidate``'s image as a ``map_from_odom``
        sample: its verdict and the estimate after it (``map -> odom`` published when the
        sample agrees or anchors)."""
        map_from_cam, covariance_map = answer
        odom_from_cam = candidate.odom_from_body @ self.node.body_from_cam
        covariance_odom = self._odometry_covariance(candidate, odom_from_cam)
        sample = sample_of(map_from_cam, covariance_map, odom_from_cam,
                           np.zeros((6, 6)) if covariance_odom is None else covariance_odom)
        verdict = self.frame.add_sample(sample, candidate.epoch)
        self.count(f"samples_{verdict.value}")
        _, estimate = self.frame.current()
        if verdict in (Verdict.AGREES, Verdict.ANCHORED) and estimate is not None:
            self.publish_tf(candidate.image.stamp, estimate)
        return verdict, estimate

    def observe(self, image: Any, odom_from_body: Array, ros_covariance: Array | None,
                map_from_cam: Array, covariance_map: Array) -> Verdict:
        """A relocalization that was not a candidate's (a Trigger call, the lost mode) as one
        more ``map_from_odom`` sample: a hovering drone anchors and re-anchors without moving
        a keyframe apart. Never adds a keyframe."""
        epoch, _ = self.frame.current()
        candidate = Candidate(image, odom_from_body, ros_covariance, epoch, None, None)
        verdict, _ = self._judge(candidate, (map_from_cam, covariance_map))
        return verdict

    def camera_covariance(self, ros_covariance: Array | None, odom_from_body: Array,
                          estimate: Sample) -> Array | None:
        """Our covariance of ``map_from_odom @ odom_from_body @ body_from_cam``: the
        odometry's (or the map's default) plus ``map_from_odom``'s; None when neither the
        odometry nor the map gives one."""
        odom_from_cam = odom_from_body @ self.node.body_from_cam
        values = self._keyframe_covariance(ros_covariance, odom_from_cam, odom_from_body,
                                           estimate)
        return None if values is None else np.reshape(values, (6, 6))

    def _odometry_covariance(self, candidate: Candidate, odom_from_cam: Array) -> Array | None:
        """The odometry's covariance of the camera (ours), else the map's default keyframe
        covariance (what a keyframe from this odometry would be taken to have)."""
        if candidate.ros_covariance is not None:
            try:
                ours = convert.odometry_covariance(candidate.ros_covariance, odom_from_cam,
                                                   candidate.odom_from_body)
                if ours is not None:
                    return ours
            except ValueError:
                pass   # counted when the keyframe is put
        rt = self.node.bridge.host.maps.get(self.node.map_name)
        return None if rt is None else rt.map_state().default_pose_covariance

    # -- adding --------------------------------------------------------------------------------
    def _add_if_new(self, image: Any, odom_from_body: Array, ros_covariance: Array | None,
                    estimate: Sample) -> None:
        """Put the image as a keyframe in the map frame if the rule still selects it."""
        odom_from_cam = odom_from_body @ self.node.body_from_cam
        world_from_cam = estimate.map_from_odom @ odom_from_cam
        with self._lock:
            self._refresh_depths()
            if not self.rule.is_new(world_from_cam, list(self.keyframes.values())):
                return
            covariance = self._keyframe_covariance(ros_covariance, odom_from_cam,
                                                   odom_from_body, estimate)
            kf_id = self.node.put_keyframe(image, world_from_cam, covariance)
            self.keyframes[kf_id] = (world_from_cam, None)
            self._last_put = kf_id
            self.counts["added"] += 1
        # "added" is logged once the map applied it (diagnostics.KeyframeReports)
        log.debug("map %s: keyframe %d put at %.3f s (%s session %d)", self.node.map_name,
                 kf_id, convert.stamp_seconds(image.stamp), self.frame.state.value,
                 self.frame.session)

    def _keyframe_covariance(self, ros_covariance: Array | None, odom_from_cam: Array,
                             odom_from_body: Array, estimate: Sample
                             ) -> tuple[float, ...] | None:
        """The odometry's covariance of the camera plus ``map_from_odom``'s seen from the
        camera (a right perturbation of ``map_from_odom`` moves the camera by
        ``Ad(cam_from_odom) xi``); None: the map's default applies."""
        odometry = self.node.keyframe_covariance(ros_covariance, odom_from_cam, odom_from_body)
        if not np.any(estimate.covariance):
            return odometry
        rt = self.node.bridge.host.maps.get(self.node.map_name)
        default = None if rt is None else rt.map_state().default_pose_covariance
        base = (np.reshape(odometry, (6, 6)) if odometry is not None
                else np.zeros((6, 6)) if default is None else default)
        adjoint = se3_adjoint(invert(odom_from_cam))
        total = base + adjoint @ estimate.covariance @ adjoint.T
        return tuple(float(v) for v in (0.5 * (total + total.T)).ravel())

    # -- /tf -----------------------------------------------------------------------------------
    def _republish_tf(self, stamp: Any, estimate: Sample) -> None:
        period = self.node.conf.tf_period_s
        if period and convert.stamp_seconds(stamp) - self._tf_last_stamp >= period:
            self.publish_tf(stamp, estimate)

    def publish_tf(self, stamp: Any, estimate: Sample) -> None:
        """``map -> odom`` (parent the map's frame id, child the odometry's) at ``stamp``."""
        if self._tf is None:
            return
        child = self.node.conf.odom_frame_id or self.frame.odom_frame_id or "odom"
        msg = tf_message(stamp, self.node.conf.frame_id, child, estimate.map_from_odom)
        attachment = graph.Attachment(next(self._tf_seq), time.time_ns(), self._tf_gid)
        self._tf.put(ros.encode(msg, ros.TF_MESSAGE), attachment=attachment.encode())
        self._tf_last_stamp = convert.stamp_seconds(stamp)
        self.count("tf_published")

    # -- the mapping service (a Zenoh callback: quick) ----------------------------------------
    def on_request(self, query: zenoh.Query) -> None:
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        try:
            request = graph.Attachment.decode(attachment)
            data = ros.decode(query.payload.to_bytes() if query.payload is not None else b"",
                              "std_srvs/srv/SetBool_Request").data
        except ValueError as exc:
            self.count("dropped_requests")
            log.warning("map %s: dropping a mapping request: %s", self.node.map_name, exc)
            query.drop()
            return
        self.enabled = bool(data)
        message = (f"mapping {'resumed' if data else 'paused'}; map frame "
                   f"{self.frame.state.value}, {len(self.keyframes)} keyframes")
        log.info("map %s: %s (std_srvs/SetBool)", self.node.map_name, message)
        response = ros.message("std_srvs/srv/SetBool_Response", success=True, message=message)
        reply = graph.Attachment(request.sequence_number, time.time_ns(), request.gid)
        try:
            query.reply(self.service_key,
                        ros.encode(response, "std_srvs/srv/SetBool_Response"),
                        attachment=reply.encode())
        except Exception as exc:   # the client may have gone
            log.debug("mapping reply not sent: %s", exc)
        finally:
            query.drop()


def tf_message(stamp: Any, parent: str, child: str, parent_from_child: Array) -> Any:
    """A tf2_msgs/TFMessage holding one transform (its pose of ``child`` in ``parent``)."""
    m = ros.message
    t = parent_from_child[:3, 3]
    q = matrix_to_quat_xyzw(parent_from_child[:3, :3])
    transform = m("geometry_msgs/msg/Transform",
                  translation=m("geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]),
                                z=float(t[2])),
                  rotation=m("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]),
                             z=float(q[2]), w=float(q[3])))
    stamped = m("geometry_msgs/msg/TransformStamped",
                header=m("std_msgs/msg/Header", stamp=stamp, frame_id=parent),
                child_frame_id=child, transform=transform)
    return m(ros.TF_MESSAGE, transforms=[stamped])
