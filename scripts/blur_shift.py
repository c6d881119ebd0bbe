"""Measure how motion blur moves a synthetic query's keypoints, against the same query sharp.

For every blurred query of a ``-hard`` preset, render the query again exactly as the dataset
did (same scene, pose, noise stream, exposure and occluder) with and without its blur, detect
SIFT and ORB keypoints in both (the default detectors of ``core.features``), pair them
(mutual nearest descriptors, positions within half the blur extent plus 3 px) and record the
shift ``blurred - sharp`` of every pair, split along the blur direction and across it. The
mean over a query's pairs is the part all its keypoints share (what a pose absorbs); the
spread is the independent part.

With ``--half DATASET`` it measures instead the shift between SIFT on a dataset's query images
reduced to half size (``FeatureConf("sift", scale=0.5)``, mapped back to full-image pixels)
and SIFT at full resolution, which the map's keypoints are: a shift common to all keypoints
that a chain's ``sift-half`` step would carry into its pose.

    python scripts/blur_shift.py PRESET [--seed 0] [--limit N] --out OUT.json
    python scripts/blur_shift.py --half DATASET [--limit N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from reloc_service.core.features import FeatureConf, extract
from reloc_service.tools.synth import _draw_nuisances, _make_jobs
from reloc_service.tools.synth.presets import get_preset
from reloc_service.tools.synth.renderer import render_frame
from reloc_service.tools.synth.scenes import build_scene
from reloc_service.tools.synth.trajectories import make_trajectories


def _all_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Na, Nb) descriptor distances: L2 for SIFT's 128 values, Hamming for ORB's 32 bytes."""
    if a.shape[1] == 32:
        bits_a, bits_b = np.unpackbits(a, axis=1), np.unpackbits(b, axis=1)
        return (bits_a[:, None] != bits_b[None]).sum(axis=2).astype(np.float64)
    fa, fb = a.astype(np.float64), b.astype(np.float64)
    return np.sqrt(np.maximum((fa**2).sum(1)[:, None] + (fb**2).sum(1)[None] - 2 * fa @ fb.T, 0))


def pair_shifts(sharp, blurred, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) sharp positions and (M, 2) shifts ``blurred - sharp`` of mutual-nearest
    descriptor pairs closer than ``radius``."""
    if len(sharp.keypoints_px) == 0 or len(blurred.keypoints_px) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    gap = np.linalg.norm(blurred.keypoints_px[:, None] - sharp.keypoints_px[None], axis=2)
    dist = _all_distances(blurred.descriptors, sharp.descriptors)
    dist = np.where(gap < radius, dist, np.inf)
    fwd, back = dist.argmin(axis=1), dist.argmin(axis=0)
    keep = (back[fwd] == np.arange(len(fwd))) & np.isfinite(dist[np.arange(len(fwd)), fwd])
    at = sharp.keypoints_px[fwd[keep]]
    return at, blurred.keypoints_px[keep] - at


def half_shift(dataset: str, limit: int) -> None:
    """Print the mean shift, per query and over all, of half-size SIFT from full-size SIFT."""
    import glob

    import cv2

    means = []
    for path in sorted(glob.glob(f"{dataset}/images/query/*.png"))[:limit or None]:
        image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        _, d = pair_shifts(extract(image, FeatureConf("sift")),
                           extract(image, FeatureConf("sift", scale=0.5)), 3.0)
        if len(d):
            means.append(d.mean(axis=0))
            print(f"{path}: {len(d)} pairs, mean shift half - full {np.round(means[-1], 3)} px")
    print(f"{dataset}: {len(means)} queries, mean of their mean shifts "
          f"{np.round(np.mean(means, axis=0), 3)} px (x, y)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("preset", nargs="?")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--limit", type=int, default=0)
    parser.add_argument("--out")
    parser.add_argument("--half", metavar="DATASET")
    args = parser.parse_args()
    if args.half:
        half_shift(args.half, args.limit)
        return
    if not args.preset or not args.out:
        parser.error("expected PRESET and --out (or --half DATASET)")
    preset = get_preset(args.preset)
    camera = preset.cameras["cam0"]
    scene = build_scene(preset.scene, args.seed)
    map_poses, query_poses = make_trajectories(preset.trajectory, preset.n_map, preset.n_query,
                                               args.seed)
    nuisances = _draw_nuisances(preset, camera, query_poses, scene, args.seed)
    jobs = [j for j in _make_jobs(preset, map_poses, query_poses, nuisances)
            if j.kind == "query" and j.nuisance is not None and j.nuisance.blur_px >= 1.0]
    rows = []
    for job in jobs[:args.limit or None]:
        nuis = job.nuisance
        images = {}
        for name, n in (("blurred", nuis), ("sharp", dataclasses.replace(nuis, blur_px=0.0))):
            images[name] = render_frame(scene, camera, job.world_from_cam,
                                        rng=job.rng(args.seed, 0),
                                        supersample=preset.supersample,
                                        noise_sigma=preset.noise_sigma, nuisance=n).image
        along = np.array([np.cos(nuis.blur_angle), np.sin(nuis.blur_angle)])
        across = np.array([-along[1], along[0]])
        row = {"query": job.image_path, "blur_px": nuis.blur_px,
               "blur_angle_deg": float(np.degrees(nuis.blur_angle))}
        for kind in ("sift", "orb"):
            conf = FeatureConf(kind)
            at, d = pair_shifts(extract(images["sharp"], conf), extract(images["blurred"], conf),
                            nuis.blur_px / 2 + 3.0)
            a, c = d @ along, d @ across
            row[kind] = {"pairs": len(d), "mean_along": float(a.mean()) if len(d) else None,
                         "mean_across": float(c.mean()) if len(d) else None,
                         "sd_along": float(a.std()) if len(d) > 1 else None,
                         "sd_across": float(c.std()) if len(d) > 1 else None,
                         "mean_xy": d.mean(axis=0).tolist() if len(d) else None,
                         "at": np.round(at, 2).tolist(), "shift": np.round(d, 3).tolist()}
        rows.append(row)
        s, o = row["sift"], row["orb"]
        print(f"{job.image_path} blur {nuis.blur_px:5.1f}px @ {row['blur_angle_deg']:5.1f}: "
              f"sift n={s['pairs']} mean {s['mean_along']:+.2f}/{s['mean_across']:+.2f} "
              f"sd {s['sd_along']:.2f}/{s['sd_across']:.2f}; orb n={o['pairs']} "
              f"mean {o['mean_along']:+.2f}/{o['mean_across']:+.2f} "
              f"sd {o['sd_along']:.2f}/{o['sd_across']:.2f}", flush=True)
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
