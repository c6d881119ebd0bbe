"""One served map (:class:`MapRuntime`): its engine front, camera registry, change ordering
(deferral during a snapshot), training jobs, counters and events, and its status.

What is written to disk and how it is restored is :mod:`.durability`'s (a :class:`MapStore`
per map directory); the runtime decides when: every accepted put is journaled before it is
applied, a snapshot runs in the background while the puts arriving meanwhile are journaled
at once and applied after the save (so queries are never held up by it), and training and
snapshots never overlap.
"""

from __future__ import annotations

import time

from reloc_client import protocol as wire

from .runtime_state import ACK_KINDS, Publish, Replicas, Stats, TrainingJob
from .training_jobs import MapTraining

__all__ = ["ACK_KINDS", "MapRuntime", "Publish", "Replicas", "Stats", "TrainingJob"]


class MapRuntime(MapTraining):
    """Everything the service holds for map ``name`` (see module docstring); its query face
    (engine, cameras, methods) is the :class:`~.served.ServedMap` a worker's replica shares.

    Map changes (:meth:`put_keyframe` etc.) come from the map's writer thread; queries
    (:meth:`relocalize`, :meth:`map_state`, :meth:`status`) from any worker thread.

    Its parts, each a class built on the one before, in a module of its own: the state and
    locks they share (:mod:`.runtime_state`), the write path (:mod:`.map_changes`), the
    restore and journal replay (:mod:`.journal_replay`), snapshots and close
    (:mod:`.map_snapshots`), training jobs (:mod:`.training_jobs`); its status is here."""

    def status(self, *, content_hash: bool = False) -> wire.StatusReply:
        """The map's status; with ``content_hash``, its content hash too (computed on demand:
        the first time, each keyframe's pixels are read)."""
        st = self.engine.status()
        counters, latency = self.stats.snapshot()
        counters["quota_bytes"] = self.usage.total   # what the map counts against [quotas]
        with self._job_lock:
            training = self._job is not None
        return wire.StatusReply(
            map=self.name, instance=self.instance, keyframes=st["keyframes"],
            landmarks=st["landmarks"],
            trained=all(m["trained"] for m in st["methods"].values()),
            map_version=st["map_version"], methods=self.methods,
            default_method=self.default_method, cameras=tuple(self.camera_ids()),
            training=training, uptime_s=time.monotonic() - self.started_at,
            counters={**counters, **self._replay_progress()}, latency_s=latency,
            degraded=self.degraded(), replaying=self.replaying, map_id=self.map_id or "",
            content_hash=self.content.of(self.map_state()) if content_hash else "",
            diverged=self.diverged, calibration_sigma=self.calibration_sigma,
            keyframe_pose_sigma=st["keyframe_pose_sigma"] or {})
