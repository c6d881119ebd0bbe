"""The compiled projection, pose Jacobian and undistortion (reloc_service.algorithms.pose.kernels) give
the numpy path's values to the bit; the fused fit (inliers and normal equations of a pose),
the Gauss-Newton update and the covariance's inverse give them to rounding (sums in another
order): on their own, and through whole relocalizations of the real TUM fixture (the same
inliers and verdicts)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from reloc_service.algorithms.pose import (
    chance,
    guided,
    guided_kernels,
    kernels,
    landmark_matches,
    pnp,
    point_uncertainty,
    projection,
)
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core.cameras import Camera, camera_from_dict
from reloc_service.core.frame import Frame
from reloc_service.engine import Engine, EngineConf
from reloc_service.tools.data.dataset import read_dataset

pytest.importorskip("numba")

FIXTURE = Path(__file__).parent / "data" / "tum_fr1_rpy_mini"


def _cameras() -> list[Camera]:
    """The fixture's real radtan camera (5 coefficients), a 4-coefficient strong radtan lens
    and a pinhole camera."""
    real = json.loads((FIXTURE / "cameras.json").read_text())["tum_fr1_rgb"]
    return [camera_from_dict(real),
            camera_from_dict({**real, "distortion": [-0.28, 0.07, 1e-4, -2e-4]}),
            camera_from_dict({**real, "model": "pinhole", "distortion": []})]


def _points_cam(n: int = 400) -> np.ndarray:
    """Camera-frame points over (and beyond) the image, a few behind the camera, one NaN."""
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), np.ones(n)]) * rng.uniform(0.3, 8, (n, 1))
    pts[:5, 2] = [-1.0, 0.0, 1e-13, -3.0, 5e-13]
    pts[5] = np.nan
    return pts


def _numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pnp, "compiled", lambda: None)
    monkeypatch.setattr(projection, "compiled", lambda: None)
    monkeypatch.setattr(landmark_matches, "compiled", lambda: None)
    monkeypatch.setattr(point_uncertainty, "compiled", lambda: None)
    monkeypatch.setattr(chance, "compiled", lambda: None)
    monkeypatch.setattr(guided, "compiled", lambda: None)


@pytest.mark.parametrize("index", range(3))
def test_projection_and_jacobian_are_the_numpy_values(index, monkeypatch):
    camera, pts = _cameras()[index], _points_cam()
    assert kernels.compiled() is not None
    fast_px, fast_jac = projection.project_cam(camera, pts), projection.pose_jacobian(camera, pts[6:])
    _numpy_path(monkeypatch)
    slow_px, slow_jac = projection.project_cam(camera, pts), projection.pose_jacobian(camera, pts[6:])
    assert np.array_equal(fast_px, slow_px, equal_nan=True)
    assert np.array_equal(fast_px, camera.project(pts), equal_nan=True)
    assert np.isnan(fast_px[:6]).all() and np.isfinite(fast_px[6:]).all()
    assert np.array_equal(fast_jac, slow_jac)


@pytest.mark.parametrize("index", range(2))
def test_undistortion_is_the_numpy_value(index, monkeypatch):
    camera = _cameras()[index]
    rng = np.random.default_rng(6)
    px = np.vstack([rng.uniform([-40, -40], [camera.width + 40, camera.height + 40], (500, 2)),
                    [[np.nan, 3.0]]])
    fast = projection.undistort_pixels(camera, px)
    _numpy_path(monkeypatch)
    assert np.array_equal(fast, projection.undistort_pixels(camera, px), equal_nan=True)
    assert np.array_equal(fast, camera.undistort_pixels(px), equal_nan=True)


def test_opencv_start_is_opencvs_undistortion():
    """The compiled start of the radtan undistortion is ``cv2.undistortPoints`` to the bit,
    also far outside the image, where a strong lens's radial factor turns negative."""
    import cv2

    rng = np.random.default_rng(8)
    assert kernels.compiled() is not None  # the compiled helper replaces the Python one
    assert hasattr(kernels._opencv_undistort, "py_func")
    for dist in ([0.262383, -0.953104, -0.005358, 0.002628, 1.163314],
                 [-0.28, 0.07, 1e-4, -2e-4], [-2.0, 0.3, 0.01, -0.02, 0.1]):
        camera = camera_from_dict({"model": "radtan", "width": 640, "height": 480, "fx": 1.0,
                                   "fy": 1.0, "cx": 0.0, "cy": 0.0, "distortion": dist})
        params, _ = kernels.camera_params(camera)
        normalised = rng.uniform(-1.5, 1.5, (4000, 2))
        want = cv2.undistortPoints(normalised.reshape(-1, 1, 2), np.eye(3),
                                   np.asarray(dist, np.float64),
                                   criteria=(cv2.TERM_CRITERIA_COUNT, 40, 0.0)).reshape(-1, 2)
        starts = np.array([kernels._opencv_undistort(u, v, params, 40) for u, v in normalised])
        assert np.array_equal(starts, want, equal_nan=True), dist
    r2 = (normalised**2).sum(1)
    assert ((1 + ((0.1 * r2 + 0.3) * r2 - 2.0) * r2) < 0).any()  # the negative factor's branch


