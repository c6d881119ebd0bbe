"""Camera paths: a training lap (map keyframes) and a different test lap (queries) over the
same scene, offset by tens of centimetres and up to ~30 degrees of yaw, with a few degrees of
roll and pitch: drone laps (room, desk), a drone flight down the room (stereo), a handheld
pass around the desk (RGB-D), and a camera panning on the spot (rotation). Deterministic per
seed. Poses are ``world_from_cam`` (z up world); for a rig, the pose of its ``cam0``.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError
from ...core.geometry import look_at, so3_exp
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
        return _jittered_poses(np.column_stack([x, y, z]), yaw, self.pitch, self.tilt_sigma, rng)


def _jittered_poses(eyes: Array, yaw: Array, pitch: float, tilt_sigma: float,
                    rng: np.random.Generator) -> list[Array]:
    """Poses at ``eyes`` (N, 3) heading ``yaw`` (N,), pitched ``pitch`` plus per-frame pitch
    then roll jitter of ``tilt_sigma`` (drawn in that order)."""
    n = len(eyes)
    pitches = pitch + _tilt(rng, tilt_sigma, n)
    roll = _tilt(rng, tilt_sigma, n)
    return [camera_pose(e, e + _direction(yw, p), r)
            for e, yw, p, r in zip(eyes, yaw, pitches, roll, strict=True)]


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


@dataclass(frozen=True)
class CorridorPass:
    """A flight along +x over ``x_range`` at ``y``, weaving sideways by ``weave`` metres (one
    sine period over the pass), looking down the room (+x): the heading turns by
    ``heading_gain`` times the path's own turn (a multirotor need not face where it goes),
    plus ``yaw_offset * sin(2 pi s + yaw_offset_phase)`` for a revisit."""

    x_range: tuple[float, float]
    y: float
    height: float
    weave: float = 0.25
    weave_phase: float = 0.0
    height_swing: float = 0.1
    heading_gain: float = 0.5
    pitch: float = np.radians(-5.0)
    yaw_offset: float = 0.0
    yaw_offset_phase: float = 0.0
    tilt_sigma: float = np.radians(1.5)

    def poses(self, n: int, rng: np.random.Generator) -> list[Array]:
        """``n`` poses spread along the pass, in flight order (a little spacing jitter)."""
        s = (np.arange(n) + rng.uniform(-0.2, 0.2, n)) / max(n - 1, 1)
        (x0, x1), angle = self.x_range, 2 * np.pi * s + self.weave_phase
        x = x0 + (x1 - x0) * s
        y = self.y + self.weave * np.sin(angle)
        z = self.height + self.height_swing * np.sin(3 * np.pi * s + 0.4)
        slope = self.weave * 2 * np.pi * np.cos(angle) / (x1 - x0)  # dy / dx of the path
        yaw = (self.heading_gain * np.arctan(slope)
               + self.yaw_offset * np.sin(2 * np.pi * s + self.yaw_offset_phase))
        return _jittered_poses(np.column_stack([x, y, z]), yaw, self.pitch, self.tilt_sigma, rng)


@dataclass(frozen=True)
class HandheldArc:
    """A person walking an arc around a target (the desk) with a handheld camera: azimuths as
    :class:`ArcLap`, plus hand sway of the eye (smooth, ``sway_m`` per axis at incommensurate
    rates so it never repeats), a wandering look point and a few degrees of roll."""

    target: tuple[float, float, float]
    radius: float
    height: float
    azimuths: tuple[float, float]
    sway_m: float = 0.06
    look_jitter: float = 0.12
    tilt_sigma: float = np.radians(3.0)

    def poses(self, n: int, rng: np.random.Generator) -> list[Array]:
        """``n`` poses along the arc in walking order."""
        s = np.linspace(0.0, 1.0, n) if n > 1 else np.array([0.5])
        az = self.azimuths[0] + (self.azimuths[1] - self.azimuths[0]) * s
        target = np.asarray(self.target)
        eyes = np.column_stack([target[0] + self.radius * np.sin(az),
                                target[1] - self.radius * np.cos(az), np.full(n, self.height)])
        phases = rng.uniform(0, 2 * np.pi, 3)
        rates = np.array([2.3, 3.1, 3.7])  # sway periods per pass, incommensurate
        eyes += self.sway_m * np.sin(2 * np.pi * np.outer(s, rates) + phases)
        looks = target + rng.uniform(-self.look_jitter, self.look_jitter, (n, 3))
        roll = _tilt(rng, self.tilt_sigma, n)
        return [camera_pose(e, t, r) for e, t, r in zip(eyes, looks, roll, strict=True)]


@dataclass(frozen=True)
class PanInPlace:
    """A camera panning on the spot, as on a pan-tilt head or a hovering drone yawing: yaw over
    ``yaw_range`` (radians, 0 = +x), pitch around ``pitch`` and roll within ``tilt`` of level.
    The optical centre sits ``lever_m`` in front of the pivot along the optical axis (no real
    lens has its centre exactly on the rotation axes), so centres lie on a sphere of that
    radius around ``pivot``, plus up to ``hover_m`` of jitter. ``scatter``: random
    orientations in the ranges (queries); otherwise an even sweep (keyframes)."""

    pivot: tuple[float, float, float]
    yaw_range: tuple[float, float]
    pitch: float = np.radians(-6.0)
    tilt: float = np.radians(6.0)
    lever_m: float = 0.004
    hover_m: float = 0.002
    scatter: bool = False

    def poses(self, n: int, rng: np.random.Generator) -> list[Array]:
        """``n`` poses, sweeping or scattered over the yaw range."""
        if self.scatter:
            yaw = rng.uniform(*self.yaw_range, n)
            pitch = self.pitch + rng.uniform(-self.tilt, self.tilt, n)
            roll = rng.uniform(-self.tilt, self.tilt, n)
        else:  # even yaw steps; pitch and roll wave at different rates so views are not coplanar
            s = np.linspace(0.0, 1.0, n) if n > 1 else np.array([0.5])
            yaw = self.yaw_range[0] + (self.yaw_range[1] - self.yaw_range[0]) * s
            pitch = self.pitch + self.tilt * np.sin(2 * np.pi * 1.3 * s + 0.5)
            roll = 0.7 * self.tilt * np.sin(2 * np.pi * 0.9 * s + 2.0)
        axes = np.array([_direction(yw, p) for yw, p in zip(yaw, pitch, strict=True)])
        eyes = np.asarray(self.pivot) + self.lever_m * axes + _in_ball(rng, self.hover_m, n)
        return [camera_pose(e, e + a, r) for e, a, r in zip(eyes, axes, roll, strict=True)]


def _in_ball(rng: np.random.Generator, radius: float, n: int) -> Array:
    """``n`` points (n, 3) uniform in a ball of ``radius`` around the origin."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * radius * rng.uniform(0.0, 1.0, (n, 1)) ** (1 / 3)


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


