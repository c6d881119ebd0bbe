"""Ferns benchmarks (run by ``reloc bench``): classification time, model memory against the
thesis's dense table, training time, online update time, classification time vs classes.

The landmarks are SIFT keypoints of the photographs bundled with scikit-image, one keyframe
per photograph, one view per landmark (so "2000 landmarks x 100 warps" is 200 000 samples).
Every function returns a plain dict of numbers; nothing here is a test.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...algorithms.ferns.keypoints import detect_keypoints
from ...algorithms.ferns.training import prepare_image
from ...algorithms.relocalizers.ferns import FernsRelocalizer
from ...algorithms.relocalizers.ferns_conf import FernsConf
from ...core.cameras import PinholeCamera
from ...core.frame import Features, Keyframe
from ...core.map import KeyframeMap

#: Photographs of ``skimage.data`` used as keyframes, in this order.
PHOTOS = ("astronaut", "camera", "coffee", "chelsea", "rocket", "brick", "grass", "gravel",
          "immunohistochemistry", "hubble_deep_field", "moon", "coins", "clock", "horse", "cat",
          "retina", "text", "page")

#: Landmarks per photo keyframe (the strongest SIFT keypoints), about a real keyframe's.
_PER_PHOTO = 300


def _grey(name: str) -> npt.NDArray[np.uint8]:
    import skimage.data

    img = getattr(skimage.data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    if max(img.shape) > 1000:  # the retina photo is 1411 px
        img = cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img.astype(np.uint8))


def photo_keyframe(index: int, first_landmark: int, max_landmarks: int) -> Keyframe:
    """Keyframe ``index``: photo ``PHOTOS[index]``, its strongest SIFT keypoints (at most
    ``max_landmarks``) each a new landmark (ids from ``first_landmark``), camera 1 m apart."""
    img = _grey(PHOTOS[index % len(PHOTOS)])
    h, w = img.shape
    px = detect_keypoints(img, "sift", min(max_landmarks, _PER_PHOTO))
    n = len(px)
    camera = PinholeCamera(width=w, height=h, fx=0.8 * w, fy=0.8 * w, cx=(w - 1) / 2,
                           cy=(h - 1) / 2)
    points = np.column_stack([camera.unproject(px)[:, :2] * 2.0 + [index, 0.0], np.full(n, 2.0)])
    feats = Features.create("sift", px, np.zeros((n, 128), np.float32),
                            landmark_ids=first_landmark + np.arange(n), points_world=points)
    pose = np.eye(4)
    pose[0, 3] = float(index)
    return Keyframe(image=img, camera=camera, id=index, world_from_cam=pose,
                    features={"sift": feats})


def photo_map(num_landmarks: int) -> KeyframeMap:
    """A map of photo keyframes holding ``num_landmarks`` landmarks in all."""
    kmap = KeyframeMap()
    total, index = 0, 0
    while total < num_landmarks:
        if index >= 3 * len(PHOTOS):
            raise ValueError(f"the photos hold fewer than {num_landmarks} keypoints")
        kf = photo_keyframe(index, total, num_landmarks - total)
        kmap.add_keyframe(kf)
        total += len(kf.features["sift"])
        index += 1
    return kmap


def _conf(num_warps: int, max_classes: int, workers: int) -> FernsConf:
    return FernsConf(num_ferns=100, num_tests=12, num_warps=num_warps, max_classes=max_classes,
                     workers=workers)


@functools.lru_cache(maxsize=2)
def _trained(num_landmarks: int, num_warps: int, workers: int
             ) -> tuple[FernsRelocalizer, float, float]:
    """A trained relocalizer, the wall seconds and the process CPU seconds of its training."""
    kmap = photo_map(num_landmarks)
    reloc = FernsRelocalizer(kmap, _conf(num_warps, num_landmarks, workers))
    start, cpu = time.perf_counter(), time.process_time()
    reloc.train(progress=True)
    return reloc, time.perf_counter() - start, time.process_time() - cpu


def bench_train(num_landmarks: int = 2000, num_warps: int = 100, workers: int = 2
                ) -> dict[str, Any]:
    """Training from scratch: ``num_landmarks`` x ``num_warps`` samples, ``workers`` threads
    (target <= 60 s on 2 cores)."""
    reloc, seconds, cpu_seconds = _trained(num_landmarks, num_warps, workers)
    clf = reloc.classifiers[0]
    return {"landmarks": num_landmarks, "warps": num_warps, "workers": workers,
            "keyframes": len(reloc.map), "samples": int(clf.class_counts.sum()),
            "seconds": round(seconds, 2), "cpu_seconds": round(cpu_seconds, 2),
            "samples_per_second": round(int(clf.class_counts.sum()) / max(seconds, 1e-9)),
            "nonzero_counts": clf.nnz, "target_seconds": 60}


def bench_memory(num_landmarks: int = 2000, num_warps: int = 100, workers: int = 2
                 ) -> dict[str, Any]:
    """Model bytes of the trained classifier next to the dense float32 table M x 2^S x C of
    the thesis (target <= 100 MB)."""
    reloc, *_ = _trained(num_landmarks, num_warps, workers)
    clf = reloc.classifiers[0]
    sparse, dense = clf.nbytes(), clf.dense_nbytes()
    return {"classes": clf.num_classes, "ferns": clf.num_ferns, "tests": clf.num_tests,
            "nonzero_counts": clf.nnz, "model_mb": round(sparse / 2**20, 1),
            "dense_table_mb": round(dense / 2**20, 1),
            "dense_over_sparse": round(dense / sparse, 1),
            "target_mb": 100}


def _query(reloc: FernsRelocalizer, num_keypoints: int, seed: int = 1
           ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """A query: the first keyframe's photo rotated by 15 degrees and enlarged 1.25 times (so
    it holds enough keypoints); its smoothed image, ``num_keypoints`` SIFT keypoints and the
    true landmark of each (-1 if no landmark lies within 2 px of its position mapped back)."""
    kf = reloc.map.snapshot().keyframe(0)
    h, w = kf.image.shape
    affine = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), 15.0, 1.25)
    affine[:, 2] += [(w - 1) * 0.125, (h - 1) * 0.125]
    size = (int(w * 1.25), int(h * 1.25))
    img = np.asarray(cv2.warpAffine(kf.image, affine, size, borderMode=cv2.BORDER_REFLECT_101),
                     np.uint8)
    px = detect_keypoints(img, "sift", num_keypoints)
    back = (px - affine[:, 2]) @ np.linalg.inv(affine[:, :2]).T
    feats = kf.features["sift"]
    d = np.linalg.norm(back[:, None, :] - feats.keypoints_px[None, :, :], axis=2)
    nearest = d.argmin(1)
    truth = np.where(d[np.arange(len(px)), nearest] < 2.0, feats.landmark_ids[nearest], -1)
    return prepare_image(img, reloc.conf.smoothing_sigma), px, truth


def _time_classify(reloc: FernsRelocalizer, scorer: Any, image: npt.NDArray[np.float32],
                   px: npt.NDArray[np.float64], repeats: int) -> dict[str, float]:
    """Median milliseconds of the leaves and of the scoring + top-2 of ``px`` on one thread:
    wall clock, and the thread's CPU time (robust to other processes on a shared machine)."""
    wall: list[list[float]] = [[], []]
    cpu: list[list[float]] = [[], []]
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.thread_time()
            leaves = reloc.tests.leaves_at(image, px)
            t1, c1 = time.perf_counter(), time.thread_time()
            scorer.classify(leaves, top_k=2)
            t2, c2 = time.perf_counter(), time.thread_time()
            wall[0].append(t1 - t0)
            wall[1].append(t2 - t1)
            cpu[0].append(c1 - c0)
            cpu[1].append(c2 - c1)
    finally:
        cv2.setNumThreads(threads)

    def ms(values: list[float]) -> float:
        return round(float(np.median(values)) * 1e3, 2)

    return {"leaves_ms": ms(wall[0]), "score_top2_ms": ms(wall[1]),
            "total_ms": ms([a + b for a, b in zip(*wall, strict=True)]),
            "total_cpu_ms": ms([a + b for a, b in zip(*cpu, strict=True)])}


