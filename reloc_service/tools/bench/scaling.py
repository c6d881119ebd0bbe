"""How relocalization scales with the map: latency per method, place-finder time, resident
memory and load time of maps of 10, 100, 1000 keyframes.

Building a 1000-keyframe map by rendering and triangulation takes too long for a benchmark,
so big maps are made cheaply and said to be made so (see :func:`grow_state`): the real map
(rendered keyframes, triangulated landmarks) plus *distractor* keyframes elsewhere in the
world. A distractor is a procedural 640x480 texture (blurred noise at four scales and random
shapes: nothing like the scene, so it must not be proposed for a query) sent as a client
sends a keyframe, JPEG (quality :data:`~.samples.JPEG_QUALITY`, as the bench's queries; the
map keeps those bytes), with real SIFT features of the decoded image, a share of them given
landmarks at random depths (1 to 4 m) like the real keyframes'. ``unique`` distractors are
rendered and described; the others repeat them at new world positions with new landmark
ids, so every keyframe holds its own arrays once loaded.

Memory and load time are measured in a fresh subprocess (:func:`probe_map`) that loads the
saved map (with trained models) through :meth:`Engine.load`, so the numbers hold only what a
service holding that map holds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.features import FeatureConf, extract
from ...core.frame import EncodedImage, Features, Keyframe
from ...core.geometry import look_at
from ...core.landmark_table import Landmark, LandmarkTable
from ...core.map import MapState
from ...core.numeric import limit_blas_threads
from .samples import JPEG_QUALITY

Array = npt.NDArray[np.float64]

#: Distractors stand on a grid this far (metres) from the world origin and from each other.
DISTRACTOR_ORIGIN_M = 100.0
DISTRACTOR_SPACING_M = 5.0


# -- distractor keyframes ----------------------------------------------------------------------

def procedural_image(rng: np.random.Generator, width: int, height: int
                     ) -> npt.NDArray[np.uint8]:
    """(height, width) uint8 texture: blurred noise at four scales plus 40 random filled
    rectangles and circles, stretched to 0..255."""
    img = np.zeros((height, width), np.float32)
    for sigma, weight in ((1.5, 0.4), (5.0, 1.0), (15.0, 2.0), (45.0, 3.0)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
        img += weight * blurred / (blurred.std() + 1e-6)
    for _ in range(40):
        grey = float(rng.uniform(-4, 4))
        x, y = (int(v) for v in rng.integers([0, 0], [width, height]))
        size = int(rng.integers(6, max(7, width // 8)))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + size, y + int(size * rng.uniform(0.3, 2))), grey, -1)
        else:
            cv2.circle(img, (x, y), size // 2, grey, -1)
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) * 255.0 / (hi - lo + 1e-6), 0, 255).astype(np.uint8)


@dataclasses.dataclass(frozen=True, eq=False)
class Distractor:
    """One unique distractor: its image (pixels, or the JPEG they decode from), SIFT
    features, and for the keypoints given landmarks their indices and (K, 3) points in the
    camera frame."""

    image: npt.NDArray[np.uint8] | EncodedImage
    features: Features
    landmark_idx: npt.NDArray[np.int64]
    points_cam: Array


def make_distractors(count: int, camera: Camera, landmarks_per_keyframe: int, *,
                     max_features: int = 2000, seed: int = 0,
                     jpeg_quality: int | None = JPEG_QUALITY) -> list[Distractor]:
    """``count`` unique distractors seen by ``camera``, each with up to
    ``landmarks_per_keyframe`` landmarked keypoints (a seeded random choice); sent as JPEG
    of ``jpeg_quality`` (None: as raw pixels, which a map saves as PNG)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        pixels = procedural_image(rng, camera.width, camera.height)
        image: npt.NDArray[np.uint8] | EncodedImage = pixels
        if jpeg_quality is not None:
            image = _as_jpeg(pixels, jpeg_quality)
            pixels = image.decode()          # what a client's JPEG gives the service
        feats = extract(pixels, FeatureConf(kind="sift", max_features=max_features))
        k = min(landmarks_per_keyframe, len(feats))
        idx = np.sort(rng.choice(len(feats), size=k, replace=False)).astype(np.int64)
        bearings = camera.unproject(feats.keypoints_px[idx])
        depth = rng.uniform(1.0, 4.0, k)
        out.append(Distractor(image, feats, idx, bearings * (depth / bearings[:, 2])[:, None]))
    return out


