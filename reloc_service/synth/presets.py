"""Named synthetic datasets: scene, trajectory, camera, frame counts and query degradations."""

from __future__ import annotations

from dataclasses import dataclass

from ..cameras import Camera, FovCamera, RadTanCamera
from ..errors import ConfigError


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
class Preset:
    """One synthetic dataset recipe (``reloc synth --preset NAME``)."""

    name: str
    description: str
    scene: str  # a key of scene.SCENES
    trajectory: str  # a key of trajectories.TRAJECTORIES
    camera: Camera
    n_map: int
    n_query: int
    degradation: Degradation | None = None  # applied to queries only
    supersample: int = 2
    noise_sigma: float = 2.0  # grey levels of 255

    def __post_init__(self) -> None:
        if self.n_map < 1 or self.n_query < 0 or self.supersample < 1 or self.noise_sigma < 0:
            raise ConfigError(f"preset {self.name!r}: expected n_map >= 1, n_query >= 0, "
                              f"supersample >= 1, noise_sigma >= 0")


# A real lens with moderate barrel distortion (k1 k2 p1 p2), 640x480, ~70 degrees wide.
LENS_640 = RadTanCamera(640, 480, fx=460.0, fy=459.0, cx=319.3, cy=241.2,
                        distortion=(-0.28, 0.07, 1e-4, -2e-4))
# SVO / PTAM style FOV (ATAN) camera, ~100 degrees wide.
FOV_640 = FovCamera(640, 480, fx=340.0, fy=340.0, cx=320.4, cy=239.6, distortion=(0.9,))

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
