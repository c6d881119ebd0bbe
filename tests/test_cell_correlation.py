"""The intra-cell correlation of reprojection errors
(:mod:`reloc_service.algorithms.pose.cell_correlation`): recovered from simulated residuals
with a known between-cell share, measured on a map whose keyframes' keypoints share an
error per image cell, and the intrinsics test on few cells judged with it."""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import numpy as np
import pytest

from reloc_service.algorithms.pose.cell_correlation import (
    cell_components,
    design_effect,
    fitted_residuals,
    grid_cells,
    mean_cell_size,
    pooled_correlation,
)
from reloc_service.algorithms.pose.intrinsics import (
    CLUSTER_GRID,
    IntrinsicsCheck,
    IntrinsicsPrior,
    Solution,
    too_few_cells,
)
from reloc_service.algorithms.pose.map_consistency import map_cell_correlation, prepare_map
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.map import MapState


def shared_residuals(rng: np.random.Generator, sizes: np.ndarray, rho: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) unit-variance residuals whose cells (N,) of ``sizes`` points share ``rho`` of
    their variance (a per-cell offset of variance ``rho`` plus noise of ``1 - rho``)."""
    cells = np.repeat(np.arange(len(sizes)), sizes)
    offsets = rng.normal(0.0, np.sqrt(rho), (len(sizes), 2))
    return offsets[cells] + rng.normal(0.0, np.sqrt(1.0 - rho), (len(cells), 2)), cells


@pytest.mark.parametrize("rho", [0.0, 0.1, 0.3])
def test_the_variance_components_recover_a_known_intra_cell_correlation(rho):
    rng = np.random.default_rng(7)
    found = []
    for _ in range(300):
        sizes = rng.integers(5, 30, 16)  # a keyframe's held-out points over a 4x4 grid
        components = cell_components(*shared_residuals(rng, sizes, rho))
        assert components is not None
        found.append(components)
    pooled = pooled_correlation(found)
    assert pooled is not None and pooled.keyframes == 300
    # The truncation at zero biases a zero correlation up by about its standard error over
    # one keyframe's 16 cells (a few hundredths); above it the mean is unbiased.
    assert pooled.rho == pytest.approx(rho, abs=0.02)
    assert pooled.upper >= pooled.rho + pooled.standard_error


def test_the_upper_bound_covers_the_correlation_over_few_keyframes():
    # Five keyframes state a bound that covers the true rho in about 95 % of maps.
    rng = np.random.default_rng(11)
    covered = 0
    for _ in range(400):
        parts = [cell_components(*shared_residuals(rng, rng.integers(5, 30, 16), 0.2))
                 for _ in range(5)]
        pooled = pooled_correlation([p for p in parts if p is not None])
        assert pooled is not None
        covered += pooled.upper >= 0.2
    assert 0.9 <= covered / 400 <= 0.99


def test_the_design_effect_is_the_variance_inflation_of_a_mean_over_shared_cells():
    rng = np.random.default_rng(3)
    sizes = np.array([12, 6, 3])  # unguided matches over three cells
    rho = 0.25
    means = np.array([shared_residuals(rng, sizes, rho)[0][:, 0].mean() for _ in range(20000)])
    independent = 1.0 / sizes.sum()
    # The mean's variance is sum_g (m_g^2 rho + m_g (1 - rho)) / N^2 = (1 + (m - 1) rho) / N
    # with m = sum m_g^2 / N: Kish's design effect with the size-weighted mean cell size.
    m = mean_cell_size(np.repeat(np.arange(3), sizes))
    assert m == pytest.approx((144 + 36 + 9) / 21)
    assert means.var() / independent == pytest.approx(design_effect(rho, m), rel=0.05)
    assert design_effect(0.0, m) == 1.0


def test_fitted_residuals_leave_nothing_the_columns_explain():
    rng = np.random.default_rng(5)
    jac = rng.normal(size=(40, 2, 8))
    weights = rng.uniform(0.5, 2.0, 40)
    residuals = np.einsum("mik,k->mi", jac, rng.normal(size=8)) + rng.normal(0, 0.1, (40, 2))
    out = fitted_residuals(residuals, jac, weights)
    whitened_jac = (jac * np.sqrt(weights)[:, None, None]).reshape(80, 8)
    assert np.abs(whitened_jac.T @ out.ravel()).max() < 1e-9
    assert np.abs(out).max() < 1.0  # the noise is left, the columns' part is gone


def test_grid_cells_are_row_major_over_the_image():
    px = np.array([[0.0, 0.0], [319.0, 0.0], [0.0, 239.0], [200.0, 130.0]])
    assert grid_cells(px, (320, 240), 4).tolist() == [0, 3, 12, 10]


def few_cell_check(rho: float | None, mean_size: float) -> IntrinsicsCheck:
    """A test of 30 matches in 3 cells whose focal is 15 % off with a 2.3 % model sigma
    (7scenes_redkitchen query 9 at x1.15): the cluster-robust covariance over 3 cells is as
    wide as the model's, so only the reference's degrees of freedom differ."""
    model = np.diag([0.023**2, 1.0])
    solution = Solution(theta=np.array([-0.15, 0.0]), model_covariance=model,
                        robust_covariance=model, clusters=3, dof=52, sigma2=1.0, inliers=30,
                        cost=0.0, twist=np.zeros(6), mean_cell_size=mean_size)
    return IntrinsicsCheck(solutions=(solution,), prior=IntrinsicsPrior(), focal_given_px=600.0,
                           pose_shift=np.zeros((6, 2)), cell_correlation=rho)


def test_a_focal_off_on_few_cells_is_refused_with_the_measured_sharing():
    # The cluster-robust reference F(2, G - 2) over 3 cells cannot reject a 6.5-sigma focal
    # error at 1e-3; the model's reference with its degrees of freedom can, where the map
    # measured little sharing, and cannot where the cells share most of their error.
    level = IntrinsicsPrior().false_refusal
    assert few_cell_check(None, 10.0).p_value > level
    assert few_cell_check(0.05, 10.0).p_value < level
    assert few_cell_check(0.9, 10.0).p_value > level
    assert few_cell_check(0.05, 10.0).p_value < few_cell_check(0.1, 10.0).p_value


def test_only_the_unguided_test_takes_the_correlation():
    check = few_cell_check(None, 10.0)
    assert check.with_unguided_cell_correlation(0.1) is check  # no unguided test: unchanged
    both = dataclasses.replace(check, unguided=few_cell_check(None, 10.0))
    judged = both.with_unguided_cell_correlation(0.1)
    assert judged.cell_correlation is None
    assert judged.unguided is not None and judged.unguided.cell_correlation == 0.1
    assert judged.with_dispersion(2.0).unguided.cell_correlation == 0.1  # type: ignore[union-attr]


def cell_shared(state: MapState, sigma_px: float, seed: int) -> MapState:
    """``state`` with every keyframe's keypoints in each cell of the test's grid moved by
    one offset per cell (``sigma_px`` per coordinate): an error shared within a cell, as a
    blurred region or landmarks from the same few keyframes share it."""
    rng = np.random.default_rng(seed)
    keyframes = {}
    for kf_id, keyframe in state.keyframes.items():
        feats = keyframe.features["sift"]
        px = feats.keypoints_px.astype(np.float64)
        cells = grid_cells(px, keyframe.camera.size, CLUSTER_GRID)
        px = px + rng.normal(0.0, sigma_px, (CLUSTER_GRID**2, 2))[cells]
        keyframes[kf_id] = keyframe.with_features(
            "sift", dataclasses.replace(feats, keypoints_px=px.astype(feats.keypoints_px.dtype)))
    return dataclasses.replace(state, keyframes=MappingProxyType(keyframes))


def test_a_map_whose_cells_share_their_errors_measures_it(synthetic_map):
    conf = PnPConf(unguided_cell_correlation=True)
    ids = synthetic_map.keyframe_ids()
    prepare_map(synthetic_map, "sift", PnPConf())  # statistics cached without the cells
    honest = map_cell_correlation(synthetic_map, "sift", ids, conf)
    shared = map_cell_correlation(cell_shared(synthetic_map, 1.0, seed=4), "sift", ids, conf)
    assert honest is not None and shared is not None
    assert honest.keyframes == shared.keyframes == len(ids)
    assert shared.rho > honest.upper
    assert shared.rho > 0.3


def test_the_sandwich_stays_where_the_cells_are_enough():
    # Over 16 cells of two matches each the sandwich's reference is sharper than the model's
    # with each cell one observation: the measured correlation does not replace it, and the
    # test is the cluster-robust one's.
    many = dataclasses.replace(few_cell_check(None, 2.0).solution, clusters=16)
    assert not too_few_cells(many, 1e-3)
    assert too_few_cells(few_cell_check(None, 2.0).solution, 1e-3)
    two = dataclasses.replace(many, clusters=2, robust_covariance=None)
    assert not too_few_cells(two, 1e-3)  # no sandwich: the model's test stands, as without
    check = dataclasses.replace(few_cell_check(None, 2.0), solutions=(many,))
    assert dataclasses.replace(check, cell_correlation=0.05).p_value == check.p_value
