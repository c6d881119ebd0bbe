"""P3P pose finder's solve and pools: exact poses through every camera model, covariance, refusal,
matching (on rendered images: test_p3p_rendered.py)."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.place.base import PlaceCandidate
from reloc_service.algorithms.pose.base import create_pose_finder
from reloc_service.algorithms.pose.landmark_pool import LandmarkPool
from reloc_service.algorithms.pose.pnp import solve_pnp, solve_pnp_indexed
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.algorithms.pose.point_uncertainty import PointUncertainty
from reloc_service.algorithms.relocalizers.base import (
    VerifyConf,
    position_sigma_m,
    result_from_estimate,
)
from reloc_service.core.cameras import Camera, camera_from_dict
from reloc_service.core.errors import ConfigError
from reloc_service.core.frame import Features, Frame, Keyframe
from reloc_service.core.geometry import invert, look_at, pose_error, se3_log, transform_points
from reloc_service.core.map import KeyframeMap

DISTORTIONS = {"pinhole": [], "radtan": [-0.28, 0.07, 1e-4, -2e-4],
               "equidistant": [0.05, -0.01, 0.003, -0.001], "fov": [0.9]}


def make_camera(model: str, width: int = 640, height: int = 480) -> Camera:
    return camera_from_dict({"model": model, "width": width, "height": height, "fx": 420.0,
                             "fy": 415.0, "cx": (width - 1) / 2 + 3, "cy": (height - 1) / 2 - 2,
                             "distortion": DISTORTIONS[model]})


def correspondences(camera: Camera, world_from_cam: np.ndarray, n: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) distorted pixels over the whole image and their (n, 3) world points, 1.5-6 m."""
    px = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (n, 2))
    bearings = camera.unproject(px)
    points_cam = bearings / bearings[:, 2:] * rng.uniform(1.5, 6.0, n)[:, None]
    return camera.project(points_cam), transform_points(world_from_cam, points_cam)


TRUE_POSE = look_at([0.4, -0.3, -4.0], [0.1, 0.2, 0.0], up=[0, -1, 0])


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
def test_recovers_pose_exactly_with_half_outliers(model):
    rng = np.random.default_rng(0)
    camera = make_camera(model)
    px, points = correspondences(camera, TRUE_POSE, 200, rng)
    outliers = rng.permutation(200)[:100]
    px[outliers] = rng.uniform([0, 0], [camera.width, camera.height], (100, 2))
    est = solve_pnp(px, points, camera)
    assert est is not None
    dt, dr = pose_error(est.world_from_cam, TRUE_POSE)
    assert dt < 1e-9 and dr < 1e-9
    assert est.num_matches == 200 and 100 <= est.inliers <= 103  # a random outlier may fit
    assert est.reprojection_rms_px < 0.5
    assert est.inlier_px.shape == (est.inliers, 2)
    assert est.inlier_points_world.shape == (est.inliers, 3)
    assert "solve" in est.timings
    assert result_from_estimate(est, VerifyConf(), method="p3p", map_version=0, timings={}).ok


