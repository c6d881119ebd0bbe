"""How each step of the default chain estimates a query's focal when the query claims a camera
whose focal is scaled: per query and step, the answered pose's error and Mahalanobis distance,
and the intrinsics test's focal estimates (whole inlier set and the matches found without the
pose, model and cluster-robust sigmas, p-values) against the true focal error ``1 / s - 1``.

    .venv/bin/python scripts/focal_census.py ../shared/data/real/7scenes_redkitchen \\
        --keyframe-sigma 0.015,0.45 --focal-scale 1.15 --queries 9,10,12,13
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import special

from reloc_service.algorithms.pose.base import PoseEstimate, total_covariance
from reloc_service.algorithms.pose.intrinsics import IntrinsicsCheck
from reloc_service.algorithms.pose.intrinsics_agreement import guided_bend_p_value
from reloc_service.algorithms.pose.intrinsics_envelope import intrinsics_moment, positive_part
from reloc_service.algorithms.pose.intrinsics_power import blind_spot_factor, governing_covariance
from reloc_service.algorithms.relocalizers.base import VerifyConf, stated_covariance
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.chain_hooks import ANSWERED
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import se3_log
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import (
    _build_map,
    ground_truth_covariance,
    record_from_result,
)
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker
from reloc_service.tools.eval.metrics import translation_mahalanobis
from reloc_service.tools.eval.query_camera import QueryCamera


def check_text(check: IntrinsicsCheck | None) -> str:
    """One test's focal estimate: value, model and robust sigma (%), p-value, inliers."""
    if check is None:
        return "-"
    s = check.solution
    model = 100 * np.sqrt(max(check.covariance[0, 0], 0.0))
    robust = ("-" if s.robust_covariance is None
              else f"{100 * np.sqrt(max(s.robust_covariance[0, 0], 0.0)):.1f}")
    shared = ("" if check.cell_correlation is None
              else f" rho {check.cell_correlation:.3f} m {s.mean_cell_size:.1f}")
    return (f"{100 * check.theta[0]:+.1f}% (m {model:.1f} r {robust} G{s.clusters}{shared}) "
            f"p={check.p_value:.1e} n={check.inliers}")


def robust_bend_p_value(check: IntrinsicsCheck) -> float:
    """Hausman's test of the focal by the cluster-robust variances: ``(a_u - a_w)^2 / (r_u -
    r_w)`` against ``F(1, G - 1)`` over ``G``, the fewer occupied cells. 1 without an
    unguided test or a robust variance, or where ``r_u <= r_w``."""
    unguided = check.unguided
    if unguided is None:
        return 1.0
    whole, alone = check.solution, unguided.solution
    if whole.robust_covariance is None or alone.robust_covariance is None:
        return 1.0
    diff = float(unguided.theta[0]) - float(check.theta[0])
    gap = float(alone.robust_covariance[0, 0]) - float(whole.robust_covariance[0, 0])
    dof = min(alone.clusters, whole.clusters) - 1
    if not (np.isfinite(gap) and gap > 0.0) or dof < 1:
        return 1.0
    return float(special.fdtrc(1, dof, diff * diff / gap))


def common_sigma_bend_p_value(check: IntrinsicsCheck) -> float:
    """Hausman's test of the focal with one residual variance for both sets, the unguided
    set's (under "guided matching did not bend it" both sets' residuals are one noise; the
    whole set's own variance is inflated where guided matches fit a wrong focal, which can
    make ``v_u - v_w`` vanish): ``v_w`` rescaled by ``sigma_u^2 / sigma_w^2``."""
    unguided = check.unguided
    if unguided is None:
        return 1.0
    ratio = unguided.solution.sigma2 / check.solution.sigma2
    diff = float(unguided.theta[0]) - float(check.theta[0])
    gap = float(unguided.covariance[0, 0]) - ratio * float(check.covariance[0, 0])
    if not (np.isfinite(gap) and gap > 0.0):
        return 1.0
    return float(special.chdtrc(1, diff * diff / gap))


