"""Per-pixel ray casting of a textured scene through any camera model: supersampled grey
image with Lambertian shading and sensor noise, exact Z-depth from the same rays.

Each pixel's ray comes from ``camera.unproject``, so lens distortion is exactly the camera
model's. Rays are grouped in square tiles; a quad is intersected only with the rays of tiles
that its (near-clipped) projection on the normalised image plane can touch, then a z-buffer
keeps the nearest hit. Textures are sampled trilinearly (mip level from the ray footprint);
2x2 supersampling and area-downsampling anti-alias edges.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.errors import CameraError
from ...core.geometry import invert
from .presets import Degradation
from .scene import Quad, Scene

Array = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

NEAR_M = 0.01  # nothing closer than this to the camera centre is drawn
TILE_PX = 32
_MIN_RAY_Z = 1e-3  # rays at or beyond 90 degrees off-axis cannot be tiled on the z = 1 plane


# -- ray grids -------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class RayGrid:
    """The unit rays (camera frame) through every pixel centre of ``camera``, stored tile by
    tile: rays ``k*T*T ... (k+1)*T*T - 1`` belong to tile k; ``order[i]`` is ray i's flat index
    in the padded (rows, cols) image. ``tile_box`` (n_tiles, 4) bounds each tile's rays on the
    normalised plane z = 1 as (x_min, y_min, x_max, y_max)."""

    camera: Camera
    rays: F32  # (3, N)
    order: npt.NDArray[np.intp]  # (N,)
    padded: tuple[int, int]  # (rows, cols), multiples of ``tile``
    tile: int
    tile_box: F32  # (n_tiles, 4)

    @property
    def tile_size(self) -> int:
        return self.tile * self.tile

    def to_image(self, values: npt.NDArray[Any]) -> npt.NDArray[Any]:
        """(N,) per-ray values to the (height, width) image of ``camera``."""
        flat = np.empty(values.shape[0], dtype=values.dtype)
        flat[self.order] = values
        rows, cols = self.padded
        return flat.reshape(rows, cols)[: self.camera.height, : self.camera.width]


def make_ray_grid(camera: Camera, tile: int = TILE_PX) -> RayGrid:
    """Unproject every pixel of ``camera`` (padded to whole tiles by repeating the last
    row / column) into unit rays grouped by tile; CameraError if a ray points backwards."""
    w, h = camera.width, camera.height
    rows, cols = -(-h // tile) * tile, -(-w // tile) * tile
    ty, tx = rows // tile, cols // tile
    order = (np.arange(rows * cols).reshape(ty, tile, tx, tile).transpose(0, 2, 1, 3).ravel())
    r, c = np.divmod(order, cols)
    px = np.column_stack([np.minimum(c, w - 1), np.minimum(r, h - 1)]).astype(np.float64)
    rays = camera.unproject(px)
    if not np.all(np.isfinite(rays)) or rays[:, 2].min() < _MIN_RAY_Z:
        raise CameraError(f"{camera.model} camera: the renderer needs every pixel ray in front "
                          "of the camera (field of view below 180 degrees)")
    xy = (rays[:, :2] / rays[:, 2:]).reshape(ty * tx, tile * tile, 2)
    # widened a little so float32 rounding of the rays never leaves a ray outside its box
    box = np.concatenate([xy.min(axis=1) - 1e-5, xy.max(axis=1) + 1e-5], axis=1)
    box = box.astype(np.float32)
    return RayGrid(camera, np.ascontiguousarray(rays.T, dtype=np.float32), order,
                   (rows, cols), tile, box)


# -- ray casting -----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Hits:
    """Nearest hit per ray: range ``t`` (metres along the unit ray, inf if none), quad index
    (-1 if none) and texture coordinates ``a``, ``b`` (metres along the quad's u and v)."""

    t: F32
    quad: npt.NDArray[np.int32]
    a: F32
    b: F32


def _clip_near(poly: Array, near: float) -> Array:
    """Sutherland-Hodgman clip of a convex polygon (k, 3) against the half-space z >= near."""
    out = []
    for cur, nxt in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        if cur[2] >= near:
            out.append(cur)
        if (cur[2] >= near) != (nxt[2] >= near):
            out.append(cur + (near - cur[2]) / (nxt[2] - cur[2]) * (nxt - cur))
    return np.array(out).reshape(-1, 3)


def _tiles_touching(tile_box: F32, poly_xy: Array) -> npt.NDArray[np.intp]:
    """Indices of tiles whose bounding boxes may overlap the convex polygon (m, 2): not
    separated by the polygon's bounding box nor by any of its edges (separating axes)."""
    lo, hi = poly_xy.min(axis=0), poly_xy.max(axis=0)
    keep = ((tile_box[:, 0] <= hi[0]) & (tile_box[:, 2] >= lo[0])
            & (tile_box[:, 1] <= hi[1]) & (tile_box[:, 3] >= lo[1]))
    edges = np.roll(poly_xy, -1, axis=0) - poly_xy
    area2 = np.sum(poly_xy[:, 0] * np.roll(poly_xy[:, 1], -1) - np.roll(poly_xy[:, 0], -1)
                   * poly_xy[:, 1])
    outward = np.column_stack([edges[:, 1], -edges[:, 0]]) * np.sign(area2)
    for p, n in zip(poly_xy, outward, strict=True):
        # the tile corner furthest against n; if even it is outside the edge, so is the tile
        x = np.where(n[0] > 0, tile_box[:, 0], tile_box[:, 2])
        y = np.where(n[1] > 0, tile_box[:, 1], tile_box[:, 3])
        keep &= n[0] * (x - p[0]) + n[1] * (y - p[1]) <= 1e-9
    return np.flatnonzero(keep)


def cast_rays(scene: Scene, cam_from_world: Array, grid: RayGrid, *,
              near: float = NEAR_M) -> Hits:
    """Nearest front-facing quad along every ray of ``grid`` for the camera ``cam_from_world``."""
    n_rays = grid.rays.shape[1]
    hits = Hits(np.full(n_rays, np.inf, dtype=np.float32), np.full(n_rays, -1, dtype=np.int32),
                np.zeros(n_rays, dtype=np.float32), np.zeros(n_rays, dtype=np.float32))
    rot, trans = cam_from_world[:3, :3], cam_from_world[:3, 3]
    origins = scene.origins @ rot.T + trans
    us, vs = scene.u_axes @ rot.T, scene.v_axes @ rot.T
    normals = np.cross(vs, us)
    for q in np.flatnonzero(np.einsum("ij,ij->i", normals, origins) < -1e-9):  # front faces
        o, u, v = origins[q], us[q], vs[q]
        su, sv = scene.sizes[q]
        poly = _clip_near(np.array([o, o + su * u, o + su * u + sv * v, o + sv * v]), near)
        if len(poly) < 3:
            continue
        tiles = _tiles_touching(grid.tile_box, poly[:, :2] / poly[:, 2:])
        for k in range(0, len(tiles), _TILES_PER_CHUNK):
            _intersect(hits, grid, tiles[k:k + _TILES_PER_CHUNK], int(q),
                       np.stack([normals[q], u, v]), o, (su, sv), near)
    return hits


_TILES_PER_CHUNK = 48  # ~50k rays: the temporaries stay in cache


def _intersect(hits: Hits, grid: RayGrid, tiles: npt.NDArray[np.intp], q: int,
               nuv: Array, origin: Array, size: tuple[float, float], near: float) -> None:
    """Intersect the rays of ``tiles`` with quad ``q`` (camera-frame normal, u, v stacked in
    ``nuv`` (3, 3), corner ``origin``) and keep the hits nearer than the current ones."""
    sel = (tiles[:, None] * grid.tile_size + np.arange(grid.tile_size)).ravel()
    rays = grid.rays[:, sel]
    w = nuv.astype(np.float32)  # elementwise, not BLAS: no thread pool per worker process
    dots = [rays[0] * w[i, 0] + rays[1] * w[i, 1] + rays[2] * w[i, 2] for i in range(3)]
    plane = (nuv @ origin).astype(np.float32)  # n . o, u . o, v . o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = plane[0] / dots[0]  # the plane n . x = n . o along the ray x = t r
        a = t * dots[1] - plane[1]
        b = t * dots[2] - plane[2]
        # t * r_z >= near also rejects t <= 0 (every ray has r_z > 0); NaN compares False
        ok = ((t * rays[2] >= near) & (t < hits.t[sel]) & (a >= 0) & (a <= size[0])
              & (b >= 0) & (b <= size[1]))
    idx = sel[ok]
    hits.t[idx], hits.quad[idx], hits.a[idx], hits.b[idx] = t[ok], q, a[ok], b[ok]


# -- shading ---------------------------------------------------------------------------------

_REMAP_COLS = 1024


def _bilinear(img: F32, x: F32, y: F32) -> F32:
    """Sample (H, W) ``img`` at texel coordinates (texel centres at integers), clamped to the
    edge. OpenCV's remap does the work (float images are interpolated in float); the sample
    list is laid out as rows of 1024 because remap's maps are images."""
    n = x.shape[0]
    rows = -(-n // _REMAP_COLS)
    maps = np.zeros((2, rows * _REMAP_COLS), dtype=np.float32)
    maps[0, :n], maps[1, :n] = x, y
    out = cv2.remap(img, maps[0].reshape(rows, _REMAP_COLS), maps[1].reshape(rows, _REMAP_COLS),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.float32).ravel()[:n]


def _mip_blend(levels: tuple[F32, ...], texel: float, level: int, a: F32, b: F32,
               frac: F32) -> F32:
    """Sample pyramid ``levels`` at (a, b) metres between ``level`` and the next coarser one,
    blended by ``frac`` in [0, 1] (trilinear filtering)."""
    vals = []
    for k in (level, min(level + 1, len(levels) - 1)):
        scale = np.float32(1.0 / (texel * 2.0**k))
        vals.append(_bilinear(levels[k], a * scale - 0.5, b * scale - 0.5))
    return vals[0] + (vals[1] - vals[0]) * frac


_MAX_LEVELS = 32
_SHADE_CHUNK = 1 << 16  # rays per chunk: temporaries stay in cache, no page faults


def shade(scene: Scene, world_from_cam: Array, grid: RayGrid, hits: Hits) -> F32:
    """(N,) radiance per ray: texture albedo times Lambertian lighting; 0 where no hit.

    The mip level follows the ray's footprint on the surface, ``t / (f cos^0.5)`` metres.
    Rays are processed in chunks of neighbouring tiles; within a chunk they are grouped by
    (quad, level) with one sort, so each group is two remap calls."""
    out = np.zeros(hits.t.shape, dtype=np.float32)
    hit = np.flatnonzero(hits.quad >= 0)
    rot = world_from_cam[:3, :3]
    normals_cam = (scene.normals @ rot).astype(np.float32)  # rows: R^T n
    texels = np.array([scene.textures[i].texel for i in scene.texture_ids], dtype=np.float32)
    top = np.array([len(scene.textures[i].levels) - 1 for i in scene.texture_ids])
    f_px = np.float32(np.sqrt(grid.camera.fx * grid.camera.fy))  # footprint: t / f metres
    for k in range(0, len(hit), _SHADE_CHUNK):
        idx = hit[k:k + _SHADE_CHUNK]
        rays = grid.rays[:, idx]
        q, t = hits.quad[idx], hits.t[idx]
        ray_n = (rays[0] * normals_cam[q, 0] + rays[1] * normals_cam[q, 1]
                 + rays[2] * normals_cam[q, 2])  # -cos(incidence), < 0 on front faces
        lod = np.log2(t / (f_px * np.sqrt(np.maximum(-ray_n, np.float32(0.05))) * texels[q]))
        albedo = _albedo(scene, q, np.clip(lod, 0, top[q].astype(np.float32)), top[q],
                         hits.a[idx], hits.b[idx])
        out[idx] = albedo * _lighting(scene, world_from_cam, q, t, ray_n, rays, normals_cam)
    return out


def _albedo(scene: Scene, q: npt.NDArray[np.int32], lod: F32, top: npt.NDArray[np.intp],
            a: F32, b: F32) -> F32:
    """Trilinear texture samples at (a, b) metres on quads ``q`` at mip level ``lod`` (clipped
    to the pyramid: 0 ... ``top``)."""
    level = np.minimum(lod.astype(np.intp), np.maximum(top - 1, 0))
    key = (q * _MAX_LEVELS + level).astype(np.uint16 if len(scene) < 2000 else np.intp)
    order = np.argsort(key, kind="stable")  # radix sort for 16-bit keys
    counts = np.bincount(key, minlength=len(scene) * _MAX_LEVELS)
    starts = np.concatenate([[0], np.cumsum(counts)])
    albedo = np.empty_like(a)
    for k in np.flatnonzero(counts):
        g = order[starts[k]:starts[k + 1]]
        tex = scene.textures[scene.texture_ids[k // _MAX_LEVELS]]
        albedo[g] = _mip_blend(tex.levels, tex.texel, int(k % _MAX_LEVELS), a[g], b[g],
                               np.minimum(lod[g] - level[g], 1))
    return albedo


def _lighting(scene: Scene, world_from_cam: Array, q: npt.NDArray[np.int32], t: F32,
              ray_n: F32, rays: F32, normals_cam: F32) -> F32:
    """Lambertian irradiance at the hit points ``t r`` (camera frame) of quads ``q``."""
    light = scene.lighting
    rot, centre = world_from_cam[:3, :3], world_from_cam[:3, 3]
    sun = np.asarray(light.sun_direction) / np.linalg.norm(light.sun_direction)
    constant = (light.ambient + light.sun * np.maximum(scene.normals @ sun, 0.0)).astype(
        np.float32)  # per quad
    lamp_cam = (rot.T @ (np.asarray(light.lamp_position) - centre)).astype(np.float32)
    # lamp at L, surface point p = t r: n . (L - p) = n . L - t (n . r), |L - p|^2
    lamp_dot = (normals_cam @ lamp_cam)[q] - t * ray_n
    ray_l = rays[0] * lamp_cam[0] + rays[1] * lamp_cam[1] + rays[2] * lamp_cam[2]
    dist2 = np.maximum(np.float32(lamp_cam @ lamp_cam) - 2 * t * ray_l + t * t, 1e-6)
    lamp = (np.maximum(lamp_dot, 0) / np.sqrt(dist2)
            / (1 + dist2 / np.float32(light.lamp_range**2)))
    return constant[q] + np.float32(light.lamp) * lamp


# -- frames ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Nuisance:
    """The degradations drawn for one query frame (all optional)."""

    blur_px: float = 0.0
    blur_angle: float = 0.0  # radians
    gain: float = 1.0
    gamma: float = 1.0
    occluder: Quad | None = None  # in the world frame

    def summary(self) -> dict[str, float]:
        """A JSON-friendly record for ``synth.json`` (degrees for angles)."""
        return {"blur_px": round(self.blur_px, 3),
                "blur_angle_deg": round(float(np.degrees(self.blur_angle)), 2),
                "gain": round(self.gain, 4), "gamma": round(self.gamma, 4),
                "occluded": self.occluder is not None}


def draw_nuisance(rng: np.random.Generator, conf: Degradation, camera: Camera,
                  world_from_cam: Array, occluder_textures: tuple[int, ...]) -> Nuisance:
    """Draw motion blur, exposure change and an occluder for one query, each with its
    probability; blur length scales with the image width (``conf`` is for 640 px)."""
    draws = rng.random(3)
    blur = rng.uniform(*conf.blur_px) * camera.width / 640.0
    angle = rng.uniform(0.0, np.pi)
    gain, gamma = rng.uniform(*conf.gain), rng.uniform(*conf.gamma)
    occluder = _occluder(rng, conf, camera, world_from_cam, occluder_textures)
    return Nuisance(blur_px=blur if draws[0] < conf.blur_prob else 0.0,
                    blur_angle=angle if draws[0] < conf.blur_prob else 0.0,
                    gain=gain if draws[1] < conf.exposure_prob else 1.0,
                    gamma=gamma if draws[1] < conf.exposure_prob else 1.0,
                    occluder=occluder if draws[2] < conf.occlusion_prob else None)


def _occluder(rng: np.random.Generator, conf: Degradation, camera: Camera,
              world_from_cam: Array, textures: tuple[int, ...]) -> Quad | None:
    """A textured rectangle ``conf.occluder_depth_m`` in front of the camera, parallel to the
    image plane, whose image is a pixel rectangle of ``conf.occlusion_area`` of the frame (its
    edge midpoints are unprojected, so with distortion the outline bends but the area holds)."""
    if not textures:
        return None
    area = rng.uniform(*conf.occlusion_area)
    aspect = rng.uniform(0.6, 1.6)
    w = min(camera.width * 0.95, np.sqrt(area * camera.width * camera.height * aspect))
    h = min(camera.height * 0.95, area * camera.width * camera.height / w)
    x0 = rng.uniform(-0.5, camera.width - 0.5 - w)
    y0 = rng.uniform(-0.5, camera.height - 0.5 - h)
    depth = rng.uniform(*conf.occluder_depth_m)
    mids = np.array([[x0, y0 + h / 2], [x0 + w, y0 + h / 2], [x0 + w / 2, y0],
                     [x0 + w / 2, y0 + h]])
    rays = camera.unproject(mids)
    xy = rays[:, :2] / rays[:, 2:] * depth  # on the plane z = depth, camera frame
    left, right, top, bottom = xy[0, 0], xy[1, 0], xy[2, 1], xy[3, 1]
    rot = world_from_cam[:3, :3]
    origin = world_from_cam[:3, 3] + rot @ np.array([left, top, depth])
    tid = textures[int(rng.integers(len(textures)))]
    # the camera's x (right) and y (down) are the quad's u and v: its front faces the camera
    return Quad(origin, rot[:, 0].copy(), rot[:, 1].copy(), (right - left, bottom - top), tid)


def motion_blur(image: F32, length_px: float, angle: float) -> F32:
    """Convolve with an anti-aliased line of ``length_px`` at ``angle`` (linear motion blur)."""
    if length_px < 1.0:
        return image
    size = int(np.ceil(length_px)) | 1
    sub = 8  # draw the line 8x larger, then area-downsample: sub-pixel kernel lengths
    canvas = np.zeros((size * sub, size * sub), dtype=np.float32)
    c = size * sub / 2.0
    dx, dy = np.cos(angle) * length_px * sub / 2, np.sin(angle) * length_px * sub / 2
    cv2.line(canvas, (int(round(c - dx)), int(round(c - dy))),
             (int(round(c + dx)), int(round(c + dy))), 1.0, thickness=sub)
    kernel = cv2.resize(canvas, (size, size), interpolation=cv2.INTER_AREA)
    return np.asarray(cv2.filter2D(image, -1, kernel / kernel.sum(),
                                   borderType=cv2.BORDER_REFLECT), dtype=np.float32)


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered frame: (H, W) uint8 image, (H, W) float32 Z-depth in metres (0: no hit)
    and (H, W) float32 cosine of the angle between each pixel's ray and the surface normal it
    hits (1: head-on, 0: grazing or no hit), which depth sensors care about."""

    image: npt.NDArray[np.uint8]
    depth: F32
    cos_incidence: F32


_GRIDS: dict[tuple[Camera, int], RayGrid] = {}


def ray_grid(camera: Camera, tile: int = TILE_PX) -> RayGrid:
    """Cached :func:`make_ray_grid` (unprojection is the costly part; cameras are few)."""
    key = (camera, tile)
    if key not in _GRIDS:
        _GRIDS[key] = make_ray_grid(camera, tile)
    return _GRIDS[key]


def render_frame(scene: Scene, camera: Camera, world_from_cam: Array, *,
                 rng: np.random.Generator, supersample: int = 2, noise_sigma: float = 2.0,
                 nuisance: Nuisance | None = None) -> RenderedFrame:
    """Render ``scene`` seen by ``camera`` at ``world_from_cam`` (4, 4): supersampled
    radiance, area-downsampled, optionally blurred / re-exposed, plus Gaussian sensor noise of
    ``noise_sigma`` grey levels; depth from the pixel-centre rays of the same cast."""
    if nuisance is not None and nuisance.occluder is not None:
        scene = scene.with_quads([nuisance.occluder])
    cam_from_world = invert(world_from_cam)
    fine = ray_grid(camera.scaled(supersample))
    hits = cast_rays(scene, cam_from_world, fine)
    radiance = fine.to_image(shade(scene, world_from_cam, fine, hits))
    s = supersample
    image = radiance.reshape(camera.height, s, camera.width, s).mean(axis=(1, 3),
                                                                    dtype=np.float32)
    centre = ray_grid(camera)
    centre_hits = cast_rays(scene, cam_from_world, centre)
    z = np.where(np.isfinite(centre_hits.t), centre_hits.t * centre.rays[2], 0.0)
    depth = centre.to_image(z.astype(np.float32))
    cos_incidence = centre.to_image(_cos_incidence(scene, world_from_cam, centre, centre_hits))
    if nuisance is not None:
        image = motion_blur(image, nuisance.blur_px, nuisance.blur_angle)
        image = np.clip(image * np.float32(nuisance.gain), 0, 1) ** np.float32(nuisance.gamma)
    image = image + rng.standard_normal(image.shape, dtype=np.float32) * np.float32(
        noise_sigma / 255.0)
    pixels = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
    return RenderedFrame(pixels, np.ascontiguousarray(depth), np.ascontiguousarray(cos_incidence))


def _cos_incidence(scene: Scene, world_from_cam: Array, grid: RayGrid, hits: Hits) -> F32:
    """(N,) -(ray . normal) of every ray's hit (front faces only, so in (0, 1]); 0 if none."""
    out = np.zeros(hits.t.shape, dtype=np.float32)
    hit = np.flatnonzero(hits.quad >= 0)
    normals_cam = (scene.normals @ world_from_cam[:3, :3]).astype(np.float32)[hits.quad[hit]]
    out[hit] = -np.einsum("ij,ji->i", normals_cam, grid.rays[:, hit])
    return out
