"""Textured 3D scenes for the synthetic renderer: one-sided rectangles (walls, box faces)
covered by real photographs from scikit-image, at a known physical size (metres per texel).

World frame: z up, floor at z = 0. A rectangle ("quad") is ``origin + a u + b v`` for
``a`` in ``[0, size_u]`` and ``b`` in ``[0, size_v]`` metres; ``u`` runs along the texture's
columns, ``v`` along its rows, and the visible side faces ``normal = v x u`` (like a camera:
x right, y down, z into the picture, so a viewer looking at the front sees the texture upright).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError

Array = npt.NDArray[np.float64]
Image = npt.NDArray[np.float32]

# Photographs bundled in the scikit-image wheel (no download). Materials look like surfaces
# (walls, floors); pictures are what posters, box prints and occluders show.
MATERIALS = ("brick", "gravel", "grass", "moon")
PICTURES = ("astronaut", "camera", "cell", "chelsea", "clock", "coffee", "coins",
            "hubble_deep_field", "immunohistochemistry", "page", "retina", "rocket", "text",
            "brick", "gravel", "moon")

ROOM_SIZE = (7.0, 3.2, 2.6)  # x, y, z extent in metres of the "room" scene
DESK_ROOM_SIZE = (4.0, 3.5, 2.6)
DESK_TARGET = (2.0, 2.95, 0.85)  # a point near the middle of the desk top, for trajectories


# -- data ------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Texture:
    """A grey texture as a mip pyramid: ``levels[k]`` is (H_k, W_k) float32 in [0, 1], each
    texel of level k covering ``texel * 2**k`` metres on a side."""

    levels: tuple[Image, ...]
    texel: float

    @classmethod
    def from_image(cls, image: Image, texel: float) -> Texture:
        """Build the pyramid of ``image`` by 2x2 area averaging down to a few texels."""
        levels = [np.ascontiguousarray(image, dtype=np.float32)]
        while min(levels[-1].shape) >= 8:
            levels.append(_half(levels[-1]))
        return cls(tuple(levels), float(texel))


@dataclass(frozen=True)
class Lighting:
    """Lambertian lighting: ambient + a directional "sun" + a point lamp with 1/(1+(d/r)^2)
    falloff. Shading depends on surface position and normal only, never on the viewer, so
    the same surface point has the same intensity in every frame (photometric consistency)."""

    ambient: float = 0.4
    sun_direction: tuple[float, float, float] = (0.35, -0.25, 0.9)  # towards the sun
    sun: float = 0.3
    lamp_position: tuple[float, float, float] = (3.5, 1.6, 2.4)
    lamp: float = 0.55
    lamp_range: float = 2.5


@dataclass(frozen=True, eq=False)
class Quad:
    """One textured rectangle: corner ``origin`` (3,), unit axes ``u``, ``v`` (3,), extent
    ``size = (size_u, size_v)`` metres, index into the scene's textures."""

    origin: Array
    u: Array
    v: Array
    size: tuple[float, float]
    texture: int