def stereo_passes(n_map: int, n_query: int, seed: int) -> tuple[list[Array], list[Array]]:
    """A stereo MAV flying down the middle of the ``room`` looking along its long axis (+x);
    the queries revisit on a second pass with another weave, height and up to ~15 degrees of
    extra yaw. The end wall is 3.8-6 m ahead; the side walls (1.6 m to either side) and floor
    and ceiling (1.3 m below and above) enter the 79 x 55 degree view from ~2 m ahead on, so
    the median depth is ~2.8 m, the most this 3.2 m wide room allows (see the tests)."""
    sx, sy, _ = ROOM_SIZE
    train = CorridorPass(x_range=(sx - 6.0, sx - 3.8), y=sy / 2 + 0.05, height=1.3,
                         pitch=np.radians(-2.0))
    r = _rng(seed, "stereo", 0)
    test = replace(train, x_range=(train.x_range[0] + 0.15, train.x_range[1] - 0.1),
                   y=train.y + _signed(r, 0.05, 0.15), height=1.3 + _signed(r, 0.08, 0.18),
                   weave=0.25 + _signed(r, 0.05, 0.1), weave_phase=r.uniform(-0.8, 0.8),
                   pitch=train.pitch + np.radians(r.uniform(-4, 4)),
                   yaw_offset=np.radians(15.0) * r.uniform(0.6, 1.0),
                   yaw_offset_phase=r.uniform(0, 2 * np.pi), tilt_sigma=np.radians(2.5))
    return (train.poses(n_map, _rng(seed, "stereo", 1)),
            test.poses(n_query, _rng(seed, "stereo", 2)))