def test_pixel_sigmas_and_chance_pairs_are_the_numpy_values(monkeypatch):
    """Depth uncertainty in pixels (rays from keyframe centres, some points on a centre,
    one NaN) and the count of chance agreements (many near ties in x), both paths."""
    camera, rng = _cameras()[0], np.random.default_rng(7)
    world_from_cam = np.eye(4)
    pts = _points_cam()[6:]
    origins = rng.normal(scale=0.5, size=pts.shape)
    origins[:3] = pts[:3]  # a zero ray: the norm's floor
    sigmas = rng.uniform(0, 0.3, len(pts))
    sigmas[3] = np.nan
    unc = point_uncertainty.PointUncertainty(sigmas, origins)
    rows = np.arange(len(pts))
    px = np.round(rng.uniform([0, 0], [640, 480], (300, 2)) / 4) * 4  # ties in x
    projected = px + rng.normal(scale=3, size=px.shape)
    fast = [unc.pixel_sigmas(world_from_cam, pts, camera, rows),
            unc.pixel_sigmas(world_from_cam, pts, camera, rows,
                             projected_px=camera.project(pts)),
            chance._pairs_within(projected, px, 5.0), chance._pairs_within(projected, px, 2.5)]
    assert np.isinf(fast[0][3]) and fast[2] > fast[3] > 0
    _numpy_path(monkeypatch)
    slow = [unc.pixel_sigmas(world_from_cam, pts, camera, rows),
            unc.pixel_sigmas(world_from_cam, pts, camera, rows,
                             projected_px=camera.project(pts)),
            chance._pairs_within(projected, px, 5.0), chance._pairs_within(projected, px, 2.5)]
    for f, s in zip(fast, slow, strict=True):
        assert np.array_equal(f, s)


def test_inlier_test_is_the_numpy_choice(monkeypatch):
    """Reprojection errors against the threshold: the same inliers, points behind the
    camera (NaN pixels) and NaN keypoints never among them."""
    camera, rng = _cameras()[0], np.random.default_rng(10)
    pts = _points_cam()
    view = pnp._View.at(np.eye(4), pts, camera)
    px = view.px + rng.normal(scale=4.0, size=view.px.shape)
    px[7] = np.nan
    conf = pnp.PnPConf()
    fast = view.inliers(px, conf)
    _numpy_path(monkeypatch)
    slow = view.inliers(px, conf)
    assert np.array_equal(fast, slow) and 0 < len(fast) < len(px) - 6
    assert not np.isin([0, 1, 2, 3, 4, 5, 7], fast).any()


def test_best_match_per_landmark_is_the_numpy_choice():
    """Many query keypoints per pool row, equal distances among them: the same kept
    matches (nearest, the first of equally near ones) from rows as from landmark ids."""
    rng = np.random.default_rng(9)
    ids = rng.permutation(np.arange(100, 400))  # a pool: one row per landmark
    rows = rng.integers(0, len(ids), 500)
    dist = rng.integers(0, 6, 500).astype(np.float32)  # many ties
    fast = landmark_matches.best_per_landmark(ids[rows], dist, rows, len(ids))
    slow = landmark_matches.best_per_landmark(ids[rows], dist)
    assert np.array_equal(fast, slow) and len(np.unique(rows)) == len(fast) < len(rows)


@pytest.mark.slow
def test_relocalizations_of_real_images_are_the_same_with_and_without_kernels(monkeypatch):
    """The default method on the TUM fixture's queries: the same poses, covariances, inliers
    and verdicts, compiled or not (one engine, the kernels switched off in between)."""
    ds = read_dataset(FIXTURE)
    engine = Engine(EngineConf(methods=(DEFAULT_METHOD,)))
    for i, entry in enumerate(ds.map_entries):
        engine.add_keyframe(i, ds.load_image(entry), ds.camera(entry), entry.world_from_cam)
    engine.train()

    def answers():
        out = []
        for entry in ds.query_entries:
            r = engine.relocalize(Frame(ds.load_image(entry), ds.camera(entry)),
                                  method=DEFAULT_METHOD)
            out.append((r.ok, r.inliers, r.world_from_cam, r.covariance, r.reason))
        return out

    fast = answers()
    _numpy_path(monkeypatch)
    slow = answers()
    assert sum(ok for ok, *_ in fast) == len(ds.query_entries)
    for (ok_f, inl_f, pose_f, cov_f, why_f), (ok_s, inl_s, pose_s, cov_s, why_s) in zip(
            fast, slow, strict=True):
        assert (ok_f, inl_f, why_f) == (ok_s, inl_s, why_s)
        np.testing.assert_allclose(pose_f, pose_s, rtol=0, atol=1e-12)
        np.testing.assert_allclose(cov_f, cov_s, rtol=1e-9, atol=0)