@pytest.mark.parametrize("model", sorted(DISTORTIONS))
def test_jacobian_matches_finite_differences(model):
    from reloc_service.algorithms.pose.pnp import _View
    from reloc_service.core.geometry import se3_exp

    def _residuals_and_jacobian(world_from_cam, px, points, camera):
        return _View.at(world_from_cam, points, camera).residuals_and_jacobian(
            px, np.arange(len(px)), camera)

    rng = np.random.default_rng(6)
    camera = make_camera(model)
    px, points = correspondences(camera, TRUE_POSE, 20, rng)
    _, jac = _residuals_and_jacobian(TRUE_POSE, px, points, camera)
    numeric = np.zeros_like(jac)
    h = 1e-6
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        plus = _residuals_and_jacobian(TRUE_POSE @ se3_exp(step), px, points, camera)[0]
        minus = _residuals_and_jacobian(TRUE_POSE @ se3_exp(-step), px, points, camera)[0]
        numeric[:, k] = -(plus - minus).ravel() / (2 * h)  # residual = px - projection
    assert np.allclose(jac, numeric, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("model", ["pinhole", "radtan", "radtan-k3", "equidistant"])
def test_poselib_camera_projects_exactly_as_ours(model):
    """The refinement's Jacobian comes from PoseLib's camera model: it must be our model,
    parameter for parameter, over the whole image."""
    from reloc_service.algorithms.pose.projection import poselib_camera

    camera = make_camera(model.split("-")[0])
    if model == "radtan-k3":
        camera = camera_from_dict({**camera.to_dict(), "distortion": [-0.28, 0.07, 1e-4, -2e-4,
                                                                      0.02]})
    rng = np.random.default_rng(7)
    bearings = camera.unproject(rng.uniform([0, 0], [camera.width - 1, camera.height - 1],
                                            (500, 2)))
    xy = bearings[:, :2] / bearings[:, 2:]
    np.testing.assert_allclose(poselib_camera(camera).project(xy), camera.project(bearings),
                               atol=1e-9)


@pytest.mark.parametrize("model", ["pinhole", "radtan", "radtan-k3"])
def test_numpy_pixel_jacobian_equals_poselibs(model):
    """Pinhole and radtan Jacobians are written out in numpy (faster than converting
    PoseLib's list of 2x2 arrays): the same values as PoseLib's analytic ones."""
    from reloc_service.algorithms.pose.projection import pixel_jacobian, poselib_camera

    camera = make_camera(model.split("-")[0])
    if model == "radtan-k3":
        camera = camera_from_dict({**camera.to_dict(), "distortion": [-0.28, 0.07, 1e-4, -2e-4,
                                                                      0.02]})
    xy = np.random.default_rng(8).uniform(-0.7, 0.7, (300, 2))
    theirs = np.asarray(poselib_camera(camera).project_with_jac(xy)[1]).reshape(-1, 2, 2)
    np.testing.assert_allclose(pixel_jacobian(camera, xy), theirs, rtol=1e-12, atol=1e-9)


def test_fov_has_no_poselib_camera():
    from reloc_service.algorithms.pose.projection import poselib_camera

    assert poselib_camera(make_camera("fov")) is None


def test_covariance_matches_monte_carlo_and_shrinks_with_more_inliers():
    rng = np.random.default_rng(1)
    camera = make_camera("radtan")
    conf = PnPConf(min_sigma_px=0.0)
    sigmas = {}
    for n in (30, 300):
        clean, points = correspondences(camera, TRUE_POSE, n, rng)
        twists, covariances = [], []
        for _ in range(60):
            est = solve_pnp(clean + rng.normal(0.0, 1.0, clean.shape), points, camera, conf)
            twists.append(se3_log(invert(TRUE_POSE) @ est.world_from_cam))
            covariances.append(est.covariance)
        predicted = np.sqrt(np.diag(np.mean(covariances, axis=0)))
        empirical = np.sqrt(np.diag(np.cov(np.array(twists).T)))
        assert np.all(np.abs(empirical / predicted - 1.0) < 0.35), (empirical, predicted)
        sigmas[n] = position_sigma_m(np.mean(covariances, axis=0))
    assert sigmas[300] < 0.5 * sigmas[30]


def test_covariance_is_floored_for_noise_free_data():
    rng = np.random.default_rng(2)
    camera = make_camera("pinhole")
    px, points = correspondences(camera, TRUE_POSE, 50, rng)
    floored = solve_pnp(px, points, camera, PnPConf(min_sigma_px=0.5))
    raw = solve_pnp(px, points, camera, PnPConf(min_sigma_px=0.0))
    assert position_sigma_m(floored.covariance) > 1e3 * position_sigma_m(raw.covariance)


def test_random_correspondences_are_refused():
    rng = np.random.default_rng(3)
    camera = make_camera("pinhole")
    refused = 0
    for _ in range(5):
        px = rng.uniform([0, 0], [640, 480], (300, 2))
        points = rng.uniform([-3, -3, 2], [3, 3, 8], (300, 3))
        est = solve_pnp(px, points, camera)
        result = result_from_estimate(est, VerifyConf(), method="p3p", map_version=0, timings={})
        refused += not result.ok
    assert refused == 5


def test_too_few_or_mismatched_correspondences():
    camera = make_camera("pinhole")
    rng = np.random.default_rng(4)
    px, points = correspondences(camera, TRUE_POSE, 3, rng)
    assert solve_pnp(px, points, camera) is None
    with pytest.raises(ValueError, match="as many points as pixels"):
        solve_pnp(px, points[:2], camera)


def test_unknown_options_raise():
    with pytest.raises(ConfigError, match="unknown option"):
        create_pose_finder({"name": "p3p", "threshold": 3.0})
    with pytest.raises(ConfigError):
        create_pose_finder({"name": "p3p", "kind": "surf"})
    finder = create_pose_finder({"name": "p3p", "kind": "orb", "max_reproj_error_px": 4})
    assert finder.required_features == {"orb"}
    assert finder.conf.max_reproj_error_px == 4.0


def test_landmark_pool_keeps_one_row_per_landmark_from_the_best_keyframe():
    camera = make_camera("pinhole", 64, 48)
    image = np.zeros((48, 64), np.uint8)

    def keyframe(kf_id: int, ids: list[int], value: float) -> Keyframe:
        n = len(ids)
        feats = Features.create("sift", np.full((n, 2), 10.0), np.full((n, 128), value, np.float32),
                                landmark_ids=ids, points_world=np.array(ids, float)[:, None]
                                * np.ones(3))
        return Keyframe(image=image, camera=camera, id=kf_id, features={"sift": feats})

    pool = LandmarkPool.gather([keyframe(7, [3, -1, 5], 1.0), keyframe(2, [5, 9], 2.0)], "sift")
    assert sorted(pool.landmark_ids.tolist()) == [3, 5, 9]
    row5 = int(np.flatnonzero(pool.landmark_ids == 5)[0])
    assert pool.descriptors[row5, 0] == 1.0 and pool.keyframe_rows[row5] == 0
    assert np.allclose(pool.points_world[row5], 5.0)
    assert len(LandmarkPool.gather([keyframe(1, [-1], 0.0)], "sift").landmark_ids) == 0


def test_landmark_pool_of_one_keyframe_is_the_general_pool_and_its_rows_are_kept():
    """One keyframe alone (the fast path's first pool) gives the rows the general path gives
    (its first keypoint of each landmark), from rows computed once per features object; a
    copy with other landmarks gets its own."""
    from reloc_service.algorithms.pose.landmark_pool import _landmark_rows

    camera = make_camera("pinhole", 64, 48)
    image = np.zeros((48, 64), np.uint8)
    ids = [4, -1, 4, 2, 9, 2, -1, 7]
    rng = np.random.default_rng(3)
    feats = Features.create("orb", rng.uniform(0, 40, (len(ids), 2)),
                            rng.integers(0, 256, (len(ids), 32), dtype=np.uint8),
                            landmark_ids=ids, points_world=rng.normal(size=(len(ids), 3)))
    alone = Keyframe(image=image, camera=camera, id=1, features={"orb": feats})
    without = Keyframe(image=image, camera=camera, id=2, features={})
    one, general = LandmarkPool.gather([alone], "orb"), LandmarkPool.gather([alone, without], "orb")
    for name in ("descriptors", "landmark_ids", "points_world", "keyframe_rows"):
        assert np.array_equal(getattr(one, name), getattr(general, name)), name
        assert getattr(one, name).dtype == getattr(general, name).dtype, name
    assert one.landmark_ids.tolist() == [4, 2, 9, 7]
    assert _landmark_rows(feats) is _landmark_rows(feats)  # once per features object
    moved = feats.with_landmarks([1], [5], [[0.0, 0.0, 1.0]])
    assert _landmark_rows(moved).tolist() == [0, 1, 3, 4, 7]
    assert _landmark_rows(feats).tolist() == [0, 3, 4, 7]


def test_find_pose_with_keyframes_lacking_features_is_refused():
    camera = make_camera("pinhole", 64, 48)
    kmap = KeyframeMap()
    kmap.add_keyframe(Keyframe(image=np.zeros((48, 64), np.uint8), camera=camera, id=0))
    finder = create_pose_finder({"name": "p3p"})
    est = finder.find_pose(Frame(np.zeros((48, 64), np.uint8), camera), [PlaceCandidate(0, 0.0)],
                           kmap.snapshot())
    assert est is not None and est.inliers == 0 and est.num_matches == 0
    assert not result_from_estimate(est, VerifyConf(), method="p3p", map_version=0,
                                    timings={}).ok


def test_chance_agreement_is_higher_for_bunched_correspondences():
    from reloc_service.algorithms.pose.chance import chance_agreement

    rng = np.random.default_rng(0)
    spread = np.column_stack([rng.uniform(0, 640, 200), rng.uniform(0, 480, 200)])
    bunched = rng.normal((320.0, 240.0), 8.0, (200, 2))
    uniform = np.pi * 25 / (640 * 480)
    assert chance_agreement(spread, spread, 5.0, (640, 480)) < 5 * uniform
    assert chance_agreement(bunched, bunched, 5.0, (640, 480)) > 100 * uniform
    assert chance_agreement(spread[:1], spread[:1], 5.0, (640, 480)) == uniform


@pytest.mark.parametrize("spread_px", [2.0, 8.0, 200.0])
def test_chance_agreement_counts_the_pairs_of_the_full_table(spread_px):
    """Only pairs near in x are measured; the count is the full (m, m) table's, also with
    points on the threshold's edge, duplicates and a NaN projection."""
    from reloc_service.algorithms.pose.chance import _pairs_within

    rng = np.random.default_rng(int(spread_px))
    px = np.round(rng.normal((320.0, 240.0), spread_px, (200, 2)))  # integer: exact ties
    projected = px + np.round(rng.normal(0.0, 3.0, px.shape))
    projected[:10] = px[10:20] + [5.0, 0.0]  # exactly the threshold away: not agreeing
    projected[20] = np.nan
    dx = projected[:, None, 0] - px[None, :, 0]
    dy = projected[:, None, 1] - px[None, :, 1]
    d2 = dx * dx + dy * dy
    np.fill_diagonal(d2, np.inf)
    with np.errstate(invalid="ignore"):
        expected = int(np.count_nonzero(d2 < 25.0))
    assert _pairs_within(projected, px, 5.0) == expected
    assert expected > 0


def test_chance_agreement_pairs_every_correspondence_up_to_max_points():
    """Up to ``max_points`` correspondences all are paired; beyond, an even choice of them."""
    from reloc_service.algorithms.pose.chance import _pairs_within, chance_agreement

    rng = np.random.default_rng(4)
    px = rng.normal((320.0, 240.0), 30.0, (450, 2))
    projected = px + rng.normal(0.0, 4.0, px.shape)
    for n in (2, 120, 200):
        want = _pairs_within(projected[:n], px[:n], 5.0) / (n * (n - 1))
        assert chance_agreement(projected[:n], px[:n], 5.0, (640, 480)) == max(
            want, np.pi * 25 / (640 * 480))
    idx = np.unique(np.linspace(0, 449, 200).astype(np.int64))
    assert len(idx) == 200
    want = _pairs_within(projected[idx], px[idx], 5.0) / (200 * 199)
    assert chance_agreement(projected, px, 5.0, (640, 480)) == want > 0


def test_refined_estimate_is_the_one_recomputed_from_scratch():
    """The pose, inliers, normal equations and covariance come from one pass per pose: the
    same values as projecting anew for the residuals, the Jacobian and the weights."""
    from reloc_service.algorithms.pose.pnp import _estimate, _refine, _View, _weights

    camera = make_camera("radtan")
    rng = np.random.default_rng(3)
    px, pts = correspondences(camera, TRUE_POSE, 150, rng)
    px = px + rng.normal(0.0, 0.5, px.shape)
    px[:30] = rng.uniform([0, 0], [639, 479], (30, 2))  # outliers
    unc = PointUncertainty(rng.uniform(0.0, 0.05, 150), pts + rng.normal(0, 1.0, pts.shape))
    conf = PnPConf()
    est, inliers = solve_pnp_indexed(px, pts, camera, conf, uncertainty=unc)
    fit = _refine(TRUE_POSE @ se3_exp_small(rng), px, pts, camera, conf, unc)
    rows = _View.at(fit.world_from_cam, pts, camera).inliers(px, conf)
    assert np.array_equal(fit.inliers, rows)
    residual = px[rows] - camera.project(transform_points(invert(fit.world_from_cam), pts[rows]))
    jac = _View.at(fit.world_from_cam, pts[rows], camera).residuals_and_jacobian(
        px[rows], np.arange(len(rows)), camera)[1]
    w = _weights(fit.world_from_cam, pts, rows, camera, conf, unc)
    w_rows = np.repeat(w, 2)
    np.testing.assert_allclose(fit.normal, jac.T @ (jac * w_rows[:, None]), rtol=1e-12)
    np.testing.assert_allclose(fit.rhs, jac.T @ (residual.ravel() * w_rows), rtol=1e-9,
                               atol=1e-9 * np.abs(fit.rhs).max())
    assert fit.sq == pytest.approx(float((residual**2).sum()), rel=1e-12)
    assert fit.weighted_sq == pytest.approx(float((w[:, None] * residual**2).sum()), rel=1e-12)
    refit = _estimate(fit, px[rows], pts[rows], camera, conf, len(px), 0.0)
    sigma2 = max(float((w[:, None] * residual**2).sum()) / (residual.size - 6),
                 conf.min_sigma_px**2)
    np.testing.assert_allclose(refit.covariance,
                               sigma2 * np.linalg.inv(jac.T @ (jac * w_rows[:, None])),
                               rtol=1e-9, atol=1e-12)
    assert refit.reprojection_rms_px == pytest.approx(np.sqrt((residual**2).sum() / len(rows)))
    assert len(inliers) >= 115 and not np.isin(np.arange(30), inliers).any()
    assert np.array_equal(est.inlier_px, px[inliers])


def se3_exp_small(rng: np.random.Generator) -> np.ndarray:
    from reloc_service.core.geometry import se3_exp

    return se3_exp(rng.normal(0.0, 0.01, 6))


def test_uncertain_points_weigh_less_in_the_refinement():
    """Points triangulated from a keyframe 1 m to the side with depths 3 % off (within their
    stated uncertainty) pull an unweighted refinement off the pose; weighted by how far their
    uncertainty spreads in the query, they barely do, and most still count as inliers."""
    rng = np.random.default_rng(3)
    camera = make_camera("pinhole")
    px, points = correspondences(camera, TRUE_POSE, 120, rng)
    px += rng.normal(0.0, 0.3, px.shape)
    origin = TRUE_POSE[:3, 3] + TRUE_POSE[:3, 0] * 1.0          # the keyframe's centre
    origins = np.repeat(origin[None], len(points), axis=0)
    ray = points - origins
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    rng_m = np.linalg.norm(points - origins, axis=1)
    sigmas = np.zeros(len(points))
    bad = np.arange(40)
    sigmas[bad] = 0.03 * rng_m[bad]
    shifted = points.copy()
    shifted[bad] += ray[bad] * sigmas[bad, None] * np.where(np.arange(40) % 2, 1.0, 0.8)[:, None]
    plain = solve_pnp_indexed(px, shifted, camera)
    weighted = solve_pnp_indexed(px, shifted, camera,
                                 uncertainty=PointUncertainty(sigmas, origins))
    assert plain is not None and weighted is not None
    assert len(weighted[1]) >= 0.9 * len(plain[1])
    err_plain = pose_error(plain[0].world_from_cam, TRUE_POSE)[0]
    err_weighted = pose_error(weighted[0].world_from_cam, TRUE_POSE)[0]
    assert err_weighted < 0.5 * err_plain


def test_level_scales_weigh_coarse_keypoints_less():
    """A keypoint found at pyramid level l is located to ``1.2^l`` pixels: weighted so, the
    pose from keypoints whose noise grows with their level is closer to the truth than with
    every keypoint weighed alike (the same correspondences, 30 draws)."""
    from reloc_service.algorithms.pose.pnp import _weights, level_scales

    camera = make_camera("radtan")
    np.testing.assert_allclose(level_scales(np.array([0, 1, 7]), 1.2), [1.0, 1.2, 1.2**7])
    scales = level_scales(np.array([0, 3]), 1.2)
    np.testing.assert_allclose(_weights(TRUE_POSE, np.zeros((2, 3)), np.arange(2), camera,
                                        PnPConf(), None, scales), [1.0, 1.2**-6])
    errors = {False: [], True: []}
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        px, points = correspondences(camera, TRUE_POSE, 80, rng)
        levels = rng.integers(0, 8, len(px))
        px = px + rng.normal(0.0, 0.4, px.shape) * level_scales(levels, 1.2)[:, None]
        for weighted in errors:
            solved = solve_pnp_indexed(px, points, camera, PnPConf(),
                                       keypoint_scales=level_scales(levels, 1.2)
                                       if weighted else None)
            assert solved is not None
            errors[weighted].append(pose_error(solved[0].world_from_cam, TRUE_POSE)[0])
    assert np.median(errors[True]) < 0.85 * np.median(errors[False])
