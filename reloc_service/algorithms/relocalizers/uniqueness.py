"""A verified pose must be the only good explanation of the query: where two candidate groups
give different verified poses (a true one and one a repeated picture, a periodic wall or an
identical object elsewhere explains), the hypothesis that explains significantly more of the
image wins, and without a clear winner the answer is "ambiguous".

Two hypotheses are the same solution when each fits the other's consensus: a pose a few
millimetres away reprojects the other's inliers within the inlier threshold, a pose that a
repetition explains sends them to the repeated copy (:func:`same_solution`). Different
solutions are compared by the query keypoints each explains (:mod:`..pose.support`), paired
as in McNemar's test: keypoints both explain carry no information about which is right; of
the ``n`` keypoints exactly one explains, the true pose should take clearly more than half.
Under "neither is better" the first's share is Binomial(n, 1/2); a hypothesis wins when that
share is beyond the level ``alpha`` (the verification's wrong-pose budget) against every
other solution (:func:`compare`, :func:`choose`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from reloc_client.result import RelocResult

from ...core import distributions as stats
from ...core.cameras import Camera
from ...core.geometry import pose_error, se3_log
from ..pose.base import PoseEstimate, Support, total_covariance
from ..pose.guided import project_into

Array = npt.NDArray[np.float64]


def fits_consensus(estimate: PoseEstimate, world_from_cam: Array, camera: Camera
                   ) -> float | None:
    """Share of ``estimate``'s inliers that ``world_from_cam`` reprojects within the
    estimate's inlier threshold; None when the estimate does not say what its inliers are."""
    px, points = estimate.inlier_px, estimate.inlier_points_world
    if px is None or points is None or len(px) == 0 or estimate.inlier_threshold_px is None:
        return None
    projected, visible = project_into(camera, world_from_cam, points)
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(projected - px, axis=1) < estimate.inlier_threshold_px
    return float(np.count_nonzero(near & visible)) / len(px)


def same_solution(first: PoseEstimate, second: PoseEstimate, camera: Camera, *,
                  alpha: float = 0.01) -> bool | None:
    """Whether two estimates are one solution: each pose fits the majority of the other's
    consensus, or they differ by less than their covariances allow (:func:`within_covariances`
    at level ``alpha``: two estimates of one place from different keyframes, a degree apart
    where their keypoints are a few pixels off); None when either does not say what its
    inliers are."""
    a = fits_consensus(first, second.world_from_cam, camera)
    b = fits_consensus(second, first.world_from_cam, camera)
    if a is None or b is None:
        return None
    return (a > 0.5 and b > 0.5) or within_covariances(first, second, alpha=alpha)


def within_covariances(first: PoseEstimate, second: PoseEstimate, *, alpha: float) -> bool:
    """Whether the two poses differ by less than chance would make them differ at level
    ``alpha`` under their stated covariances (the map's keyframe uncertainty included: two
    estimates from different keyframes differ by those keyframes' errors too): the squared
    Mahalanobis length of the twist between them under the sum of the two covariances (both
    right perturbations; for poses this close the second's frame is the first's to first
    order) below chi-square(6)'s ``1 - alpha`` quantile. False when either has no covariance."""
    a, b = total_covariance(first), total_covariance(second)
    if a is None or b is None:
        return False
    xi = se3_log(np.linalg.inv(first.world_from_cam) @ second.world_from_cam)
    joint = a + b
    try:
        m2 = float(xi @ np.linalg.solve(joint, xi))
    except np.linalg.LinAlgError:
        return False
    return bool(np.isfinite(m2) and m2 < stats.chi2.ppf(1.0 - alpha, 6))


@dataclass(frozen=True)
class Comparison:
    """The paired comparison of two hypotheses' supports: query keypoints only the first
    explains, only the second, and the one-sided binomial p-values of each count under
    "neither explains more" (small: that one explains significantly more)."""

    only_first: int
    only_second: int
    p_first: float
    p_second: float


def compare(first: Support, second: Support) -> Comparison:
    """McNemar's exact test on the keypoints exactly one of two supports explains."""
    a = int(np.setdiff1d(first.keypoints, second.keypoints, assume_unique=True).size)
    b = int(np.setdiff1d(second.keypoints, first.keypoints, assume_unique=True).size)
    n = a + b
    if n == 0:
        return Comparison(0, 0, 1.0, 1.0)
    return Comparison(a, b, float(stats.binom.sf(a - 1, n, 0.5)),
                      float(stats.binom.sf(b - 1, n, 0.5)))


@dataclass(frozen=True)
class Choice:
    """The index of the winning hypothesis among the solutions compared (None when none
    wins) and, when none does, why."""

    index: int | None
    reason: str = ""


