"""Cheaper second opinions for a held underpowered pose, measured against the chain's own.

The default chain holds the half-size SIFT step's verified pose where its intrinsics test
lacks the power to vouch for it (:func:`reloc_service.algorithms.pose.intrinsics_power.
estimate_underpowered`) and asks ``bow+p3p`` (full-size SIFT, 2000 features) for a second
opinion. For every query on which the half-size step alone verifies such a pose, this asks
``bow+p3p`` with each candidate set of full-size features put on the query in place of its
own extraction. It prints the held pose (error, inliers, the half-size step's time), then
for each candidate the answer's position error (``U``: its own intrinsics test
underpowered too), its inliers (with the share of them found in the upsampled octave,
finer than the half-size image shows) and the time of the features + the step:

- ``full``: the step's own extraction (what the chain does; the reference);
- ``crop M``: full-size SIFT of the image box the held pose's inliers span, widened by the
  share ``M`` of the image on each side (keypoints shifted back to the image);
- ``desc``: full-resolution SIFT descriptors at the half-size keypoints (OpenCV's
  ``compute`` with keypoints of octave 0 or above does not build the upsampled octave);
- ``relocated``: ``desc``, with the half-size keypoints of level 0 first re-located on the
  full image's difference of Gaussians (Lowe's quadratic fit of the extremum, a move of at
  most 1.5 pixels kept);
- ``fine``: the 2000 strongest extrema of the full image's DoG at the scales of SIFT's
  upsampled octave, found on the image's own grid (:func:`fine_dog_features`, NumPy),
  described at the upsampled octave (which OpenCV's ``compute`` then builds); ``fine0``:
  described at the image's own octave instead;
- ``held``: the held pose itself, with its stated position sigma and its error in those
  sigmas (the ground truth's own uncertainty included, as ``reloc eval`` scores it): the
  best that a second opinion which only votes for the held pose's place can keep, since
  it cannot move the pose.

    .venv/bin/python scripts/second_opinion_candidates.py ../shared/data/real/tum_fr1_rpy \\
        --keyframe-sigma 0.01,0.3
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from time import perf_counter
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from reloc_service.algorithms.pose.base import PoseEstimate
from reloc_service.algorithms.pose.intrinsics_power import estimate_underpowered
from reloc_service.algorithms.relocalizers.base import position_sigma_m
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.chain_hooks import ANSWERED
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core import features as feature_lib
from reloc_service.core.frame import Features, Frame
from reloc_service.core.geometry import pose_error
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval import metrics
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import _build_map, ground_truth_covariance
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker

Image = npt.NDArray[np.uint8]
#: OpenCV SIFT's layers per octave and base blur (its defaults).
LAYERS, SIGMA = 3, 1.6


def crop_features(image: Image, held: PoseEstimate, margin: float,
                  conf: feature_lib.FeatureConf) -> Features:
    """Full-size SIFT of the box ``held``'s inliers span, widened by ``margin`` of the image."""
    h, w = image.shape[:2]
    px = np.asarray(held.inlier_px)
    x0, x1 = int(max(0, px[:, 0].min() - margin * w)), int(min(w, px[:, 0].max() + margin * w + 1))
    y0, y1 = int(max(0, px[:, 1].min() - margin * h)), int(min(h, px[:, 1].max() + margin * h + 1))
    feats = feature_lib.extract(np.ascontiguousarray(image[y0:y1, x0:x1]), conf)
    return dataclasses.replace(feats, keypoints_px=feats.keypoints_px + [x0, y0])


def dog_octave0(image: Image) -> npt.NDArray[np.float64]:
    """(LAYERS + 2, H, W) difference of Gaussians of the image's own octave (no upsampling),
    with OpenCV's blurs (the image taken as blurred by 0.5 pixel)."""
    k = 2.0 ** (1.0 / LAYERS)
    blurred = [cv2.GaussianBlur(image.astype(np.float32), (0, 0), np.sqrt(SIGMA**2 - 0.25))]
    for i in range(1, LAYERS + 3):
        step = SIGMA * np.sqrt(k ** (2 * i) - k ** (2 * i - 2))
        blurred.append(cv2.GaussianBlur(blurred[-1], (0, 0), step))
    return np.stack([b - a for a, b in zip(blurred, blurred[1:], strict=False)]) / 255.0


