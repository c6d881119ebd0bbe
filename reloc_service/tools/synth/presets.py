"""Named synthetic datasets: scene, trajectory, cameras (one, or a rigid multi-camera rig),
frame counts, query degradations and an optional RGB-D depth sensor model."""

from __future__ import annotations

from dataclasses import dataclass

from ...core.cameras import Camera, FovCamera, PinholeCamera, RadTanCamera
from ...core.errors import ConfigError

CAMERA_ID = "cam0"  # the preset's main camera; queries are always taken by it


@dataclass(frozen=True)
class Degradation:
    """Query-only nuisances of the ``-hard`` presets; each is applied to a query independently
    with its probability. Ranges are (low, high) of uniform draws; blur lengths are for a
    640 px wide image and scale with the width."""

    blur_prob: float = 0.75
    blur_px: tuple[float, float] = (4.0, 14.0)
    exposure_prob: float = 0.75
    gain: tuple[float, float] = (0.5, 1.6)
    gamma: tuple[float, float] = (0.7, 1.45)
    occlusion_prob: float = 0.75
    occlusion_area: tuple[float, float] = (0.2, 0.3)  # fraction of the image
    occluder_depth_m: tuple[float, float] = (0.25, 0.5)


@dataclass(frozen=True)
class RigCamera:
    """A further camera rigidly mounted next to ``cam0`` with the same orientation, at
    ``offset_m`` (x right, y down, z forward) in cam0's frame: its ``world_from_cam`` is
    ``cam0_world_from_cam @ translation(offset_m)``. It takes a map keyframe at every map pose
    (a stereo pair shares the trajectory's pose index); queries come from cam0 only."""

    camera_id: str
    camera: Camera
    offset_m: tuple[float, float, float]


@dataclass(frozen=True)
class DepthSensor:
    """How an RGB-D camera (structured light or time of flight, Kinect / RealSense class)
    corrupts the exact Z-depth; ``depth.txt`` then lists this sensor depth, 0 = no value.

    Defaults follow the Kinect v1 analysis of Khoshelham & Elberink (2012): axial noise grows
    with the square of depth (depth is triangulated from disparity, so dz = z^2 / (f b) dd),
    sigma ~ 1.5e-3 z^2 m (1.5 mm at 1 m, 3.4 cm at 4.75 m); no value outside the working range
    ([0.5, 4.5] m: nearer, the projected pattern falls outside the disparity search range,
    further, its dots are too faint); none where the surface is seen at more than ~75 degrees
    incidence (the pattern stretches beyond what block matching recognises); none within a
    band of a few pixels of a depth discontinuity (the 9x9 matching window straddles two
    surfaces there); and a small fraction of random dropouts (speckle, specularities)."""

    axial_noise_per_m2: float = 1.5e-3  # sigma = k z^2 (metres)
    min_range_m: float = 0.5
    max_range_m: float = 4.5
    max_incidence_deg: float = 75.0
    # A plane at incidence theta changes Z by about z tan(theta) / f per pixel: 0.7 % of z at
    # 75 degrees with f = 525 px. A step above 3 % of z between neighbours is therefore not one
    # surface the sensor sees but an occlusion boundary.
    discontinuity_rel: float = 0.03
    edge_band_px: float = 3.0  # at 640 px width: half the 9x9 window, scaled with the image
    dropout_fraction: float = 0.005
    metres_per_unit: float = 0.001  # 1 mm units, as the Kinect / TUM RGB-D driver output

    def __post_init__(self) -> None:
        if not (0 <= self.axial_noise_per_m2 and 0 <= self.min_range_m < self.max_range_m
                and 0 < self.max_incidence_deg <= 90 and self.discontinuity_rel > 0
                and self.edge_band_px >= 0 and 0 <= self.dropout_fraction < 1
                and self.metres_per_unit > 0):
            raise ConfigError(f"depth sensor: expected non-negative noise, 0 <= min_range < "
                              f"max_range, 0 < max_incidence <= 90 deg, positive discontinuity "
                              f"threshold and units, dropout fraction in [0, 1); got {self}")


@dataclass(frozen=True)
class Preset:
    """One synthetic dataset recipe (``reloc synth --preset NAME``). ``camera`` is ``cam0``;
    ``rig`` adds cameras mounted with it; ``depth_sensor`` makes it an RGB-D dataset whose
    ``depth.txt`` lists sensor-like depth (every preset lists its exact depth in
    ``truth_depth.txt``)."""

    name: str
    description: str
    scene: str  # a key of scenes.SCENES
    trajectory: str  # a key of trajectories.TRAJECTORIES
    camera: Camera
    n_map: int
    n_query: int
    degradation: Degradation | None = None  # applied to queries only
    supersample: int = 2
    noise_sigma: float = 2.0  # grey levels of 255
    rig: tuple[RigCamera, ...] = ()
    depth_sensor: DepthSensor | None = None

    def __post_init__(self) -> None:
        if self.n_map < 1 or self.n_query < 0 or self.supersample < 1 or self.noise_sigma < 0:
            raise ConfigError(f"preset {self.name!r}: expected n_map >= 1, n_query >= 0, "
                              f"supersample >= 1, noise_sigma >= 0")
        ids = [CAMERA_ID] + [c.camera_id for c in self.rig]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"preset {self.name!r}: rig camera ids {ids} must be unique and "
                              f"differ from {CAMERA_ID!r}")

    @property
    def cameras(self) -> dict[str, Camera]:
        """Camera id -> camera: ``cam0`` first, then the rig's."""
        return {CAMERA_ID: self.camera, **{c.camera_id: c.camera for c in self.rig}}

    @property
    def n_map_frames(self) -> int:
        """Map keyframes: one per map pose and camera."""
        return self.n_map * (1 + len(self.rig))