@dataclass(frozen=True, eq=False)
class Scene:
    """Quads stacked as arrays (Q, ...) for vectorised ray casting, their textures, lighting,
    and the textures that query occluders may use."""

    name: str
    origins: Array  # (Q, 3) world
    u_axes: Array  # (Q, 3) unit
    v_axes: Array  # (Q, 3) unit
    sizes: Array  # (Q, 2) metres
    texture_ids: npt.NDArray[np.int32]  # (Q,)
    textures: tuple[Texture, ...]
    lighting: Lighting
    occluder_textures: tuple[int, ...] = ()

    @classmethod
    def from_quads(cls, name: str, quads: Sequence[Quad], textures: Sequence[Texture],
                   lighting: Lighting, occluder_textures: Sequence[int] = ()) -> Scene:
        return cls(name, np.array([q.origin for q in quads], dtype=np.float64).reshape(-1, 3),
                   np.array([q.u for q in quads], dtype=np.float64).reshape(-1, 3),
                   np.array([q.v for q in quads], dtype=np.float64).reshape(-1, 3),
                   np.array([q.size for q in quads], dtype=np.float64).reshape(-1, 2),
                   np.array([q.texture for q in quads], dtype=np.int32),
                   tuple(textures), lighting, tuple(occluder_textures))

    @property
    def normals(self) -> Array:
        """(Q, 3) unit normals of the visible sides."""
        return np.cross(self.v_axes, self.u_axes)

    def __len__(self) -> int:
        return len(self.origins)

    def with_quads(self, quads: Sequence[Quad]) -> Scene:
        """This scene plus ``quads`` (which use this scene's textures)."""
        extra = Scene.from_quads(self.name, quads, (), self.lighting)
        return Scene(self.name, np.vstack([self.origins, extra.origins]),
                     np.vstack([self.u_axes, extra.u_axes]),
                     np.vstack([self.v_axes, extra.v_axes]),
                     np.vstack([self.sizes, extra.sizes]),
                     np.concatenate([self.texture_ids, extra.texture_ids]),
                     self.textures, self.lighting, self.occluder_textures)

    def surface_points(self, rng: np.random.Generator, n: int) -> tuple[Array, Array]:
        """``n`` random points (n, 3) on the quads (area-weighted) and their normals (n, 3)."""
        area = self.sizes[:, 0] * self.sizes[:, 1]
        q = rng.choice(len(self), size=n, p=area / area.sum())
        ab = rng.uniform(0.02, 0.98, size=(n, 2)) * self.sizes[q]
        points = self.origins[q] + ab[:, :1] * self.u_axes[q] + ab[:, 1:] * self.v_axes[q]
        return points, self.normals[q]


# -- geometry builders -----------------------------------------------------------------------

def facing_quad(center: npt.ArrayLike, normal: npt.ArrayLike, up: npt.ArrayLike,
                size: tuple[float, float], texture: int) -> Quad:
    """The rectangle centred at ``center`` whose visible side faces ``normal``, with the
    texture's top towards ``up`` (a direction not parallel to ``normal``)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    up_w = np.asarray(up, dtype=np.float64)
    u = np.cross(-n, up_w)  # "right" for a viewer looking at the front, along -normal
    u /= np.linalg.norm(u)
    v = np.cross(u, n)  # so that normal = v x u; "down" on the texture
    origin = np.asarray(center, dtype=np.float64) - 0.5 * size[0] * u - 0.5 * size[1] * v
    return Quad(origin, u, v, (float(size[0]), float(size[1])), texture)


def room_quads(size: tuple[float, float, float], textures: Sequence[int]) -> list[Quad]:
    """Floor, ceiling and four walls of the box ``[0, sx] x [0, sy] x [0, sz]``, seen from
    inside; ``textures`` in that order (floor, ceiling, y=0, y=sy, x=0, x=sx walls)."""
    sx, sy, sz = size
    mid = np.array([sx, sy, sz]) / 2
    z = np.array([0.0, 0.0, 1.0])
    specs: list[tuple[Any, Any, Any, tuple[float, float]]] = [
             ((mid[0], mid[1], 0.0), (0, 0, 1), (0, 1, 0), (sx, sy)),
             ((mid[0], mid[1], sz), (0, 0, -1), (0, 1, 0), (sx, sy)),
             ((mid[0], 0.0, mid[2]), (0, 1, 0), z, (sx, sz)),
             ((mid[0], sy, mid[2]), (0, -1, 0), z, (sx, sz)),
             ((0.0, mid[1], mid[2]), (1, 0, 0), z, (sy, sz)),
             ((sx, mid[1], mid[2]), (-1, 0, 0), z, (sy, sz))]
    return [facing_quad(c, n, up, s, t) for (c, n, up, s), t in zip(specs, textures, strict=True)]


@dataclass(frozen=True)
class Box:
    """An axis-aligned (up to ``yaw`` radians about z) box standing on ``z0``: footprint
    centre (x, y), extent (dx, dy, dz) metres."""

    x: float
    y: float
    z0: float
    dx: float
    dy: float
    dz: float
    yaw: float = 0.0

    def faces(self) -> list[tuple[Array, Array, Array, tuple[float, float]]]:
        """(center, outward normal, up, size) of the four sides and the top; no bottom."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
        mid = np.array([self.x, self.y, self.z0 + self.dz / 2])
        hx, hy, hz = self.dx / 2, self.dy / 2, self.dz / 2
        return [(mid + hx * ex, ex, ez, (self.dy, self.dz)),
                (mid - hx * ex, -ex, ez, (self.dy, self.dz)),
                (mid + hy * ey, ey, ez, (self.dx, self.dz)),
                (mid - hy * ey, -ey, ez, (self.dx, self.dz)),
                (mid + hz * ez, ez, ey, (self.dx, self.dy))]