def relocate_level0(image: Image, half: Features, iterations: int = 5) -> npt.NDArray[np.float64]:
    """(N, 2) ``half``'s keypoints with those of level 0 moved to the full image's DoG
    extremum near them (at most ``iterations`` Newton steps of Lowe's quadratic fit; a
    keypoint that does not converge or moves 1.5 pixels or more keeps its position)."""
    dog = dog_octave0(image)
    layers, h, w = dog.shape
    pts = half.keypoints_px.copy()
    sel = np.flatnonzero(half.levels == 0)
    x = np.round(pts[sel, 0]).astype(np.int64)
    y = np.round(pts[sel, 1]).astype(np.int64)
    s = np.clip(np.round(LAYERS * np.log2(half.sizes[sel] / (2 * SIGMA))), 1, layers - 2)
    s = s.astype(np.int64)
    ok = np.ones(len(sel), bool)
    offset: npt.NDArray[np.float64] = np.zeros((len(sel), 3))
    for _ in range(iterations):
        ok &= (x >= 1) & (x < w - 1) & (y >= 1) & (y < h - 1)
        xi, yi = np.clip(x, 1, w - 2), np.clip(y, 1, h - 2)

        def at(ds: int, dy: int, dx: int) -> npt.NDArray[np.float64]:
            return dog[s + ds, yi + dy, xi + dx].astype(np.float64)  # noqa: B023

        c = at(0, 0, 0)
        grad = np.stack([(at(0, 0, 1) - at(0, 0, -1)) / 2, (at(0, 1, 0) - at(0, -1, 0)) / 2,
                         (at(1, 0, 0) - at(-1, 0, 0)) / 2], 1)
        dxx, dyy = at(0, 0, 1) + at(0, 0, -1) - 2 * c, at(0, 1, 0) + at(0, -1, 0) - 2 * c
        dss = at(1, 0, 0) + at(-1, 0, 0) - 2 * c
        dxy = (at(0, 1, 1) - at(0, 1, -1) - at(0, -1, 1) + at(0, -1, -1)) / 4
        dxs = (at(1, 0, 1) - at(1, 0, -1) - at(-1, 0, 1) + at(-1, 0, -1)) / 4
        dys = (at(1, 1, 0) - at(1, -1, 0) - at(-1, 1, 0) + at(-1, -1, 0)) / 4
        hess = np.stack([np.stack([dxx, dxy, dxs], 1), np.stack([dxy, dyy, dys], 1),
                         np.stack([dxs, dys, dss], 1)], 1)
        regular = np.abs(np.linalg.det(hess)) > 1e-12
        hess[~regular] = np.eye(3)
        offset = np.asarray(-np.linalg.solve(hess, grad[..., None])[..., 0], np.float64)
        ok &= regular & np.all(np.isfinite(offset), 1)
        done = np.all(np.abs(offset) < 0.5, 1)
        move = ok & ~done
        if not move.any():
            break
        x[move] += np.round(offset[move, 0]).astype(np.int64)
        y[move] += np.round(offset[move, 1]).astype(np.int64)
        s[move] += np.round(offset[move, 2]).astype(np.int64)
        ok &= (s >= 1) & (s <= layers - 2)
        s = np.clip(s, 1, layers - 2)
    new = np.stack([x + offset[:, 0], y + offset[:, 1]], 1).astype(np.float64)
    ok &= np.all(np.abs(offset) < 0.5, 1) & (np.hypot(*(new - pts[sel]).T) < 1.5)
    pts[sel[ok]] = new[ok]
    return pts


def describe_full(image: Image, half: Features, pts: npt.NDArray[np.float64]) -> Features:
    """Full-resolution SIFT descriptors at ``pts`` with ``half``'s sizes, angles and levels
    (octave = level: no upsampled octave is built); keypoints OpenCV drops are dropped."""
    levels = half.levels.astype(np.int64)
    layer = np.clip(np.round(LAYERS * np.log2(half.sizes / (2 * SIGMA * np.exp2(levels)))), 1, 3)
    kps = [cv2.KeyPoint(float(p[0]), float(p[1]), float(size), float(angle), 0.0,
                        int((int(lv) & 0xFF) | (int(la) << 8)), i)
           for i, (p, size, angle, lv, la) in enumerate(zip(pts, half.sizes, half.angles,
                                                           levels, layer, strict=True))]
    kept, desc = cv2.SIFT.create().compute(image, kps)
    idx = np.fromiter((k.class_id for k in kept), np.int64, len(kept))
    return Features.create("sift", pts[idx], np.asarray(desc).astype(np.uint8),
                           levels=half.levels[idx], sizes=half.sizes[idx],
                           angles=half.angles[idx])