def _as_jpeg(image: npt.NDArray[np.uint8], quality: int) -> EncodedImage:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("could not encode a distractor as JPEG")
    return EncodedImage(buf.tobytes(), image.shape)


def distractor_pose(index: int) -> Array:
    """``world_from_cam`` of distractor ``index``: on a grid far from the scene, looking
    along +y with a yaw that varies with the index."""
    x = DISTRACTOR_ORIGIN_M + DISTRACTOR_SPACING_M * (index % 40)
    y = DISTRACTOR_ORIGIN_M + DISTRACTOR_SPACING_M * (index // 40)
    yaw = 0.37 * index
    return look_at((x, y, 1.5), (x + np.sin(yaw), y + np.cos(yaw), 1.5), up=(0.0, 0.0, 1.0))


def grow_state(base: MapState, size: int, distractors: Sequence[Distractor],
               camera: Camera) -> MapState:
    """``base`` plus ``size - len(base.keyframes)`` distractor keyframes (cycling through
    ``distractors``), each with its own new landmarks (one observation each)."""
    extra = size - len(base.keyframes)
    if extra <= 0:
        return base
    if not distractors:
        raise ValueError("growing a map needs at least one distractor")
    keyframes = dict(base.keyframes)
    landmarks = dict(base.landmarks)
    next_kf = max(keyframes, default=-1) + 1
    next_lm = base.next_landmark_id
    for j in range(extra):
        d = distractors[j % len(distractors)]
        kf_id = next_kf + j
        world_from_cam = distractor_pose(j)
        ids = next_lm + np.arange(len(d.landmark_idx), dtype=np.int64)
        next_lm += len(ids)
        points = d.points_cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
        keyframes[kf_id] = Keyframe(image=d.image, camera=camera, id=kf_id,  # type: ignore[arg-type]
                                    world_from_cam=world_from_cam,
                                    features={"sift": d.features.with_landmarks(
                                        d.landmark_idx, ids, points)})
        for lm_id, idx, point in zip(ids.tolist(), d.landmark_idx.tolist(), points,
                                     strict=True):
            landmarks[lm_id] = Landmark(lm_id, point, frozenset({(kf_id, "sift", idx)}))
    return MapState(MappingProxyType(keyframes), LandmarkTable.from_mapping(landmarks),
                    base.version + 1, next_lm)


def landmarks_per_keyframe(state: MapState, kind: str = "sift") -> int:
    """Median number of ``kind`` keypoints with a landmark per keyframe of ``state``."""
    counts = [int((kf.features[kind].landmark_ids >= 0).sum())
              for kf in state.keyframes.values() if kind in kf.features]
    return int(np.median(counts)) if counts else 0


# -- one map size ------------------------------------------------------------------------------

def prepare_size(state: MapState, conf: Any, directory: Path) -> dict[str, Any]:
    """Save ``state``, load it into an :class:`Engine` with ``conf`` (which trains every
    method), save it again with the trained models under ``directory / "map"`` as a service
    with the default ``[service]`` options stores it; returns
    the times (seconds) and the counts."""
    from ...engine import Engine
    from ...service.config import ServiceSection
    from ...storage.snapshot import save_map

    raw = directory / "raw"
    start = time.perf_counter()
    save_map(state, raw)
    saved = time.perf_counter() - start
    start = time.perf_counter()
    engine = Engine.load(raw, conf)
    trained = time.perf_counter() - start
    start = time.perf_counter()
    engine.save(directory / "map", parts=ServiceSection().stored_parts())   # as a service saves
    saved_models = time.perf_counter() - start
    return {"keyframes": len(state.keyframes), "landmarks": len(state.landmarks),
            "save_raw_s": saved, "load_and_train_s": trained, "save_with_models_s": saved_models,
            "snapshot_mb": tree_mb(directory / "map"),
            "snapshot_bytes_per_keyframe": part_bytes_per_keyframe(directory / "map",
                                                                   len(state.keyframes))}


def part_bytes_per_keyframe(map_dir: Path, keyframes: int) -> dict[str, float]:
    """Bytes per keyframe of each part of the current snapshot of ``map_dir`` (the kinds of
    :func:`..storage.map_archive.part_kind`: images, depth, features, landmarks, models,
    thumbnails; ``meta`` is the manifest), and their ``total``."""
    from ...storage.map_archive import part_kind
    from ...storage.snapshot_files import current_snapshot

    snapshot = current_snapshot(map_dir)
    sizes: dict[str, int] = {}
    for path in _stored_once(snapshot):
        kind = part_kind(f"map/snapshots/{snapshot.name}/{path.relative_to(snapshot)}")
        sizes[kind] = sizes.get(kind, 0) + path.stat().st_size
    per = {kind: size / max(keyframes, 1) for kind, size in sorted(sizes.items())}
    return {**per, "total": sum(per.values())}


def run_probe(map_dir: Path, queries_dir: Path, methods: Sequence[str],
              options: Mapping[str, Mapping[str, Any]], *, repeats: int, plain_queries: int,
              timeout_s: float = 1800.0) -> dict[str, Any]:
    """:func:`probe_map` in a fresh Python process (so its memory holds only this map)."""
    cmd = [sys.executable, "-m", "reloc_service.tools.bench.scaling", "--map", str(map_dir),
           "--queries", str(queries_dir), "--methods", json.dumps(list(methods)),
           "--options", json.dumps({k: dict(v) for k, v in options.items()}),
           "--repeats", str(repeats), "--plain-queries", str(plain_queries)]
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s,
                          check=False)
    if done.returncode != 0:
        tail = "\n".join(done.stderr.strip().splitlines()[-8:])
        raise RuntimeError(f"map probe failed (exit {done.returncode}):\n{tail}")
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def probe_map(map_dir: Path, queries_dir: Path, methods: Sequence[str],
              options: Mapping[str, Mapping[str, Any]], *, repeats: int,
              plain_queries: int) -> dict[str, Any]:
    """In this (fresh) process: resident memory before and after :meth:`Engine.load` of
    ``map_dir``, the load times, then every query of ``queries_dir`` by each method (latency,
    place-finder time, recall) and by the plain OpenCV pipeline."""
    from ...engine import Engine, EngineConf
    from ...storage.snapshot import load_map
    from .machine import rss_mb
    from .samples import QuerySet

    cv2.setNumThreads(1)
    conf = EngineConf(methods=tuple(methods), options=options)
    Engine(conf)  # every method's modules imported and warmed before the baseline
    limit_blas_threads(1)  # as the suite (one OpenCV and one BLAS thread, as a worker)
    queries = QuerySet.load(queries_dir)
    baseline = rss_mb()
    start = time.perf_counter()
    engine = Engine.load(map_dir, conf)
    engine_load_s = time.perf_counter() - start
    loaded = rss_mb()
    out: dict[str, Any] = {
        "rss_baseline_mb": baseline, "rss_loaded_mb": loaded,
        "map_rss_mb": None if loaded is None or baseline is None else loaded - baseline,
        "engine_load_s": engine_load_s}
    start = time.perf_counter()
    state, _ = load_map(map_dir)
    out["load_map_s"] = time.perf_counter() - start
    del state
    out["methods"] = _probe_methods(engine, queries, methods, repeats)
    out["place_finder_ms"] = _place_finder_times(engine, queries, methods, repeats)
    if plain_queries > 0:
        try:
            out["plain_opencv"] = _probe_plain(engine, queries, plain_queries)
        except cv2.error as exc:  # a limit of OpenCV's matcher is a result, not a crash
            out["plain_opencv"] = {"error": f"cv2.error: {str(exc).strip().splitlines()[-1]}"}
    out["peak_rss_mb"] = rss_mb("VmHWM")
    return out