# -- photographs and textures ----------------------------------------------------------------

@functools.cache
def load_photo(name: str) -> Image:
    """A scikit-image sample photograph as (H, W) float32 grey in [0, 1] (bundled, offline)."""
    import skimage.data

    loader = "immunohistochemistry" if name == "ihc" else name
    try:
        img = np.asarray(getattr(skimage.data, loader)())
    except (AttributeError, ModuleNotFoundError, OSError) as exc:
        raise ConfigError(f"photo {name!r} is not a bundled scikit-image sample ({exc})") from exc
    img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 1.0)
    if img.ndim == 3:  # Rec. 601 luma, as OpenCV's BGR2GRAY
        img = img[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    img.setflags(write=False)
    return img


def _half(img: Image) -> Image:
    """2x2 area average (odd sizes padded by edge replication)."""
    h, w = img.shape
    p = np.pad(img, ((0, h % 2), (0, w % 2)), mode="edge") if (h % 2 or w % 2) else img
    return np.asarray(cv2.resize(p, (p.shape[1] // 2, p.shape[0] // 2),
                                 interpolation=cv2.INTER_AREA), dtype=np.float32)


def _resize(img: Image, shape: tuple[int, int]) -> Image:
    """Resize to (h, w): area averaging when shrinking, bicubic (clipped) when enlarging."""
    h, w = max(1, shape[0]), max(1, shape[1])
    shrink = h * w < img.shape[0] * img.shape[1]
    out = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
    return np.clip(out, 0.0, 1.0).astype(np.float32).reshape(h, w)


def _stretch(img: Image) -> Image:
    """Contrast-stretch to [0.04, 0.96] between the 1st and 99th percentiles."""
    lo, hi = np.percentile(img, [1, 99])
    return (0.04 + 0.92 * np.clip((img - lo) / max(hi - lo, 1e-3), 0, 1)).astype(np.float32)


def random_crop(rng: np.random.Generator, photo: Image, aspect: float, min_frac: float) -> Image:
    """A random crop of ``photo`` with width/height ``aspect``, spanning between ``min_frac``
    and all of the largest such crop (so the same photo appears at different scales)."""
    h, w = photo.shape
    ch, cw = (h, h * aspect) if h * aspect <= w else (w / aspect, w)
    f = rng.uniform(min_frac, 1.0)
    ch, cw = max(2, int(ch * f)), max(2, int(cw * f))
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(photo[y0:y0 + ch, x0:x0 + cw])  # never mirrored: text reads


def material(rng: np.random.Generator, shape: tuple[int, int], name: str, tile_px: int, *,
             contrast: float, brightness: float) -> Image:
    """Fill ``shape`` (h, w) texels with a photo at a scale of ``tile_px`` texels per photo
    width: a quilt of random crops (random flips) cross-faded over narrow seams, modulated by
    a smooth random field. Unlike plain or mirrored tiling it has no period and no symmetry."""
    photo = load_photo(name)
    photo = np.ascontiguousarray(photo.T) if rng.random() < 0.5 else photo  # e.g. brick courses
    photo = _resize(photo, (max(8, int(tile_px * photo.shape[0] / photo.shape[1])), tile_px))
    cell = max(4, min(photo.shape) // 3)  # crops of cell + 2 * fade: a third of the photo
    fade = max(1, cell // 8)
    ramp = np.minimum(1.0, (np.arange(cell + 2 * fade, dtype=np.float32) + 0.5) / (2 * fade))
    ramp = np.minimum(ramp, ramp[::-1])  # trapezoid: 0 -> 1 over 2 * fade at each end
    weight = np.outer(ramp, ramp)
    ys, xs = range(0, shape[0] + fade, cell), range(0, shape[1] + fade, cell)
    acc = np.zeros((len(ys) * cell + 2 * fade, len(xs) * cell + 2 * fade), dtype=np.float32)
    norm = np.zeros_like(acc)
    for y in ys:
        for x in xs:
            y0 = int(rng.integers(0, photo.shape[0] - cell - 2 * fade + 1))
            x0 = int(rng.integers(0, photo.shape[1] - cell - 2 * fade + 1))
            crop = photo[y0:y0 + cell + 2 * fade, x0:x0 + cell + 2 * fade]
            crop = crop[:, ::-1] if rng.random() < 0.5 else crop
            acc[y:y + cell + 2 * fade, x:x + cell + 2 * fade] += crop * weight
            norm[y:y + cell + 2 * fade, x:x + cell + 2 * fade] += weight
    base = (acc / np.maximum(norm, 1e-6))[fade:fade + shape[0], fade:fade + shape[1]]
    base = brightness + contrast * (base - np.float32(photo.mean()))
    coarse = rng.normal(0.0, 1.0, size=(max(2, shape[0] // 150), max(2, shape[1] // 150)))
    field = cv2.resize(coarse.astype(np.float32), (shape[1], shape[0]),
                       interpolation=cv2.INTER_CUBIC)
    return np.clip(base * (1.0 + 0.12 * field), 0.0, 1.0).astype(np.float32)


def paste_posters(rng: np.random.Generator, tex: Image, texel: float, n: int, *,
                  width_m: tuple[float, float], frame_m: float = 0.015, tries: int = 30) -> None:
    """Paste ``n`` framed pictures of random width (metres) at free random places, in place."""
    taken: list[tuple[int, int, int, int]] = []
    margin = int(0.05 / texel)
    for _ in range(n):
        for _ in range(tries):
            crop = random_crop(rng, load_photo(str(rng.choice(PICTURES))),
                               float(rng.uniform(0.6, 1.6)), 0.35)
            pw = int(rng.uniform(*width_m) / texel)
            ph = int(pw * crop.shape[0] / crop.shape[1])
            if ph + 2 * margin >= tex.shape[0] or pw + 2 * margin >= tex.shape[1]:
                continue
            y0 = int(rng.integers(margin, tex.shape[0] - ph - margin))
            x0 = int(rng.integers(margin, tex.shape[1] - pw - margin))
            box = (y0 - margin, x0 - margin, y0 + ph + margin, x0 + pw + margin)
            if any(_overlap(box, other) for other in taken):
                continue
            taken.append(box)
            f = max(1, int(frame_m / texel))
            tex[y0:y0 + ph, x0:x0 + pw] = 0.08 if rng.random() < 0.5 else 0.92
            tex[y0 + f:y0 + ph - f, x0 + f:x0 + pw - f] = _stretch(
                _resize(crop, (ph - 2 * f, pw - 2 * f)))
            break


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def surface_texture(rng: np.random.Generator, size_m: tuple[float, float], texel: float, *,
                    base: str, base_tile_m: float, contrast: float = 0.6,
                    brightness: float = 0.6, posters_per_m2: float = 0.0,
                    poster_width_m: tuple[float, float] = (0.25, 0.8)) -> Texture:
    """A wall / floor texture of ``size_m`` (u, v) metres: a material plus framed pictures."""
    shape = (int(np.ceil(size_m[1] / texel)), int(np.ceil(size_m[0] / texel)))
    tex = material(rng, shape, base, max(4, int(base_tile_m / texel)),
                   contrast=contrast, brightness=brightness)
    n = int(round(posters_per_m2 * size_m[0] * size_m[1]))
    paste_posters(rng, tex, texel, n, width_m=poster_width_m)
    return Texture.from_image(tex, texel)


def print_texture(rng: np.random.Generator, size_m: tuple[float, float], texel: float) -> Texture:
    """A box face: small faces show a crop of a random picture (at a random scale), sometimes
    with a label; large faces (furniture) a material with pictures pasted on, as walls do, so
    that no photo is magnified across a metre."""
    if max(size_m) > 0.45:
        return surface_texture(rng, size_m, max(texel, 0.002), base=str(rng.choice(MATERIALS)),
                               base_tile_m=float(rng.uniform(0.3, 0.9)),
                               contrast=float(rng.uniform(0.4, 0.9)),
                               brightness=float(rng.uniform(0.35, 0.65)),
                               posters_per_m2=2.5, poster_width_m=(0.12, 0.4))
    shape = (max(4, int(np.ceil(size_m[1] / texel))), max(4, int(np.ceil(size_m[0] / texel))))
    crop = random_crop(rng, load_photo(str(rng.choice(PICTURES))), shape[1] / shape[0], 0.3)
    tex = _stretch(_resize(crop, shape)) * rng.uniform(0.6, 1.0)
    if rng.random() < 0.5 and min(size_m) > 0.08:
        label = min(size_m) * rng.uniform(0.3, 0.6)
        paste_posters(rng, tex, texel, 1, width_m=(label, label * 1.01), frame_m=0.005)
    return Texture.from_image(tex.astype(np.float32), texel)


# -- scenes ----------------------------------------------------------------------------------

class _Builder:
    """Collects quads and textures while a scene is laid out."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.quads: list[Quad] = []
        self.textures: list[Texture] = []

    def texture(self, tex: Texture) -> int:
        self.textures.append(tex)
        return len(self.textures) - 1

    def room(self, size: tuple[float, float, float], wall_texel: float, floor_texel: float,
             posters_per_m2: float) -> None:
        sx, sy, sz = size
        r = self.rng
        floor = surface_texture(r, (sx, sy), floor_texel, base=str(r.choice(["gravel", "grass"])),
                                base_tile_m=0.9, contrast=0.7, brightness=0.45,
                                posters_per_m2=0.08, poster_width_m=(0.6, 1.4))  # rugs
        ceiling = surface_texture(r, (sx, sy), floor_texel, base="moon", base_tile_m=1.5,
                                  contrast=0.35, brightness=0.7)
        walls = [surface_texture(r, s, wall_texel, base=str(r.choice(["brick", "moon", "gravel"])),
                                 base_tile_m=float(r.uniform(1.4, 2.2)),
                                 contrast=float(r.uniform(0.35, 0.8)),
                                 brightness=float(r.uniform(0.5, 0.7)),
                                 posters_per_m2=posters_per_m2)
                 for s in ((sx, sz), (sx, sz), (sy, sz), (sy, sz))]
        ids = [self.texture(t) for t in (floor, ceiling, *walls)]
        self.quads += room_quads(size, ids)

    def box(self, box: Box, texel: float) -> None:
        for center, normal, up, size in box.faces():
            tid = self.texture(print_texture(self.rng, size, texel))
            self.quads.append(facing_quad(center, normal, up, size, tid))

    def occluders(self, n: int, size_m: float, texel: float) -> list[int]:
        return [self.texture(print_texture(self.rng, (size_m, size_m), texel)) for _ in range(n)]

    def scene(self, name: str, lighting: Lighting, occluders: list[int]) -> Scene:
        return Scene.from_quads(name, self.quads, self.textures, lighting, occluders)


ROOM_FURNITURE = (  # along the long walls, leaving the middle strip free for the drone
    Box(0.9, 0.225, 0.0, 1.2, 0.45, 0.9), Box(2.8, 0.175, 0.0, 1.6, 0.35, 1.1),
    Box(5.1, 0.275, 0.0, 1.6, 0.55, 0.75), Box(4.8, 0.25, 0.75, 0.4, 0.3, 0.25, 0.3),
    Box(5.55, 0.2, 0.75, 0.35, 0.25, 0.4, -0.2), Box(1.8, 2.925, 0.0, 2.0, 0.55, 0.45),
    Box(1.8, 3.1, 0.45, 2.0, 0.2, 0.4), Box(3.8, 2.975, 0.0, 0.8, 0.45, 1.9),
    Box(5.3, 2.95, 0.0, 0.6, 0.5, 0.6, 0.15), Box(5.3, 2.95, 0.6, 0.45, 0.4, 0.35, -0.25),
    Box(0.2, 1.6, 0.0, 0.4, 0.6, 0.7), Box(6.775, 1.55, 0.0, 0.45, 1.3, 1.0),
    Box(6.55, 0.45, 0.0, 0.5, 0.5, 0.55, 0.35),
)

DESK_FURNITURE = (  # a desk against the y = 3.5 wall and things on it
    Box(2.0, 3.1, 0.0, 1.8, 0.8, 0.75),  # desk
    Box(2.15, 3.38, 0.75, 0.08, 0.08, 0.2),  # monitor stand
    Box(2.15, 3.36, 0.95, 0.6, 0.05, 0.38),  # monitor
    Box(1.9, 2.95, 0.75, 0.45, 0.15, 0.025),  # keyboard
    Box(1.35, 3.05, 0.75, 0.22, 0.3, 0.05, 0.2), Box(1.36, 3.05, 0.8, 0.2, 0.27, 0.04, 0.05),
    Box(1.33, 3.07, 0.84, 0.19, 0.25, 0.035, -0.15),  # a stack of books
    Box(2.55, 2.9, 0.75, 0.08, 0.08, 0.1),  # mug
    Box(2.7, 3.2, 0.75, 0.25, 0.2, 0.18, 0.4),  # a box
    Box(1.6, 2.82, 0.75, 0.3, 0.21, 0.012, -0.3),  # a sheet of paper
    Box(2.55, 3.35, 0.75, 0.12, 0.12, 0.3),  # a tall box (speaker)
    Box(0.5, 3.2, 0.0, 0.5, 0.6, 1.2),  # cabinet left of the desk
    Box(3.5, 3.25, 0.0, 0.6, 0.5, 0.6, 0.1),  # crate right of the desk
)


def build_room(rng: np.random.Generator) -> Scene:
    """~7 x 3 m room with posters on brick / plaster walls and furniture-like boxes."""
    b = _Builder(rng)
    b.room(ROOM_SIZE, wall_texel=0.003, floor_texel=0.004, posters_per_m2=0.8)
    for box in ROOM_FURNITURE:
        b.box(box, 0.002)
    occ = b.occluders(6, 0.5, 0.0015)
    return b.scene("room", Lighting(lamp_position=(3.5, 1.6, 2.4)), occ)


def build_desk(rng: np.random.Generator) -> Scene:
    """A desk with a monitor, books and boxes against a postered wall, inside a small room."""
    b = _Builder(rng)
    b.room(DESK_ROOM_SIZE, wall_texel=0.0025, floor_texel=0.003, posters_per_m2=0.8)
    for box in DESK_FURNITURE:
        b.box(box, 0.001)
    occ = b.occluders(6, 0.5, 0.0015)
    return b.scene("desk", Lighting(lamp_position=(2.2, 2.2, 2.3), lamp_range=2.0), occ)
