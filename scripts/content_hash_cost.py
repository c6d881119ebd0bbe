"""The cost of a map's content hash (status ``content_hash``): the first computation over N
VGA keyframes (each keyframe's pixels checksummed) and a repeat on the unchanged map (cached).

    .venv/bin/python scripts/content_hash_cost.py
"""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Keyframe
from reloc_service.service.map_digest import ContentDigest

VGA = PinholeCamera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)


def main() -> None:
    rng = np.random.default_rng(0)
    for n in (100, 1000):
        keyframes = {i: Keyframe(image=rng.integers(0, 255, (480, 640), dtype=np.uint8),
                                 camera=VGA, id=i, world_from_cam=np.eye(4),
                                 timestamp=float(i)) for i in range(n)}
        state = SimpleNamespace(keyframes=keyframes)
        digest = ContentDigest()
        start = time.perf_counter()
        digest.of(state)   # type: ignore[arg-type]
        first = time.perf_counter() - start
        start = time.perf_counter()
        digest.of(state)   # type: ignore[arg-type]
        again = time.perf_counter() - start
        print(f"{n} VGA keyframes: first {first * 1e3:.1f} ms, cached {again * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
