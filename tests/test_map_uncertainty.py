"""algorithms/pose/map_uncertainty.py: the keyframes' pose covariances carried into a relocalized pose,
checked against Monte-Carlo: keyframe poses drawn from their covariance move their
landmarks rigidly, the query pose is solved again on exact pixels, and the spread of the
solved poses is compared with the propagated covariance."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np
import pytest

from reloc_service.algorithms.pose.map_uncertainty import keyframe_shares, map_covariance
from reloc_service.algorithms.pose.pnp import solve_pnp
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Keyframe
from reloc_service.core.geometry import invert, look_at, se3_exp, se3_log, transform_points
from reloc_service.core.landmark_table import Landmark, LandmarkTable
from reloc_service.core.map import MapState

CAMERA = PinholeCamera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
DRAWS = 1500


def _scene(rng: np.random.Generator, n_keyframes: int):
    """A query looking at 240 points 2-4 m away and ``n_keyframes`` keyframes 0.3-0.6 m to
    its sides, each the only observer of an equal share of the points."""
    world_from_query = look_at((0.0, 0.0, 1.5), (0.0, 3.0, 1.4))
    px = rng.uniform((20, 20), (620, 460), size=(240, 2))
    depth = rng.uniform(2.0, 4.0, size=240)
    rays = np.column_stack([(px - (CAMERA.cx, CAMERA.cy)) / CAMERA.fx, np.ones(240)])
    points = transform_points(world_from_query, rays * depth[:, None])
    owners = np.arange(240) % n_keyframes
    keyframes = {}
    for k in range(n_keyframes):
        side = (-1) ** k * (0.3 + 0.3 * k)
        pose = look_at((side, 0.2 * k, 1.5 + 0.1 * k), (0.3 * side, 3.0, 1.3))
        keyframes[k] = Keyframe(image=np.zeros((480, 640), np.uint8), camera=CAMERA, id=k,
                                world_from_cam=pose, pose_covariance=_covariance(rng, k))
    landmarks = LandmarkTable.from_mapping({
        i: Landmark(i, points[i], frozenset({(int(owners[i]), "sift", i)}), 0.0)
        for i in range(240)})
    state = MapState(MappingProxyType(keyframes), landmarks)
    return world_from_query, px, points, owners, state


def _covariance(rng: np.random.Generator, k: int) -> np.ndarray:
    """A full keyframe pose covariance: about 2 cm and 0.5 deg, correlated axes."""
    a = rng.normal(size=(6, 6)) * np.array([0.02, 0.02, 0.02, 0.009, 0.009, 0.009])[:, None]
    return a @ a.T / 6 + np.diag([1e-4, 1e-4, 1e-4, 2e-5, 2e-5, 2e-5]) * (1 + k)


def _solved_errors(world_from_query, px, points, owners, state, draws, *, shared: bool,
                   rng: np.random.Generator) -> np.ndarray:
    """(D, 6) right-perturbation errors of the query pose solved on landmarks moved by drawn
    keyframe errors (one draw per keyframe, or one shared unit draw when ``shared``)."""
    kf_ids = sorted(state.keyframes)
    chol = [np.linalg.cholesky(state.keyframes[k].pose_covariance) for k in kf_ids]
    conf = PnPConf(max_reproj_error_px=50.0, refine_iterations=3)
    out = []
    for _ in range(draws):
        unit = rng.standard_normal(6)
        moved = points.copy()
        for k, ell in zip(kf_ids, chol, strict=True):
            eps = ell @ (unit if shared else rng.standard_normal(6))
            kf = state.keyframes[k].world_from_cam
            motion = kf @ se3_exp(eps) @ invert(kf)   # the landmarks of k move with it
            moved[owners == k] = transform_points(motion, points[owners == k])
        est = solve_pnp(px, moved, CAMERA, conf)
        assert est is not None and est.inliers == len(px)
        out.append(se3_log(invert(world_from_query) @ est.world_from_cam))
    return np.array(out)


def _close(measured: np.ndarray, expected: np.ndarray, rel: float) -> bool:
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    return bool(np.all(np.abs(measured - expected) <= rel * scale))


def test_one_keyframe_matches_monte_carlo():
    """All landmarks from one keyframe: the pose moves exactly with it, so the adjoint-moved
    covariance is the spread of the solved poses."""
    rng = np.random.default_rng(0)
    world_from_query, px, points, owners, state = _scene(rng, 1)
    expected = map_covariance(world_from_query, state, np.arange(240))
    errors = _solved_errors(world_from_query, px, points, owners, state, DRAWS, shared=False,
                            rng=rng)
    measured = np.cov(errors.T)
    # 1500 draws: a variance is known to about 4 % (sqrt(2 / 1500)); 12 % is 3 of those
    assert _close(measured, expected, 0.12), (np.diag(measured), np.diag(expected))
    # moved to the query's frame, not the keyframe's covariance as it is
    assert not _close(expected, state.keyframes[0].pose_covariance, 0.12)


@pytest.mark.slow
def test_keyframes_that_share_one_error_match_monte_carlo():
    """Three keyframes drawing one shared error (a drifting trajectory): the share-weighted
    mean of the moved covariances is what the solved poses show."""
    rng = np.random.default_rng(1)
    world_from_query, px, points, owners, state = _scene(rng, 3)
    shared = np.linalg.cholesky(state.keyframes[0].pose_covariance)
    for k in state.keyframes:  # one error for all: the same covariance
        object.__setattr__(state.keyframes[k], "pose_covariance", shared @ shared.T)
    expected = map_covariance(world_from_query, state, np.arange(240))
    errors = _solved_errors(world_from_query, px, points, owners, state, DRAWS, shared=True,
                            rng=rng)
    assert _close(np.cov(errors.T), expected, 0.2), (np.diag(np.cov(errors.T)),
                                                       np.diag(expected))


@pytest.mark.slow
def test_independent_keyframes_stay_near_it():
    """Independent keyframe errors (the assumption not made): rotations partly cancel, down
    to what three independent equal shares give (a third of the variance); translations
    cancel less, since landmark sets moving differently also shift the solved position. The
    propagated covariance stays within a factor 1.3 above and 2 below the spread."""
    rng = np.random.default_rng(2)
    world_from_query, px, points, owners, state = _scene(rng, 3)
    expected = map_covariance(world_from_query, state, np.arange(240))
    measured = np.cov(_solved_errors(world_from_query, px, points, owners, state, DRAWS,
                                     shared=False, rng=rng).T)
    sigma_ratio = np.sqrt(np.diag(measured) / np.diag(expected))
    assert np.all(sigma_ratio[:3] < 1.3) and np.all(sigma_ratio[:3] > 0.5), sigma_ratio
    assert np.all(sigma_ratio[3:] < 1.0) and np.all(sigma_ratio[3:] > 0.45), sigma_ratio


def test_shares_and_defaults():
    rng = np.random.default_rng(3)
    world_from_query, _, _, _, state = _scene(rng, 3)
    kf_ids, shares = keyframe_shares(state, np.arange(240))
    assert kf_ids.tolist() == [0, 1, 2] and np.allclose(shares, 1 / 3)
    kf_ids, shares = keyframe_shares(state, [0, 3, 1])           # landmarks 0, 3 of kf 0
    assert kf_ids.tolist() == [0, 1] and np.allclose(shares, [2 / 3, 1 / 3])
    assert map_covariance(world_from_query, state, [10_000]) is None   # not landmarks
    # a keyframe put without a covariance takes the map's default; none: exact
    bare = {k: Keyframe(image=kf.image, camera=CAMERA, id=k, world_from_cam=kf.world_from_cam)
            for k, kf in state.keyframes.items()}
    exact = MapState(MappingProxyType(bare), state.landmarks)
    np.testing.assert_array_equal(map_covariance(world_from_query, exact, np.arange(240)),
                                  np.zeros((6, 6)))
    default = np.diag([4e-4] * 3 + [1e-4] * 3)
    defaulted = MapState(MappingProxyType(bare), state.landmarks, default_pose_covariance=default)
    one = map_covariance(world_from_query, defaulted, [0])
    assert one is not None and np.trace(one[:3, :3]) > np.trace(default[:3, :3])


@pytest.mark.parametrize("sigma", [0.0, 0.05])
def test_answer_covariance_adds_the_map_part(sigma):
    """A relocalization result's covariance is the measurement part plus the map part (the
    verification keeps judging the first)."""
    from reloc_service.algorithms.pose.base import PoseEstimate, total_covariance

    measured = np.diag([1e-6] * 3 + [1e-7] * 3)
    est = PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[], covariance=measured,
                       map_covariance=np.eye(6) * sigma**2)
    total = total_covariance(est)
    assert total is not None
    np.testing.assert_allclose(total, measured + np.eye(6) * sigma**2)


def test_a_pose_on_keyframe_rays_takes_their_covariances_by_share():
    """The five-point finder's pose rests on the keyframes directly: one keyframe with all
    the inliers gives its covariance moved by the adjoint; a keyframe without inliers none."""
    from reloc_service.algorithms.pose.map_uncertainty import keyframes_covariance
    from reloc_service.core.geometry import se3_adjoint

    rng = np.random.default_rng(4)
    world_from_query, _, _, _, state = _scene(rng, 2)
    only_first = keyframes_covariance(world_from_query, state, [0, 1], [12, 0])
    adjoint = se3_adjoint(invert(world_from_query) @ state.keyframes[0].world_from_cam)
    np.testing.assert_allclose(only_first,
                               adjoint @ state.keyframes[0].pose_covariance @ adjoint.T,
                               rtol=1e-12, atol=1e-15)
    both = keyframes_covariance(world_from_query, state, [0, 1], [1, 3])
    second = keyframes_covariance(world_from_query, state, [1], [1])
    np.testing.assert_allclose(both, 0.25 * only_first + 0.75 * second, rtol=1e-12, atol=1e-15)
    assert keyframes_covariance(world_from_query, state, [7], [1]) is None
