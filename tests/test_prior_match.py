"""The window test of localization with a prior (every query keypoint inside a landmark's
gate is a candidate, numpy and compiled paths alike) and the covariance of a pose pooled
from keyframes that disagree."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.pose import prior_match
from reloc_service.algorithms.pose.cluster_covariance import at_least, cluster_robust_covariance
from reloc_service.algorithms.pose.prior_windows import Windows, match_in_windows
from reloc_service.algorithms.pose.projection import pose_projector
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Features

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)
GATE = 9.21  # chi-square 2 dof at 0.99


def _features(px: np.ndarray, desc: np.ndarray) -> Features:
    n = len(px)
    return Features("orb", np.asarray(px, np.float64), np.zeros(n, np.int16),
                    np.full(n, 31.0, np.float32), np.full(n, -1.0, np.float32), desc,
                    np.full(n, -1, np.int64), np.full((n, 3), np.nan))


def _windows(px: np.ndarray, sigma_px: np.ndarray) -> Windows:
    n = len(px)
    inv = np.zeros((n, 2, 2))
    inv[:, 0, 0] = inv[:, 1, 1] = 1.0 / sigma_px**2
    radius = np.sqrt(GATE) * sigma_px
    return Windows(np.asarray(px, np.float64), inv, radius, np.pi * GATE * sigma_px**2,
                   np.ones(n, bool))


def test_the_numpy_and_compiled_window_tests_agree_ties_included():
    rng = np.random.default_rng(0)
    keypoints = rng.uniform([0, 0], [320, 240], (300, 2))
    query = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    px = rng.uniform([0, 0], [320, 240], (400, 2))
    sigma = rng.uniform(3.0, 25.0, 400)
    landmarks = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    picked = rng.integers(0, 300, 100)
    landmarks[:100] = query[picked]                      # exact matches: distance 0 ties
    px[:100] = keypoints[picked] + rng.normal(0, 1.0, (100, 2))
    query[150:170] = query[130:150]                      # duplicate keypoint descriptors
    w = _windows(px, sigma)
    numpy_path = prior_match._gated_best_numpy(keypoints, query, px, w.inv_cov, w.radius_px,
                                               landmarks, GATE)
    chosen = prior_match.gated_best(keypoints, query, px, w.inv_cov, w.radius_px, landmarks,
                                    GATE)
    for a, b in zip(numpy_path, chosen, strict=True):
        np.testing.assert_array_equal(a, b)
    # Some landmarks have a candidate, some a second, and distance-0 matches are found.
    assert 0 < np.isfinite(numpy_path[1]).sum() < np.isfinite(numpy_path[0]).sum() < 400
    assert np.sum(numpy_path[0] == 0) > 10


@pytest.mark.parametrize("angle_deg", [0.0, 35.0, 90.0, 150.0])
def test_long_tilted_gates_keep_every_keypoint_near_their_rim(angle_deg):
    # Gates 40 sigma long and 1.5 wide, tilted: the compiled pass looks for candidates in
    # each gate's bounding box, band by band; keypoints at 0.999 and 1.001 of the gate's
    # Mahalanobis radius along random directions must be kept and left out as the numpy
    # pairs are.
    rng = np.random.default_rng(3)
    n_lm = 60
    theta = np.deg2rad(angle_deg) + rng.normal(0, 0.2, n_lm)
    rot = np.stack([np.c_[np.cos(theta), -np.sin(theta)], np.c_[np.sin(theta), np.cos(theta)]],
                   axis=1)
    cov = rot @ np.diag([40.0**2, 1.5**2]) @ rot.transpose(0, 2, 1)
    inv = np.linalg.inv(cov)
    px = rng.uniform([60, 60], [260, 180], (n_lm, 2))
    chol = np.linalg.cholesky(cov)
    unit = rng.normal(size=(n_lm, 6, 2))
    unit /= np.linalg.norm(unit, axis=2, keepdims=True)
    reach = np.sqrt(GATE) * np.array([0.999, 1.001, 0.999, 1.001, 0.5, 0.999])
    keypoints = (px[:, None, :] + np.einsum("lij,lkj->lki", chol, unit * reach[None, :, None])
                 ).reshape(-1, 2)
    query = rng.integers(0, 256, (len(keypoints), 32), dtype=np.uint8)
    landmarks = rng.integers(0, 256, (n_lm, 32), dtype=np.uint8)
    radius = np.sqrt(GATE * np.linalg.eigvalsh(cov)[:, -1])
    numpy_path = prior_match._gated_best_numpy(keypoints, query, px, inv, radius, landmarks,
                                               GATE)
    chosen = prior_match.gated_best(keypoints, query, px, inv, radius, landmarks, GATE)
    for a, b in zip(numpy_path, chosen, strict=True):
        np.testing.assert_array_equal(a, b)
    # Every landmark has candidates (at least its four inside), some near their rim.
    assert np.isfinite(numpy_path[1]).all()


def test_only_keypoints_inside_the_gate_are_candidates():
    desc = np.random.default_rng(1).integers(0, 256, (2, 32), dtype=np.uint8)
    # The landmark's own descriptor sits just outside its 10 px (1 sigma ~ 3.3 px) gate.
    sigma = np.array([10.0 / np.sqrt(GATE)])
    feats = _features(np.array([[110.5, 100.0], [100.0, 150.0]]), desc)
    windows = _windows(np.array([[100.0, 100.0]]), sigma)
    q, rows = match_in_windows(feats, windows, np.array([0]), desc[:1], GATE, ratio=0.9,
                               background_quantile=0.5)
    assert len(q) == 0
    feats = _features(np.array([[109.5, 100.0], [100.0, 150.0]]), desc)
    q, rows = match_in_windows(feats, windows, np.array([0]), desc[:1], GATE, ratio=0.9,
                               background_quantile=0.5)
    assert q.tolist() == [0] and rows.tolist() == [0]


def test_a_confuser_anywhere_in_the_gate_fails_the_ratio_test():
    # Forty keypoints inside one wide gate: the landmark's descriptor (10 bits off) near the
    # projection and another copy (11 bits off) at the gate's rim, beyond the 32 nearest a
    # nearest-neighbour search would have examined. The pair is ambiguous: no match.
    rng = np.random.default_rng(2)
    landmark = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    angles = np.linspace(0, 2 * np.pi, 38, endpoint=False)
    ring = np.c_[100 + 20 * np.cos(angles), 100 + 20 * np.sin(angles)]
    px = np.vstack([[101.0, 100.0], ring, [179.0, 100.0]])
    desc = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    desc[0] = _flip_bits(landmark[0], 10)
    desc[-1] = _flip_bits(landmark[0], 11)
    feats = _features(px, desc)
    windows = _windows(np.array([[100.0, 100.0]]), np.array([80.0 / np.sqrt(GATE)]))
    q, _ = match_in_windows(feats, windows, np.array([0]), landmark, GATE, ratio=0.9,
                            background_quantile=0.5)
    assert len(q) == 0
    # Without the confuser the landmark matches its keypoint.
    desc[-1] = rng.integers(0, 256, 32, dtype=np.uint8)
    q, _ = match_in_windows(_features(px, desc), windows, np.array([0]), landmark, GATE,
                            ratio=0.9, background_quantile=0.5)
    assert q.tolist() == [0]


def _flip_bits(descriptor: np.ndarray, count: int) -> np.ndarray:
    bits = np.unpackbits(descriptor)
    bits[:count] ^= 1
    return np.packbits(bits)


def _two_keyframes(shift_m: float, rng: np.random.Generator):
    """Points in front of an identity camera, half of them (the second keyframe's) moved
    by ``shift_m`` along x as a keyframe pose error would move them; pixels of the true
    points with 0.5 px noise; the pose refitted by Gauss-Newton to all of them."""
    points = np.c_[rng.uniform(-1.5, 1.5, (200, 2)), rng.uniform(2.0, 5.0, 200)]
    project = pose_projector(points, CAMERA)
    px = project(np.eye(4))[0] + rng.normal(0, 0.5, (200, 2))
    clusters = np.repeat([0, 1], 100)
    moved = points + np.outer(clusters == 1, [shift_m, 0.0, 0.0])
    pose = np.eye(4)
    from reloc_service.core.geometry import se3_exp

    for _ in range(5):
        projected, jac = pose_projector(moved, CAMERA)(pose)
        j = jac.reshape(-1, 6)
        pose = pose @ se3_exp(np.linalg.lstsq(j, (px - projected).ravel(), rcond=None)[0])
    projected, jac = pose_projector(moved, CAMERA)(pose)
    residual = (px - projected).ravel()
    j = jac.reshape(-1, 6)
    model = residual @ residual / (len(residual) - 6) * np.linalg.inv(j.T @ j)
    return pose, px, moved, clusters, model


@pytest.mark.parametrize("shift_m", [0.0, 0.05])
def test_the_covariance_widens_to_the_keyframes_disagreement(shift_m):
    rng = np.random.default_rng(3)
    pose, px, points, clusters, model = _two_keyframes(shift_m, rng)
    robust = cluster_robust_covariance(pose, px, points, CAMERA, clusters)
    assert robust is not None
    widened = at_least(model, robust)
    # Never narrower than the model's.
    assert np.all(np.linalg.eigvalsh(widened - model) > -1e-12)
    error_x = abs(pose[0, 3])
    if shift_m == 0.0:
        # Groups that agree: the model covariance stands, within the sandwich's noise.
        assert np.sqrt(widened[0, 0]) < 4.0 * np.sqrt(model[0, 0])
    else:
        # The compromise is centimetres off along x, several model sigmas; the widened
        # covariance covers it within 2 sigma.
        assert error_x > 0.01 and error_x > 2.5 * np.sqrt(model[0, 0])
        assert error_x < 2.0 * np.sqrt(widened[0, 0])


def test_one_keyframe_leaves_nothing_to_compare():
    rng = np.random.default_rng(4)
    pose, px, points, clusters, _ = _two_keyframes(0.05, rng)
    assert cluster_robust_covariance(pose, px, points, CAMERA, np.zeros(len(px), int)) is None


def test_an_unknown_covariance_stays_unknown_when_widened():
    """A singular fit states an infinite covariance (every direction unknown); widening it
    to the keyframes' spread leaves it so instead of failing in the eigen-solver."""
    rng = np.random.default_rng(5)
    pose, px, points, clusters, _ = _two_keyframes(0.05, rng)
    robust = cluster_robust_covariance(pose, px, points, CAMERA, clusters)
    assert robust is not None
    unknown = np.full((6, 6), np.inf)
    assert np.all(np.isinf(at_least(unknown, robust)))
