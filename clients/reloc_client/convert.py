"""Argument conversion for the client: numpy arrays, bytes, files and mappings to wire types.

Each function raises ValueError or TypeError naming what was expected, before anything is
sent, so a bad argument never reaches the service.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from . import protocol as wire

ImageLike = wire.WireImage | bytes | bytearray | str | os.PathLike[str] | npt.NDArray[Any]
PoseLike = wire.WirePose | npt.ArrayLike | tuple[Sequence[float], Sequence[float]]
CameraLike = wire.WireCamera | Mapping[str, Any] | Any  # or any object with .to_dict()


def to_wire_image(image: ImageLike, *, image_format: str | None = None,
                  jpeg_quality: int = 90) -> wire.WireImage:
    """An image argument as a wire image.

    ``image`` may be a :class:`WireImage`; PNG/JPEG file bytes or a path to such a file (sent
    as is); or a numpy array: (H, W) uint8 is sent raw as ``mono8`` (no OpenCV), a colour
    (H, W, 3) BGR array as JPEG. ``image_format`` ("mono8", "jpeg", "png") forces the
    encoding of an array (JPEG/PNG encoding imports OpenCV)."""
    if isinstance(image, wire.WireImage):
        return image
    if isinstance(image, bytes | bytearray | memoryview):
        return wire.WireImage.from_bytes(bytes(image))
    if isinstance(image, str | os.PathLike):
        return wire.WireImage.from_bytes(Path(image).read_bytes())
    array = np.asarray(image)
    fmt = image_format or ("mono8" if array.ndim == 2 else "jpeg")
    if fmt == "mono8":
        return wire.WireImage.from_array(array)
    if fmt not in ("jpeg", "png"):
        raise ValueError(f"image_format: expected 'mono8', 'jpeg' or 'png', got {fmt!r}")
    import cv2  # only for encoding arrays as JPEG/PNG

    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(f".{'jpg' if fmt == 'jpeg' else 'png'}", array, params)
    if not ok:
        raise ValueError(f"could not encode an array of shape {array.shape} {array.dtype} as "
                         f"{fmt}")
    return wire.WireImage.from_bytes(buf.tobytes())


def to_wire_pose(world_from_cam: PoseLike, path: str = "world_from_cam") -> wire.WirePose:
    """A (4, 4) matrix, a (t, q) pair (q = x y z w) or a WirePose as a wire pose."""
    if isinstance(world_from_cam, wire.WirePose):
        return world_from_cam
    if isinstance(world_from_cam, tuple | list) and len(world_from_cam) == 2:
        t, q = world_from_cam
        return wire.WirePose.from_tq(t, q, path)
    return wire.WirePose.from_matrix(np.asarray(world_from_cam, dtype=np.float64), path)


def to_wire_camera(camera: CameraLike) -> wire.WireCamera:
    """A camera dict, a WireCamera, or any object with ``to_dict()`` (e.g. a reloc Camera)."""
    if isinstance(camera, wire.WireCamera):
        return camera
    if not isinstance(camera, Mapping) and hasattr(camera, "to_dict"):
        camera = camera.to_dict()
    if not isinstance(camera, Mapping):
        raise TypeError(f"camera: expected a camera dict, got {type(camera).__name__}")
    return wire.WireCamera.from_dict(camera)


def to_wire_features(features: wire.WireFeatures | Mapping[str, Any]) -> wire.WireFeatures:
    """A WireFeatures, or a dict with ``keypoints_px`` (N, 2) and optional ``landmark_ids``
    (N,) and ``points_world`` (N, 3) arrays."""
    if isinstance(features, wire.WireFeatures):
        return features
    unknown = set(features) - {"keypoints_px", "landmark_ids", "points_world"}
    if unknown:
        raise ValueError(f"features: unknown key(s) {sorted(unknown)}; expected keypoints_px, "
                         "landmark_ids, points_world")
    return wire.WireFeatures(**features)


def to_wire_depth(depth: wire.WireDepth | npt.ArrayLike | tuple[Any, float]) -> wire.WireDepth:
    """A WireDepth; an (H, W) float array in metres (NaN = unknown, sent at 1 mm per unit);
    or a pair (uint16 (H, W) array or 16-bit PNG bytes, metres per unit)."""
    if isinstance(depth, wire.WireDepth):
        return depth
    if isinstance(depth, tuple):
        raw, mpu = depth
        if isinstance(raw, bytes | bytearray):
            header = wire.png_header(bytes(raw))
            if header is None:
                raise ValueError("depth: expected 16-bit PNG bytes")
            return wire.WireDepth(wire.DepthFormat.PNG, header[0], header[1], bytes(raw),
                                  float(mpu))
        a = np.asarray(raw)
        if a.ndim != 2 or a.dtype != np.uint16:
            raise ValueError(f"depth: expected an (H, W) uint16 array, got {a.shape} {a.dtype}")
        return wire.WireDepth(wire.DepthFormat.MONO16, a.shape[1], a.shape[0],
                              a.astype("<u2").tobytes(), float(mpu))
    return wire.WireDepth.from_metres(depth)


def keyframe_put_bytes(kf_id: int, image: ImageLike, world_from_cam: PoseLike, *,
                       camera_id: str | None = None, camera: CameraLike | None = None,
                       timestamp: float | None = None,
                       features: wire.WireFeatures | Mapping[str, Any] | None = None,
                       depth: Any = None, image_format: str | None = None,
                       pose_covariance: Any = None) -> bytes:
    """An encoded KeyframePut (see :meth:`RelocClient.add_keyframe` for the arguments)."""
    return wire.KeyframePut(
        id=kf_id, image=to_wire_image(image, image_format=image_format),
        world_from_cam=to_wire_pose(world_from_cam), camera_id=camera_id,
        camera=None if camera is None else to_wire_camera(camera),
        timestamp=None if timestamp is None else float(timestamp),
        features=None if features is None else to_wire_features(features),
        depth=None if depth is None else to_wire_depth(depth),
        pose_covariance=to_wire_covariance(pose_covariance)).encode()


def to_wire_covariance(covariance: Any) -> tuple[float, ...] | None:
    """A (6, 6) pose covariance (or its 36 row-major values) as the wire's 36 floats; None
    stays None. ValueError naming the problem unless it is a pose covariance (finite,
    symmetric, positive semi-definite)."""
    if covariance is None:
        return None
    try:
        c = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    except (TypeError, ValueError):
        raise ValueError(f"pose_covariance: expected a (6, 6) array or 36 numbers, got "
                         f"shape {np.shape(covariance)}") from None
    problem = wire.pose_covariance_problem(c)
    if problem is not None:
        raise ValueError(f"pose_covariance: expected a pose covariance (symmetric, positive "
                         f"semi-definite): {problem}")
    return tuple(float(v) for v in c.ravel())
