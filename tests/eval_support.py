"""What the evaluation tests share: a small pinhole camera, poses along a corridor, an answer."""

import numpy as np

from reloc_service.algorithms.relocalizers.base import RelocResult, RelocStatus
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.geometry import look_at

CAMERA = PinholeCamera(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)


def pose_at(x: float, y: float = 0.0) -> np.ndarray:
    return look_at((x, y, 1.0), (x, 3.0, 1.0))


def ok_result(world_from_cam, **kw) -> RelocResult:
    return RelocResult(status=RelocStatus.OK, method=kw.pop("method", "fake"),
                       world_from_cam=world_from_cam, **kw)