def bend_text(check: IntrinsicsCheck | None) -> str:
    """Hausman's test that guided matching bent the focal: the model-based p-value
    (:func:`guided_bend_p_value`) and the cluster-robust one (``F(1, G - 1)``)."""
    if check is None or check.unguided is None:
        return ""
    return (f" bend p model {guided_bend_p_value(check):.1e} "
            f"robust {robust_bend_p_value(check):.1e} "
            f"common-sigma {common_sigma_bend_p_value(check):.1e} "
            f"(sigma {np.sqrt(check.unguided.solution.sigma2):.2f} / "
            f"{np.sqrt(check.solution.sigma2):.2f} px)")


def shift_text(est: PoseEstimate, check: IntrinsicsCheck, gt: np.ndarray, truth: float) -> str:
    """Where the pose's error lies (twist from the answered pose to the true one, cm, in the
    camera's frame) against the shift the test predicts for the true focal error (``B
    theta``), for its own estimate, the tested solution's twist, and the stated position
    sigmas along the error."""
    err = se3_log(np.linalg.inv(est.world_from_cam) @ gt)
    b = check.pose_shift
    pred = b @ np.array([truth, 0.0])
    own = b @ check.theta
    cov = total_covariance(est)
    along = "-"
    if cov is not None:
        t = err[:3]
        along = (f"{np.sqrt(float(t @ cov[:3, :3] @ t) / float(t @ t)) * 100:.1f} "
                 f"(decision cov {np.sqrt(float(t @ np.linalg.solve(cov[:3, :3], t))):.1f} sig; "
                 f"sigmas {' '.join(f'{100 * v:.1f}' for v in np.sqrt(np.linalg.eigvalsh(cov[:3, :3])))})")
    cm = lambda v: "(" + " ".join(f"{100 * x:+.1f}" for x in v[:3]) + ")"  # noqa: E731
    unguided = "" if check.unguided is None else (
        f" unguided: B*est {cm(b @ check.unguided.theta)} sol-twist "
        f"{cm(check.unguided.solution.twist)} far {cm(check.unguided.unexcluded_twist)}")
    return (f"err {cm(err)} B*truth {cm(pred)} B*est {cm(own)} sol-twist "
            f"{cm(check.solution.twist)} far {cm(check.unexcluded_twist)} sigma-along {along} cm"
            f"{unguided}")


def _spread(check: IntrinsicsCheck) -> np.ndarray:
    """``V + P + (k - 1) W`` of ``check`` (:func:`.intrinsics_envelope.intrinsics_moment`)."""
    widening = blind_spot_factor(check) - 1.0
    return check.covariance + check.prior.covariance + widening * governing_covariance(check)


def _linear_moment(check: IntrinsicsCheck, shift: np.ndarray) -> np.ndarray:
    """``B (theta theta^T + V + P + (k - 1) W) B^T``: the moment without the far solution."""
    return shift @ (np.outer(check.theta, check.theta) + _spread(check)) @ shift.T


def _weighted_moment(check: IntrinsicsCheck, shift: np.ndarray) -> np.ndarray:
    """``sum_i w_i s_i s_i^T + B (V + P + (k - 1) W) B^T``: the solutions the test cannot
    exclude, weighed by their likelihood ``exp(-LR / 2)``, instead of ``B theta`` and the
    farthest at weight 1."""
    best = min(check.solutions, key=lambda s: s.cost)
    kept = [s for s in check.solutions if check._likelihood_ratio(s, best) <= check._limit]
    logs = np.array([-0.5 * check._likelihood_ratio(s, best) for s in kept])
    weights = np.exp(logs - logs.max())
    weights /= weights.sum()
    offsets = sum((w * np.outer(s.twist, s.twist) for s, w in zip(kept, weights, strict=True)),
                  np.zeros((6, 6)))
    return offsets + shift @ _spread(check) @ shift.T


def _variant_widenings(check: IntrinsicsCheck | None) -> dict[str, np.ndarray | None]:
    """The envelope's widening as committed and two variants the diagnosis compares: the
    unguided moment without its far solution (``linear``: ``B theta_u`` alone) and with its
    solutions weighed by their likelihood (``weighted``)."""
    if check is None or check.unguided is None or not check.passed:
        return {"linear": None, "weighted": None}
    shift, whole = check.pose_shift, intrinsics_moment(check, check.pose_shift)
    return {"linear": positive_part(_linear_moment(check.unguided, shift) - whole),
            "weighted": positive_part(_weighted_moment(check.unguided, shift) - whole)}