# A real lens with moderate barrel distortion (k1 k2 p1 p2), 640x480, ~70 degrees wide.
LENS_640 = RadTanCamera(640, 480, fx=460.0, fy=459.0, cx=319.3, cy=241.2,
                        distortion=(-0.28, 0.07, 1e-4, -2e-4))
# SVO / PTAM style FOV (ATAN) camera, ~100 degrees wide.
FOV_640 = FovCamera(640, 480, fx=340.0, fy=340.0, cx=320.4, cy=239.6, distortion=(0.9,))
# A MAV stereo pair like EuRoC's (MT9V034 global shutter, 752x480, ~79 degrees wide), with a
# milder barrel distortion than EuRoC's and, as in any real rig, slightly different lenses.
STEREO_LEFT = RadTanCamera(752, 480, fx=460.2, fy=459.1, cx=371.4, cy=246.8,
                           distortion=(-0.12, 0.018, 2e-4, -1e-4))
STEREO_RIGHT = RadTanCamera(752, 480, fx=458.9, fy=458.3, cx=377.9, cy=251.6,
                            distortion=(-0.115, 0.016, -1e-4, 1.5e-4))
STEREO_BASELINE_M = 0.11  # EuRoC's VI-Sensor baseline
# The factory default of a Kinect / TUM RGB-D colour camera registered with its depth.
RGBD_640 = PinholeCamera(640, 480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)

PRESETS: dict[str, Preset] = {}


def register_preset(preset: Preset) -> Preset:
    """Add ``preset`` to :data:`PRESETS`; a duplicate name is a ConfigError."""
    if preset.name in PRESETS:
        raise ConfigError(f"duplicate synth preset {preset.name!r}")
    PRESETS[preset.name] = preset
    return preset


def get_preset(name: str) -> Preset:
    """The preset called ``name``; ConfigError listing the known names otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown synth preset {name!r}; expected one of "
                          f"{sorted(PRESETS)}") from None


register_preset(Preset(
    "desk", "desk with monitor, books and boxes, ~2 m^2 covered, 10 map / 10 query frames "
    "(the thesis's desktop dataset)", "desk", "desk", LENS_640, 10, 10))
register_preset(Preset(
    "desk-hard", "desk, queries with motion blur, exposure change and occlusion",
    "desk", "desk", LENS_640, 10, 10, Degradation()))
register_preset(Preset(
    "room", "7 x 3 m room with furniture and posters, 84 map / 69 query frames "
    "(the thesis's large dataset)", "room", "room", LENS_640, 84, 69))
register_preset(Preset(
    "room-hard", "room, queries with motion blur, exposure change and occlusion",
    "room", "room", LENS_640, 84, 69, Degradation()))
register_preset(Preset(
    "room-fov", "room seen through a wide FOV (ATAN, omega 0.9) camera as used by SVO",
    "room", "room", FOV_640, 84, 69))
register_preset(Preset(
    "stereo", "EuRoC-like MAV stereo pair (752x480, 11 cm baseline) flying down the room, "
    "14 rig poses = 28 map keyframes (cam0, cam1), 20 cam0 queries from a second pass",
    "room", "room-stereo", STEREO_LEFT, 14, 20,
    rig=(RigCamera("cam1", STEREO_RIGHT, (STEREO_BASELINE_M, 0.0, 0.0)),)))
register_preset(Preset(
    "rgbd", "handheld Kinect-like RGB-D camera around the desk: depth.txt holds sensor depth "
    "(noise, holes), truth_depth.txt the exact depth; 24 map / 20 query frames",
    "desk", "desk-handheld", RGBD_640, 24, 20, depth_sensor=DepthSensor()))
register_preset(Preset(
    "rotation", "camera rotating in place in the room (centres within 1 cm, ~120 deg of yaw), "
    "12 map / 12 query frames from the same spot, for relative-pose relocalizers",
    "room", "rotation", LENS_640, 12, 12))
register_preset(Preset(
    "rotation-baseline", "as rotation, but keyframe centres spread over 3-4 cm (tiny "
    "baselines), queries within ~5 cm", "room", "rotation-baseline", LENS_640, 12, 12))
register_preset(Preset(
    "repeated", "a room built from repetition: four pictures hung 12 times (as printed, "
    "mirrored, cropped, as mosaics), periodic tiled walls and floor, identical windows, rugs, "
    "cabinets, crates and benches; 84 map / 69 query frames on the room laps",
    "repeated", "room", LENS_640, 84, 69))
register_preset(Preset(
    "repeated-hard", "repeated, queries with motion blur, exposure change and occlusion",
    "repeated", "room", LENS_640, 84, 69, Degradation()))