def bench_classify(num_keypoints: int = 500, num_landmarks: int = 2000, num_warps: int = 100,
                   repeats: int = 20) -> dict[str, Any]:
    """Classifying ``num_keypoints`` query keypoints against ``num_landmarks`` classes with
    100 ferns x 12 tests, one thread (target <= 20 ms); also the top-1 recognition rate of the
    query keypoints that lie on a landmark."""
    reloc, *_ = _trained(num_landmarks, num_warps, 2)
    image, px, truth = _query(reloc, num_keypoints)
    scorer = reloc.scorers[0]
    timing = _time_classify(reloc, scorer, image, px, repeats)
    predicted = scorer.predict(reloc.tests.leaves_at(image, px))
    on_landmark = truth >= 0
    hits = predicted[on_landmark] == truth[on_landmark]
    rate = float(hits.mean()) if on_landmark.any() else 0.0
    return {"keypoints": len(px), "classes": scorer.num_classes, **timing, "target_ms": 20,
            "keypoints_on_landmarks": int(on_landmark.sum()), "top1_rate": round(rate, 3)}


def bench_online_add(num_landmarks: int = 2000, num_warps: int = 100,
                     new_landmarks: int = 300) -> dict[str, Any]:
    """Adding (then removing) one keyframe with ``new_landmarks`` observations to a trained
    model of ``num_landmarks`` (target <= 1 s for the add)."""
    kmap = photo_map(num_landmarks)
    reloc = FernsRelocalizer(kmap, _conf(num_warps, num_landmarks + new_landmarks, 2))
    reloc.train()
    state = kmap.snapshot()
    kf = photo_keyframe(len(state.keyframes), state.next_landmark_id, new_landmarks)
    kmap.add_keyframe(kf)
    start, cpu = time.perf_counter(), time.process_time()
    reloc.add_keyframe(kf)
    added, added_cpu = time.perf_counter() - start, time.process_time() - cpu
    kmap.remove_keyframe(kf.id)
    start = time.perf_counter()
    reloc.remove_keyframe(kf)
    removed = time.perf_counter() - start
    return {"model_landmarks": num_landmarks, "new_observations": len(kf.features["sift"]),
            "warps": num_warps, "add_seconds": round(added, 3),
            "add_cpu_seconds": round(added_cpu, 3), "remove_seconds": round(removed, 3),
            "target_seconds": 1.0}


