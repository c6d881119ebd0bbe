"""The camera each query claims: the dataset's, or one made deliberately wrong (its focal
scaled, its radial ``k1`` replaced) while the images stay as taken, as a stale calibration
would send them: what the relocalizers' intrinsics test (:mod:`reloc_service.algorithms.pose.intrinsics`)
is measured against."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ...core.cameras import Camera, RadTanCamera
from ...core.errors import ConfigError


@dataclass(frozen=True)
class QueryCamera:
    """How a query's claimed camera differs from the one that took it: ``focal_scale`` times
    its ``fx`` and ``fy``; ``k1`` (when not None) as its first radial coefficient (a pinhole
    camera then claims to be radtan with that ``k1`` alone)."""

    focal_scale: float = 1.0
    k1: float | None = None

    def __post_init__(self) -> None:
        if not self.focal_scale > 0:
            raise ConfigError(f"query focal scale must be positive, got {self.focal_scale}")

    @property
    def unchanged(self) -> bool:
        return self.focal_scale == 1.0 and self.k1 is None

    def claimed(self, camera: Camera) -> Camera:
        """The camera a query taken with ``camera`` claims."""
        out = dataclasses.replace(camera, fx=camera.fx * self.focal_scale,
                                  fy=camera.fy * self.focal_scale)
        if self.k1 is None:
            return out
        if isinstance(out, RadTanCamera):
            return dataclasses.replace(out, distortion=(self.k1, *out.distortion[1:]))
        if out.model != "pinhole":
            raise ConfigError(f"query k1: the {out.model} camera has no radtan k1")
        return RadTanCamera(out.width, out.height, out.fx, out.fy, out.cx, out.cy,
                            (self.k1, 0.0, 0.0, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {"focal_scale": self.focal_scale, "k1": self.k1}
