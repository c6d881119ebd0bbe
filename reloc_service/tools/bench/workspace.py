"""What the sections of ``reloc bench`` share: the run's sizes (:class:`SuiteConf`), the
methods as benchmarked (:data:`VARIANTS`), and the :class:`Workspace`: the rendered scene's
queries, one trained engine per plugin-options group, each saved for a loopback service."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...algorithms.relocalizers.factory import DEFAULT_METHOD
from ...core.cameras import Camera
from ...core.progress import progress
from ...engine import Engine, EngineConf, MappingConf
from .samples import JPEG_QUALITY, QuerySet

SECTIONS = ("latency", "peers", "throughput", "scaling", "ferns", "planar", "intrinsics")
#: Label of the service's default method (:data:`DEFAULT_METHOD`) in every table.
DEFAULT_LABEL = "default"
#: Name of the map the loopback services serve, and the camera id queries name.
MAP_NAME = "bench"
CAMERA_ID = "cam0"
#: Pose thresholds (metres, degrees) of the headline recall.
HEADLINE_RECALL = "5cm_5deg"


@dataclass(frozen=True)
class Variant:
    """A method as benchmarked: its label, method string, the engine group holding it (one
    engine per plugin options) and the features whose extraction is its limit."""

    label: str
    method: str
    group: str
    limit: str


#: The ORB fast path's options (multi_bench's preset: 500 query features, 3 candidates).
ORB_OPTIONS: dict[str, dict[str, Any]] = {"p3p": {"kind": "orb", "max_features": 500},
                                          "multi": {"num_candidates": 3}}

#: The default method's limit is decode + ORB extraction: it is meant to answer most queries
#: at ORB cost (its fast ORB step first), whatever its steps are named.
VARIANTS: tuple[Variant, ...] = (
    Variant(DEFAULT_LABEL, DEFAULT_METHOD, "default", "orb"),
    Variant("sbi+esm", "sbi+esm", "default", "sift"),
    Variant("sbi+p3p", "sbi+p3p", "default", "sift"),
    Variant("sbi+p3p orb", "sbi+p3p", "orb", "orb"),
    Variant("bow+p3p", "bow+p3p", "default", "sift"),
    Variant("ferns", "ferns", "default", "sift"),
)


@dataclass(frozen=True)
class SuiteConf:
    """Sizes of one run. ``scale`` shrinks the rendered 640x480 images (quick runs)."""

    name: str
    preset: str = "desk"
    scale: float = 1.0
    seed: int = 0
    #: Measured passes over the queries (after one warm-up query per method).
    repeats: int = 5
    ferns_options: Mapping[str, Any] = field(default_factory=dict)
    throughput_clients: tuple[int, ...] = (1, 2, 4, 8)
    throughput_seconds: float = 10.0
    service_workers: int = 2
    service_queue: int = 8
    map_sizes: tuple[int, ...] = (10, 100, 1000)
    unique_distractors: int = 50
    scaling_repeats: int = 2
    scaling_plain_queries: int = 3
    #: Methods probed at every map size. Ferns is left out: its classes are capped per model
    #: (``max_classes``), so its query cost does not grow with keyframes (the ``ferns``
    #: section sweeps classes instead), and training it on the 1000-keyframe map took over
    #: 10 minutes and 12 GB, beyond this benchmark's budget. Only the default method: the
    #: resident memory measured is the map's and the models a deployed service holds.
    scaling_methods: tuple[str, ...] = (DEFAULT_METHOD,)
    ferns_classes: tuple[int, ...] = (200, 500, 1000, 2000, 5000)
    ferns_warps: int = 100
    ferns_online_landmarks: int = 1000
    ferns_repeats: int = 10
    #: Throughput: the service's worker modes compared (``service.worker_mode``; only those
    #: the service knows are run, the first is the headline's).
    worker_modes: tuple[str, ...] = ("process", "thread")
    #: Seconds a throughput client waits for a reply before counting the query as lost.
    reply_timeout_s: float = 60.0
    sections: tuple[str, ...] = SECTIONS

    def __post_init__(self) -> None:
        unknown = sorted(set(self.sections) - set(SECTIONS))
        if unknown:
            raise ValueError(f"unknown bench section(s) {unknown}; expected some of {SECTIONS}")
        if self.repeats < 1 or not self.throughput_clients or not self.map_sizes:
            raise ValueError("repeats >= 1, throughput_clients and map_sizes are required")


QUICK = SuiteConf("quick", scale=0.5, repeats=2, ferns_options={"num_warps": 20},
                  throughput_clients=(1, 2, 4, 8), throughput_seconds=2.0,
                  map_sizes=(10, 40), unique_distractors=6, scaling_repeats=1,
                  scaling_plain_queries=2, ferns_classes=(200, 500), ferns_warps=10,
                  ferns_online_landmarks=200, ferns_repeats=3,
                  sections=tuple(s for s in SECTIONS if s != "planar"))
FULL = SuiteConf("full")


def say(message: str) -> None:
    print(f"[reloc bench] {message}", file=sys.stderr, flush=True)


# -- workspace: the scene, its map, the engines ------------------------------------------------

@dataclass(eq=False)
class Workspace:
    """What every section shares: the queries, one engine per options group (trained, over
    the same map) and each engine's saved map in a service storage folder."""

    conf: SuiteConf
    tmp: Path
    queries: QuerySet
    engines: dict[str, Engine]
    options: dict[str, dict[str, dict[str, Any]]]
    storage: dict[str, Path]
    info: dict[str, Any]

    def methods(self, group: str) -> list[str]:
        return list(dict.fromkeys(v.method for v in VARIANTS if v.group == group))


