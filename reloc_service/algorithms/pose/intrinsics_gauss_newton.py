"""The intrinsics test's joint Gauss-Newton on the pose and ``theta`` (:mod:`.intrinsics`),
run from every start at once: each round takes the steps of every start still running in
one batched solve and exponential, projects their trials in one pass, and builds the normal
equations of the trials taken from one pass of pose Jacobians and the projections and
residuals their gating computed, instead of a few dozen small numpy calls per start and step;
each start's equations are kept, not rebuilt at the end.

Each start follows the serial algorithm exactly (the same steps, halvings and stopping
rule); the batched sums round differently from per-start ones, so estimates agree with a
start-by-start loop to rounding, not bit for bit (``tests/test_intrinsics_gauss_newton.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from ...core.geometry import se3_exp_many
from .intrinsics_model import IntrinsicsModel

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Halvings of a Gauss-Newton step before the estimate is taken as converged.
MAX_HALVINGS = 8

#: Fewest gated correspondences a joint estimate needs (8 unknowns).
MIN_ROWS = 8

#: A step below these in every component has converged: ``a`` (relative focal), ``b``
#: (pixels at the farthest corner) and the pose twist (metres, radians).
_THETA_TOLERANCE = np.array([1e-4, 1e-2])
_POSE_TOLERANCE = 1e-6


class Projector(Protocol):
    """Projection of every correspondence's point at a pose through the given camera
    (:func:`.projection.pose_projector`): the pixels of all, the Jacobian of those asked for."""

    def pixels(self, world_from_cam: Array) -> tuple[Array, Array]:
        """(N, 2) pixels and (N, 3) camera-frame points at ``world_from_cam``."""

    def pixels_many(self, world_from_cams: Array) -> tuple[Array, Array]:
        """(K, N, 2) pixels and (K, N, 3) camera-frame points at each of (K, 4, 4) poses."""

    def jacobian(self, points_cam: Array) -> Array:
        """(M, 2, 6) Jacobian of the pixels of (M, 3) camera-frame points w.r.t. a right
        perturbation of ``world_from_cam``, each row from its own point alone."""


@dataclass(frozen=True, eq=False)
class Equations:
    """The weighted normal equations of the pose and ``theta`` (8 unknowns, order pose
    twist then ``a``, ``b``) on ``rows``, with what the covariances need: the (M, 2) residuals,
    the (M, 2, 8) Jacobian and the (M,) weights of the rows, and their pixels; ``cost``, the
    weighted truncated squared error of every correspondence (MSAC: ``w min(|r|^2, t^2)``,
    whose descent direction on the inliers is the weighted Gauss-Newton step's)."""

    rows: npt.NDArray[np.int64]
    normal: Array
    rhs: Array
    residuals: Array
    jac: Array
    weights: Array
    px: Array
    cost: float


@dataclass(frozen=True)
class Problem:
    """The correspondences every start fits: (N, 2) query pixels, (N,) residual weights,
    the error model, the projection of their points and the inlier threshold."""

    px: Array
    weights: Array
    model: IntrinsicsModel
    project: Projector
    threshold_px: float


@dataclass
class _State:
    """K starts' current estimates: poses (K, 4, 4), ``theta`` (K, 2), truncated costs
    (K,), normal equations (K, 8, 8) and (K, 8) (and each start's :class:`Equations`), and
    each one's step (K, 8), halvings so far and steps taken."""

    poses: Array
    thetas: Array
    costs: Array
    normal: Array
    rhs: Array
    equations: list[Equations]
    steps: Array
    halvings: npt.NDArray[np.int64]
    taken: npt.NDArray[np.int64]


def joint_estimates(world_from_cams: Array, thetas: Array, given_rows: npt.NDArray[np.int64],
                    problem: Problem, iterations: int
                    ) -> tuple[Array, Array, list[Equations]]:
    """Gauss-Newton from K starts (K, 4, 4) poses and (K, 2) ``theta``: the first on
    ``given_rows`` (at least :data:`MIN_ROWS`), the others on the correspondences they gate;
    those gating fewer than :data:`MIN_ROWS` are dropped. Returns the kept starts' final poses, ``theta`` and
    normal equations, in the starts' order."""
    masks, costs, trial = _gate(world_from_cams, thetas, problem)
    masks[0] = False
    masks[0, given_rows] = True
    kept = np.flatnonzero(masks.sum(axis=1) >= MIN_ROWS)
    poses, thetas, masks, costs = world_from_cams[kept], thetas[kept], masks[kept], costs[kept]
    equations = _normal_equations(thetas, masks, costs, problem, trial.take(kept))
    k = len(kept)
    state = _State(poses.copy(), thetas.copy(), costs,
                   np.stack([eq.normal for eq in equations]),
                   np.stack([eq.rhs for eq in equations]), equations, np.zeros((k, 8)),
                   np.zeros(k, np.int64), np.zeros(k, np.int64))
    running = _new_steps(state, np.arange(k))
    while len(running):
        running = _round(state, running, problem, iterations)
    return state.poses, state.thetas, state.equations


def _round(state: _State, running: npt.NDArray[np.int64], problem: Problem,
           iterations: int) -> npt.NDArray[np.int64]:
    """One trial of each running start: taken where its truncated (MSAC) cost falls with
    enough rows left (then a new step, unless converged or out of iterations), else its
    step halved (the start stops after :data:`MAX_HALVINGS`). Returns those still running."""
    steps = state.steps[running]
    poses = state.poses[running] @ se3_exp_many(steps[:, :6])
    thetas = state.thetas[running] + steps[:, 6:]
    masks, costs, trial = _gate(poses, thetas, problem)
    better = (costs < state.costs[running]) & (masks.sum(axis=1) >= MIN_ROWS)
    refused = running[~better]
    state.steps[refused] /= 2.0
    state.halvings[refused] += 1
    taken = running[better]
    state.poses[taken], state.thetas[taken] = poses[better], thetas[better]
    state.costs[taken] = costs[better]
    equations = _normal_equations(thetas[better], masks[better], costs[better], problem,
                                  trial.take(np.flatnonzero(better)))
    for k, eq in zip(taken, equations, strict=True):
        state.equations[k], state.normal[k], state.rhs[k] = eq, eq.normal, eq.rhs
    state.taken[taken] += 1
    small = ((np.abs(steps[better, 6:] / _THETA_TOLERANCE).max(axis=1) < 1.0)
             & (np.abs(steps[better, :6]).max(axis=1) < _POSE_TOLERANCE))
    going = taken[~small & (state.taken[taken] < iterations)]
    halving = refused[state.halvings[refused] < MAX_HALVINGS]
    return np.sort(np.concatenate([halving, _new_steps(state, going)]))


def _new_steps(state: _State, starts: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Solve the normal equations of ``starts`` for their next steps (halvings reset);
    returns those with a finite step (a singular or non-finite system stops its start)."""
    if len(starts) == 0:
        return starts
    steps = np.full((len(starts), 8), np.nan)
    try:
        steps = np.linalg.solve(state.normal[starts], state.rhs[starts][:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # one singular system fails the batch: solve each
        for i, k in enumerate(starts):
            try:
                steps[i] = np.linalg.solve(state.normal[k], state.rhs[k])
            except np.linalg.LinAlgError:
                pass
    state.steps[starts], state.halvings[starts] = steps, 0
    return starts[np.isfinite(steps).all(axis=1)]


@dataclass(frozen=True)
class _Trial:
    """What gating K estimates computed that their normal equations need again: (K, N, 2)
    pixels, (K, N, 3) camera-frame points and (K, N, 2) residuals under each ``theta``."""

    projected: Array
    points_cam: Array
    residuals: Array

    def take(self, which: npt.NDArray[np.int64]) -> _Trial:
        """The trial of the estimates ``which`` alone."""
        return _Trial(self.projected[which], self.points_cam[which], self.residuals[which])


def _gate(world_from_cams: Array, thetas: Array, problem: Problem
          ) -> tuple[BoolArray, Array, _Trial]:
    """(K, N) correspondences within the threshold of their modelled pixels at each of K
    poses and ``theta``, (K,) the weighted truncated squared errors (MSAC), and the
    projections and residuals, which the normal equations of the estimates taken reuse (a
    row's values are its own: the same numbers for any subset of rows or estimates). The
    projections are one batched pass; the model runs per estimate (one compiled pass each
    where numba is installed: faster than numpy's temporaries over K x N rows)."""
    projected, points_cam = problem.project.pixels_many(world_from_cams)
    squared = np.empty(projected.shape[:2])
    residuals = np.empty(projected.shape)
    for k, theta in enumerate(thetas):
        residuals[k], squared[k] = problem.model.residuals(projected[k], problem.px, theta)
    limit = problem.threshold_px**2
    return (squared < limit, (problem.weights * np.minimum(squared, limit)).sum(axis=1),
            _Trial(projected, points_cam, residuals))


def _normal_equations(thetas: Array, masks: BoolArray, costs: Array, problem: Problem,
                      trial: _Trial) -> list[Equations]:
    """The :class:`Equations` of K estimates (``theta``, (K, N) gated rows, (K,) costs and
    the ``trial`` their poses' gating made): the pose Jacobians of all gated rows in one pass,
    the model and the products per estimate."""
    projected, points_cam = trial.projected, trial.points_cam
    which, rows = np.nonzero(masks)  # grouped by estimate
    jac = problem.project.jacobian(points_cam[which, rows])
    bounds = np.concatenate([[0], np.cumsum(masks.sum(axis=1))])
    out = []
    for k, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        mine = rows[lo:hi]
        residuals = trial.residuals[k, mine]
        full = problem.model.jacobian_of(projected[k, mine], jac[lo:hi],
                                         np.arange(hi - lo), thetas[k])  # (M, 2, 8)
        weights = problem.weights[mine]
        flat = full.reshape(-1, 8)
        weighted = flat * np.repeat(weights, 2)[:, None]
        out.append(Equations(mine, weighted.T @ flat, weighted.T @ residuals.ravel(),
                             residuals, full, weights, problem.px[mine], float(costs[k])))
    return out
