"""Decompose the covariance the default method states into its parts, per answered query.

Runs ``reloc eval``'s in-process evaluation of one dataset and records, for every pose that
is answered, the parts its stated covariance is the sum of: the measurement part (the a-posteriori
variance factor times the normal equations' inverse, ``C``), what the map's dispersion ``d``
adds to it (``(d - 1) C``), what the intrinsics add (``covariance_with_intrinsics``) and the
keyframe poses' part (``map_covariance``). The output lists each answered query's errors,
stated covariance and parts, so a change to one part can be scored offline: the Mahalanobis
length of the position error under the stated covariance minus a part tells whether that
part makes it too wide. It also records the covariance the answer would state under the
intrinsics test's own prior instead of the map's stated calibration accuracy
(``stated_test_prior``), the one main states with the decision's map dispersion
(``stated_plain``: differs unless ``--plain-stated-dispersion`` is given), and for the
keyframe poses' part the alternative where their errors are independent between keyframes
(``map_independent``, ``sum_k w_k^2 A_k S_k A_k^T``, and ``keyframes_effective``,
``1 / sum_k w_k^2``), and prints the cov scale of each stated covariance.

    python scripts/covariance_parts.py DATASET [--keyframe-sigma T_M,R_DEG]
        [--calibration-sigma FOCAL_REL,RADIAL_PX] [--plain-stated-dispersion]
        --out OUT.json [--json EVAL.json]
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from reloc_service.algorithms.pose import map_consistency
from reloc_service.algorithms.relocalizers import base as relocalizer_base
from reloc_service.tools.eval import evaluate as eval_lib
from reloc_service.tools.eval.metrics import covariance_scale, translation_mahalanobis
from reloc_service.tools.eval.query_camera import QueryCamera

_PARTS: list[dict[str, Any]] = []
#: id of a map covariance returned -> (the same with the keyframes' errors taken as
#: independent, the effective number of keyframes ``1 / sum w_k^2``)
_MAP_ALTERNATIVES: dict[int, tuple[np.ndarray, float]] = {}


def _record_map_covariance(original: Any) -> Any:
    from reloc_service.algorithms.pose import map_uncertainty

    def wrapper(world_from_cam: Any, state: Any, landmark_ids: Any) -> Any:
        out = original(world_from_cam, state, landmark_ids)
        if out is not None:
            kf_ids, shares = map_uncertainty.keyframe_shares(state, landmark_ids)
            poses = np.stack([state.keyframes[k].world_from_cam for k in kf_ids.tolist()])
            independent = map_uncertainty.transported_covariance(
                world_from_cam, poses, state.pose_covariances(kf_ids.tolist()), shares ** 2)
            _MAP_ALTERNATIVES[id(out)] = (independent, float(1.0 / np.sum(shares ** 2)))
        return out
    return wrapper


def _record_settle(original: Any) -> Any:
    def wrapper(estimate: Any, state: Any, kind: str, conf: Any) -> None:
        before = None if estimate.covariance is None else estimate.covariance.copy()
        original(estimate, state, kind, conf)
        check = estimate.intrinsics
        if before is not None and check is not None and check.passed:
            estimate._parts = _intrinsics_parts(before, check, estimate.covariance)
    return wrapper


def _intrinsics_parts(own: np.ndarray, check: Any, stated: np.ndarray) -> dict[str, np.ndarray]:
    """The measurement part ``C``, what the map's dispersion adds to it, and what the
    intrinsics add beyond both (whatever :func:`covariance_with_intrinsics` computes)."""
    scaled = check.dispersion * own
    return {"measurement": own, "dispersion": scaled - own, "intrinsics": stated - scaled}


def _record_result(original: Any) -> Any:
    def wrapper(estimate: Any, conf: Any, **kwargs: Any) -> Any:
        result = original(estimate, conf, **kwargs)
        if estimate is not None and result.world_from_cam is not None:
            parts = dict(getattr(estimate, "_parts", {}))
            if estimate.map_covariance is not None:
                parts["map"] = estimate.map_covariance
            if "measurement" in parts:  # what the answer's covariance adds to d C and the map's
                parts["intrinsics"] = (np.asarray(result.covariance) - parts.get("map", 0.0)
                                       - parts["measurement"] - parts["dispersion"])
            unchecked = relocalizer_base.intrinsics_unchecked(estimate, conf.max_position_sigma_m)
            # The covariance the answer would state under the intrinsics test's own prior
            # (no calibration accuracy stated by the map): the stated covariance before the
            # map stated one, from the same run.
            stated_calibration = estimate.calibration_covariance
            estimate.calibration_covariance = None
            test_prior = relocalizer_base.stated_covariance(estimate, conf.max_position_sigma_m)
            estimate.calibration_covariance = stated_calibration
            # The covariance main states: the decision's dispersion throughout.
            stated_dispersion = estimate.stated_dispersion
            estimate.stated_dispersion = None
            plain = relocalizer_base.stated_covariance(estimate, conf.max_position_sigma_m)
            estimate.stated_dispersion = stated_dispersion
            alternative = _MAP_ALTERNATIVES.get(id(estimate.map_covariance))
            _PARTS.append({"t": np.asarray(result.world_from_cam)[:3, 3].tolist(),
                           "stated": np.asarray(result.covariance).tolist(),
                           "stated_test_prior": np.asarray(test_prior).tolist(),
                           "stated_plain": np.asarray(plain).tolist(),
                           "map_independent": None if alternative is None
                           else alternative[0].tolist(),
                           "keyframes_effective": None if alternative is None
                           else alternative[1],
                           "unchecked": bool(unchecked), "inliers": estimate.inliers,
                           "dispersion": float(estimate.intrinsics.dispersion)
                           if estimate.intrinsics is not None else None,
                           "stated_dispersion": estimate.stated_dispersion,
                           "parts": {k: np.asarray(v).tolist() for k, v in parts.items()}})
        return result
    return wrapper


def _pose(seven: list[float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(seven[3:]).as_matrix()
    out[:3, 3] = seven[:3]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--keyframe-sigma", default="0,0")
    parser.add_argument("--calibration-sigma", default=None,
                        help="FOCAL_REL,RADIAL_PX: the calibration accuracy the map states "
                        "(reloc eval --calibration-sigma); default: the mapping config's")
    parser.add_argument("--method", default="sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p")
    parser.add_argument("--query-focal-scale", type=float, default=1.0,
                        help="the queries claim a focal this many times their camera's")
    parser.add_argument("--plain-stated-dispersion", action="store_true",
                        help="state the decision's map dispersion ([options.p3p] "
                        "robust_stated_dispersion = false); by default the answer states the "
                        "one robust to mis-associated landmarks and 'stated_plain' is the "
                        "covariance stated with the decision's, from the same run")
    parser.add_argument("--out", required=True)
    parser.add_argument("--json", help="also write reloc eval's JSON here")
    args = parser.parse_args()
    sigma = tuple(float(v) for v in args.keyframe_sigma.split(","))
    calibration = (None if args.calibration_sigma is None else
                   tuple(float(v) for v in args.calibration_sigma.split(",")))
    map_consistency.settle_intrinsics = _record_settle(map_consistency.settle_intrinsics)
    map_consistency.map_covariance = _record_map_covariance(map_consistency.map_covariance)
    from reloc_service.algorithms.relocalizers import multi
    multi.result_from_estimate = _record_result(relocalizer_base.result_from_estimate)
    options = ({"p3p": {"robust_stated_dispersion": False}} if args.plain_stated_dispersion
               else None)
    result = eval_lib.evaluate(args.dataset, args.method, progress=False, options=options,
                               keyframe_sigma=(sigma[0], sigma[1]),
                               query_camera=QueryCamera(focal_scale=args.query_focal_scale),
                               calibration_sigma=None if calibration is None
                               else (calibration[0], calibration[1]))
    if args.json:
        result.write_json(args.json)
    truth = eval_lib.ground_truth_covariance((sigma[0], sigma[1]))
    queries = []
    for rec in result.methods[0].queries:
        if not rec.returned or rec.est_world_from_cam is None:
            continue
        t = np.asarray(rec.est_world_from_cam[:3])
        match = min(_PARTS, key=lambda p: float(np.linalg.norm(np.asarray(p["t"]) - t)))
        est, gt = _pose(rec.est_world_from_cam), _pose(rec.gt_world_from_cam)
        queries.append({"image": rec.image_path, "t_err_m": rec.t_err_m, "r_err_deg": rec.r_err_deg,
                        "gt": gt.tolist(), "est": est.tolist(), "truth": truth.tolist(),
                        "mahalanobis": translation_mahalanobis(est, gt, match["stated"], truth),
                        "mahalanobis_test_prior": translation_mahalanobis(
                            est, gt, match["stated_test_prior"], truth),
                        **match})
    for q in queries:
        q["mahalanobis_plain"] = translation_mahalanobis(q["est"], q["gt"], q["stated_plain"],
                                                         truth)
    for key in ("mahalanobis", "mahalanobis_plain", "mahalanobis_test_prior"):
        lengths = [q[key] for q in queries]
        print(f"cov scale ({key.replace('mahalanobis', 'stated')}): "
              f"{covariance_scale(lengths, [True] * len(lengths)):.3f} over {len(lengths)}")
    with open(args.out, "w") as fh:
        json.dump(queries, fh)


if __name__ == "__main__":
    main()
