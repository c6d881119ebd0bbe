"""``reloc bench --only fleet``: many stored maps served by one ``reloc serve`` with a memory
budget (``[service] max_resident_mb``), queried at random.

One template map is built once (:func:`build_template`): the rendered scene's keyframes, grown
to ``keyframes`` with distractor keyframes as the scaling section grows its maps
(:func:`.scaling.grow_state`), trained, and stored as a service stores a map
(:mod:`.stored_map`). It is copied ``maps`` times into one storage (snapshot files
hard-linked, so 200 copies of a 1000-keyframe map take the disk of one); the copies are
removed afterwards, whatever happens.

Two services are run, each ``reloc serve`` in its own process, as deployed (the packages
compiled to bytecode first, as an installed package is: :func:`.fleet_service.compile_bytecode`):

- the *baseline*: one copy, resident from its first query on (a budget no map reaches):
  the p50 of a warm query when nothing else is served, and the processes' own memory;
- the *fleet*: every copy, ``max_resident_mb = budget``. Start-up is timed from the process
  start to the first answer on a map picked at random (a cold load included); then
  ``queries`` times a map and a query are picked at random, the query is sent (cold when the
  map is not resident, as its ``status`` says just before) and sent again at once (warm:
  the map was just used). A ``busy`` reply is retried after its hint and counted; a query
  without any reply is lost. Meanwhile the service's resident memory (its process and its
  children) and the maps it says are resident (liveliness) are sampled; the residency
  manager's own accounting is read from its log lines.

Answers are scored against the queries' ground truth like every section (recall, wrong
poses, ``cov scale``). :func:`run_fleet` returns the JSON section, :func:`markdown_lines` its
part of docs/performance.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import random
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...algorithms.relocalizers.factory import DEFAULT_METHOD
from ...core.cameras import Camera
from ...core.geometry import pose_error
from ..eval import metrics
from ..eval.results import json_safe
from .fleet_memory import ResidencyLog, RssSampler
from .fleet_pool import repetition_pool
from .fleet_service import compile_bytecode, first_answer, serve
from .samples import QuerySet, pct_ms
from .stored_map import CAMERA_ID, StoredMap, copies, disk_bytes

MB = 1024 * 1024
#: The baseline service's budget: one no map of a fleet run reaches (its map stays resident).
AMPLE_MB = 1_000_000.0


@dataclasses.dataclass(frozen=True)
class FleetConf:
    """Sizes of one fleet run (the default is the issue's: 200 maps of 1000 keyframes, a
    budget of 1000 MB). ``budget_mb`` None: ``budget_maps`` maps' counted bytes over the
    processes' own memory (``max_resident_mb`` is the whole service's budget), as the
    baseline service measured it."""

    maps: int = 200
    keyframes: int = 1000
    budget_mb: float | None = 1000.0
    budget_maps: float = 3.5
    queries: int = 200
    baseline_queries: int = 60
    preset: str = "desk"
    scale: float = 1.0
    seed: int = 0
    method: str = DEFAULT_METHOD
    worker_mode: str = "thread"
    workers: int = 2
    #: How long a query waits for its map's cold load before a ``busy`` reply; the clients'
    #: timeout is above it, so a cold query gets an answer or ``busy``, never silence.
    cold_load_wait_s: float = 30.0
    query_timeout_s: float = 60.0
    unique_distractors: int = 50
    rss_period_s: float = 0.2
    startup_timeout_s: float = 300.0

    def __post_init__(self) -> None:
        if self.maps < 1 or self.keyframes < 1 or self.queries < 1:
            raise ValueError(f"fleet: expected maps, keyframes and queries >= 1, got "
                             f"{self.maps}, {self.keyframes}, {self.queries}")
        if self.budget_mb is not None and self.budget_mb <= 0:
            raise ValueError(f"fleet: expected a budget > 0 MB, got {self.budget_mb}")


#: ``--quick``: a few small maps, a budget of a few maps, the half-size scene.
QUICK_FLEET = FleetConf(maps=8, keyframes=40, budget_mb=None, queries=16, baseline_queries=16,
                        scale=0.5, unique_distractors=6)


# -- the template ------------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class FleetScene:
    """What the template is made of: the camera, posed keyframe images ((H, W) uint8 grey,
    ``world_from_cam`` (4, 4)), the queries (JPEG, with their ground truth) and how the
    scene was made."""

    camera: Camera
    keyframe_images: list[npt.NDArray[np.uint8]]
    keyframe_poses: list[npt.NDArray[np.float64]]
    queries: QuerySet
    info: dict[str, Any] = dataclasses.field(default_factory=dict)


def render_scene(conf: FleetConf, cache: Path) -> FleetScene:
    """The ``reloc synth`` preset ``conf.preset`` at ``conf.scale`` (cached in ``cache``)."""
    from ..data.dataset import read_dataset
    from .workspace import render_cached

    root, render_s, _ = render_cached(conf.preset, cache, seed=conf.seed, scale=conf.scale)
    ds = read_dataset(root)
    camera = ds.camera(ds.map_entries[0])
    queries = QuerySet.from_images(camera, [ds.load_image(e) for e in ds.query_entries],
                                   [np.array(e.world_from_cam) for e in ds.query_entries])
    return FleetScene(camera, [ds.load_image(e) for e in ds.map_entries],
                      [np.array(e.world_from_cam, np.float64) for e in ds.map_entries],
                      queries, {"preset": conf.preset, "scale": conf.scale,
                                "render_s": render_s})


def build_template(conf: FleetConf, scene: FleetScene, tmp: Path,
                   say: Callable[[str], None]) -> tuple[StoredMap, dict[str, Any]]:
    """The stored template map (see module docstring) and how it was made (seconds,
    counts)."""
    from ...engine import Engine, EngineConf, MappingConf
    from ...storage.snapshot import save_map
    from . import scaling
    from .stored_map import engine_from_images, stored_template

    engine_conf = EngineConf(methods=(conf.method,),
                             mapping=MappingConf(feature_kinds=("sift", "orb")))
    n = min(conf.keyframes, len(scene.keyframe_images))
    start = time.perf_counter()
    say(f"fleet: building the template map ({conf.keyframes} keyframes)")
    engine = engine_from_images(scene.camera, scene.keyframe_images[:n],
                                scene.keyframe_poses[:n], engine_conf,
                                train=conf.keyframes <= n)
    if conf.keyframes > n:
        base = engine.map.snapshot()
        distractors = scaling.make_distractors(
            min(conf.unique_distractors, conf.keyframes - n), scene.camera,
            scaling.landmarks_per_keyframe(base), seed=conf.seed)
        save_map(scaling.grow_state(base, conf.keyframes, distractors, scene.camera),
                 tmp / "raw")
        engine = Engine.load(tmp / "raw", engine_conf)   # trains every method
        shutil.rmtree(tmp / "raw")
    built_s = time.perf_counter() - start
    landmarks = len(engine.map.snapshot().landmarks)
    stored = stored_template(tmp / "template", "template", engine, {CAMERA_ID: scene.camera})
    apparent, _ = disk_bytes(stored.directory)
    return stored, {
        **scene.info, "image": f"{scene.camera.width}x{scene.camera.height}",
        "scene_keyframes": len(scene.keyframe_images), "keyframes": stored.keyframes,
        "landmarks": landmarks, "build_s": built_s, "counted_mb": stored.counted_bytes / MB,
        "disk_mb": apparent / MB, "queries": len(scene.queries)}


def reuse_template(directory: Path, scene: FleetScene) -> tuple[StoredMap, dict[str, Any]]:
    """A template stored by an earlier run (see :func:`run_fleet`), as :func:`build_template`
    describes its own; ValueError if ``directory`` holds no stored map."""
    from ...service.durability import read_service_file
    from ...service.quotas import MapUsage
    from ...storage.snapshot import load_map

    if not (directory / "service.json").is_file():
        raise ValueError(f"--fleet-template {directory}: expected a map directory a fleet run "
                         "stored (WORKDIR/fleet/template/template)")
    state, _ = load_map(directory / "map")
    stored = StoredMap(directory, len(read_service_file(directory)["keyframe_ids"]),
                       MapUsage.of(state).total)
    apparent, _ = disk_bytes(directory)
    return stored, {
        **scene.info, "image": f"{scene.camera.width}x{scene.camera.height}",
        "scene_keyframes": len(scene.keyframe_images), "keyframes": stored.keyframes,
        "landmarks": len(state.landmarks), "build_s": None, "reused": str(directory),
        "counted_mb": stored.counted_bytes / MB, "disk_mb": apparent / MB,
        "queries": len(scene.queries)}


# -- queries -----------------------------------------------------------------------------------

@dataclasses.dataclass
class Tally:
    """Queries sent to a service: round trips by kind, answers, busy replies, losses."""

    seconds: dict[str, list[float]] = dataclasses.field(
        default_factory=lambda: {"cold": [], "warm": []})
    #: The query image of each round trip in ``seconds``, by kind.
    images: dict[str, list[int]] = dataclasses.field(
        default_factory=lambda: {"cold": [], "warm": []})
    answers: list[tuple[int, Any]] = dataclasses.field(default_factory=list)
    busy: int = 0
    lost: int = 0
    errors: list[str] = dataclasses.field(default_factory=list)

    def summary(self, queries: QuerySet) -> dict[str, Any]:
        out: dict[str, Any] = {"answered": len(self.answers), "busy_replies": self.busy,
                               "lost": self.lost, "errors": self.errors[:5]}
        for kind, values in self.seconds.items():
            out[kind] = {"n": len(values), "p50_ms": pct_ms(values, 50),
                         "p99_ms": pct_ms(values, 99), "max_ms": pct_ms(values, 100),
                         "seconds": values, "images": self.images[kind]}
        return {**out, **score(self.answers, queries)}


def paired_ratio(fleet: dict[str, Any], baseline: dict[str, Any]) -> float | None:
    """The median, over the fleet's warm queries, of each one's round trip over the
    baseline's median round trip for the same query image: the two services' p50s compare
    different random mixes of images (some answered by the ORB step, some by SIFT at several
    times the cost), this compares like with like."""
    by_image: dict[int, list[float]] = {}
    for image, seconds in zip(baseline["images"], baseline["seconds"], strict=True):
        by_image.setdefault(image, []).append(seconds)
    ratios = [seconds / float(np.median(by_image[image]))
              for image, seconds in zip(fleet["images"], fleet["seconds"], strict=True)
              if image in by_image]
    return float(np.median(ratios)) if ratios else None


def ask(client: Any, tally: Tally, kind: str, jpeg: bytes, index: int, attempts: int = 10
        ) -> None:
    """One relocalize query (``busy`` retried after its hint), timed into ``tally``."""
    from reloc_client.client import NoReplyError, ServiceBusy

    start = time.perf_counter()
    for _ in range(attempts):
        try:
            result = client.relocalize(jpeg, camera_id=CAMERA_ID)
        except ServiceBusy:   # "being loaded from storage; retry in a few seconds"
            tally.busy += 1
            time.sleep(1.0)
            continue
        except NoReplyError:
            tally.lost += 1
            return
        except Exception as exc:   # reported, never hidden
            tally.errors.append(f"{client.map}: {type(exc).__name__}: {exc}")
            return
        tally.seconds[kind].append(time.perf_counter() - start)
        tally.images[kind].append(index)
        tally.answers.append((index, result))
        return
    tally.errors.append(f"{client.map}: busy {attempts} times")


def score(answers: list[tuple[int, Any]], queries: QuerySet) -> dict[str, Any]:
    """Recall, wrong-pose rate and ``cov scale`` of (query index, result) answers."""
    n = len(answers)
    t, r, maha = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    ok = np.array([res.ok for _, res in answers], bool)
    for k, (i, res) in enumerate(answers):
        if not res.ok:
            continue
        dt, dr = pose_error(np.asarray(res.world_from_cam), queries.gts[i])
        t[k], r[k] = dt, math.degrees(dr)
        if res.covariance is not None:
            maha[k] = metrics.translation_mahalanobis(res.world_from_cam, queries.gts[i],
                                                      res.covariance)
    if not n:
        return {"recall": {}, "returned_rate": math.nan, "wrong_rate": math.nan,
                "cov_scale": math.nan}
    return {"recall": metrics.recalls(t, r, ok), "returned_rate": float(ok.mean()),
            "wrong_rate": metrics.wrong_rate(t, r, ok),
            "cov_scale": metrics.covariance_scale(maha, ok)}


def run_baseline(conf: FleetConf, template: StoredMap, queries: QuerySet, work: Path
                 ) -> dict[str, Any]:
    """One copy, resident from its first query on (a budget no map reaches): warm queries
    alone, and the processes' own memory the service counts (``memory_baseline_bytes``
    of its status: measured before its warm-up, plus the warm-up's growth, measured at its
    end with no map resident, else as recorded or estimated: its first load does not wait)."""
    from reloc_client.client import RelocClient

    storage = work / "baseline-storage"
    copies(template, storage, ["site000"])
    tally = Tally()
    pixels = queries.camera.width * queries.camera.height
    with serve(conf, storage, AMPLE_MB, work / "baseline", pixels) as served:
        startup = first_answer(served, "site000", queries.jpegs[0], conf.startup_timeout_s)
        with RelocClient(served.endpoint, map="site000", timeout=conf.query_timeout_s) as c:
            for k in range(conf.baseline_queries):
                i = k % len(queries)
                ask(c, tally, "warm", queries.jpegs[i], i)
            own_mb = c.status().counters.get("memory_baseline_bytes", 0) / MB
    return {"startup_to_first_answer_s": startup, "processes_baseline_mb": own_mb,
            **tally.summary(queries)}


def run_spread(conf: FleetConf, storage: Path, names: list[str], queries: QuerySet,
               budget_mb: float, counted_mb: float, work: Path) -> dict[str, Any]:
    """The fleet service (see module docstring)."""
    from reloc_client.client import RelocClient

    rng = random.Random(conf.seed)
    tally = Tally()
    pixels = queries.camera.width * queries.camera.height
    with serve(conf, storage, budget_mb, work / "fleet", pixels) as served:
        sampler = RssSampler(served.process.pid, conf.rss_period_s)
        with sampler.running():
            startup = first_answer(served, rng.choice(names), queries.jpegs[0],
                                   conf.startup_timeout_s)
            rss_at_start = sampler.sample()
            resident_counts = []
            with RelocClient(served.endpoint, map=names[0], timeout=conf.query_timeout_s) as c:
                for _ in range(conf.queries):
                    c.map = rng.choice(names)
                    i = rng.randrange(len(queries))
                    resident = c.status().resident
                    ask(c, tally, "warm" if resident else "cold", queries.jpegs[i], i)
                    ask(c, tally, "warm", queries.jpegs[i], i)
                    resident_counts.append(len(c.resident_maps(timeout=5.0)))
                resident_at_end = len(c.resident_maps(timeout=5.0))
        accounting = ResidencyLog.read(served.log)
    rss = sampler.summary()
    return {"budget_mb": budget_mb, "startup_to_first_answer_s": startup,
            "queries": conf.queries, **tally.summary(queries),
            "rss_at_first_answer_mb": rss_at_start, "rss": rss,
            "max_rss_over_budget": (rss["max_mb"] / budget_mb) if rss["max_mb"] else None,
            "resident_maps_max": max(resident_counts, default=0),
            "resident_maps_at_end": resident_at_end,
            "resident_counted_max_mb": max(resident_counts, default=0) * counted_mb,
            "accounting": accounting.summary(), "loads": accounting.loads}


# -- the section -------------------------------------------------------------------------------

def run_fleet(conf: FleetConf, *, workdir: Path | None = None, cache: Path,
              scene: FleetScene | None = None, template_dir: Path | None = None,
              say: Callable[[str], None] = print) -> dict[str, Any]:
    """The fleet section's JSON (see module docstring) on ``scene`` (default: the preset
    rendered, :func:`render_scene`); its copies are removed before it returns (the
    template too, unless ``workdir`` keeps it). ``template_dir``: a template map stored by
    an earlier run of the same scene (``WORKDIR/fleet/template/template``), used as it is
    instead of being built again."""
    with contextlib.ExitStack() as stack:
        if workdir is None:
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="reloc-fleet-")))
        else:
            tmp = workdir / "fleet"
            tmp.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        scene = scene or render_scene(conf, cache)
        queries = scene.queries
        template, info = (build_template(conf, scene, tmp, say) if template_dir is None
                          else reuse_template(template_dir, scene))
        names = [f"site{i:03d}" for i in range(conf.maps)]
        storage = tmp / "storage"
        try:
            say(f"fleet: {conf.maps} copies of the template in {storage}")
            copies(template, storage, names)
            apparent, allocated = disk_bytes(storage)
            compiled_s = compile_bytecode()   # the services start as installed ones do
            say("fleet: the baseline service (one map, always resident)")
            baseline = run_baseline(conf, template, queries, tmp)
            budget_mb = conf.budget_mb or round(baseline["processes_baseline_mb"]
                                                + conf.budget_maps * template.counted_bytes / MB,
                                                1)
            say(f"fleet: {conf.maps} maps, max_resident_mb = {budget_mb:g}, "
                f"{conf.queries} random picks")
            fleet = run_spread(conf, storage, names, queries, budget_mb, info["counted_mb"], tmp)
        finally:
            shutil.rmtree(storage, ignore_errors=True)
            shutil.rmtree(tmp / "baseline-storage", ignore_errors=True)
        warm, base = fleet["warm"]["p50_ms"], baseline["warm"]["p50_ms"]
        say("fleet: the repetition check's pool of the template, indexed and scanned")
        pool = repetition_pool(template.directory / "map", queries)
        return json_safe({
            "conf": dataclasses.asdict(conf), "template": info, "maps": conf.maps,
            "storage": {"apparent_mb": apparent / MB, "on_disk_mb": allocated / MB,
                        "hard_links": True, "removed": not storage.exists()},
            "bytecode": {"compiled": True, "seconds": compiled_s},
            "baseline": baseline, "fleet": fleet,
            "warm_p50_over_baseline": warm / base if base and warm else None,
            "warm_over_baseline_by_image": paired_ratio(fleet["warm"], baseline["warm"]),
            "repetition_pool": pool,
            "seconds": time.perf_counter() - start})


def run_into(result: dict[str, Any], conf: FleetConf, workdir: Path | None, cache: Path,
             say: Callable[[str], None], *, template_dir: Path | None = None) -> None:
    """Add the ``fleet`` section to ``result`` (its error, if it fails)."""
    import traceback

    try:
        result["fleet"] = run_fleet(conf, workdir=workdir, cache=cache, say=say,
                                    template_dir=template_dir)
    except Exception as exc:   # the other sections' figures still count
        traceback.print_exc()
        result["fleet"] = {"error": f"{type(exc).__name__}: {exc}"}