def handheld_desk_passes(n_map: int, n_query: int,
                         seed: int) -> tuple[list[Array], list[Array]]:
    """A handheld RGB-D camera carried around the desk of the ``desk`` scene at 0.8-1.2 m (the
    TUM fr1/desk distance), then a second pass at another radius, height and span."""
    train = HandheldArc(target=DESK_TARGET, radius=1.0, height=1.45,
                        azimuths=(np.radians(-55.0), np.radians(55.0)))
    r = _rng(seed, "rgbd", 0)
    shift = np.radians(r.uniform(-10, 10))
    test = replace(train, radius=1.0 + _signed(r, 0.08, 0.18), height=1.45 + _signed(r, 0.06, 0.15),
                   azimuths=(train.azimuths[0] + shift + np.radians(6),
                             train.azimuths[1] + shift - np.radians(6)),
                   look_jitter=0.18, tilt_sigma=np.radians(4.0))
    return (train.poses(n_map, _rng(seed, "rgbd", 1)),
            test.poses(n_query, _rng(seed, "rgbd", 2)))


def _pan_in_place(name: str, lever_m: float, query_offset_m: float, n_map: int, n_query: int,
                  seed: int) -> tuple[list[Array], list[Array]]:
    """Keyframes sweeping 120 degrees of yaw from one spot of the ``room``, from facing the
    x = 7 m end wall (~3.5 m away) to facing past the y = 3.2 m wall (~2 m away, the furniture
    along it ~1.5 m): 90 % of the depths lie in 1.5-3.5 m. Queries from the same spot at random
    orientations between and up to 10 degrees around the keyframes'."""
    sx, sy, _ = ROOM_SIZE
    r = _rng(seed, name, 0)
    pivot = (sx / 2 + r.uniform(-0.1, 0.1), sy / 2 - 0.4 + r.uniform(-0.1, 0.1),
             1.35 + r.uniform(-0.05, 0.05))
    start = np.radians(r.uniform(-5.0, 5.0))
    train = PanInPlace(pivot, (start, start + np.radians(120.0)), lever_m=lever_m)
    test = replace(train, yaw_range=(start - np.radians(10.0), start + np.radians(130.0)),
                   scatter=True, hover_m=query_offset_m)
    return train.poses(n_map, _rng(seed, name, 1)), test.poses(n_query, _rng(seed, name, 2))


def rotation_spot(n_map: int, n_query: int, seed: int) -> tuple[list[Array], list[Array]]:
    """Pure rotation: the optical centre 4 mm from the pan axes (centres within 1 cm), queries
    within 2 cm more."""
    return _pan_in_place("rotation", 0.004, 0.02, n_map, n_query, seed)


def rotation_baseline_spot(n_map: int, n_query: int,
                           seed: int) -> tuple[list[Array], list[Array]]:
    """Nearly pure rotation: a handheld camera 2 cm in front of the wrist (keyframe centres on
    a 2 cm arc, ~3.5 cm apart at the ends of the 120 degree sweep), queries within 2.5 cm
    more."""
    return _pan_in_place("rotation-baseline", 0.02, 0.025, n_map, n_query, seed)


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    """A random offset of magnitude in [low, high] and random sign (laps never coincide)."""
    return float(rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _tilt(rng: np.random.Generator, sigma: float, n: int) -> Array:
    """Roll / pitch jitter: Gaussian, clipped at two sigma (a few degrees, never a flip)."""
    return np.clip(rng.normal(0.0, sigma, n), -2 * sigma, 2 * sigma)


def _rng(seed: int, name: str, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(f"trajectory {name}".encode()), stream])


TRAJECTORIES: dict[str, Callable[[int, int, int], tuple[list[Array], list[Array]]]] = {
    "room": room_laps, "desk": desk_laps, "room-stereo": stereo_passes,
    "desk-handheld": handheld_desk_passes, "rotation": rotation_spot,
    "rotation-baseline": rotation_baseline_spot}


def make_trajectories(name: str, n_map: int, n_query: int,
                      seed: int) -> tuple[list[Array], list[Array]]:
    """(map poses, query poses) of trajectory ``name``, each a list of (4, 4) world_from_cam."""
    if name not in TRAJECTORIES:
        raise ConfigError(f"unknown trajectory {name!r}; expected one of {sorted(TRAJECTORIES)}")
    return TRAJECTORIES[name](n_map, n_query, seed)
