"""The triangulation's precision gate, candidate by candidate, and a false-discovery-rate
version of it (docs/covariance_tails.md, section 4).

    python scripts/triangulation_gate.py SET [--alpha A]

Builds a set's map (``sbi+p3p``: SIFT landmarks) and, for every keyframe's batch of
new points, records each candidate's signed inverse-depth SNR ``z = rho / sigma_rho`` along
the new keyframe's ray (one Gauss-Newton step from the point at infinity over every other
view, the triangulation's keypoint sigmas) and its :class:`TrackStatus`; then it simulates a
false-discovery-rate version of the precision gate (``z >= 3``, i.e. a depth sigma within a
third of the range): the candidates that failed it (depth too uncertain or behind a view)
stand for the undetermined ones, each of which passes by noise with odds
``P(N(z_i, 1) >= t) / P(N(z_i, 1) < 3)``, and a batch keeps its accepted points above the
smallest ``t`` whose expected noise passes are at most ``alpha`` of the points kept
(Benjamini-Hochberg's rule). With a ground truth (synthetic sets) it also compares the kept
and the dropped points' ``z`` to their true value.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from scipy import stats


def _inverse_depth(views: Any, num_points: int, sigma_px: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(P,) signed inverse depth (1/m) along ``views[0]``'s rays and (P,) its sigma, from the
    other views' pixels (one Gauss-Newton step from infinity: the projection is nearly linear
    in the inverse depth)."""
    from reloc_service.core.triangulation import rotate_points, to_camera

    ref = views[0]
    row = np.full(num_points, -1)
    row[ref.point_index] = np.arange(len(ref.point_index))
    dirs = rotate_points(ref.camera.unproject(ref.pixels_px), ref.cam_from_world[:3, :3].T)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    info, num = np.zeros(num_points), np.zeros(num_points)
    far, near = 1e-4, 1e-2          # inverse depths, 1/m
    for v in views[1:]:
        d = dirs[row[v.point_index]]
        at_far = v.camera.project(to_camera(v.cam_from_world, ref.centre_world + d / far))
        at_near = v.camera.project(to_camera(v.cam_from_world, ref.centre_world + d / near))
        slope = (at_near - at_far) / (near - far)
        var = (sigma_px * v.sigmas) ** 2
        step_info = np.sum(slope * slope, axis=1) / var
        step_num = np.sum(slope * (v.pixels_px - at_far), axis=1) / var
        ok = np.isfinite(step_info) & np.isfinite(step_num)
        np.add.at(info, v.point_index[ok], step_info[ok])
        np.add.at(num, v.point_index[ok], step_num[ok])
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / info + far, 1.0 / np.sqrt(info)


def fdr_kept(z: np.ndarray, status: np.ndarray, alpha: float, gate: float = 3.0) -> np.ndarray:
    """Mask of the accepted candidates (status OK) that Benjamini-Hochberg's rule keeps (see
    the module docstring); ``z`` and ``status`` (P,) of one batch."""
    from reloc_service.core.triangulation import TrackStatus

    ok = status == TrackStatus.OK
    failed = np.isin(status, [TrackStatus.UNCERTAIN, TrackStatus.DEPTH])
    zf = np.clip(np.nan_to_num(z[failed], nan=0.0, posinf=0.0, neginf=0.0), -5.0, gate)
    odds_den = np.maximum(stats.norm.cdf(gate - zf), 1e-12)
    for t in np.sort(z[ok]):
        if np.sum(stats.norm.sf(t - zf) / odds_den) <= alpha * np.sum(z[ok] >= t):
            return ok & (z >= t)
    return np.zeros(len(z), bool)


def gate(dataset: str, alpha: float) -> None:
    """Print the batches' counts and, with a ground truth, kept against dropped points."""
    from reloc_service.core import landmarks as core_landmarks
    from reloc_service.core.mapping import sample_depth
    from reloc_service.tools.data.dataset import read_dataset
    from reloc_service.tools.eval import evaluate

    data = read_dataset(dataset)
    poses = [(e, e.world_from_cam) for e in data.map_entries]
    batches: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    triangulate = core_landmarks.triangulate_tracks

    def on_tracks(views: Any, num_points: int, conf: Any) -> Any:
        result = triangulate(views, num_points, conf)
        rho, sigma_rho = _inverse_depth(views, num_points, conf.keypoint_sigma_px)
        true_rho = np.full(num_points, np.nan)
        ref = views[0]
        world_from_ref = np.linalg.inv(ref.cam_from_world)
        entry = min(poses, key=lambda p: float(np.linalg.norm(p[1] - world_from_ref)))[0]
        depth = data.load_truth_depth(entry)
        if depth is not None:
            z, valid = sample_depth(depth, ref.pixels_px, max_jump=0.03)
            ray = ref.camera.unproject(ref.pixels_px)
            ranges = z * np.linalg.norm(ray / ray[:, 2:3], axis=1)
            true_rho[ref.point_index[valid]] = 1.0 / ranges[valid]
        with np.errstate(divide="ignore", invalid="ignore"):
            batches.append((rho / sigma_rho, np.asarray(result.status), true_rho / sigma_rho))
        return result

    core_landmarks.triangulate_tracks = on_tracks  # type: ignore[assignment]
    evaluate.evaluate(dataset, "sbi+p3p", progress=False)
    accepted = kept = 0
    ratio_kept: list[float] = []
    ratio_dropped: list[float] = []
    for z, status, true_z in batches:
        keep = fdr_kept(z, status, alpha)
        ok = status == 0
        accepted += int(ok.sum())
        kept += int(keep.sum())
        known = np.isfinite(true_z) & (true_z > 0)
        ratio_kept += list((z / true_z)[keep & known])
        ratio_dropped += list((z / true_z)[ok & ~keep & known])
    print(f"{len(batches)} batches: {accepted} points accepted by the gate, {kept} kept at an "
          f"FDR of {alpha} ({100 * kept / max(accepted, 1):.1f} %)")
    for name, r in (("kept", np.array(ratio_kept)), ("dropped", np.array(ratio_dropped))):
        if len(r):
            print(f"{name}: {len(r)} with a ground truth, median z / true z {np.median(r):.2f}, "
                  f"depth off by more than 30 % {100 * np.mean(np.abs(1 / r - 1) > 0.3):.0f} %")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--alpha", type=float, default=0.05)
    args = parser.parse_args()
    gate(args.dataset, args.alpha)


if __name__ == "__main__":
    main()