def fine_dog_features(image: Image, count: int, descriptor_octave: int) -> Features:
    """The ``count`` strongest extrema of the full image's difference of Gaussians at SIFT's
    upsampled-octave scales (sigma 0.8-1.6 full-image pixels, found on the image's own grid,
    not upsampled), located to sub-pixel by a quadratic fit, with edge responses rejected
    (principal-curvature ratio 10) and SIFT's contrast threshold (0.04 / 3 / 2), oriented by
    the peak of a 36-bin gradient histogram and described by OpenCV's SIFT at octave
    ``descriptor_octave`` (-1: the upsampled octave's images, which OpenCV then builds; 0: the
    image's own)."""
    k = 2.0 ** (1.0 / LAYERS)
    sig = SIGMA / 2 * k ** np.arange(LAYERS + 3)
    blurred = [cv2.GaussianBlur(image.astype(np.float32) / 255.0, (0, 0),
                                float(np.sqrt(sig[0] ** 2 - 0.25)))]
    for i in range(1, LAYERS + 3):
        blurred.append(cv2.GaussianBlur(blurred[-1], (0, 0),
                                        float(np.sqrt(sig[i] ** 2 - sig[i - 1] ** 2))))
    dog = np.stack([b - a for a, b in zip(blurred, blurred[1:], strict=False)])
    ker = np.ones((3, 3), np.uint8)
    high = np.stack([cv2.dilate(layer, ker) for layer in dog])
    low = np.stack([cv2.erode(layer, ker) for layer in dog])
    high = np.maximum(np.maximum(high, np.roll(high, 1, 0)), np.roll(high, -1, 0))
    low = np.minimum(np.minimum(low, np.roll(low, 1, 0)), np.roll(low, -1, 0))
    ext = ((dog == high) | (dog == low)) & (np.abs(dog) > 0.5 * 0.04 / LAYERS)
    ext[0] = ext[-1] = False
    ext[:, :5], ext[:, -5:], ext[:, :, :5], ext[:, :, -5:] = False, False, False, False
    s, y, x = np.nonzero(ext)
    c = dog[s, y, x]
    dxx = dog[s, y, x + 1] + dog[s, y, x - 1] - 2 * c
    dyy = dog[s, y + 1, x] + dog[s, y - 1, x] - 2 * c
    dxy = (dog[s, y + 1, x + 1] - dog[s, y + 1, x - 1] - dog[s, y - 1, x + 1]
           + dog[s, y - 1, x - 1]) / 4
    det = dxx * dyy - dxy**2
    gx = (dog[s, y, x + 1] - dog[s, y, x - 1]) / 2
    gy = (dog[s, y + 1, x] - dog[s, y - 1, x]) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        ox, oy = -(dyy * gx - dxy * gy) / det, -(dxx * gy - dxy * gx) / det
    keep = (det > 0) & ((dxx + dyy) ** 2 * 10 < 121 * det) & (np.abs(ox) < 1) & (np.abs(oy) < 1)
    order = np.argsort(-np.abs(c[keep]), kind="stable")[:count]
    s, y, x = s[keep][order], y[keep][order], x[keep][order]
    pts = np.stack([x + ox[keep][order], y + oy[keep][order]], 1).astype(np.float64)
    angles = _orientations(blurred, sig, s, y, x)
    sizes = (2 * sig[s]).astype(np.float32)
    code = descriptor_octave & 0xFF
    kps = [cv2.KeyPoint(float(p[0]), float(p[1]), float(size), float(angle), 0.0,
                        int(code | (int(min(max(layer, 1), LAYERS)) << 8)), i)
           for i, (p, size, angle, layer) in enumerate(zip(pts, sizes, angles, s, strict=True))]
    kept, desc = cv2.SIFT.create().compute(image, kps)
    idx = np.fromiter((kp.class_id for kp in kept), np.int64, len(kept))
    return Features.create("sift", pts[idx], np.asarray(desc).astype(np.uint8),
                           levels=np.full(len(idx), descriptor_octave, np.int16),
                           sizes=sizes[idx], angles=angles[idx])


