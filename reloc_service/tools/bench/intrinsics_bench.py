"""Micro-benchmark of the intrinsics test (:func:`.intrinsics.check_intrinsics`, run by
``reloc bench``): wall and CPU time of one test on the correspondences of a PnP pose, per
correspondence count, for a query with the given focal and one with a focal 8 % off, each
with one BLAS thread and with one per core.

The correspondences are synthetic and seeded: pixels of a distorted 640x480 camera (TUM
fr1's calibration) over the whole image, points 1.5 to 6 m deep, 1 px noise and 30 %
outliers anywhere in the image, as ORB matches of a room give. Nothing here is a test.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from ...algorithms.pose.intrinsics import IntrinsicsCheck
from ...algorithms.pose.pnp import solve_pnp_indexed
from ...algorithms.pose.pnp_conf import PnPConf
from ...core.cameras import RadTanCamera
from ...core.geometry import look_at, transform_points

CAMERA = RadTanCamera(640, 480, 517.306408, 516.469215, 318.64304, 255.313989,
                      (0.262383, -0.953104, -0.005358, 0.002628, 1.163314))
WORLD_FROM_CAM = look_at([0.4, -0.3, -4.0], [0.1, 0.2, 0.0], up=[0, -1, 0])

#: Correspondence counts timed (a query's PnP correspondences are a few hundred).
SIZES = (100, 300, 1000)
#: Focal of the camera that took the query over the given one.
FOCAL_SCALES = (1.0, 1.08)


def _test_of(n: int, focal_scale: float, seed: int) -> Any:
    """The intrinsics test (a zero-argument callable) of the PnP pose of ``n`` synthetic
    correspondences seen by a camera with ``focal_scale`` times the given focal."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([0.0, 0.0], [CAMERA.width - 1.0, CAMERA.height - 1.0], (n, 2))
    bearings = CAMERA.unproject(px)
    points_world = transform_points(
        WORLD_FROM_CAM, bearings / bearings[:, 2:] * rng.uniform(1.5, 6.0, n)[:, None])
    centre = np.array([CAMERA.cx, CAMERA.cy])
    px = centre + focal_scale * (px - centre) + rng.normal(0.0, 1.0, (n, 2))
    outliers = rng.random(n) < 0.3
    px[outliers] = rng.uniform([0.0, 0.0], [CAMERA.width - 1.0, CAMERA.height - 1.0],
                               (int(outliers.sum()), 2))
    solved = solve_pnp_indexed(px, points_world, CAMERA, PnPConf())
    if solved is None or solved[0].intrinsics_test is None:
        raise RuntimeError(f"intrinsics bench: no PnP pose on {n} correspondences")
    return solved[0].intrinsics_test


def _timed(test: Any, repeats: int) -> dict[str, Any]:
    """p50 / p90 wall and CPU milliseconds of ``repeats`` runs of ``test`` (after one to
    load any compiled kernel), and what the last one found."""
    check: IntrinsicsCheck | None = test()
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        check = test()
        cpu.append(1e3 * (time.process_time() - c))
        wall.append(1e3 * (time.perf_counter() - w))
    return {"p50_ms": float(np.median(wall)), "p90_ms": float(np.percentile(wall, 90)),
            "cpu_p50_ms": float(np.median(cpu)), "repeats": repeats,
            "solutions": None if check is None else len(check.solutions),
            "passed": None if check is None else bool(check.passed)}


def run(*, repeats: int = 30) -> dict[str, Any]:
    """Per correspondence count and query focal, the test's times with one BLAS thread and
    with one per core (OpenBLAS's default; the limits in force are restored afterwards)."""
    from threadpoolctl import threadpool_limits

    cores = os.cpu_count() or 1

    rows = []
    for n in SIZES:
        for scale in FOCAL_SCALES:
            test = _test_of(n, scale, seed=n)
            row: dict[str, Any] = {"correspondences": n, "focal_scale": scale}
            with threadpool_limits(limits=1, user_api="blas"):
                row["one_blas_thread"] = _timed(test, repeats)
            with threadpool_limits(limits=cores, user_api="blas"):
                row["blas_threads_per_core"] = _timed(test, repeats)
            rows.append(row)
    return {"camera": "radtan 640x480 (TUM fr1)", "outlier_share": 0.3, "noise_px": 1.0,
            "cores": cores, "rows": rows}
