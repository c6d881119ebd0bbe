"""A textured plane with a keyframe map, rendered exactly by homography: the planar scene of
the multi relocalizer's tests and benchmarks (SIFT/ORB landmarks lifted onto the plane z = 0).

Importing this module loads OpenCV and SciPy; the texture loads scikit-image when built.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ...core import features as feature_lib
from ...core.cameras import Camera, PinholeCamera
from ...core.frame import Features, Keyframe
from ...core.geometry import invert, look_at
from ...core.map import KeyframeMap

Array = npt.NDArray[np.float64]

DEFAULT_CAMERA = PinholeCamera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)


def texture_mosaic() -> npt.NDArray[np.uint8]:
    """(1024, 1536) grey mosaic of six scikit-image photographs (bundled, no download)."""
    import skimage.data as data

    def tile(img: npt.NDArray) -> npt.NDArray[np.uint8]:
        grey = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
        small = cv2.resize(np.ascontiguousarray(grey), (512, 512), interpolation=cv2.INTER_AREA)
        return np.asarray(small, np.uint8)

    photos = [data.astronaut(), data.camera(), data.coffee(), data.immunohistochemistry(),
              data.rocket(), data.hubble_deep_field()]
    return np.vstack([np.hstack([tile(p) for p in photos[:3]]),
                      np.hstack([tile(p) for p in photos[3:]])])


@dataclass(eq=False)
class PlanarScene:
    """The texture on the world plane z = 0 (texel (u, v) at ``((u - cu) s, (v - cv) s, 0)``),
    a keyframe map of it, and a renderer for any pinhole view (exact, by homography)."""

    texture: npt.NDArray[np.uint8]
    metres_per_texel: float
    camera: Camera
    map: KeyframeMap

    def world_from_texture(self) -> Array:
        """(3, 3) affine map of homogeneous texel coordinates to plane coordinates (x, y, 1)."""
        h, w = self.texture.shape
        s = self.metres_per_texel
        return np.array([[s, 0.0, -s * (w - 1) / 2], [0.0, s, -s * (h - 1) / 2], [0.0, 0.0, 1.0]])

    def render(self, world_from_cam: Array, camera: Camera | None = None) -> npt.NDArray[np.uint8]:
        """Grey image of the plane seen by a pinhole ``camera`` at ``world_from_cam``."""
        cam = camera or self.camera
        cam_from_world = invert(world_from_cam)
        plane_to_cam = cam_from_world[:3][:, [0, 1, 3]]  # z = 0 drops the third column
        homography = cam.K @ plane_to_cam @ self.world_from_texture()
        image = cv2.warpPerspective(self.texture, homography, cam.size, flags=cv2.INTER_LINEAR)
        return np.asarray(image, np.uint8)

    def lift(self, px: Array, world_from_cam: Array, camera: Camera | None = None) -> Array:
        """(N, 3) plane points seen at pixels ``px`` (N, 2) from ``world_from_cam``."""
        cam = camera or self.camera
        rays = cam.unproject(px) @ world_from_cam[:3, :3].T
        centre = world_from_cam[:3, 3]
        return centre + rays * (-centre[2] / rays[:, 2])[:, None]

    def inside(self, points_world: Array, margin_m: float = 0.02) -> npt.NDArray[np.bool_]:
        """(N,) mask of plane points on the texture, ``margin_m`` from its edge."""
        h, w = self.texture.shape
        half = np.array([w, h]) * self.metres_per_texel / 2 - margin_m
        return np.all(np.abs(points_world[:, :2]) < half, axis=1)


def downward_pose(x: float, y: float, height: float, *, yaw: float = 0.0,
                  tilt: tuple[float, float] = (0.0, 0.0)) -> Array:
    """``world_from_cam`` of a camera at (x, y, height) looking down at the plane, rotated by
    ``yaw`` about the vertical and aimed ``tilt`` metres off the point below it."""
    up = (np.sin(yaw), np.cos(yaw), 0.0)
    return look_at((x, y, height), (x + tilt[0], y + tilt[1], 0.0), up=up)


def keyframe_grid(nx: int = 4, ny: int = 3, *, extent: tuple[float, float] = (1.2, 0.6),
                  height: float = 1.2) -> list[Array]:
    """``nx`` x ``ny`` downward keyframe poses over the middle of the plane."""
    xs = np.linspace(-extent[0] / 2, extent[0] / 2, nx)
    ys = np.linspace(-extent[1] / 2, extent[1] / 2, ny)
    return [downward_pose(x, y, height) for y in ys for x in xs]


def planar_scene(keyframe_poses: Sequence[Array] | None = None, *,
                 kinds: Sequence[str] = ("sift",), camera: Camera = DEFAULT_CAMERA,
                 metres_per_texel: float = 1.0 / 512, max_features: int = 2000,
                 merge_radius_texels: float = 2.0,
                 texture: npt.NDArray[np.uint8] | None = None) -> PlanarScene:
    """A map of the textured plane: keyframes rendered at ``keyframe_poses`` (default
    :func:`keyframe_grid`), features of each kind lifted onto the plane as landmarks. Keypoints
    of different keyframes within ``merge_radius_texels`` on the plane share a landmark, as a
    SLAM map's points are observed by several keyframes. ``texture``: the (H, W) grey
    texture on the plane (default :func:`texture_mosaic`)."""
    scene = PlanarScene(texture_mosaic() if texture is None else texture, metres_per_texel,
                        camera, KeyframeMap())
    poses = keyframe_grid() if keyframe_poses is None else list(keyframe_poses)
    registry = {kind: _LandmarkRegistry(merge_radius_texels * metres_per_texel) for kind in kinds}
    for kf_id, world_from_cam in enumerate(poses):
        image = scene.render(world_from_cam)
        feats = {kind: registry[kind].attach(scene, image, world_from_cam, kind, max_features)
                 for kind in kinds}
        scene.map.add_keyframe(Keyframe(image=image, camera=camera, id=kf_id,
                                        world_from_cam=world_from_cam, features=feats))
    return scene


class _LandmarkRegistry:
    """Landmark ids and points of one feature kind, merged by proximity on the plane."""

    def __init__(self, radius_m: float) -> None:
        self.radius_m = radius_m
        self.points = np.zeros((0, 3))
        self.offset = {"sift": 0, "orb": 10_000_000}  # disjoint ids per kind

    def attach(self, scene: PlanarScene, image: npt.NDArray[np.uint8], world_from_cam: Array,
               kind: str, max_features: int) -> Features:
        """Extract ``kind`` features in ``image``; give the ones on the texture landmarks."""
        feats = feature_lib.extract(image, feature_lib.FeatureConf(kind=kind,
                                                                   max_features=max_features))
        points = scene.lift(feats.keypoints_px, world_from_cam)
        on_plane = np.flatnonzero(scene.inside(points))
        ids = self._ids_for(points[on_plane])
        return feats.with_landmarks(on_plane, ids + self.offset[kind], self.points[ids])

    def _ids_for(self, points: Array) -> npt.NDArray[np.int64]:
        """Existing landmark within the radius, else a new one, for each of ``points``."""
        if len(self.points):
            dist, nearest = cKDTree(self.points).query(points, distance_upper_bound=self.radius_m)
            known = np.isfinite(dist)
        else:
            nearest, known = np.zeros(len(points), np.int64), np.zeros(len(points), bool)
        ids = np.where(known, nearest, 0).astype(np.int64)
        fresh = np.flatnonzero(~known)
        ids[fresh] = len(self.points) + np.arange(len(fresh))
        self.points = np.vstack([self.points, points[fresh]])
        return ids


def query_pose(index: int = 0) -> Array:
    """A query between keyframes of :func:`keyframe_grid`, slightly yawed and tilted."""
    rng = np.random.default_rng(index)
    x, y = rng.uniform(-0.5, 0.5), rng.uniform(-0.25, 0.25)
    return downward_pose(x, y, rng.uniform(1.1, 1.3), yaw=rng.uniform(-0.2, 0.2),
                         tilt=tuple(rng.uniform(-0.15, 0.15, 2)))
