"""The trivial pose finder: the best candidate keyframe's pose, unchanged (thesis 4, fig. 4.3)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

from ...core.frame import Frame, ThumbnailConf
from ...core.map import MapState
from ...core.numeric import zncc
from ..place.base import PlaceCandidate
from .base import PoseEstimate, PoseFinder, register


@register("none")
class KeyframePoseFinder(PoseFinder):
    """Answers the best candidate keyframe's ``world_from_cam``; the evidence for verification
    is the NCC of the query's and the keyframe's small blurry images."""

    needs_agreement: ClassVar[bool] = True

    @dataclass(frozen=True)
    class Conf(ThumbnailConf):
        pass

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        """The first candidate still in ``state``, with its thumbnail NCC; None if none is."""
        start = time.perf_counter()
        keyframe = next((state.keyframes[c.keyframe_id] for c in candidates
                         if c.keyframe_id in state.keyframes), None)
        if keyframe is None:
            return None
        c = self.conf
        # One candidate, no ranking: a flat thumbnail is reported as uncorrelated (0).
        ncc = zncc(query.small_blurry_image(c.width, c.height, c.blur_sigma),
                   keyframe.small_blurry_image(c.width, c.height, c.blur_sigma))
        return PoseEstimate(world_from_cam=keyframe.world_from_cam.copy(),
                            keyframe_ids=[keyframe.id], ncc=ncc,
                            timings={"pose": time.perf_counter() - start})
