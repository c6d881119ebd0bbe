"""The ``repeated`` scene: a room built from repetition, as real buildings are. A few pictures
hang several times (as printed, mirrored, cropped or tiled into a mosaic), the walls and floor
are periodic tiles of one photograph, a row of identical windows runs along one wall, two
identical rugs lie on the floor, and identical cabinets, crates and benches stand in several
places. Only a few things are unique. A pose that a repeated picture explains has plenty of
well-spread inliers; only the rest of the image tells it from the true one.

Same footprint as the ``room`` scene (:data:`.scene.ROOM_SIZE`), so the room laps fly it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .scene import (
    MATERIALS,
    PICTURES,
    ROOM_SIZE,
    Box,
    Image,
    Lighting,
    Scene,
    Texture,
    _Builder,
    _resize,
    _stretch,
    facing_quad,
    load_photo,
    material,
    random_crop,
    room_quads,
)

#: Ways a picture is repeated: as printed, mirrored left-right, a crop of it (60-85 % of its
#: width), a 2 x 2 mosaic of it with alternate copies mirrored.
VARIANTS = ("same", "mirror", "crop", "mosaic")


@dataclass(frozen=True)
class Placed:
    """A model (its index into the scene's box models) standing at (x, y) on ``z0`` with
    ``yaw`` radians about z."""

    model: int
    x: float
    y: float
    z0: float = 0.0
    yaw: float = 0.0


#: Box models (dx, dy, dz metres): a cabinet, a crate, a bench, a small box; each is textured
#: once and every copy shows the same prints.
MODELS = ((0.8, 0.45, 1.2), (0.5, 0.5, 0.5), (1.4, 0.45, 0.8), (0.35, 0.3, 0.3))

#: Copies along the long walls (the middle strip stays free for the drone), then two unique
#: pieces: the only furniture a second copy does not exist of.
LAYOUT = (
    Placed(0, 0.7, 0.25), Placed(0, 4.3, 0.25), Placed(0, 6.3, 2.95),
    Placed(1, 1.7, 0.28), Placed(1, 5.2, 0.28), Placed(1, 2.6, 2.9), Placed(1, 5.3, 2.9, 0, 0.3),
    Placed(2, 2.9, 0.25), Placed(2, 4.1, 2.95),
    Placed(3, 1.7, 0.28, 0.5, 0.2), Placed(3, 2.6, 2.9, 0.5, -0.3), Placed(3, 6.6, 0.6),
)
UNIQUE = (Box(1.2, 2.95, 0.0, 1.0, 0.45, 0.9), Box(5.9, 0.3, 0.0, 0.6, 0.5, 1.0, 0.2))


def motif(rng: np.random.Generator, aspect: float) -> Image:
    """A picture to hang several times: a contrast-stretched crop of a bundled photograph
    with width / height ``aspect``."""
    return _stretch(random_crop(rng, load_photo(str(rng.choice(PICTURES))), aspect, 0.5))


def variant(rng: np.random.Generator, picture: Image, kind: str) -> Image:
    """``picture`` repeated as ``kind`` (one of :data:`VARIANTS`)."""
    if kind == "same":
        return picture
    if kind == "mirror":
        return np.ascontiguousarray(picture[:, ::-1])
    if kind == "crop":
        h, w = picture.shape
        f = rng.uniform(0.6, 0.85)
        ch, cw = max(4, int(h * f)), max(4, int(w * f))
        y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        return np.ascontiguousarray(picture[y0:y0 + ch, x0:x0 + cw])
    if kind == "mosaic":
        row = np.hstack([picture, picture[:, ::-1]])
        return np.ascontiguousarray(np.vstack([row, row[:, ::-1]]))
    raise ValueError(f"unknown variant {kind!r}; expected one of {VARIANTS}")


def periodic_tiles(rng: np.random.Generator, shape: tuple[int, int], photo: str, tile_px: int,
                   *, grout_px: int, contrast: float, brightness: float) -> Image:
    """(h, w) texels of square tiles of ``tile_px`` texels, every tile the same crop of
    ``photo`` (alternate tiles mirrored, as laid tiles are), between grout lines: exactly
    periodic, so any patch of it recurs every two tiles."""
    crop = random_crop(rng, load_photo(photo), 1.0, 0.4)
    tile = _resize(crop, (tile_px, tile_px))
    tile = brightness + contrast * (tile - np.float32(tile.mean()))
    pair = np.hstack([tile, tile[:, ::-1]])
    block = np.vstack([pair, pair[:, ::-1]])
    block[:grout_px, :] = block[:, :grout_px] = brightness * 0.55
    block[tile_px:tile_px + grout_px, :] = block[:, tile_px:tile_px + grout_px] = brightness * 0.55
    reps = (shape[0] // block.shape[0] + 1, shape[1] // block.shape[1] + 1)
    return np.clip(np.tile(block, reps)[:shape[0], :shape[1]], 0.0, 1.0).astype(np.float32)


def hang(tex: Image, texel: float, picture: Image, centre_m: tuple[float, float], width_m: float,
         *, frame: float, frame_m: float = 0.015) -> None:
    """Paste ``picture`` framed (grey level ``frame``) ``width_m`` wide centred at
    ``centre_m`` (u, v metres) on ``tex``, in place; clipped at the texture's edges."""
    pw = max(4, int(width_m / texel))
    ph = max(4, int(pw * picture.shape[0] / picture.shape[1]))
    y0, x0 = int(centre_m[1] / texel) - ph // 2, int(centre_m[0] / texel) - pw // 2
    f = max(1, int(frame_m / texel))
    framed = np.full((ph, pw), frame, np.float32)
    framed[f:ph - f, f:pw - f] = _resize(picture, (ph - 2 * f, pw - 2 * f))
    ys, xs = slice(max(y0, 0), min(y0 + ph, tex.shape[0])), slice(max(x0, 0),
                                                                  min(x0 + pw, tex.shape[1]))
    tex[ys, xs] = framed[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]


def _free_spots(rng: np.random.Generator, size_m: tuple[float, float], n: int,
                width_m: tuple[float, float], height_m: tuple[float, float]
                ) -> list[tuple[float, float, float]]:
    """Up to ``n`` non-overlapping (u, v, width) spots for pictures on a wall ``size_m``, at
    heights (from the wall's top, v down) within ``height_m``."""
    spots: list[tuple[float, float, float]] = []
    for _ in range(40 * n):
        if len(spots) == n:
            break
        w = float(rng.uniform(*width_m))
        u = float(rng.uniform(w / 2 + 0.1, size_m[0] - w / 2 - 0.1))
        v = float(rng.uniform(*height_m))
        if all(abs(u - su) > (w + sw) / 2 + 0.12 for su, _, sw in spots):
            spots.append((u, v, w))
    return spots


def _wall(rng: np.random.Generator, size_m: tuple[float, float], texel: float, base: Image,
          pictures: Sequence[Image], n_pictures: int) -> Texture:
    """A wall of ``base`` texels with ``n_pictures`` drawn from ``pictures`` (each a variant
    of a shared motif) hung at free spots."""
    tex = base.copy()
    for u, v, w in _free_spots(rng, size_m, n_pictures, (0.35, 0.8), (0.55, 1.3)):
        picture = variant(rng, pictures[int(rng.integers(len(pictures)))],
                          str(rng.choice(VARIANTS)))
        hang(tex, texel, picture, (u, v), w, frame=0.08 if rng.random() < 0.5 else 0.92)
    return Texture.from_image(tex, texel)


def _windows(tex: Image, texel: float, size_m: tuple[float, float], pane: Image) -> None:
    """A row of identical windows (the same ``pane`` in every one) 1.3 m apart across the
    upper part of a wall, in place."""
    for u in np.arange(0.9, size_m[0] - 0.5, 1.3):
        hang(tex, texel, pane, (float(u), 0.55), 0.7, frame=0.95, frame_m=0.04)


def _walls(b: _Builder, size: tuple[float, float, float], pictures: Sequence[Image],
           pane: Image) -> list[int]:
    """Texture ids of the four walls (y = 0, y = sy, x = 0, x = sx): periodic brick tiles on
    the long walls, a quilt of the same photograph on the short ones, every wall hung with
    copies of the shared pictures, windows along the y = sy wall."""
    r, texel = b.rng, 0.003
    sx, sy, sz = size
    photo = str(r.choice(MATERIALS))
    ids = []
    for k, wall in enumerate(((sx, sz), (sx, sz), (sy, sz), (sy, sz))):
        shape = (int(np.ceil(wall[1] / texel)), int(np.ceil(wall[0] / texel)))
        base = (periodic_tiles(r, shape, photo, int(0.6 / texel), grout_px=3,
                               contrast=0.6, brightness=0.6) if k < 2 else
                material(r, shape, photo, int(1.6 / texel), contrast=0.55, brightness=0.6))
        if k == 1:
            _windows(base, texel, wall, pane)
        ids.append(b.texture(_wall(r, wall, texel, base, pictures, 4 if k < 2 else 2)))
    return ids


def _floor_and_ceiling(b: _Builder, size: tuple[float, float, float], rug: Image) -> list[int]:
    """Texture ids of the floor (periodic tiles and two identical rugs) and the ceiling."""
    r = b.rng
    sx, sy, _ = size
    texel = 0.004
    shape = (int(np.ceil(sy / texel)), int(np.ceil(sx / texel)))
    floor = periodic_tiles(r, shape, str(r.choice(["gravel", "grass"])), int(0.5 / texel),
                           grout_px=2, contrast=0.7, brightness=0.45)
    for u in (sx * 0.3, sx * 0.7):
        hang(floor, texel, rug, (u, sy / 2), 1.3, frame=0.2, frame_m=0.03)
    ceiling = material(r, shape, "moon", int(1.5 / texel), contrast=0.35, brightness=0.7)
    return [b.texture(Texture.from_image(floor, texel)),
            b.texture(Texture.from_image(ceiling, texel))]


def _furniture(b: _Builder, texel: float) -> None:
    """The copies of each box model (textured once, so every copy shows the same prints),
    then the unique pieces."""
    faces_of = []
    for dx, dy, dz in MODELS:
        faces = Box(0.0, 0.0, 0.0, dx, dy, dz).faces()
        faces_of.append([b.texture(_model_face(b.rng, size, texel)) for *_, size in faces])
    for placed in LAYOUT:
        dx, dy, dz = MODELS[placed.model]
        box = Box(placed.x, placed.y, placed.z0, dx, dy, dz, placed.yaw)
        for (center, normal, up, size), tid in zip(box.faces(), faces_of[placed.model],
                                                   strict=True):
            b.quads.append(facing_quad(center, normal, up, size, tid))
    for box in UNIQUE:
        b.box(box, texel)


def _model_face(rng: np.random.Generator, size_m: tuple[float, float], texel: float) -> Texture:
    """One face of a box model: a crop of a photograph filling it."""
    texel = max(texel, max(size_m) / 1500)  # no face wider than 1500 texels
    shape = (max(4, int(np.ceil(size_m[1] / texel))), max(4, int(np.ceil(size_m[0] / texel))))
    crop = random_crop(rng, load_photo(str(rng.choice(PICTURES))), shape[1] / shape[0], 0.3)
    return Texture.from_image(_stretch(_resize(crop, shape)) * np.float32(rng.uniform(0.6, 1.0)),
                              texel)


def build_repeated(rng: np.random.Generator) -> Scene:
    """The ``repeated`` scene (see the module's docstring): four pictures hung 12 times in
    all, periodic walls and floor, identical windows, rugs and furniture."""
    b = _Builder(rng)
    pictures = [motif(rng, float(rng.uniform(0.7, 1.5))) for _ in range(4)]
    pane, rug = motif(rng, 1.2), motif(rng, 1.6)
    walls = _walls(b, ROOM_SIZE, pictures, pane)
    floor, ceiling = _floor_and_ceiling(b, ROOM_SIZE, rug)
    b.quads += room_quads(ROOM_SIZE, [floor, ceiling, *walls])
    _furniture(b, 0.002)
    occ = b.occluders(6, 0.5, 0.0015)
    return b.scene("repeated", Lighting(lamp_position=(3.5, 1.6, 2.4)), occ)
