"""Drone-like camera paths: a training lap (map keyframes) and a different test lap (queries)
over the same scene, offset by tens of centimetres and up to ~30 degrees of yaw, with a few
degrees of roll and pitch. Deterministic per seed. Poses are ``world_from_cam`` (z up world).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from ..errors import ConfigError
from ..geometry import look_at, so3_exp
from .scene import DESK_TARGET, ROOM_SIZE

Array = npt.NDArray[np.float64]


def camera_pose(eye: npt.ArrayLike, target: npt.ArrayLike, roll: float = 0.0) -> Array:
    """``world_from_cam`` at ``eye`` looking at ``target`` (world z up), rolled by ``roll``
    radians about the optical axis."""
    world_from_cam = look_at(eye, target, up=(0.0, 0.0, 1.0))
    world_from_cam[:3, :3] = world_from_cam[:3, :3] @ so3_exp([0.0, 0.0, roll])
    return world_from_cam


def _direction(yaw: float, pitch: float) -> Array:
    """Unit viewing direction for heading ``yaw`` (from +x towards +y) and ``pitch`` (up > 0)."""
    return np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])


@dataclass(frozen=True)
class EllipseLap:
    """A closed lap on a horizontal ellipse, looking outwards at the walls. Heading is the
    ellipse's outward normal plus ``yaw_swing * sin(3 s)`` (so some views run along a wall)
    plus ``yaw_offset * sin(2 s + yaw_offset_phase)`` (the test lap's extra yaw)."""

    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    height: float
    height_swing: float = 0.12
    pitch: float = np.radians(-10.0)
    yaw_swing: float = np.radians(25.0)
    phase: float = 0.0
    yaw_offset: float = 0.0
    yaw_offset_phase: float = 0.0
    tilt_sigma: float = np.radians(1.5)  # per-frame roll and pitch jitter

    def poses(self, n: int, rng: np.random.Generator) -> list[Array]:
        """``n`` poses spread along the lap (with a little spacing jitter)."""
        s = self.phase + 2 * np.pi * (np.arange(n) + rng.uniform(-0.2, 0.2, n)) / n
        ax, ay = self.semi_axes
        x = self.centre[0] + ax * np.cos(s)
        y = self.centre[1] + ay * np.sin(s)
        z = self.height + self.height_swing * np.sin(2 * s + 0.7)
        outward = np.arctan2(np.sin(s) / ay, np.cos(s) / ax)
        yaw = (outward + self.yaw_swing * np.sin(3 * s)
               + self.yaw_offset * np.sin(2 * s + self.yaw_offset_phase))
        pitch = self.pitch + _tilt(rng, self.tilt_sigma, n)
        roll = _tilt(rng, self.tilt_sigma, n)
        eyes = np.column_stack([x, y, z])
        return [camera_pose(e, e + _direction(yw, p), r)
                for e, yw, p, r in zip(eyes, yaw, pitch, roll, strict=True)]


@dataclass(frozen=True)
class ArcLap:
    """An arc in front of a target (a desk), at ``radius`` metres horizontally and ``height``,
    azimuth from ``azimuths[0]`` to ``azimuths[1]`` (radians; 0 = looking along +y), looking at
    the target moved by up to ``look_jitter`` metres."""

    target: tuple[float, float, float]
    radius: float
    height: float
    azimuths: tuple[float, float]
    look_jitter: float = 0.08
    tilt_sigma: float = np.radians(1.5)

    def poses(self, n: int, rng: np.random.Generator) -> list[Array]:
        """``n`` poses evenly along the arc."""
        az = np.linspace(*self.azimuths, n) if n > 1 else np.array([np.mean(self.azimuths)])
        target = np.asarray(self.target)
        eyes = np.column_stack([target[0] + self.radius * np.sin(az),
                                target[1] - self.radius * np.cos(az),
                                np.full(n, self.height)])
        looks = target + rng.uniform(-self.look_jitter, self.look_jitter, (n, 3))
        roll = _tilt(rng, self.tilt_sigma, n)
        return [camera_pose(e, t, r) for e, t, r in zip(eyes, looks, roll, strict=True)]


def room_laps(n_map: int, n_query: int, seed: int) -> tuple[list[Array], list[Array]]:
    """Training and test laps through the middle strip of the ``room`` scene."""
    sx, sy, _ = ROOM_SIZE
    train = EllipseLap(centre=(sx / 2, sy / 2), semi_axes=(2.2, 0.35), height=1.25)
    r = _rng(seed, "room", 0)
    test = replace(train,
                   semi_axes=(2.2 + _signed(r, 0.1, 0.25), 0.35 + _signed(r, 0.08, 0.15)),
                   height=1.25 + _signed(r, 0.1, 0.22), phase=r.uniform(0, 2 * np.pi),
                   pitch=train.pitch + np.radians(r.uniform(-4, 4)),
                   yaw_offset=np.radians(30.0) * r.uniform(0.6, 1.0),
                   yaw_offset_phase=r.uniform(0, 2 * np.pi), tilt_sigma=np.radians(2.5))
    return train.poses(n_map, _rng(seed, "room", 1)), test.poses(n_query, _rng(seed, "room", 2))


def desk_laps(n_map: int, n_query: int, seed: int) -> tuple[list[Array], list[Array]]:
    """Training and test arcs in front of the desk of the ``desk`` scene."""
    train = ArcLap(target=DESK_TARGET, radius=0.95, height=1.35,
                   azimuths=(np.radians(-50.0), np.radians(50.0)))
    r = _rng(seed, "desk", 0)
    shift = np.radians(r.uniform(-12, 12))
    test = replace(train, radius=0.95 + _signed(r, 0.08, 0.15),
                   height=1.35 + _signed(r, 0.08, 0.15),
                   azimuths=(train.azimuths[0] + shift + np.radians(5),
                             train.azimuths[1] + shift - np.radians(5)),
                   look_jitter=0.2, tilt_sigma=np.radians(2.5))
    return train.poses(n_map, _rng(seed, "desk", 1)), test.poses(n_query, _rng(seed, "desk", 2))


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    """A random offset of magnitude in [low, high] and random sign (laps never coincide)."""
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _tilt(rng: np.random.Generator, sigma: float, n: int) -> Array:
    """Roll / pitch jitter: Gaussian, clipped at two sigma (a few degrees, never a flip)."""
    return np.clip(rng.normal(0.0, sigma, n), -2 * sigma, 2 * sigma)


def _rng(seed: int, name: str, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(f"trajectory {name}".encode()), stream])


TRAJECTORIES: dict[str, Callable[[int, int, int], tuple[list[Array], list[Array]]]] = {
    "room": room_laps, "desk": desk_laps}


def make_trajectories(name: str, n_map: int, n_query: int,
                      seed: int) -> tuple[list[Array], list[Array]]:
    """(map poses, query poses) of trajectory ``name``, each a list of (4, 4) world_from_cam."""
    if name not in TRAJECTORIES:
        raise ConfigError(f"unknown trajectory {name!r}; expected one of {sorted(TRAJECTORIES)}")
    return TRAJECTORIES[name](n_map, n_query, seed)
