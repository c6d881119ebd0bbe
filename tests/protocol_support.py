"""Messages and encoded images the protocol tests share (tests/test_protocol*.py)."""

from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from reloc_client import protocol as P

ROOT = Path(__file__).resolve().parents[1]


def random_pose(rng: np.random.Generator) -> P.WirePose:
    q = rng.normal(size=4)
    return P.WirePose.from_tq(rng.normal(size=3).tolist(), (q / np.linalg.norm(q)).tolist())


CAMERA = P.WireCamera("radtan", 8, 6, 5.0, 5.5, 3.5, 2.5, (0.1, -0.01, 0.001, 0.002))
IMAGE = P.WireImage(P.ImageFormat.MONO8, 8, 6, bytes(range(48)))


def png_bytes(width: int = 8, height: int = 6, dtype=np.uint8) -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros((height, width), dtype))
    assert ok
    return buf.tobytes()


def jpeg_bytes(width: int = 8, height: int = 6, progressive: bool = False) -> bytes:
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    ok, buf = cv2.imencode(".jpg", np.full((height, width, 3), 128, np.uint8), params)
    assert ok
    return buf.tobytes()


def features(rng: np.random.Generator, n: int = 5) -> P.WireFeatures:
    pts = rng.normal(size=(n, 3))
    pts[1] = np.nan
    ids = np.arange(n) * 3
    ids[1] = -1
    return P.WireFeatures(rng.uniform(0, 8, size=(n, 2)), ids, pts)


def pose_covariance(rng: np.random.Generator) -> tuple[float, ...]:
    """A full-rank 6x6 pose covariance, 36 row-major floats (cm and tenths of a degree)."""
    a = rng.normal(size=(6, 6)) * np.array([0.01, 0.02, 0.01, 0.003, 0.002, 0.004])[:, None]
    c = a @ a.T
    return tuple(float(v) for v in (0.5 * (c + c.T)).ravel())


POSE_COVARIANCE = pose_covariance(np.random.default_rng(3))


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def decode_error(data: bytes, cls=P.RelocalizeRequest, limits=P.DEFAULT_LIMITS) -> P.ProtocolError:
    with pytest.raises(P.ProtocolError) as info:
        cls.decode(data, limits)
    return info.value