def _probe_methods(engine: Any, queries: Any, methods: Sequence[str], repeats: int
                   ) -> dict[str, Any]:
    """Every query by every method in turn (so load changes hit all alike), one warm-up."""
    from .samples import relocalize_jpeg, summarize_samples

    for method in methods:
        relocalize_jpeg(engine, queries.jpegs[0], queries.camera, method)
    samples: dict[str, list[Any]] = {m: [] for m in methods}
    for _ in range(repeats):
        for i in range(len(queries)):
            for method in methods:
                samples[method].append((i, relocalize_jpeg(engine, queries.jpegs[i],
                                                           queries.camera, method)))
    return {m: summarize_samples(samples[m], queries) for m in methods}


def _place_finder_times(engine: Any, queries: Any, methods: Sequence[str], repeats: int
                        ) -> dict[str, float]:
    """Median ms of ``find_places(query, 5)`` alone, per place finder of ``methods``, on
    frames whose SIFT features are already extracted (BoW needs them; SBI does not)."""
    from ...core.frame import Frame
    from .samples import decode_jpeg

    out: dict[str, float] = {}
    relocs = [engine.relocalizer(m) for m in methods]
    # a fallback chain's place finders are its steps'
    steps = [step for r in relocs for step in getattr(r, "steps", [r])]
    for step in steps:
        place = getattr(step, "place", None)
        if place is None or place.name in out:
            continue
        times = []
        for _ in range(repeats):
            for jpeg in queries.jpegs:
                image = decode_jpeg(jpeg)
                frame = Frame(image, queries.camera)
                frame.features["sift"] = extract(image, FeatureConf(kind="sift"))
                start = time.perf_counter()
                place.find_places(frame, 5)
                times.append(time.perf_counter() - start)
        out[place.name] = 1e3 * float(np.median(times))
    return out