def choose(estimates: Sequence[PoseEstimate], supports: Sequence[Support], *, alpha: float
           ) -> Choice:
    """The one estimate whose support is significantly larger (level ``alpha``) than every
    other's, or None with the closest pair that no test separates as the reason."""
    n = len(estimates)
    worst: tuple[float, int, int, Comparison] | None = None
    for i in range(n):
        beaten = [compare(supports[i], supports[j]) for j in range(n) if j != i]
        if all(c.p_first < alpha for c in beaten):
            return Choice(i)
        if i == 0:
            j, c = max(((j, compare(supports[0], supports[j])) for j in range(1, n)),
                       key=lambda jc: jc[1].p_first)
            worst = (c.p_first, 0, j, c)
    assert worst is not None
    _, i, j, c = worst
    dist, angle = pose_error(estimates[i].world_from_cam, estimates[j].world_from_cam)
    return Choice(None, f"ambiguous: {n} different poses explain the image comparably "
                        f"({dist:.2f} m and {np.degrees(angle):.1f} deg apart: "
                        f"{c.only_first} vs {c.only_second} query keypoints explained by one "
                        f"alone, p = {c.p_first:.2g} >= {alpha:g})")


def solutions(estimates: Sequence[PoseEstimate], camera: Camera,
              close: Callable[[PoseEstimate, PoseEstimate], bool], *, alpha: float = 0.01
              ) -> list[list[int]]:
    """Indices of ``estimates`` grouped into distinct solutions (:func:`same_solution` with
    each group's first member, or ``close``: poses within the caller's agreement tolerance
    are one place, however their inliers differ, as two keyframes of an imperfect map give
    the same place a few centimetres and degrees apart), in order of first appearance."""
    groups: list[list[int]] = []
    for i, est in enumerate(estimates):
        for group in groups:
            same = same_solution(estimates[group[0]], est, camera, alpha=alpha)
            if same or close(estimates[group[0]], est):
                group.append(i)
                break
        else:
            groups.append([i])
    return groups


def decide(estimates: Sequence[PoseEstimate], camera: Camera,
           support: Callable[[PoseEstimate], Support | None],
           close: Callable[[PoseEstimate, PoseEstimate], bool], *, alpha: float) -> Choice:
    """Which of the verified ``estimates`` (best-ranked first) answers: the first of the one
    solution they form (:func:`solutions`), or the first of the solution whose ``support``
    beats every other's (:func:`choose`). Different solutions that cannot be compared (no
    support) leave the query ambiguous."""
    groups = solutions(estimates, camera, close, alpha=alpha)
    if len(groups) == 1:
        return Choice(0)
    firsts = [estimates[g[0]] for g in groups]
    supports = [support(e) for e in firsts]
    known = [s for s in supports if s is not None]
    if len(known) < len(supports):
        dist, angle = pose_error(firsts[0].world_from_cam, firsts[1].world_from_cam)
        return Choice(None, f"ambiguous places: verified hypotheses disagree by {dist:.2f} m "
                            f"and {np.degrees(angle):.1f} deg, with no features to compare "
                            "them by")
    chosen = choose(firsts, known, alpha=alpha)
    return chosen if chosen.index is None else Choice(groups[chosen.index][0])


def refusing_rival(answer: PoseEstimate, refused: Sequence[tuple[RelocResult, PoseEstimate]],
                   camera: Camera, support: Callable[[PoseEstimate], Support | None],
                   close: Callable[[PoseEstimate, PoseEstimate], bool], *, alpha: float
                   ) -> tuple[RelocResult, PoseEstimate, str] | None:
    """The first of the ``refused`` hypotheses (each an intrinsics refusal of the query's
    camera and the estimate it refused) of another solution than ``answer`` whose support
    ``answer``'s does not beat at level ``alpha`` (:func:`compare`), with the refusal's
    reason saying so; None where ``answer`` beats every one. Such a hypothesis is as likely
    the true place as the answer, and there the correspondences disagree with the camera:
    the answer cannot vouch for it (one that cannot be compared, without support, does not
    either)."""
    mine = None
    for result, estimate in refused:
        if close(answer, estimate) or same_solution(answer, estimate, camera, alpha=alpha):
            continue  # the answer's own place, whose own test passed
        mine = support(answer) if mine is None else mine
        theirs = support(estimate)
        c = None if mine is None or theirs is None else compare(mine, theirs)
        if c is not None and c.p_first < alpha:
            continue
        dist, angle = pose_error(answer.world_from_cam, estimate.world_from_cam)
        weighed = ("no features to compare them by" if c is None else
                   f"{c.only_first} vs {c.only_second} query keypoints explained by one "
                   f"alone, p = {c.p_first:.2g} >= {alpha:g}")
        return result, estimate, (f"{result.reason}, at a pose {dist:.2f} m and "
                                  f"{np.degrees(angle):.1f} deg from the verified one, which "
                                  f"does not explain the query better ({weighed})")
    return None
