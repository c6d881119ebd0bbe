import numpy as np
import pytest

from reloc_service.core.cameras import CAMERA_MODELS, camera_from_dict
from reloc_service.core.errors import CameraError

BASE = dict(width=640, height=480, fx=458.0, fy=457.0, cx=321.5, cy=238.2)
MODELS = {
    "pinhole": [],
    "radtan": [-0.28, 0.073, 1.8e-4, -2.0e-4, 0.01],
    "equidistant": [-0.013, 0.02, -0.011, 0.0025],
    "fov": [0.93],
}


@pytest.fixture(params=sorted(MODELS))
def camera(request):
    return camera_from_dict(dict(BASE, model=request.param, distortion=MODELS[request.param]))


def image_grid(cam, n=120):
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, n), np.linspace(-0.5, cam.height - 0.5, n))
    return np.column_stack([u.ravel(), v.ravel()])


def test_every_model_is_tested():
    assert set(MODELS) == set(CAMERA_MODELS)


def test_unproject_project_round_trip_whole_image(camera):
    px = image_grid(camera)
    bearings = camera.unproject(px)
    assert np.allclose(np.linalg.norm(bearings, axis=1), 1.0)
    depth = np.random.default_rng(0).uniform(0.2, 30.0, size=(len(px), 1))
    assert np.abs(camera.project(bearings * depth) - px).max() < 1e-6


def test_project_unproject_round_trip(camera):
    rng = np.random.default_rng(1)
    px = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(500, 2))
    points = camera.unproject(px) * rng.uniform(0.5, 5.0, size=(500, 1))
    bearings = camera.unproject(camera.project(points))
    assert np.allclose(bearings, points / np.linalg.norm(points, axis=1, keepdims=True), atol=1e-9)


def test_undistort_pixels_is_pinhole_of_bearing(camera):
    px = image_grid(camera, 30)
    b = camera.unproject(px)
    ideal = b[:, :2] / b[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    assert np.allclose(camera.undistort_pixels(px), ideal, atol=1e-9)


def test_behind_camera_is_nan(camera):
    assert np.all(np.isnan(camera.project([[0.0, 0.0, -1.0]])))


def test_dict_round_trip(camera):
    assert camera_from_dict(camera.to_dict()) == camera


def test_scaled_keeps_rays(camera):
    half = camera.scaled(0.5)
    b = camera.unproject([[100.0, 50.0]])
    assert np.allclose(half.project(b), ([[100.0, 50.0]] + np.array(0.5)) * 0.5 - 0.5, atol=1e-9)


@pytest.mark.parametrize("bad, match", [
    (dict(BASE, model="kannala"), "unknown model"),
    (dict(BASE, model="radtan", distortion=[0.1]), "expected 4 or 5 distortion"),
    (dict(BASE, model="pinhole", fx=-1.0), "positive"),
    ({"model": "pinhole", "width": 10}, "missing field"),
    (dict(BASE, model="fov", distortion=[4.0]), "omega"),
    (dict(BASE, model="pinhole", fx="a lot"), "numbers"),
    (dict(BASE, model="pinhole", colour=True), "unknown field"),
])
def test_camera_errors(bad, match):
    with pytest.raises(CameraError, match=match):
        camera_from_dict(bad)


def _newton_from_distorted(camera, xy_distorted):
    """The radtan undistortion's definition: 2x2 Newton started at the distorted point."""
    q = xy_distorted.copy()
    for _ in range(30):
        res = camera.distort(q) - xy_distorted
        a, b, c, d = camera._jacobian(q[:, 0], q[:, 1])
        det = a * d - b * c
        step = np.column_stack([(d * res[:, 0] - b * res[:, 1]) / det,
                                (-c * res[:, 0] + a * res[:, 1]) / det])
        q = q - step
        if np.abs(step).max() < 1e-15:
            break
    return q


@pytest.mark.parametrize("distortion", [[-0.28, 0.07, 1e-4, -2e-4], [-0.4, 0.15, 0.0, 0.0],
                                        [0.1, -0.05, 1e-3, 2e-3], [0.0, 0.0, 0.0, 0.0],
                                        [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]])
def test_radtan_undistort_from_opencv_start_is_newtons_root(distortion):
    """Newton starts from OpenCV's fixed-point undistortion (fewer numpy steps): the same
    root as started from the distorted point, over the whole image and a little beyond."""
    camera = camera_from_dict({"model": "radtan", "width": 640, "height": 480, "fx": 460.0,
                               "fy": 459.0, "cx": 319.3, "cy": 241.2,
                               "distortion": distortion})
    px = np.random.default_rng(3).uniform([-20, -20], [660, 500], (3000, 2))
    xy_distorted = camera.pixels_to_normalized(px)
    np.testing.assert_allclose(camera.undistort(xy_distorted),
                               _newton_from_distorted(camera, xy_distorted), rtol=0, atol=1e-12)
    assert camera.undistort(np.zeros((0, 2))).shape == (0, 2)