def stated_text(est: PoseEstimate, gt: np.ndarray, truth_covariance: np.ndarray) -> str:
    """The answer's position Mahalanobis length under its stated covariance without and with
    the unguided matches' intrinsics envelope (:mod:`.intrinsics_envelope`), and with the
    two variants of :func:`_variant_widenings`, as ``reloc eval`` measures it (the ground
    truth's own uncertainty included)."""
    lengths = []

    def length(cov: np.ndarray | None) -> str:
        return ("-" if cov is None else
                f"{translation_mahalanobis(est.world_from_cam, gt, cov, truth_covariance):.1f}")

    for flag in (False, True):
        est.stated_unguided_intrinsics = flag
        lengths.append(length(stated_covariance(est, VerifyConf().max_position_sigma_m)))
    est.stated_unguided_intrinsics = False
    plain = stated_covariance(est, VerifyConf().max_position_sigma_m)
    variants = {name: length(None if plain is None else plain + (0.0 if w is None else w))
                for name, w in _variant_widenings(est.intrinsics).items()}
    return (f"stated sig: without envelope {lengths[0]}, with {lengths[1]} "
            f"(linear {variants['linear']}, weighted {variants['weighted']})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--method", default=DEFAULT_METHOD)
    parser.add_argument("--keyframe-sigma", default="0,0")
    parser.add_argument("--focal-scale", type=float, default=1.0)
    parser.add_argument("--queries", default="", help="comma-separated indices (all: empty)")
    parser.add_argument("--answering-step", action="store_true",
                        help="run the chain, then only the step that answered (not every step)")
    parser.add_argument("--options", default="", help="TOML-like 'section.key=value;...'")
    args = parser.parse_args(argv)
    t_m, r_deg = (float(v) for v in args.keyframe_sigma.split(","))
    dataset = read_dataset(args.dataset)
    truth = ground_truth_covariance((t_m, r_deg))
    options: dict[str, dict[str, object]] = {}
    for item in filter(None, args.options.split(";")):
        key, value = item.split("=")
        section, name = key.split(".")
        options.setdefault(section, {})[name] = eval(value)  # noqa: S307 (a diagnosis tool)
    backend = InProcessBackend([args.method], options, LandmarkSource.AUTO)
    claim = QueryCamera(focal_scale=args.focal_scale)
    wanted = {int(v) for v in args.queries.split(",") if v}
    print(f"true focal error {100 * (1 / args.focal_scale - 1):+.1f} %")
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False, truth)
        backend.train(progress=False)
        chain = backend.engine.relocalizer(args.method)
        assert isinstance(chain, ChainRelocalizer), args.method
        with as_a_service_worker():
            for q, entry in enumerate(dataset.query_entries):
                if wanted and q not in wanted:
                    continue
                image = dataset.load_image(entry)
                gt = np.array(entry.world_from_cam)
                camera = claim.claimed(dataset.camera(entry))
                steps = [chain, *chain.steps]
                if args.answering_step:
                    answer = chain.relocalize(Frame(image, camera, gt_world_from_cam=gt))
                    steps = [s for s in chain.steps if s.method == answer.method]
                for step in steps:
                    frame = Frame(image, camera, gt_world_from_cam=gt)
                    result = step.relocalize(frame)
                    rec = record_from_result(entry.image_path, result, gt, 0.0,
                                             truth_covariance=truth)
                    est = frame.cache.get(ANSWERED)
                    check = None if est is None else est.intrinsics
                    name = "CHAIN" if step is chain else step.method
                    err = ("refused" if not rec.returned else
                           f"{100 * rec.t_err_m:.0f}cm {rec.t_err_mahalanobis:.1f}sig")
                    print(f"q{q:<3d} {name:<22s} {err:>14s} whole {check_text(check)} | "
                          f"unguided {check_text(None if check is None else check.unguided)}"
                          f"{bend_text(check)}")
                    if est is not None and check is not None and rec.returned:
                        print("      " + shift_text(est, check, gt, 1 / args.focal_scale - 1))
                        print("      " + stated_text(est, gt, truth))
                    if not rec.returned:
                        print(f"      {rec.reason[:200]}")
                    assert isinstance(step, (ChainRelocalizer, MultiRelocalizer))
    finally:
        backend.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