def group_options(conf: SuiteConf) -> dict[str, dict[str, dict[str, Any]]]:
    """Plugin options of each engine group."""
    # Ferns trains online as keyframes arrive; nothing arrives after training here, and
    # Engine.load would otherwise retrain ferns while it feeds the keyframes, before
    # restoring the saved model, which the load times would then include.
    return {"default": {"ferns": {"online": False, **conf.ferns_options}},
            "orb": {k: dict(v) for k, v in ORB_OPTIONS.items()}}


def synth_fingerprint() -> str:
    """A hash of the renderer's source (``tools/synth``): a cached scene is reused only if it
    was rendered by this very code."""
    import hashlib

    digest = hashlib.sha256()
    for path in sorted((Path(__file__).resolve().parents[1] / "synth").rglob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def render_cached(preset: str, cache: Path, *, seed: int, scale: float, workers: int = 2,
                  show: bool = True) -> tuple[Path, float, bool]:
    """``reloc synth`` of ``preset`` into ``cache``, reused when a folder rendered with the same
    (preset, seed, scale) by the same renderer code (:func:`synth_fingerprint`) is there:
    rendering is a pure function of those. Returns the dataset folder, the seconds rendering
    took (0 when cached) and whether it was cached."""
    import json
    import shutil

    from ..synth import render_dataset

    key = {"preset": preset, "seed": seed, "scale": scale, "renderer": synth_fingerprint()}
    out = cache / f"{preset}-seed{seed}-scale{scale:g}"
    marker = out / ".bench-rendered.json"
    if marker.is_file() and json.loads(marker.read_text()) == key:
        say(f"preset {preset!r} (seed {seed}, scale {scale:g}): cached in {out}")
        return out, 0.0, True
    if out.exists():  # a stale or interrupted render: start afresh
        shutil.rmtree(out)
    say(f"rendering preset {preset!r} (seed {seed}, scale {scale:g}) into {out}")
    start = time.perf_counter()
    root = render_dataset(preset, out, seed=seed, scale=scale, workers=workers, progress=show)
    seconds = time.perf_counter() - start
    marker.write_text(json.dumps(key))  # written last: its presence means the render finished
    return root, seconds, False


def prepare(conf: SuiteConf, tmp: Path, cache: Path | None = None) -> Workspace:
    """Render the scene (or reuse it from ``cache``, default ``tmp/cache``), build its map
    (SIFT and ORB landmarks, triangulated), train every method, and save each group's engine
    into a service storage folder."""
    from ..data.dataset import read_dataset

    info: dict[str, Any] = {"preset": conf.preset, "scale": conf.scale, "seed": conf.seed}
    root, info["render_s"], info["render_cached"] = render_cached(
        conf.preset, cache or tmp / "cache", seed=conf.seed, scale=conf.scale)
    ds = read_dataset(root)
    camera = ds.camera(ds.map_entries[0])
    queries = QuerySet.from_images(camera, [ds.load_image(e) for e in ds.query_entries],
                                   [np.array(e.world_from_cam) for e in ds.query_entries])
    options = group_options(conf)
    ws = Workspace(conf, tmp, queries, {}, options, {}, info)
    default = Engine(EngineConf(methods=tuple(ws.methods("default")), options=options["default"],
                                mapping=MappingConf(feature_kinds=("sift", "orb"))))
    start = time.perf_counter()
    for kf_id, entry in progress(list(enumerate(ds.map_entries)), desc="map keyframes"):
        default.add_keyframe(kf_id, ds.load_image(entry), camera, np.array(entry.world_from_cam))
    info["build_s"] = time.perf_counter() - start
    info["train_s"] = {}
    for method in ws.methods("default"):
        start = time.perf_counter()
        default.train([method], progress=True)
        info["train_s"][method] = time.perf_counter() - start
    status = default.status()
    info.update(keyframes=status["keyframes"], landmarks=status["landmarks"],
                queries=len(queries), image=f"{camera.width}x{camera.height}",
                camera_model=camera.model, jpeg_quality=JPEG_QUALITY,
                jpeg_kb_median=float(np.median([len(j) for j in queries.jpegs])) / 1024)
    ws.engines["default"] = default
    ws.storage["default"] = _save_for_service(default, tmp / "storage-default")
    start = time.perf_counter()
    orb = Engine.load(ws.storage["default"] / MAP_NAME / "map",
                      EngineConf(methods=tuple(ws.methods("orb")), options=options["orb"]))
    info["engine_load_s"] = time.perf_counter() - start
    ws.engines["orb"] = orb
    ws.storage["orb"] = _save_for_service(orb, tmp / "storage-orb")
    return ws


def _save_for_service(engine: Engine, storage: Path) -> Path:
    """Save ``engine`` where a service with ``storage`` finds map :data:`MAP_NAME`."""
    from ...service.map_dirs import map_dirname

    engine.save(storage / map_dirname(MAP_NAME) / "map")
    return storage


def group_service(ws: Workspace, group: str, *, process: bool = False,
                  worker_mode: str | None = None) -> contextlib.AbstractContextManager[str]:
    """The loopback service of ``group``'s saved map (see :mod:`.loopback`)."""
    from .loopback import loopback_service

    return loopback_service(ws.storage[group], ws.methods(group), ws.options[group],
                            map_name=MAP_NAME, workers=ws.conf.service_workers,
                            queue_size=ws.conf.service_queue, process=process,
                            worker_mode=worker_mode)


def group_client(endpoint: str, camera: Camera) -> Any:
    """A client on map :data:`MAP_NAME` whose camera :data:`CAMERA_ID` is applied."""
    from .loopback import camera_client

    return camera_client(endpoint, MAP_NAME, CAMERA_ID, camera)
