"""Shared synthetic fixtures: a small textured room rendered by ray casting (deterministic,
no files, about 1 s of CPU per scene).

- ``synthetic_scene`` (pinhole) and ``synthetic_scene_radtan`` (mild radial-tangential
  distortion): session-scoped :class:`SyntheticScene` objects with 6 keyframes and 3 queries,
  320x240, Z-depth maps and ``world_from_cam`` ground truth. The room is 3.6 m wide; its walls
  show photographs from ``skimage.data``; the back wall is about 2 m in front of the cameras
  and a free-standing panel 1.3 m in front of them makes depth discontinuities.
  ``scene.render(world_from_cam)`` renders any other view from inside the room.
- ``synthetic_map``: the pinhole scene's keyframes mapped with SIFT landmarks (a MapState).

World frame: z up; the cameras look along +y.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from reloc_service.core.cameras import Camera, PinholeCamera, RadTanCamera
from reloc_service.core.geometry import look_at

Array = npt.NDArray[np.float64]

SUPERSAMPLE = 2


@dataclass(frozen=True, eq=False)
class TexturedPlane:
    """A rectangle ``origin + a u + b v`` (a in [0, size[0]], b in [0, size[1]], metres) showing
    ``texture`` ((H, W) float32 grey, row 0 at b = size[1])."""

    origin_world: Array
    u_world: Array
    v_world: Array
    size_m: tuple[float, float]
    texture: npt.NDArray[np.float32]
    #: A free-standing panel inside the room (hit only inside its rectangle), not a wall.
    bounded: bool = False

    @property
    def normal_world(self) -> Array:
        return np.cross(self.u_world, self.v_world)


@dataclass(eq=False)
class SyntheticScene:
    """Rendered keyframes and queries of a textured room, with ground truth."""

    camera: Camera
    planes: tuple[TexturedPlane, ...]
    keyframe_images: list[npt.NDArray[np.uint8]]
    keyframe_poses: list[Array]
    keyframe_depths: list[npt.NDArray[np.float32]]
    query_images: list[npt.NDArray[np.uint8]]
    query_poses: list[Array]
    query_depths: list[npt.NDArray[np.float32]] = field(default_factory=list)

    def render(self, world_from_cam: Array, camera: Camera | None = None
               ) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.float32]]:
        """Grey (H, W) uint8 image and Z-depth (H, W) float32 of another view."""
        return render_view(self.planes, camera or self.camera, world_from_cam)


def _grey(image: npt.NDArray) -> npt.NDArray[np.float32]:
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY)
    img = image.astype(np.float32)
    lo, hi = np.percentile(img, [1, 99])
    return np.clip(30.0 + 195.0 * (img - lo) / max(hi - lo, 1.0), 0, 255).astype(np.float32)


@functools.lru_cache(maxsize=1)
def _textures() -> dict[str, npt.NDArray[np.float32]]:
    import skimage.data as data

    def fit(img: npt.NDArray[np.float32], height: int) -> npt.NDArray[np.float32]:
        width = int(round(img.shape[1] * height / img.shape[0]))
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)

    back = np.hstack([fit(_grey(data.astronaut()), 512), fit(_grey(data.camera()), 512),
                      fit(_grey(data.coffee()), 512)])
    return {"back": back, "left": _grey(data.rocket()), "right": _grey(data.chelsea()),
            "floor": _grey(data.gravel()), "ceiling": _grey(data.immunohistochemistry()),
            "front": _grey(data.hubble_deep_field()), "panel": _grey(data.text())}


def room_planes() -> tuple[TexturedPlane, ...]:
    """The six textured faces of a 3.6 x 3.5 x 2.6 m room (x in [-1.8, 1.8], y in [-1, 2.5],
    z in [0, 2.6]) and a 0.8 x 1.0 m panel standing 0.9 m in front of the back wall."""
    tex = _textures()
    ex, ey, ez = np.eye(3)

    def plane(origin: Sequence[float], u: Array, v: Array, size: tuple[float, float], name: str,
              bounded: bool = False) -> TexturedPlane:
        return TexturedPlane(np.asarray(origin, float), u, v, size, tex[name], bounded)

    return (plane((-1.8, 2.5, 0.0), ex, ez, (3.6, 2.6), "back"),
            plane((-1.8, -1.0, 0.0), ey, ez, (3.5, 2.6), "left"),
            plane((1.8, 2.5, 0.0), -ey, ez, (3.5, 2.6), "right"),
            plane((-1.8, -1.0, 0.0), ex, ey, (3.6, 3.5), "floor"),
            plane((-1.8, 2.5, 2.6), ex, -ey, (3.6, 3.5), "ceiling"),
            plane((1.8, -1.0, 0.0), -ex, ez, (3.6, 2.6), "front"),
            plane((-0.95, 1.6, 0.45), ex, ez, (0.8, 1.0), "panel", bounded=True))


_RAYS: dict[tuple[Camera, int], Array] = {}


def _camera_rays(camera: Camera, factor: int) -> Array:
    """(H*f, W*f, 3) rays (z = 1) through the sub-pixel centres of a ``factor`` supersampling."""
    key = (camera, factor)
    if key not in _RAYS:
        offsets = (np.arange(factor) + 0.5) / factor - 0.5
        xs = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
        ys = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
        gx, gy = np.meshgrid(xs, ys)
        bearings = camera.unproject(np.column_stack([gx.ravel(), gy.ravel()]))
        _RAYS[key] = (bearings / bearings[:, 2:3]).astype(np.float32).reshape(len(ys), len(xs), 3)
    return _RAYS[key]


def _sample(texture: npt.NDArray[np.float32], x: Array, y: Array) -> npt.NDArray[np.float32]:
    """Bilinear texture values at (M,) positions (remap needs 2D maps under 32767 columns)."""
    n = len(x)
    cols = 1024
    rows = max(1, -(-n // cols))
    maps = np.zeros((2, rows * cols), np.float32)
    maps[0, :n], maps[1, :n] = x, y
    out = cv2.remap(texture, maps[0].reshape(rows, cols), maps[1].reshape(rows, cols),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out.ravel()[:n]


def _cast(planes: Sequence[TexturedPlane], rays_cam: Array, world_from_cam: Array, *,
          shade: bool = True) -> tuple[Array, Array | None]:
    """Z-depth (H, W) and, if ``shade``, intensity (H, W) of the nearest plane hit by every ray
    (z = 1 rays, so the ray parameter is the Z-depth). The unbounded planes must close a convex
    room around the camera (then the nearest wall hit lies inside its rectangle)."""
    h, w, _ = rays_cam.shape
    # float32 and einsum (multi-threaded BLAS on (N, 3) x (3, 3) is slow on a busy machine).
    d = np.einsum("nj,ij->ni", rays_cam.reshape(-1, 3), world_from_cam[:3, :3].astype(np.float32))
    c = world_from_cam[:3, 3]
    normals = np.stack([pl.normal_world for pl in planes]).astype(np.float32)
    offsets = np.array([(pl.origin_world - c) @ pl.normal_world for pl in planes], np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = offsets[None, :] / np.einsum("nj,pj->np", d, normals)   # (N, P)
    t[~(t > 1e-6)] = np.inf   # seen from inside a closed box, the nearest hit is a wall's
    for k in (k for k, pl in enumerate(planes) if pl.bounded):
        pl = planes[k]
        idx = np.flatnonzero(np.isfinite(t[:, k]))
        rel = (c - pl.origin_world).astype(np.float32) + t[idx, k:k + 1] * d[idx]
        a = np.einsum("nj,j->n", rel, pl.u_world.astype(np.float32))
        b = np.einsum("nj,j->n", rel, pl.v_world.astype(np.float32))
        t[idx[~((a >= 0) & (a <= pl.size_m[0]) & (b >= 0) & (b <= pl.size_m[1]))], k] = np.inf
    nearest = np.argmin(t, axis=1)
    depth = np.take_along_axis(t, nearest[:, None], axis=1)[:, 0]
    if not shade:
        return depth.reshape(h, w).astype(np.float64), None
    value = np.zeros(len(d), np.float32)
    for k, pl in enumerate(planes):
        idx = np.flatnonzero((nearest == k) & np.isfinite(depth))
        rel = (c - pl.origin_world).astype(np.float32) + depth[idx, None] * d[idx]
        th, tw = pl.texture.shape
        a = np.einsum("nj,j->n", rel, pl.u_world.astype(np.float32))
        b = np.einsum("nj,j->n", rel, pl.v_world.astype(np.float32))
        value[idx] = _sample(pl.texture, a / pl.size_m[0] * (tw - 1),
                             (1.0 - b / pl.size_m[1]) * (th - 1))
    return depth.reshape(h, w).astype(np.float64), value.reshape(h, w)


def render_view(planes: Sequence[TexturedPlane], camera: Camera, world_from_cam: Array
                ) -> tuple[npt.NDArray[np.uint8], npt.NDArray[np.float32]]:
    """Grey image (supersampled 2x, area-averaged) and Z-depth at pixel centres (NaN: no hit)."""
    _, value = _cast(planes, _camera_rays(camera, SUPERSAMPLE), world_from_cam)
    assert value is not None
    image = cv2.resize(value, camera.size, interpolation=cv2.INTER_AREA)
    depth, _ = _cast(planes, _camera_rays(camera, 1), world_from_cam, shade=False)
    depth[~np.isfinite(depth)] = np.nan
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), depth.astype(np.float32)


def scene_poses() -> tuple[list[Array], list[Array]]:
    """World_from_cam of the 6 keyframes (a 1.2 m sideways sweep) and 3 queries between them."""
    keyframes = []
    for i, x in enumerate(np.linspace(-0.6, 0.6, 6)):
        eye = (x, 0.3 + 0.05 * (i % 2), 1.2 + 0.04 * i)
        keyframes.append(look_at(eye, (0.4 * x, 2.5, 1.25 - 0.03 * i)))
    queries = [look_at((-0.35, 0.45, 1.25), (0.1, 2.5, 1.1)),
               look_at((0.1, 0.5, 1.15), (-0.2, 2.5, 1.3)),
               look_at((0.45, 0.35, 1.3), (0.05, 2.5, 1.2))]
    return keyframes, queries


def make_scene(camera: Camera) -> SyntheticScene:
    planes = room_planes()
    kf_poses, q_poses = scene_poses()
    kf = [render_view(planes, camera, p) for p in kf_poses]
    qs = [render_view(planes, camera, p) for p in q_poses]
    return SyntheticScene(camera=camera, planes=planes,
                          keyframe_images=[im for im, _ in kf], keyframe_poses=kf_poses,
                          keyframe_depths=[d for _, d in kf],
                          query_images=[im for im, _ in qs], query_poses=q_poses,
                          query_depths=[d for _, d in qs])


PINHOLE = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)
RADTAN = RadTanCamera(width=320, height=240, fx=250.0, fy=252.0, cx=161.0, cy=118.5,
                      distortion=(-0.12, 0.03, 0.001, -0.0005))


@pytest.fixture(scope="session")
def synthetic_scene() -> SyntheticScene:
    """The textured room seen by a 320x240 pinhole camera (see module docstring)."""
    return make_scene(PINHOLE)


@pytest.fixture(scope="session")
def synthetic_scene_radtan() -> SyntheticScene:
    """The same room and poses seen by a 320x240 radtan camera."""
    return make_scene(RADTAN)


@pytest.fixture(scope="session")
def synthetic_map(synthetic_scene):
    """The ``synthetic_scene`` keyframes mapped with SIFT landmarks (an immutable MapState;
    ``KeyframeMap().replace_state(state)`` gives a map to change)."""
    from reloc_service.core.map import KeyframeMap
    from reloc_service.core.mapping import MapBuilder

    kmap = KeyframeMap()
    builder = MapBuilder(kmap)
    for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                          synthetic_scene.keyframe_poses, strict=True)):
        builder.add_keyframe(i, image, synthetic_scene.camera, pose, timestamp=float(i))
    return kmap.snapshot()


@dataclass
class PanningDepthMap:
    """Keyframes of a camera panning in place with exact depth, mapped: the keyframes' depth
    maps (ground truth) and the map built from them."""

    depths: list[npt.NDArray[np.float32]]
    state: Any  # MapState


@pytest.fixture(scope="session")
def panning_depth_map(synthetic_scene) -> PanningDepthMap:
    """``synthetic_scene``'s first keyframe turned 0-12 deg about its own y axis in 3 deg steps,
    each centre within 3 mm of the first (a drone yawing on the spot), rendered with exact
    depth and mapped with it: nearly parallel rays between every pair of keyframes."""
    from reloc_service.core.map import KeyframeMap
    from reloc_service.core.mapping import MapBuilder

    first = synthetic_scene.keyframe_poses[0]
    rng = np.random.default_rng(0)
    builder = MapBuilder(KeyframeMap())
    depths = []
    for i, yaw in enumerate(np.radians([0.0, 3.0, 6.0, 9.0, 12.0])):
        turn = np.eye(4)
        turn[:3, :3] = [[np.cos(yaw), 0.0, np.sin(yaw)], [0.0, 1.0, 0.0],
                        [-np.sin(yaw), 0.0, np.cos(yaw)]]
        pose = first @ turn
        pose[:3, 3] += rng.uniform(-0.003, 0.003, 3)
        image, depth = synthetic_scene.render(pose)
        builder.add_keyframe(i, image, synthetic_scene.camera, pose, depth=depth)
        depths.append(depth)
    return PanningDepthMap(depths, builder.map.snapshot())