def _orientations(blurred: list[npt.NDArray[Any]], sig: npt.NDArray[np.float64],
                  s: npt.NDArray[np.int64], y: npt.NDArray[np.int64],
                  x: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
    """(N,) OpenCV keypoint angles (degrees, ``360 - `` the gradient's): the peak of each
    keypoint's 36-bin histogram of gradient directions within 3 x 1.5 sigma of it (weighted
    by magnitude and a Gaussian of 1.5 sigma, smoothed, the peak fitted by a parabola)."""
    radius = 7
    off = np.arange(-radius, radius + 1)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    h, w = blurred[0].shape
    yy = np.clip(y[:, None, None] + oy, 0, h - 1)
    xx = np.clip(x[:, None, None] + ox, 0, w - 1)
    angles = np.zeros(len(s), np.float32)
    for layer in np.unique(s):
        m = s == layer
        gx = cv2.Sobel(blurred[layer], cv2.CV_32F, 1, 0, ksize=1)[yy[m], xx[m]]
        gy = cv2.Sobel(blurred[layer], cv2.CV_32F, 0, 1, ksize=1)[yy[m], xx[m]]
        spread = 1.5 * sig[layer]
        r2 = ox**2 + oy**2
        weight = np.exp(-r2 / (2 * spread**2)) * (r2 <= (3 * spread) ** 2)
        bins = np.round(np.degrees(np.arctan2(-gy, gx)) % 360 / 10).astype(np.int64) % 36
        n = int(m.sum())
        hist = np.zeros((n, 36))
        np.add.at(hist, (np.repeat(np.arange(n), off.size**2), bins.reshape(n, -1).ravel()),
                  (np.hypot(gx, gy) * weight).reshape(n, -1).ravel())
        hist = 0.5 * hist + 0.25 * (np.roll(hist, 1, 1) + np.roll(hist, -1, 1))
        peak = hist.argmax(1)
        rows = np.arange(n)
        left, mid, right = hist[rows, (peak - 1) % 36], hist[rows, peak], hist[rows, (peak + 1) % 36]
        shift = 0.5 * (left - right) / np.where(left - 2 * mid + right == 0, -1e-12,
                                                 left - 2 * mid + right)
        angles[m] = (360.0 - 10.0 * (peak + shift)) % 360.0
    return angles


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--keyframe-sigma", default="0,0")
    args = parser.parse_args(argv)
    sigma = tuple(float(v) for v in args.keyframe_sigma.split(","))
    dataset = read_dataset(args.dataset)
    truth = ground_truth_covariance(sigma)  # type: ignore[arg-type]
    backend = InProcessBackend([DEFAULT_METHOD], {}, LandmarkSource.AUTO)
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False, truth)
        backend.train(progress=False)
        chain = backend.engine.relocalizer(DEFAULT_METHOD)
        assert isinstance(chain, ChainRelocalizer), DEFAULT_METHOD
        half, bow = chain.steps[1], chain.steps[2]
        (half_kind,), (conf,) = half.feature_confs(), bow.feature_confs().values()
        with as_a_service_worker():
            for q, entry in enumerate(dataset.query_entries):
                image, camera = dataset.load_image(entry), dataset.camera(entry)
                frame = Frame(image, camera)
                start = perf_counter()
                held_result = half.relocalize(frame)
                half_ms = 1e3 * (perf_counter() - start)
                held = frame.cache.get(ANSWERED)
                if not held_result.ok or held is None or not chain._underpowered(1, held):
                    continue

                def cm(pose: npt.NDArray[np.float64] | None) -> str:
                    return "-" if pose is None else \
                        f"{100 * pose_error(pose, entry.world_from_cam)[0]:.1f}"  # noqa: B023

                sift_half = frame.features[half_kind]
                candidates: dict[str, Callable[[], Features | None]] = {
                    "full": lambda: None,
                    "crop 1/8": lambda: crop_features(image, held, 1 / 8, conf),  # noqa: B023
                    "crop 1/4": lambda: crop_features(image, held, 1 / 4, conf),  # noqa: B023
                    "desc": lambda: describe_full(image, sift_half,  # noqa: B023
                                                  sift_half.keypoints_px),  # noqa: B023
                    "relocated": lambda: describe_full(  # noqa: B023
                        image, sift_half, relocate_level0(image, sift_half)),  # noqa: B023
                    "fine": lambda: fine_dog_features(image, 2000, -1),  # noqa: B023
                    "fine0": lambda: fine_dog_features(image, 2000, 0),  # noqa: B023
                }
                maha = metrics.translation_mahalanobis(
                    held_result.world_from_cam, entry.world_from_cam, held_result.covariance,
                    truth)
                cells = [f"q{q} held {cm(held_result.world_from_cam)}U "
                         f"(sigma {100 * position_sigma_m(held_result.covariance):.1f} cm, "
                         f"error {maha:.1f} sigma) {held_result.inliers} {half_ms:.0f} ms"]
                for name, make in candidates.items():
                    ask = Frame(image, camera)
                    ask.features.update(frame.features)
                    start = perf_counter()
                    feats = make() if name != "full" else feature_lib.extract(image, conf)
                    ask.features[conf.kind] = feats  # type: ignore[assignment]
                    mid = perf_counter()
                    got = bow.relocalize(ask)
                    end = perf_counter()
                    own = ask.cache.get(ANSWERED)
                    weak = "U" if got.ok and own is not None and estimate_underpowered(own) else ""
                    pose = got.world_from_cam if got.ok else None
                    fine = "" if own is None or own.inlier_keypoints is None else \
                        f" ({np.mean(ask.features[conf.kind].levels[own.inlier_keypoints] < 0):.0%} fine)"
                    cells.append(f"{name} {cm(pose)}{weak} cm {got.inliers}{fine} "
                                 f"{1e3 * (mid - start):.0f}+{1e3 * (end - mid):.0f} ms")
                print(" | ".join(cells), flush=True)
    finally:
        backend.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
