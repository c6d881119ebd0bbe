"""The in-process backend of ``reloc eval``: an :class:`~reloc_service.engine.Engine` in this
process, its queries answered as a service worker answers them (:func:`as_a_service_worker`)."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np
import numpy.typing as npt

from ...algorithms.relocalizers.base import RelocResult
from ...core.cameras import Camera
from ...core.frame import Frame
from ..data.dataset import Dataset
from .backends import LandmarkSource

Array = npt.NDArray[np.float64]


@contextmanager
def as_a_service_worker() -> Iterator[None]:
    """Queries answered in this process run as a service worker runs them: one OpenCV
    thread and one BLAS thread (restored after). So the latencies are the service's, and a
    query's helper thread (:mod:`~reloc_service.algorithms.relocalizers.overlap`) finds the idle core
    it would find there, not one taken by a BLAS thread spinning after a product."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
    finally:
        cv2.setNumThreads(before)


class InProcessBackend:
    """An :class:`~reloc_service.engine.Engine` in this process, created in evaluation mode
    (so the ground-truth ``gt`` place finder is allowed)."""

    description = "in-process"

    def __init__(self, methods: Sequence[str], options: Mapping[str, Any],
                 landmark_source: LandmarkSource) -> None:
        from ...core.plugins import make_conf
        from ...engine import Engine
        from ...service.config import ServiceSection

        #: ``options["service"]``: the service settings a round trip saves with (its
        #: ``stored_parts``), e.g. ``keyframe_descriptors``; default: the service's defaults.
        #: Checked here, before a map is built: a ConfigError names a key unknown or wrong.
        self._service = make_conf(ServiceSection, dict(options.get("service") or {}),
                                  owner="options: [service]")
        self.engine = Engine(engine_conf(methods, options, landmark_source))
        self._snapshot_dir: tempfile.TemporaryDirectory[str] | None = None

    def add_keyframe(self, kf_id: int, image: npt.NDArray[np.uint8], camera: Camera,
                     world_from_cam: Array, *, depth: npt.NDArray[np.float32] | None,
                     pose_covariance: Array | None = None) -> None:
        self.engine.add_keyframe(kf_id, image, camera, world_from_cam, depth=depth,
                                 pose_covariance=pose_covariance)

    def train(self, *, progress: bool) -> None:
        self.engine.train(progress=progress)

    def round_trip(self) -> None:
        """Save the map and its trained models as a service's snapshot stores them by default,
        or as the ``[service]`` options given say
        (:meth:`~reloc_service.service.config.ServiceSection.stored_parts`), and go on with the
        engine loaded from it (its files stay until :meth:`close`: it reads them lazily)."""
        from ...engine import Engine

        self._snapshot_dir = tempfile.TemporaryDirectory(prefix="reloc-eval-")
        self.engine.save(self._snapshot_dir.name, parts=self._service.stored_parts())
        self.engine = Engine.load(self._snapshot_dir.name, self.engine.conf)

    def relocalize(self, image: npt.NDArray[np.uint8], camera: Camera, *, method: str,
                   gt_world_from_cam: Array) -> RelocResult:
        return self.engine.relocalize(Frame(image, camera, gt_world_from_cam=gt_world_from_cam),
                                      method=method)

    def map_counts(self) -> tuple[int, int]:
        state = self.engine.map.snapshot()
        return len(state.keyframes), len(state.landmarks)

    def keyframe_pose_sigma(self) -> dict[str, Any] | None:
        """The keyframe pose uncertainty the map measured of itself (None: none measured)."""
        measured = self.engine.keyframe_pose_sigma
        return None if measured is None else measured.as_dict()

    def landmarks_per_keyframe(self) -> list[int]:
        """Distinct landmarks each keyframe observes (any feature kind), in id order."""
        state = self.engine.map.snapshot()
        return [len(np.unique(np.concatenate([f.landmark_ids[f.landmark_ids >= 0]
                                              for f in state.keyframes[k].features.values()]
                                             or [np.zeros(0, np.int64)])))
                for k in state.keyframe_ids()]

    def landmark_errors_m(self, dataset: Dataset) -> Array | None:
        try:
            from ...core.mapping import landmark_errors
        except ImportError:
            return None
        errors = landmark_errors(self.engine.map.snapshot(), dataset)  # type: ignore[arg-type]
        return np.asarray(errors, dtype=np.float64)

    def close(self) -> None:
        """Close the engine and stop the queries' helper threads: a step a chain started
        ahead for the last query may still run inside OpenCV, and must end before the
        interpreter does (:func:`~reloc_service.algorithms.relocalizers.overlap.close_helpers`)."""
        from ...algorithms.relocalizers.overlap import close_helpers

        close = getattr(self.engine, "close", None)
        if close is not None:
            close()
        close_helpers()
        if self._snapshot_dir is not None:
            self._snapshot_dir.cleanup()


def engine_conf(methods: Sequence[str], options: Mapping[str, Any],
                landmark_source: LandmarkSource) -> Any:
    """The :class:`~reloc_service.engine.EngineConf` for ``methods``; ``options["mapping"]``
    (if any) configures the map building, ``options["service"]`` a round trip's snapshot
    (:meth:`InProcessBackend.round_trip`), the other keys are plugin options."""
    from ...engine import EngineConf, MappingConf

    plugin_options = {k: v for k, v in options.items() if k not in ("mapping", "service")}
    mapping = MappingConf.from_options(options.get("mapping"))
    return EngineConf(methods=tuple(methods), options=plugin_options, mapping=mapping)