def bench_classes_sweep(class_counts: Sequence[int] = (200, 500, 1000, 2000, 5000),
                        num_keypoints: int = 500, num_warps: int = 100, repeats: int = 10
                        ) -> dict[str, Any]:
    """Classification time of ``num_keypoints`` keypoints vs the number of classes: one model
    trained with the largest count, restricted to the first classes for the smaller ones."""
    reloc, *_ = _trained(max(class_counts), num_warps, 2)
    clf = reloc.classifiers[0]
    image, px, _ = _query(reloc, num_keypoints)
    rows = []
    for count in sorted(class_counts):
        sub = clf.subset(np.arange(count))
        timing = _time_classify(reloc, sub.scorer(), image, px, repeats)
        rows.append({"classes": sub.num_classes, "nonzero_counts": sub.nnz,
                     "model_mb": round(sub.nbytes() / 2**20, 1), **timing})
    return {"keypoints": len(px), "warps": num_warps, "rows": rows}


def run_all() -> dict[str, Any]:
    """Every ferns benchmark with its default arguments."""
    return {"train": bench_train(), "memory": bench_memory(), "classify": bench_classify(),
            "online_add": bench_online_add(), "classes_sweep": bench_classes_sweep()}


if __name__ == "__main__":
    import json
    import sys

    os.environ.setdefault("RELOC_PROGRESS", "1")
    names = sys.argv[1:] or ["train", "memory", "classify", "online_add", "classes_sweep"]
    for name in names:
        print(name, json.dumps(globals()[f"bench_{name}"]()), flush=True)
