"""Whether the query's camera is the one it claims: a focal scale and a radial distortion term
estimated with the pose on the PnP correspondences, and the hypothesis "the given intrinsics,
within their calibration uncertainty" tested at a chosen false-refusal rate.

The given camera projects a point to ``p``; the camera that took the image, with its focal
``(1 + a)`` times the given one and a radial error, to ``c + (1 + a) (p - c) + b g(p - c)``,
with ``c`` the principal point and ``g(v) = |v|^2 v / R^3`` (``R``: the principal point's
distance to the farthest image corner), so ``b`` is the error in pixels at that corner: a
wrong ``k1`` bends pixels with the cube of their radius. Gauss-Newton on the pose and
``theta = (a, b)`` together, its steps halved until the truncated error falls and the inliers
re-gated under each new ``theta`` (a wrong focal leaves the image's outer part outside the
first consensus), gives ``theta`` and, by the Schur complement of the pose block, its
covariance ``V``. The pose absorbs much of a wrong focal (moved along its axis, it explains
the image's centre), so the estimate starts from the given camera and from focal scales
0.66 to 1.52 too; another start replaces the given one only where it fits significantly
better (likelihood ratio at the test's level), and the farthest pose among the solutions the
data cannot exclude is kept for the covariance.

Under the hypothesis, ``theta`` is drawn from the calibration prior ``N(0, P)`` and estimated
with noise ``V``: ``T^2 = theta^T (V + P)^-1 theta`` is chi-square with 2 degrees of freedom
(Hotelling's, with ``V`` from the residuals: ``T^2 / 2 ~ F(2, dof)``). Two things make ``V``
too small. Residuals in one image region share the errors of the landmarks there: the test
also needs the cluster-robust covariance (the sandwich over the cells of a 4x4 grid, Cameron
& Miller 2015, with Hotelling's small-sample reference over the cells) to reject. And a map
built from imprecise keyframe poses bends everywhere a little, which no cell sees: ``V`` is
scaled by the dispersion such estimates show on the map's own keyframes
(:mod:`.map_consistency`). The test refuses only where both reject.

A test that passes has not shown the intrinsics right: a focal 5 % off moves the pose by
several of its sigmas yet passes when the keypoints are as coarse as ORB's. So the stated
covariance of the pose (estimated at the given intrinsics) becomes its expected squared error
with the intrinsics marginalised: :func:`.map_consistency.covariance_with_intrinsics`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import special

from ...core import distributions as stats
from ...core.cameras import Camera
from ...core.geometry import invert, se3_log_many
from .cell_correlation import (
    CellComponents,
    cell_components,
    design_effect,
    fitted_residuals,
    grid_cells,
    mean_cell_size,
)
from .intrinsics_gauss_newton import Equations, Problem, Projector, joint_estimates
from .intrinsics_model import IntrinsicsModel

Array = npt.NDArray[np.float64]



#: How every refusal of this test begins: relocalizers stop at it (the same camera would meet
#: any other place or method), and callers may recognise it.
REFUSAL = "intrinsics disagree"

#: Focal scales (times the given focal) the estimate also starts from: a geometric series of
#: ratio 1.15 from 0.66 to 1.52, so that any focal in between is within 7.5 % of a start
#: (Gauss-Newton converges from there on a scene with depth).
FOCAL_STARTS = tuple(float(1.15**k) for k in (-3, -2, -1, 1, 2, 3))

#: Cells per side of the grid whose cells are the clusters of the robust covariance (the
#: verification's coverage grid: inliers in one cell share the landmarks' local errors).
CLUSTER_GRID = 4


@dataclass(frozen=True)
class IntrinsicsPrior:
    """How well a correct calibration knows the camera, 1 sigma: the focal's relative error
    and the radial error at the farthest image corner, pixels; the false-refusal rate of
    the test (the share of queries with correct intrinsics it refuses); and the
    missed-detection rate a passing pose's covariance allows for (an intrinsics error the
    test misses more often than this moves the pose within 3 of its stated sigmas:
    :mod:`.intrinsics_power`)."""

    focal_sigma_rel: float = 0.005
    radial_sigma_px: float = 2.0
    false_refusal: float = 1e-3
    missed_detection: float = 0.5

    @property
    def covariance(self) -> Array:
        return np.diag([self.focal_sigma_rel**2, self.radial_sigma_px**2])


@dataclass(frozen=True, eq=False)
class Solution:
    """One joint estimate of the pose and ``theta = (a, b)``: the focal ``1 + a`` times the
    given one and ``b`` pixels of radial error at the farthest image corner.
    ``model_covariance`` (2, 2) is the covariance of ``theta`` from the residuals' variance
    ``sigma2`` (px^2; the Schur complement of the pose in the weighted normal equations),
    ``robust_covariance`` the cluster-robust one over ``clusters`` occupied grid cells (None
    below 3), ``dof`` the residual degrees of freedom, ``inliers`` the correspondences it
    re-gated, ``cost`` their weighted truncated squared error (px^2), ``twist`` (6,) its
    pose relative to the pose at the given intrinsics (right perturbation) and
    ``mean_cell_size`` the size-weighted mean number of inliers per occupied cell (``sum m_g^2
    / sum m_g``, what a design effect scales with: :mod:`.cell_correlation`)."""

    theta: Array
    model_covariance: Array
    robust_covariance: Array | None
    clusters: int
    dof: int
    sigma2: float
    inliers: int
    cost: float
    twist: Array
    mean_cell_size: float = 1.0


@dataclass(frozen=True, eq=False)
class IntrinsicsCheck:
    """The verdict on a query's intrinsics from one pose's correspondences.

    ``solutions``: the joint estimates from the given camera (first) and from the other
    focal starts; the one tested (:attr:`solution`) is the first unless another explains the
    correspondences significantly better. ``dispersion`` scales the model covariance by how
    much more such estimates vary on this map than the model says (:mod:`.map_consistency`;
    1 until known). ``pose_shift`` (6, 2) is ``B``: the pose at the given intrinsics moves by
    ``B theta`` (twist of a right perturbation) when the camera is ``theta`` off."""

    solutions: tuple[Solution, ...]
    prior: IntrinsicsPrior
    focal_given_px: float
    pose_shift: Array
    dispersion: float = 1.0
    #: The same test on the correspondences found without the pose (before guided matching
    #: grew it), where there were enough: matches found in windows around the projections
    #: of a pose agree with its intrinsics by construction, so they may confirm the given
    #: camera but not overrule what the unguided ones say (:mod:`.intrinsics_guided`).
    unguided: IntrinsicsCheck | None = None
    #: The intra-cell correlation of reprojection errors the map's keyframes show (the upper
    #: confidence bound of :mod:`.cell_correlation`), where measured and asked for: over too
    #: few cells (:func:`too_few_cells`) the test then allows for errors shared within a
    #: cell by the design effect on the model covariance (keeping the model's degrees of
    #: freedom) instead of the cluster-robust sandwich, whose reference over the 3-5 cells
    #: unguided matches occupy has almost no degrees of freedom. None: the cluster-robust
    #: reference.
    cell_correlation: float | None = None

    def _likelihood_ratio(self, worse: Solution, better: Solution) -> float:
        """The likelihood-ratio statistic of ``better`` against ``worse``: their cost
        difference over the residual variance (times the dispersion), chi-square with 2
        degrees of freedom where ``worse`` is right."""
        return (worse.cost - better.cost) / (self.solutions[0].sigma2 * self.dispersion)

    @property
    def _limit(self) -> float:
        # scipy.special's inverse survival function, the value stats.chi2.isf returns at a
        # hundredth of its cost (the property is read several times per test).
        return float(special.chdtri(2, self.prior.false_refusal))

    @property
    def solution(self) -> Solution:
        """The solution tested: the one from the given camera, unless another explains the
        correspondences better beyond the likelihood-ratio limit (the test's level): a
        start that merely ties does not replace it (the best of several ties would be
        chosen for its noise)."""
        given = self.solutions[0]
        best = min(self.solutions, key=lambda s: s.cost)
        return best if self._likelihood_ratio(given, best) > self._limit else given

    @property
    def unexcluded_twist(self) -> Array:
        """(6,) the pose shift, relative to the pose at the given intrinsics, of the solution
        farthest from it (in position) that the data cannot exclude: whose cost exceeds the
        best's by less than the likelihood-ratio limit. A wrong focal seen on a scene with
        little depth may fit as well as the right one, from a pose far away; where the test
        lets it pass, the stated covariance must reach it."""
        best = min(self.solutions, key=lambda s: s.cost)
        near = [s for s in self.solutions if self._likelihood_ratio(s, best) <= self._limit]
        return max(near, key=lambda s: float(np.linalg.norm(s.twist[:3]))).twist

    @property
    def theta(self) -> Array:
        return self.solution.theta

    @property
    def model_covariance(self) -> Array:
        return self.solution.model_covariance

    @property
    def inliers(self) -> int:
        return self.solution.inliers

    @property
    def focal_scale(self) -> float:
        return 1.0 + float(self.theta[0])

    @property
    def radial_px(self) -> float:
        return float(self.theta[1])

    @property
    def covariance(self) -> Array:
        """(2, 2) the data's covariance of ``theta``: the model's times the dispersion."""
        return self.dispersion * self.model_covariance

    @property
    def data_statistic(self) -> float:
        """``theta^T V^-1 theta`` under the model covariance alone (no prior, no dispersion):
        chi-square with 2 degrees of freedom where the model's noise is the whole story."""
        return hotelling_t2(self.theta, self.model_covariance)

    @property
    def p_value(self) -> float:
        """P-value of "the given intrinsics" (``theta ~ N(0, P)``, estimated with noise):
        the larger of the model-based test's (covariance ``dispersion V + P``, Hotelling's
        ``T^2 / 2 ~ F(2, dof)``) and the cluster-robust one's (``V_c + P`` over ``G``
        cells: ``T^2 (G - 2) / (2 (G - 1)) ~ F(2, G - 2)``): each allows for what the other
        misses (a map bent everywhere, noise shared by one region). With a measured
        :attr:`cell_correlation` ``rho`` over too few cells (:func:`too_few_cells`) the
        second is the design-effect one instead (``(1 + (m - 1) rho) dispersion V + P``,
        ``F(2, dof)``)."""
        chosen = self.solution
        p_model = hotelling_p_value(hotelling_t2(chosen.theta, self.covariance + self.prior.covariance),
                             chosen.dof)
        if self.cell_correlation is not None and too_few_cells(chosen, self.prior.false_refusal):
            inflation = design_effect(self.cell_correlation, chosen.mean_cell_size)
            t2 = hotelling_t2(chosen.theta, inflation * self.covariance + self.prior.covariance)
            return max(p_model, hotelling_p_value(t2, chosen.dof))
        if chosen.robust_covariance is None:
            return p_model
        g = chosen.clusters
        t2 = hotelling_t2(chosen.theta, chosen.robust_covariance + self.prior.covariance)
        return max(p_model, hotelling_p_value(t2 * (g - 2) / (g - 1), g - 2))

    @property
    def passed(self) -> bool:
        """Whether the given intrinsics pass; with an :attr:`unguided` test, both tests must
        pass, each at the false-refusal rate: together they refuse a correct camera at most
        twice as often (the union bound; less, since the unguided matches are part of the
        whole set). Halving each level instead (Bonferroni) would weaken the whole set's
        test, which refuses stale focals the unguided matches alone cannot."""
        level = self.prior.false_refusal
        return not (self.p_value < level
                    or (self.unguided is not None and self.unguided.p_value < level))

    def with_unguided_cell_correlation(self, rho: float) -> IntrinsicsCheck:
        """This check with its :attr:`unguided` test allowing for the intra-cell
        correlation ``rho`` (:attr:`cell_correlation`); itself where it has none."""
        if self.unguided is None:
            return self
        return dataclasses.replace(
            self, unguided=dataclasses.replace(self.unguided, cell_correlation=float(rho)))

    def with_dispersion(self, dispersion: float) -> IntrinsicsCheck:
        unguided = None if self.unguided is None else self.unguided.with_dispersion(dispersion)
        return dataclasses.replace(self, dispersion=max(1.0, float(dispersion)),
                                   unguided=unguided)

    @property
    def reason(self) -> str:
        """Why the check refuses (the component that disagrees most, in units of its own
        sigma), or "" when it passes."""
        if self.passed:
            return ""
        if self.unguided is not None and self.unguided.p_value < self.prior.false_refusal:
            return self.unguided._disagreement() + " on the matches found without the pose"
        return self._disagreement()

    def _disagreement(self) -> str:
        """The refusal naming the component that disagrees most, in units of its sigma."""
        sigma = np.sqrt(np.maximum(np.diag(self.covariance + self.prior.covariance), 1e-300))
        z_focal, z_radial = np.abs(self.theta) / sigma
        if z_focal >= z_radial:
            what = (f"focal {self.focal_scale * self.focal_given_px:.1f} px estimated, "
                    f"{self.focal_given_px:.1f} given")
        else:
            what = (f"distortion {self.radial_px:+.1f} px at the image corner estimated, "
                    f"0 given")
        return f"{REFUSAL}: {what} (p = {self.p_value:.1e})"


def check_intrinsics(world_from_cam: Array, px: Array, inliers: npt.NDArray[np.int64],
                     weights: Array, camera: Camera, project: Projector, *, depth_m: float,
                     threshold_px: float, min_sigma_px: float, prior: IntrinsicsPrior,
                     iterations: int = 5, focal_starts: tuple[float, ...] = FOCAL_STARTS
                     ) -> IntrinsicsCheck | None:
    """Test the intrinsics ``camera`` claims on N correspondences: ``px`` (N, 2) query pixels
    whose points ``project`` maps through ``camera``, ``weights`` (N,) their residuals'
    inverse variances (units of the keypoint noise), ``inliers`` those of the
    fixed-intrinsics ``world_from_cam`` within ``threshold_px``, ``depth_m`` their median
    depth. None with fewer than 8 inliers (no test: the pose alone has 6 unknowns).

    A wrong focal is partly absorbed by the pose (the camera moved along its axis explains
    the centre of the image), so the inliers at the given camera may all agree with it, and
    Gauss-Newton from there would find the given focal again. So the estimate also starts at
    each focal of ``focal_starts``, the camera moved along its axis by as much as that focal
    needs at ``depth_m``, each re-gated (:attr:`IntrinsicsCheck.solution` says which is
    tested)."""
    if len(inliers) < 8:
        return None
    model = IntrinsicsModel(camera)
    given = _normal_equations(world_from_cam, np.zeros(2), px, weights, model, project,
                              threshold_px, rows=inliers)
    starts = [world_from_cam] + [world_from_cam @ _along_axis(-(factor - 1.0) * depth_m)
                                 for factor in focal_starts]
    thetas = np.array([[0.0, 0.0]] + [[factor - 1.0, 0.0] for factor in focal_starts])
    poses, thetas, found = joint_estimates(
        np.stack(starts), thetas, inliers, Problem(px, weights, model, project, threshold_px),
        iterations)
    twists = se3_log_many(invert(world_from_cam)[None] @ poses)
    solutions = tuple(_solution(eq, theta, twist, camera, min_sigma_px)
                      for theta, twist, eq in zip(thetas, twists, found, strict=True))
    return IntrinsicsCheck(solutions=solutions, prior=prior, focal_given_px=float(camera.fx),
                           pose_shift=_pose_shift(given.normal))


def cell_shared_components(world_from_cam: Array, px: Array, rows: npt.NDArray[np.int64],
                           weights: Array, camera: Camera, project: Projector, *,
                           threshold_px: float) -> CellComponents | None:
    """The variance components over this test's grid cells (:mod:`.cell_correlation`) of
    the residuals of the correspondences ``rows`` at ``world_from_cam`` and the given camera
    (arguments as :func:`check_intrinsics`'s), whitened by their weights and with what the
    pose and ``theta`` explain projected out, as the test's joint fit would; None with fewer
    than two occupied cells."""
    eq = _normal_equations(world_from_cam, np.zeros(2), px, weights, IntrinsicsModel(camera),
                           project, threshold_px, rows=rows)
    residuals = fitted_residuals(eq.residuals, eq.jac, eq.weights)
    return cell_components(residuals, grid_cells(eq.px, camera.size, CLUSTER_GRID))


def _along_axis(distance_m: float) -> Array:
    """(4, 4) ``cam_from_moved``: the camera moved ``distance_m`` along its optical axis."""
    out = np.eye(4)
    out[2, 3] = distance_m
    return out


def _normal_equations(world_from_cam: Array, theta: Array, px: Array, weights: Array,
                      model: IntrinsicsModel, project: Projector, threshold_px: float, *,
                      rows: npt.NDArray[np.int64] | None = None) -> Equations:
    """:class:`Equations` at ``world_from_cam`` and ``theta`` on ``rows`` or (None) on the
    correspondences within ``threshold_px`` of their modelled pixels."""
    projected, points_cam = project.pixels(world_from_cam)
    residuals, squared = model.residuals(projected, px, theta)
    if rows is None:
        rows = np.flatnonzero(squared < threshold_px**2)
    cost = float((weights * np.minimum(squared, threshold_px**2)).sum())
    jac = project.jacobian(points_cam[rows])  # each row's Jacobian is its own point's
    full = model.jacobian_of(projected[rows], jac, np.arange(len(rows)), theta)  # (M, 2, 8)
    w = weights[rows]
    flat = full.reshape(-1, 8)
    weighted = flat * np.repeat(w, 2)[:, None]
    return Equations(rows, weighted.T @ flat, weighted.T @ residuals[rows].ravel(),
                      residuals[rows], full, w, px[rows], cost)


def _pose_shift(normal: Array) -> Array:
    """(6, 2) ``B = N_pp^-1 N_p theta``: how the fixed-intrinsics pose moves per unit of
    ``theta`` (the pose that best explains pixels bent by ``theta`` with the given camera)."""
    try:
        return np.asarray(np.linalg.solve(normal[:6, :6], normal[:6, 6:]), np.float64)
    except np.linalg.LinAlgError:
        return np.full((6, 2), np.inf)


def _solution(eq: Equations, theta: Array, twist: Array, camera: Camera,
              min_sigma_px: float) -> Solution:
    """The :class:`Solution` of the normal equations ``eq`` at a joint estimate: the model
    covariance ``sigma^2 [N^-1]_theta`` (the Schur complement of the pose; sigma from the
    weighted residuals, at least ``min_sigma_px``) and the cluster-robust one."""
    dof = max(2 * len(eq.rows) - 8, 1)
    sigma2 = max(float((eq.weights[:, None] * eq.residuals**2).sum()) / dof, min_sigma_px**2)
    try:
        inverse = np.asarray(np.linalg.inv(eq.normal), np.float64)
    except np.linalg.LinAlgError:
        inverse = np.full((8, 8), np.inf)
    cells = grid_cells(eq.px, camera.size, CLUSTER_GRID)
    robust, clusters = _cluster_robust(eq, inverse, cells)
    return Solution(theta=theta, model_covariance=sigma2 * inverse[6:, 6:],
                    robust_covariance=robust, clusters=clusters, dof=dof, sigma2=sigma2,
                    inliers=len(eq.rows), cost=eq.cost, twist=twist,
                    mean_cell_size=mean_cell_size(cells))


def _cluster_robust(eq: Equations, inverse: Array, cell: npt.NDArray[np.int64]
                    ) -> tuple[Array | None, int]:
    """The (2, 2) cluster-robust covariance of ``theta`` (sandwich ``N^-1 M N^-1`` with
    ``M`` the sum over grid cells ``cell`` (the rows' cells) of each cell's outer product of
    its score ``J^T W r``, times ``G / (G - 1)``) and the number ``G`` of occupied cells;
    None when ``G < 3``."""
    scores_per_point = np.einsum("mik,mi->mk", eq.jac, eq.residuals) * eq.weights[:, None]
    # Per-cell sums in the points' order (np.add.at's), in one bincount over (cell, column).
    scores = np.bincount((cell[:, None] * 8 + np.arange(8)).ravel(),
                         weights=scores_per_point.ravel(),
                         minlength=8 * CLUSTER_GRID**2).reshape(CLUSTER_GRID**2, 8)
    occupied = np.flatnonzero(np.bincount(cell, minlength=CLUSTER_GRID**2))
    g = len(occupied)
    if g < 3 or not np.all(np.isfinite(inverse)):
        return None, g
    s = scores[occupied]
    meat = s.T @ s * (g / (g - 1))
    sandwich = inverse @ meat @ inverse
    return sandwich[6:, 6:], g


def too_few_cells(solution: Solution, level: float) -> bool:
    """Whether the cluster-robust reference over ``solution``'s occupied cells is weaker
    than the model's with every cell counted as one observation: its critical ``T^2`` at
    ``level`` (``2 (G - 1) / (G - 2) F(2, G - 2)``, in units of the sandwich, whose
    expectation is the model covariance times the design effect) at least ``m`` times the
    model's (``2 F(2, dof)``), ``m`` the size-weighted mean cell size (the design effect of
    a correlation of 1). There any measured correlation gives a sharper reference than the
    sandwich's; with more cells the sandwich, which sees the query's own cells, stays. Below
    3 cells there is no sandwich and the model's reference stands alone, as without a
    measured correlation: the design effect would only weaken that test there (a stale
    focal's unguided matches in two cells passed it: tum_fr1_rpy x1.15 query 6, answered
    12 cm off at 3.5 sigma), and a wrong pose is worse than no pose."""
    g = solution.clusters
    if g < 3:
        return False
    robust = 2.0 * (g - 1) / (g - 2) * float(special.fdtri(2, g - 2, 1.0 - level))
    model = 2.0 * float(special.fdtri(2, max(solution.dof, 1), 1.0 - level))
    return robust >= solution.mean_cell_size * model


def hotelling_p_value(t2: float, dof: int) -> float:
    """``P(F(2, dof) > t2 / 2)``, Hotelling's test of a two-parameter error with ``dof``
    residual degrees of freedom; 1 where there is no evidence (a statistic that is not
    finite, as from a singular covariance, or no residual degree of freedom)."""
    if not np.isfinite(t2) or dof < 1:
        return 1.0
    return stats.f.sf(t2 / 2.0, 2, dof)


def hotelling_t2(theta: Array, covariance: Array) -> float:
    """``theta^T covariance^-1 theta``; infinite for a singular covariance (no evidence,
    which :func:`hotelling_p_value` turns into a p-value of 1)."""
    try:
        return float(theta @ np.linalg.solve(covariance, theta))
    except np.linalg.LinAlgError:
        return float("inf")
