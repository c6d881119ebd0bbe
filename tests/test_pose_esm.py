"""Tests of the ESM pose finder: SE(2) thumbnail alignment and the SE(2) -> SO(3) fit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from reloc_service.algorithms.place.base import PlaceCandidate
from reloc_service.algorithms.pose import esm
from reloc_service.algorithms.pose.base import create_pose_finder
from reloc_service.algorithms.relocalizers.base import VerifyConf, verify
from reloc_service.core.cameras import FovCamera, PinholeCamera
from reloc_service.core.errors import ConfigError
from reloc_service.core.frame import Frame, Keyframe
from reloc_service.core.geometry import look_at, pose_error, so3_exp, so3_log
from reloc_service.core.map import KeyframeMap
from reloc_service.core.numeric import zncc

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
WORLD_FROM_KF = look_at([1.0, 2.0, 1.5], [3.0, 2.0, 1.0])


def _source(name: str) -> np.ndarray:
    """A 1280x960 grey photo: the scene the 640x480 views are cut from."""
    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return cv2.resize(img, (1280, 960), interpolation=cv2.INTER_AREA)


def _se2_view(source: np.ndarray, warp_centred: np.ndarray) -> np.ndarray:
    """640x480 view of the source's centre, moved so that view(W(x)) = centre_view(x)."""
    h, w = source.shape
    offset = np.array([[1.0, 0.0, (w - 640) / 2], [0.0, 1.0, (h - 480) / 2], [0.0, 0.0, 1.0]])
    dst_to_src = offset @ np.linalg.inv(esm.about_centre(warp_centred, (640, 480)))
    return cv2.warpAffine(source, dst_to_src[:2], (640, 480),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _rotated_view(source: np.ndarray, kf_from_cam_rotation: np.ndarray) -> np.ndarray:
    """What a camera turned by ``kf_from_cam_rotation`` about the keyframe's centre sees of a
    distant plane (the source, focal 500 px): the homography K R K^-1."""
    h, w = source.shape
    k_src = np.array([[500.0, 0.0, (w - 1) / 2], [0.0, 500.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    dst_to_src = k_src @ kf_from_cam_rotation @ np.linalg.inv(CAMERA.K)
    return cv2.warpPerspective(source, dst_to_src, (640, 480),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _keyframe(image: np.ndarray, kf_id: int = 0) -> Keyframe:
    return Keyframe(image=image, camera=CAMERA, id=kf_id, world_from_cam=WORLD_FROM_KF)


@pytest.fixture(scope="module")
def finder() -> esm.EsmPoseFinder:
    f = create_pose_finder({"name": "esm"})
    assert isinstance(f, esm.EsmPoseFinder)
    return f


@pytest.mark.parametrize("name", ["astronaut", "coffee", "chelsea"])
@pytest.mark.parametrize("alpha_deg,shift_px", [(8.0, (12.0, -20.0)), (-15.0, (-24.0, 8.0))])
def test_se2_alignment_recovers_rotation_and_shift(finder, name, alpha_deg, shift_px):
    source = _source(name)
    # Full-resolution motion; the 80x60 thumbnails move by the same angle and 1/8 the shift.
    truth = esm.se2(np.deg2rad(alpha_deg), *shift_px)
    query = Frame(image=_se2_view(source, truth), camera=CAMERA)
    alignment = finder.align(query, _keyframe(_se2_view(source, np.eye(3))))
    alpha, tx, ty = esm.se2_params(alignment.warp_centred)
    assert abs(np.rad2deg(alpha) - alpha_deg) < 0.3
    assert np.hypot(tx * 8 - shift_px[0], ty * 8 - shift_px[1]) < 1.5  # full-resolution px
    assert alignment.converged
    assert alignment.ncc > 0.98 and alignment.ncc > alignment.ncc_initial + 0.05


@pytest.mark.parametrize("shift_thumb_px", [(3.0, 0.0), (-2.0, 3.0), (4.0, -4.0)])
def test_converges_from_a_few_pixels_offset(finder, shift_thumb_px):
    source = _source("camera")
    truth = esm.se2(0.0, shift_thumb_px[0] * 8, shift_thumb_px[1] * 8)
    query = Frame(image=_se2_view(source, truth), camera=CAMERA)
    alignment = finder.align(query, _keyframe(_se2_view(source, np.eye(3))))
    alpha, tx, ty = esm.se2_params(alignment.warp_centred)
    assert abs(alpha) < np.deg2rad(0.3)
    assert np.hypot(tx - shift_thumb_px[0], ty - shift_thumb_px[1]) < 0.15
    assert alignment.ncc > 0.98 > alignment.ncc_initial


def test_single_level_esm_step_reduces_the_error():
    source = _source("astronaut")
    kf, query = _keyframe(_se2_view(source, np.eye(3))), Frame(
        image=_se2_view(source, esm.se2(0.05, 8.0, 0.0)), camera=CAMERA)
    tpl, img = kf.small_blurry_image(40, 30, 2.5), query.small_blurry_image(40, 30, 2.5)
    warp, iterations, converged = esm.esm_level(tpl, img, np.eye(3), max_iterations=1,
                                                convergence_px=1e-6)
    before = zncc(tpl, *esm.warp_image(img, np.eye(3)))
    after = zncc(tpl, *esm.warp_image(img, warp))
    assert iterations == 1 and not converged and after > before


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.1), (0.03, 0.0, 0.0), (0.0, -0.04, 0.0),
                                    (0.02, -0.03, 0.08)])
def test_pose_is_the_keyframe_turned_about_its_centre(finder, rotvec):
    """A query from the keyframe camera turned by a known rotation: the estimate turns the
    same way (not the inverse), about the keyframe's centre."""
    source = _source("coffee")
    kf = _keyframe(_rotated_view(source, np.eye(3)), kf_id=3)
    kmap = KeyframeMap()
    kmap.add_keyframe(kf)
    kf_from_query = so3_exp(rotvec)
    query = Frame(image=_rotated_view(source, kf_from_query), camera=CAMERA)
    estimate = finder.find_pose(query, [PlaceCandidate(3, 1.0)], kmap.snapshot())
    assert estimate is not None and estimate.keyframe_ids == [3]
    truth = WORLD_FROM_KF.copy()
    truth[:3, :3] = WORLD_FROM_KF[:3, :3] @ kf_from_query
    wrong = WORLD_FROM_KF.copy()
    wrong[:3, :3] = WORLD_FROM_KF[:3, :3] @ kf_from_query.T
    dt, dr = pose_error(estimate.world_from_cam, truth)
    angle = np.linalg.norm(rotvec)
    assert dt < 1e-9  # a rotation about the keyframe's centre
    # SE(2) only approximates a rotation's perspective image motion (PTAM's model): the
    # translation is averaged over a wide (65 deg) field of view, hence a relative tolerance.
    assert dr < 0.2 * angle + np.deg2rad(0.05)
    assert pose_error(estimate.world_from_cam, wrong)[1] > 1.5 * angle
    assert estimate.ncc > 0.95
    assert verify(estimate, VerifyConf())[0]


def test_rotation_fit_roll_and_pan_with_a_fisheye_model():
    camera = FovCamera(640, 480, 300.0, 300.0, 319.5, 239.5, distortion=(0.9,))
    size = (80, 60)
    # In-plane rotation of the thumbnail about the principal point: the camera rolls.
    roll = esm.about_centre(esm.se2(0.1, 0.0, 0.0), size)
    query_from_kf = esm.rotation_from_se2(roll, size, camera, camera, offset_px=10.0)
    assert query_from_kf is not None
    np.testing.assert_allclose(so3_log(query_from_kf), [0.0, 0.0, 0.1], atol=1e-6)
    # Scene moving right in the query: the camera turned left (about its y axis, down).
    pan = esm.about_centre(esm.se2(0.0, 2.0, 0.0), size)
    query_from_kf = esm.rotation_from_se2(pan, size, camera, camera, offset_px=10.0)
    assert query_from_kf is not None
    omega = so3_log(query_from_kf)
    assert omega[1] > 0 and abs(omega[0]) < 1e-6 and abs(omega[2]) < 1e-6
    # The fitted rotation moves the two fit points where the warp sends them (up to the small
    # residual left because a pan does not translate an image exactly).
    centre = esm.full_to_thumb(np.array([[camera.cx, camera.cy]]), size, camera)[0]
    u = centre + np.array([[10.0, 0.0], [-10.0, 0.0]])
    moved = camera.project(camera.unproject(esm.thumb_to_full(u, size, camera)) @ query_from_kf.T)
    np.testing.assert_allclose(esm.full_to_thumb(moved, size, camera), u + [2.0, 0.0], atol=0.01)


def test_best_ncc_among_candidates(finder):
    right_source, other_source = _source("astronaut"), _source("brick")
    right = _keyframe(_se2_view(right_source, np.eye(3)), kf_id=1)
    other = _keyframe(_se2_view(other_source, np.eye(3)), kf_id=2)
    kmap = KeyframeMap()
    kmap.add_keyframe(right)
    kmap.add_keyframe(other)
    query = Frame(image=_se2_view(right_source, esm.se2(0.1, 10.0, 5.0)), camera=CAMERA)
    ranked = [PlaceCandidate(2, 1.0), PlaceCandidate(1, 0.5)]  # the wrong one first
    first_only = finder.find_pose(query, ranked, kmap.snapshot())
    two = create_pose_finder({"name": "esm", "candidates": 2})
    both = two.find_pose(query, ranked, kmap.snapshot())
    assert both is not None and both.keyframe_ids == [1] and both.ncc > 0.95
    # With one candidate the wrong keyframe is used, and its NCC does not pass verification.
    assert first_only is None or (first_only.keyframe_ids == [2]
                                  and not verify(first_only, VerifyConf())[0])


def test_missing_keyframes_and_no_candidates_give_none(finder):
    query = Frame(image=_se2_view(_source("camera"), np.eye(3)), camera=CAMERA)
    state = KeyframeMap().snapshot()
    assert finder.find_pose(query, [], state) is None
    assert finder.find_pose(query, [PlaceCandidate(7, 1.0)], state) is None


def test_config_errors():
    with pytest.raises(ConfigError, match="coarsest"):
        create_pose_finder({"name": "esm", "width": 40, "height": 30, "levels": 4})
    with pytest.raises(ConfigError):
        create_pose_finder({"name": "esm", "candidates": 0})
    with pytest.raises(ConfigError, match="unknown option"):
        create_pose_finder({"name": "esm", "pyramid": 3})