def _probe_plain(engine: Any, queries: Any, count: int) -> dict[str, Any]:
    from .peers import PlainMap, PlainOpenCVPipeline
    from .samples import summarize_plain

    start = time.perf_counter()
    plain = PlainMap.from_state(engine.map.snapshot())
    build = time.perf_counter() - start
    pipeline = PlainOpenCVPipeline(plain, queries.camera)
    samples = [(i, pipeline.relocalize_jpeg(queries.jpegs[i]))
               for i in range(min(count, len(queries)))]
    return {"map_descriptors": len(plain), "stack_s": build, **summarize_plain(samples, queries)}


def tree_mb(path: Path) -> float:
    """Size of the files under ``path`` on disk, MiB (hard links to one file counted once)."""
    return sum(f.stat().st_size for f in _stored_once(path)) / 2**20


def _stored_once(root: Path) -> list[Path]:
    """The files under ``root``, one path per stored file: a snapshot's model file equal to
    another method's is a hard link to it (:func:`..storage.snapshot_save.link_duplicate_models`),
    its bytes on disk once."""
    seen: set[tuple[int, int]] = set()
    once = []
    for path in sorted(root.rglob("*")):
        if path.is_file():
            stat = path.stat()
            if (stat.st_dev, stat.st_ino) not in seen:
                seen.add((stat.st_dev, stat.st_ino))
                once.append(path)
    return once


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m reloc_service.tools.bench.scaling --map DIR --queries DIR ...``: run
    :func:`probe_map` and print its result as one JSON line."""
    parser = argparse.ArgumentParser(description=probe_map.__doc__)
    parser.add_argument("--map", required=True, type=Path)
    parser.add_argument("--queries", required=True, type=Path)
    parser.add_argument("--methods", required=True, help="JSON list of method strings")
    parser.add_argument("--options", default="{}", help="JSON plugin options")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--plain-queries", type=int, default=0)
    args = parser.parse_args(argv)
    result = probe_map(args.map, args.queries, json.loads(args.methods),
                       json.loads(args.options), repeats=args.repeats,
                       plain_queries=args.plain_queries)
    from ..eval.results import json_safe

    print(json.dumps(json_safe(result), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
