"""Guided growth of a tracked pose: the pose solved on the matches found in the prior's
windows is grown onto the landmarks matched around it (windows of twice the inlier
threshold, :func:`..pose.prior_windows.search_around`). The prior's windows are wide, and a
crowd of similar descriptors hides matches that the solved pose's narrow windows find."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core import distributions as stats
from ...core.frame import Features, Frame
from ..pose.base import PoseEstimate
from ..pose.guided import GuidedConf
from ..pose.landmark_matches import union_matches
from ..pose.landmark_pool import LandmarkPool
from ..pose.pnp import solve_pnp_indexed
from ..pose.pnp_conf import PnPConf
from ..pose.point_uncertainty import PointUncertainty
from ..pose.prior_windows import search_around
from ..pose.regated_refinement import refine_from

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The ways a tracked pose grows onto the matches found around it: "ransac" solves the
#: window consensus plus those matches again (P3P LO-RANSAC); "regated" refines from the
#: solved pose, each match gated by the residual its covariance predicts
#: (:mod:`..pose.regated_refinement`).
GROWTH = ("ransac", "regated")


def keypoint_scales(scale: float, n: int) -> Array | None:
    """(n,) keypoint localisation scales of features found on an image reduced by
    ``1 / scale``; None (one pixel each) at full size."""
    return None if scale == 1 else np.full(n, scale)


def grow(query: Frame, feats: Features, est: PoseEstimate, pool: LandmarkPool,
         seed_q: IntArray, seed_rows: IntArray, uncertainty: PointUncertainty, *,
         pnp_conf: PnPConf, growth: str, gate_probability: float, background_quantile: float,
         scale: float, background: float
         ) -> tuple[PoseEstimate, IntArray, IntArray, IntArray] | None:
    """The pose solved again or refined (``growth``, one of :data:`GROWTH`) on the window
    consensus (``seed_q``, ``seed_rows``) plus the landmarks matched around the solved
    pose. ``gate_probability``: the regated refinement's residual gate (chi-square, 2
    degrees of freedom); ``scale``: the query keypoints' localisation in full-image
    pixels; ``background``: the descriptors' chance distance at ``background_quantile``,
    reused where guided matching's quantile is that one. (estimate, query indices, pool
    rows, inlier indices), or None when that adds no inlier."""
    guided = GuidedConf()
    same = guided.background_quantile == background_quantile
    g_idx, g_rows = search_around(
        feats, query.camera, est.world_from_cam, pool.descriptors, pool.points_world,
        guided.window_factor * pnp_conf.max_reproj_error_px, ratio=guided.window_ratio,
        background_quantile=guided.background_quantile,
        background=background if same else None)
    q_all, rows_all = union_matches(seed_q, seed_rows, g_idx, g_rows)
    px, points = feats.keypoints_px[q_all], pool.points_world[rows_all]
    if growth == "regated":
        # Each correspondence gated by the residual the solved pose's covariance predicts
        # for it: a fixed inlier threshold can leave out the right guided matches where
        # the window consensus did not reach, and keep that pose in its own basin.
        solved = refine_from(est, px, points, query.camera, pnp_conf,
                             uncertainty.take(rows_all),
                             float(stats.chi2.ppf(gate_probability, 2)))
    else:
        # A RANSAC again, not a refinement at the inlier threshold from the solved pose:
        # that pose rests on the window consensus alone, and at its inlier threshold it
        # can leave out the right guided matches and settle in its own basin
        # (centimetres off on the synthetic room).
        solved = solve_pnp_indexed(px, points, query.camera, pnp_conf,
                                   uncertainty=uncertainty.take(rows_all),
                                   keypoint_scales=keypoint_scales(scale, len(q_all)))
    if solved is None or (solved[0].inliers or 0) <= (est.inliers or 0):
        return None
    return solved[0], q_all, rows_all, solved[1]