def _correspondences(camera: Camera, uncertain: bool, scaled: bool):
    """Points seen from a pose, their pixels with noise, outliers, a NaN keypoint and points
    behind the camera; optional depth uncertainty and keypoint scales."""
    rng = np.random.default_rng(12)
    world_from_cam = pnp.se3_exp(np.array([0.3, -0.2, 0.1, 0.05, -0.1, 0.02]))
    pts_cam = _points_cam()
    pts_cam[5] = [0.1, 0.1, 2.0]  # _points_cam's NaN point: a finite one, the NaN is a pixel
    px = projection.project_cam(camera, pts_cam) + rng.normal(0.0, 1.5, (len(pts_cam), 2))
    px[6:60] = rng.uniform([0, 0], [640, 480], (54, 2))
    px[61] = np.nan
    pts = pts_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    unc = (point_uncertainty.PointUncertainty(rng.uniform(0.0, 0.2, len(pts)),
                                pts + rng.normal(0.0, 1.0, pts.shape)) if uncertain else None)
    scales = pnp.level_scales(rng.integers(0, 8, len(pts)), 1.2) if scaled else None
    return world_from_cam @ pnp.se3_exp(rng.normal(0.0, 0.003, 6)), px, pts, unc, scales


@pytest.mark.parametrize("index", range(3))
@pytest.mark.parametrize("uncertain,scaled", [(False, False), (True, False), (False, True),
                                              (True, True)])
def test_fused_fit_is_the_numpy_fit(index, uncertain, scaled):
    """One pass per pose gives the inliers, their projections, the normal equations and the
    residual sums of the numpy path's projections, residuals, Jacobian and weights."""
    camera = _cameras()[index]
    pose, px, pts, unc, scales = _correspondences(camera, uncertain, scaled)
    conf = pnp.PnPConf()
    fast = pnp._fit_at(pose, px, pts, camera, conf, unc, scales)
    slow = pnp._fit_numpy(pose, px, pts, camera, conf, unc, scales)
    assert np.array_equal(fast.inliers, slow.inliers) and 200 < len(fast.inliers) < 340
    assert not np.isin([0, 1, 2, 3, 4, 61], fast.inliers).any()
    np.testing.assert_allclose(fast.projected_px, slow.projected_px, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.normal, slow.normal, rtol=1e-11)
    np.testing.assert_allclose(fast.rhs, slow.rhs, rtol=1e-9, atol=1e-9 * np.abs(slow.rhs).max())
    assert fast.sq == pytest.approx(slow.sq, rel=1e-12)
    assert fast.weighted_sq == pytest.approx(slow.weighted_sq, rel=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 2e-4, 0.3, 3.0])
def test_gauss_newton_update_is_solve_then_exp(angle, monkeypatch):
    """The compiled update (Cholesky solve, Rodrigues and the left Jacobian, Taylor series
    for small angles) gives LAPACK's step and ``geometry.se3_exp``'s pose; the covariance's
    inverse is LAPACK's."""
    rng = np.random.default_rng(int(angle * 1e9) % 1000)
    a = rng.normal(size=(40, 6))
    normal = a.T @ a
    axis = rng.normal(size=3)
    step = np.concatenate([rng.normal(size=3), axis / np.linalg.norm(axis) * angle])
    fit = pnp._Fit(pnp.se3_exp(rng.normal(size=6)), np.arange(4), np.zeros((4, 2)), normal,
                   normal @ step, 0.0, 0.0)
    fast_step, fast_pose = pnp._gauss_newton_update(fit)
    fast_inverse = pnp._normal_inverse(normal)
    _numpy_path(monkeypatch)
    slow_step, slow_pose = pnp._gauss_newton_update(fit)
    np.testing.assert_allclose(fast_step, slow_step, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast_pose, slow_pose, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast_inverse, pnp._normal_inverse(normal), rtol=1e-9,
                               atol=1e-12 * np.abs(fast_inverse).max())


def test_singular_normal_equations_take_the_least_squares_step():
    """Normal equations that are not positive definite (a direction the points do not
    constrain) leave the kernel to LAPACK: the minimum-norm step, an infinite covariance
    where they are exactly singular."""
    k = kernels.compiled()
    a = np.random.default_rng(2).normal(size=(40, 6))
    a[:, 5] = 0.0
    normal, rhs = a.T @ a, a.T @ np.ones(40)
    assert not k.gauss_newton_update(np.eye(4), normal, rhs, np.empty(6), np.empty((4, 4)))
    assert not k.spd_inverse(normal, np.empty((6, 6)))
    fit = pnp._Fit(np.eye(4), np.arange(4), np.zeros((4, 2)), normal, rhs, 0.0, 0.0)
    step, pose = pnp._gauss_newton_update(fit)
    np.testing.assert_allclose(step, np.linalg.lstsq(a, np.ones(40), rcond=None)[0], atol=1e-12)
    assert step[5] == 0.0 and np.isfinite(pose).all()
    assert np.isinf(pnp._normal_inverse(np.zeros((6, 6)))).all()


def test_warm_up_loads_every_kernel():
    """A service worker's start loads each kernel (compiled or from numba's disk cache),
    guided matching's too."""
    kernels.warm_up()
    assert all(fn.signatures for fn in kernels.compiled())
    assert all(fn.signatures for fn in guided_kernels.compiled())
