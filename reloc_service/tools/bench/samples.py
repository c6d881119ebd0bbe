"""Measurement primitives of ``reloc bench``: query sets as the drone sends them (JPEG
bytes and ground truth), a query as the service runs it in-process, and the statistics every
section reports (percentiles, stage medians, recall, strict-JSON values)."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...algorithms.relocalizers.base import RelocResult
from ...core.cameras import Camera, camera_from_dict
from ...core.frame import Frame
from ...core.geometry import pose_error
from ...engine import Engine
from ..eval import metrics

Array = npt.NDArray[np.float64]

JPEG_QUALITY = 90


# -- queries -----------------------------------------------------------------------------------

@dataclass(eq=False)
class QuerySet:
    """Query images as the drone sends them (JPEG bytes), their ground-truth
    ``world_from_cam`` and the camera."""

    camera: Camera
    jpegs: list[bytes]
    gts: list[Array]

    def __len__(self) -> int:
        return len(self.jpegs)

    @classmethod
    def from_images(cls, camera: Camera, images: Sequence[npt.NDArray[np.uint8]],
                    gts: Sequence[Array], quality: int = JPEG_QUALITY) -> QuerySet:
        jpegs = []
        for image in images:
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if not ok:
                raise ValueError("JPEG encoding failed")
            jpegs.append(buf.tobytes())
        return cls(camera, jpegs, [np.asarray(g, np.float64) for g in gts])

    def save(self, directory: Path) -> Path:
        """Write ``camera.json``, ``gt.npy`` and ``NNNN.jpg`` into ``directory``."""
        import json

        directory.mkdir(parents=True, exist_ok=True)
        (directory / "camera.json").write_text(json.dumps(self.camera.to_dict()))
        np.save(directory / "gt.npy", np.stack(self.gts))
        for i, jpeg in enumerate(self.jpegs):
            (directory / f"{i:04d}.jpg").write_bytes(jpeg)
        return directory

    @classmethod
    def load(cls, directory: Path) -> QuerySet:
        import json

        camera = camera_from_dict(json.loads((directory / "camera.json").read_text()))
        gts = list(np.load(directory / "gt.npy"))
        jpegs = [(directory / f"{i:04d}.jpg").read_bytes() for i in range(len(gts))]
        return cls(camera, jpegs, gts)


def random_texture_jpeg(width: int, height: int, seed: int = 0) -> bytes:
    """A JPEG of random texture, blurred noise at a few scales: an image of no map's scene,
    which the default method runs through all its steps (full-size SIFT included) and
    refuses, so the costliest query of that size."""
    rng = np.random.default_rng(seed)
    image = np.zeros((height, width), np.float32)
    for sigma in (1.0, 3.0, 9.0):
        image += cv2.GaussianBlur(rng.random((height, width), np.float32), (0, 0), sigma)
    image = (255 * (image - image.min()) / np.ptp(image)).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("could not encode the texture as JPEG")
    return bytes(jpeg.tobytes())


def decode_jpeg(jpeg: bytes) -> npt.NDArray[np.uint8]:
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError("query does not decode")
    return np.asarray(image, np.uint8)


def relocalize_jpeg(engine: Engine, jpeg: bytes, camera: Camera, method: str) -> RelocResult:
    """What the service does with a query, in-process: decode, Frame, ``Engine.relocalize``.
    ``timings`` gains ``decode`` and ``wall`` (the whole, seconds)."""
    start = time.perf_counter()
    image = decode_jpeg(jpeg)
    decoded = time.perf_counter()
    result = engine.relocalize(Frame(image, camera), method=method)
    result.timings["decode"] = decoded - start
    result.timings["wall"] = time.perf_counter() - start
    return result


# -- statistics --------------------------------------------------------------------------------

def pct_ms(seconds: Sequence[float], q: float) -> float:
    """The ``q``-th percentile of ``seconds`` in milliseconds (NaN for no value)."""
    values = [s for s in seconds if s is not None and math.isfinite(s)]
    return 1e3 * float(np.percentile(values, q)) if values else math.nan


def stage_medians_ms(timings: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Median milliseconds of every stage over ``timings`` (a missing stage counts 0)."""
    stages = sorted({k for t in timings for k in t})
    return {k: 1e3 * float(np.median([t.get(k, 0.0) for t in timings])) for k in stages}


def accuracy(poses: Sequence[Array | None], gts: Sequence[Array]) -> dict[str, Any]:
    """Recall at the eval thresholds, the rate of returned poses and of wrong ones."""
    t = np.full(len(poses), np.nan)
    r = np.full(len(poses), np.nan)
    ok = np.array([p is not None for p in poses], bool)
    for i, (pose, gt) in enumerate(zip(poses, gts, strict=True)):
        if pose is not None:
            dt, dr = pose_error(pose, gt)
            t[i], r[i] = dt, math.degrees(dr)
    return {"recall": metrics.recalls(t, r, ok), "returned_rate": float(ok.mean()) if len(ok)
            else math.nan, "wrong_rate": metrics.wrong_rate(t, r, ok),
            "median_t_err_m": float(np.nanmedian(t)) if ok.any() else math.nan}


def summarize_samples(samples: Sequence[tuple[int, RelocResult]], queries: QuerySet
                      ) -> dict[str, Any]:
    """p50/p99 of the whole (``wall``), stage medians and accuracy of (query index, result)
    samples from :func:`relocalize_jpeg`."""
    walls = [r.timings["wall"] for _, r in samples]
    return {"samples": len(samples), "p50_ms": pct_ms(walls, 50), "p99_ms": pct_ms(walls, 99),
            "mean_ms": 1e3 * float(np.mean(walls)) if walls else math.nan,
            "stages_ms": stage_medians_ms([r.timings for _, r in samples]),
            **accuracy([r.world_from_cam if r.ok else None for _, r in samples],
                       [queries.gts[i] for i, _ in samples])}


def summarize_plain(samples: Sequence[tuple[int, Any]], queries: QuerySet) -> dict[str, Any]:
    """As :func:`summarize_samples`, for :class:`~.peers.PlainResult` samples."""
    walls = [sum(r.timings.values()) for _, r in samples]
    return {"samples": len(samples), "p50_ms": pct_ms(walls, 50), "p99_ms": pct_ms(walls, 99),
            "stages_ms": stage_medians_ms([r.timings for _, r in samples]),
            "matches_median": float(np.median([r.matches for _, r in samples])) if samples
            else math.nan,
            **accuracy([r.world_from_cam for _, r in samples],
                       [queries.gts[i] for i, _ in samples])}


