"""Do a dataset's images, depth maps and poses agree? Keyframe B is warped into keyframe A
through A's depth map and both poses; per 64-pixel patch the remaining shift between A and
the warped B is measured by phase correlation. Where all three agree the shifts are a few
hundredths to a tenth of a pixel; a wrong depth scale, a pose convention mixed up, a
time offset between image and pose, or a wrong camera model show as shifts of pixels that grow
with the baseline or differ between near and far patches.

    python scripts/depth_pose_consistency.py DATASET A,B [A,B ...] [--truth]

``A,B``: map keyframe rows (0-based, ``map.txt`` order). The depth map is the dataset's
``depth.txt`` one, or with ``--truth`` its ``truth_depth.txt`` one. Prints, per pair, the
baseline, the patches measured, the median shift and the mean shift of the nearer and the
farther half of the patches (pixels)."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import numpy.typing as npt

from reloc_service.algorithms.pose.projection import project_cam
from reloc_service.core.geometry import invert, transform_points
from reloc_service.core.mapping import lift_pixels
from reloc_service.tools.data.dataset import Dataset, read_dataset

PATCH = 64
STEP = 48
#: Phase-correlation peaks below this response are texture too weak to measure a shift on.
MIN_RESPONSE = 0.2
#: Share of a patch the depth map must cover (sensor depth has holes).
MIN_COVERED = 0.9


def _depth(dataset: Dataset, row: int, truth: bool) -> npt.NDArray[np.float32]:
    entry = dataset.map_entries[row]
    depth = dataset.load_truth_depth(entry) if truth else dataset.load_depth(entry)
    if depth is None:
        raise SystemExit(f"keyframe {row} ({entry.image_path}) has no "
                         f"{'truth_depth.txt' if truth else 'depth.txt'} depth map")
    return depth


def pair_shifts(dataset: Dataset, a: int, b: int, truth: bool
                ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(P, 2) shifts (pixels) of A's textured patches against B warped into A, and (P,) the
    patches' median depth."""
    ea, eb = dataset.map_entries[a], dataset.map_entries[b]
    image_a, image_b = dataset.load_image(ea), dataset.load_image(eb)
    depth = _depth(dataset, a, truth)
    h, w = image_a.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = depth.ravel().astype(np.float64)
    ok = z > 0
    world = lift_pixels(dataset.camera(ea), ea.world_from_cam, np.c_[u.ravel(), v.ravel()][ok],
                        z[ok])
    in_b = project_cam(dataset.camera(eb), transform_points(invert(eb.world_from_cam), world))
    map_x = np.full(h * w, -1.0, np.float32)
    map_y = np.full(h * w, -1.0, np.float32)
    map_x[ok], map_y[ok] = in_b[:, 0], in_b[:, 1]
    map_x, map_y = map_x.reshape(h, w), map_y.reshape(h, w)
    warped = cv2.remap(image_b, map_x, map_y, cv2.INTER_LINEAR, borderValue=0)
    covered = cv2.remap(np.full_like(image_b, 255), map_x, map_y, cv2.INTER_NEAREST,
                        borderValue=0) > 0
    shifts, depths = [], []
    for y0 in range(0, h - PATCH, STEP):
        for x0 in range(0, w - PATCH, STEP):
            window = (slice(y0, y0 + PATCH), slice(x0, x0 + PATCH))
            mask = covered[window]
            if mask.mean() < MIN_COVERED or np.std(image_a[window][mask]) < 8:
                continue
            # Pixels the depth map does not cover (holes, edges) set to the patch's mean in both.
            fill = float(image_a[window][mask].mean())
            patch_a = np.where(mask, image_a[window], fill).astype(np.float32)
            patch_b = np.where(mask, warped[window], fill).astype(np.float32)
            (dx, dy), response = cv2.phaseCorrelate(patch_a, patch_b)
            if response > MIN_RESPONSE:
                shifts.append((dx, dy))
                depths.append(float(np.median(depth[window])))
    return np.array(shifts, np.float64).reshape(-1, 2), np.array(depths, np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("pairs", nargs="+", help="A,B: map keyframe rows")
    parser.add_argument("--truth", action="store_true", help="use truth_depth.txt")
    args = parser.parse_args()
    dataset = read_dataset(args.dataset)
    for pair in args.pairs:
        a, b = (int(x) for x in pair.split(","))
        shifts, depths = pair_shifts(dataset, a, b, args.truth)
        baseline = np.linalg.norm(dataset.map_entries[a].world_from_cam[:3, 3]
                                  - dataset.map_entries[b].world_from_cam[:3, 3])
        if not len(shifts):
            print(f"{a} -> {b}: baseline {1000 * baseline:.1f} mm, no textured patch measured")
            continue
        near = np.zeros(len(depths), bool)                   # the nearer half, by rank
        near[np.argsort(depths, kind="stable")[:max(1, len(depths) // 2)]] = True
        print(f"{a} -> {b}: baseline {1000 * baseline:.1f} mm, {len(shifts)} patches, median "
              f"|shift| {np.median(np.linalg.norm(shifts, axis=1)):.2f} px, mean shift near "
              f"{np.round(shifts[near].mean(axis=0), 2)} far "
              f"{np.round(shifts[~near].mean(axis=0), 2) if (~near).any() else '-'} px")


if __name__ == "__main__":
    main()
