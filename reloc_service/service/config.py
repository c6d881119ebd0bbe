"""The service configuration: a TOML file (``config/default.toml``) read strictly into frozen
dataclasses; explicit command-line flags override it.

Layout (every section and key optional; the embedded default equals ``config/default.toml``)::

    [zenoh]     mode, listen, connect, multicast_scouting, config_file (a Zenoh JSON5 file)
    [service]   instance, prefix, storage, workers, worker_mode, queue_size, methods, ...
    [limits]    max_payload_bytes, max_image_pixels, max_features, max_hypotheses
    [quotas]    max_maps, max_keyframes_per_map, max_map_bytes, max_total_bytes
    [maps.NAME] maps served from the start (a table, possibly empty, per map; it may set
                the map's own calibration_focal_sigma_rel / calibration_radial_sigma_px)
    [options.PLUGIN]  plugin options (``[options.sbi]``, ``[options.p3p]``, ``[options.verify]``)
    [mapping]   map-building options (the engine's MappingConf)
    [ros2]      each map as a ROS 2 node on rmw_zenoh (off by default; ros2/conf.py)

An unknown section or key is a :class:`ConfigError` naming it and the allowed ones.
"""

from __future__ import annotations

import dataclasses
import math
import os
import socket
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from ..algorithms.relocalizers.factory import DEFAULT_METHOD
from ..core.errors import ConfigError
from ..core.methods import parse_method
from ..core.plugins import make_conf
from ..storage.keyframe_parts import StoredParts
from .ros2.conf import Ros2Conf

ZENOH_MODES = ("peer", "client", "router")
WORKER_MODES = ("process", "thread")
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_CONFIG_FILE = Path(__file__).resolve().parents[2] / "config" / "default.toml"


@dataclass(frozen=True)
class ZenohConf:
    """How the service joins Zenoh. ``config_file`` (a Zenoh JSON5 file) is read first; the
    keys here are applied on top of it (an empty list leaves the file's value)."""

    mode: str = "peer"
    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str = ""

    def __post_init__(self) -> None:
        if self.mode not in ZENOH_MODES:
            raise ConfigError(f"zenoh.mode: expected one of {list(ZENOH_MODES)}, got "
                              f"{self.mode!r}")
        for name in ("listen", "connect"):
            endpoints = getattr(self, name)
            object.__setattr__(self, name, _str_tuple(endpoints, f"zenoh.{name}"))
            for ep in getattr(self, name):
                if "/" not in ep:
                    raise ConfigError(f"zenoh.{name}: expected endpoints like "
                                      f"'tcp/127.0.0.1:7447', got {ep!r}")


@dataclass(frozen=True)
class LimitsConf:
    """Sizes above which a request is refused before it is parsed (docs/protocol.md)."""

    max_payload_bytes: int = 32 * 1024 * 1024
    #: 1280 x 960: a query holds up to 12 MB + 224 B a pixel (275 MB here; 3.1 Mpx took +690
    #: MB), so one request stays under +300 MB on a 4-8 GB companion computer with VGA to
    #: 1280x960 cameras. ``max_resident_mb`` keeps that much per worker out of the maps'
    #: share (:func:`.memory_baseline.query_working_bytes`): set it to the cameras' size.
    max_image_pixels: int = 1280 * 960
    max_features: int = 50_000
    max_hypotheses: int = 32

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if getattr(self, f.name) < 1:
                raise ConfigError(f"limits.{f.name}: expected a positive integer, got "
                                  f"{getattr(self, f.name)}")

    def to_wire(self) -> Any:
        """The protocol's :class:`~reloc_client.protocol.Limits`."""
        from reloc_client import protocol as wire

        return wire.Limits(max_payload_bytes=self.max_payload_bytes,
                           max_image_pixels=self.max_image_pixels,
                           max_features=self.max_features, max_hypotheses=self.max_hypotheses)


@dataclass(frozen=True)
class QuotasConf:
    """What the maps may hold; a put beyond is refused with QUOTA_EXCEEDED (maps restored or
    configured are served whatever their size; only their further puts are refused). Bytes
    are counted as :mod:`.quotas` says: each keyframe's image as held, depth and features
    (about 365 KB for a 640x480 JPEG keyframe with the default methods).

    The defaults are safe for a development machine that creates maps by puts; the files of
    ``config/`` and ``deploy/`` size them for a companion computer's 1 GB ``MemoryMax`` and
    for a ground station (docs/reliability.md, "Quotas": the service grew by about 5.5x what
    is counted)."""

    #: Maps served at once; a put creating one more is refused.
    max_maps: int = 16
    #: Keyframes per map (a replaced keyframe is not one more).
    max_keyframes_per_map: int = 10_000
    #: Bytes one map counts (its keyframes' images, depth and features).
    max_map_bytes: int = 256 * 1024 * 1024
    #: Bytes every map counts together.
    max_total_bytes: int = 512 * 1024 * 1024

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"quotas.{f.name}: expected a positive integer, got "
                                  f"{value!r}")


@dataclass(frozen=True)
class ServiceSection:
    """The service itself: names, threads, queues, storage, methods."""

    #: Instance name in liveliness tokens; empty: ``<hostname>-<pid>``.
    instance: str = ""
    prefix: str = "reloc"
    #: Directory of journals and snapshots (``~`` expanded; relative to the working
    #: directory); empty: keep maps in memory only (nothing survives a restart).
    storage: str = "~/.local/share/reloc/maps"
    #: Relocalize workers (processes or threads, see ``worker_mode``).
    workers: int = 2
    #: "process": each worker is a process holding a read-only replica of every served map,
    #: kept current by the changes applied here, in order (queries scale with cores: no GIL
    #: shared; memory: one replica per worker). "thread": threads of this process querying
    #: its maps directly (one copy of each map; the GIL held outside OpenCV limits scaling).
    worker_mode: str = "process"
    #: OpenCV's own threads (``cv2.setNumThreads``) in the service process (map building,
    #: and queries with thread workers); 0 keeps OpenCV's default (every core, best latency
    #: for one query at a time). With as many thread workers as cores, 1 avoids workers
    #: fighting over cores inside OpenCV. Worker processes always use 1 thread each.
    opencv_threads: int = 0
    #: Threads of the BLAS behind NumPy and SciPy in the service process (0: the BLAS's
    #: default, every core). reloc's products are small: 1 keeps an idle BLAS thread from
    #: spinning on the core another worker or a query's helper thread would use (the default
    #: method measured 10.0 vs 10.3 ms on desk, the SIFT path 111 vs 105 ms; one run, 2
    #: cores). Worker processes always use 1 thread each.
    blas_threads: int = 1
    #: Relocalize queries waiting for a worker; one more is answered "busy" at once.
    queue_size: int = 8
    #: Threads applying the maps' keyframe and camera puts, shared by every map: one map's
    #: puts run one at a time and in order, up to this many maps at once. A map with nothing
    #: queued holds no thread, so 300 maps cost no more threads than one.
    writer_threads: int = 4
    #: Keyframe puts/deletes waiting for a map's writer; one more is rejected (BUSY event).
    writer_queue_size: int = 512
    #: Payload bytes the writers may hold (queued and running puts, every map together); a
    #: put beyond is rejected (BUSY event). 128 MiB: four puts at the 32 MiB payload limit, or
    #: about 400 VGA keyframes, while 40 puts of 30 MiB no longer hold 1.2 GB on a 4-8 GB
    #: companion.
    writer_queue_bytes: int = 128 * 1024 * 1024
    #: A put on a map that is not served creates it (else the put is ignored).
    allow_new_maps: bool = True
    #: On start, copy each served map's cameras and keyframes from a running replica (a get
    #: on ``<prefix>/<map>/keyframes/**?image=true``) before answering queries; keyframe puts
    #: arriving meanwhile are buffered in the writer queue and applied after the copy.
    bootstrap_from_peers: bool = False
    #: Seconds between comparisons of each served map with the peers serving it (identity,
    #: map version, content hash), divergence reported; 0: never. Only a replica
    #: (``bootstrap_from_peers``) compares.
    replica_check_s: float = 5.0
    #: Journal records between background snapshots (0: snapshot only after training and at
    #: shutdown).
    snapshot_every: int = 200
    #: fsync every journal record (off only for benchmarks of the non-durable path).
    fsync: bool = True
    #: Methods every map serves (each a method or a fallback chain) and the default one.
    methods: tuple[str, ...] = (DEFAULT_METHOD,)
    default_method: str = DEFAULT_METHOD
    #: Train a map's methods after loading it if no trained models were restored.
    train_on_load: bool = True
    #: Seconds a stop (SIGTERM) may take: queued puts are journaled (applied at the next
    #: start), the final snapshot is taken only within what is left. Keep it well under
    #: systemd's TimeoutStopSec (60 s in deploy/), which kills -9 after.
    stop_timeout_s: float = 20.0
    #: Memory budget of the whole service, in MB: the processes' own resident memory with
    #: no map (measured once each process has warmed up; status counters ``memory_*``) plus
    #: what the resident maps count (as the quotas count
    #: them: images, depth, features, and the relocalizers' pools); 0: unlimited, every
    #: stored map is restored at start and stays resident. Above 0, maps are opened on
    #: first use and the least recently used idle ones are closed past the budget
    #: (:mod:`.residency`).
    max_resident_mb: float = 0.0
    #: Seconds a query on a stored map that is not resident waits for it to load; past
    #: that it is answered "busy" with a retry hint (the load goes on).
    cold_load_wait_s: float = 5.0
    #: What a snapshot keeps of each keyframe's depth map once its landmarks are made:
    #: "drop", "lossless" (zlib, bit-exact) or "raw" (:mod:`..storage.keyframe_parts`).
    keyframe_depth: str = "drop"
    #: Keyframe images on disk: "needed" (only when a served method reads pixels: ferns,
    #: sbi+esm) or "always" (needed later to add such a method or a feature kind, and by a
    #: replica that bootstraps from this one: ``bootstrap_from_peers`` keeps them).
    keyframe_images: str = "needed"
    #: SIFT descriptors on disk: "none" (in full), "pq" (product-quantization codes, a
    #: quarter of the bytes, decoded on load; keypoints in 1/8 px, float16 small blurry
    #: images) or "pq16" (as "pq" with 16-byte codes, an eighth of the bytes; it cost
    #: sbi+p3p 5 net of the validation repeated-hard_s1's 69 queries)
    #: (:mod:`..storage.descriptor_pq`). "none" by default: "pq" cost one of ten
    #: tum_fr1_rpy queries for the default, bow+p3p and ferns (README, "Map size").
    #: "pq-hybrid": "pq" codes, and in full the rows whose code's squared error exceeds a
    #: quarter of the map's median two-view descriptor distance (format 11)
    #: (:mod:`..storage.descriptor_hybrid`; docs/performance.md, "PQ with exact rows").
    descriptor_codec: str = "none"
    #: Keyframe features on disk: "landmarks" (the keypoints that carry a landmark: all
    #: relocalization reads once the map's methods are trained; a snapshot of a map with an
    #: untrained method, or one that reads other keypoints (5pt), keeps them all) or "all"
    #: (needed to re-train a bag-of-words vocabulary on a restored map, or to add 5pt);
    #: options: "per-landmark" (those rows, one descriptor a landmark: its first row's) and
    #: "per-landmark-medoid" (the medoid of its rows'), each about half the descriptor bytes
    #: and each more than 2 points of recall short on some set (docs/performance.md)
    #: (:mod:`..storage.landmark_descriptors`).
    keyframe_descriptors: str = "landmarks"
    #: A bag-of-words vocabulary's SIFT centres on disk: "float16" or "uint8" (rounded to
    #: SIFT's integer values; half the bytes, read by older reloc too)
    #: (:meth:`..algorithms.place.vocabulary.VocabularyTree.to_state`). An option: it changes
    #: which word a descriptor near a cell boundary gets (docs/performance.md, "Map size").
    vocabulary_centres: str = "float16"
    #: Landmark points on disk: "float32" offsets from their anchor keyframe, or "float16"
    #: where the rounding stays within half of each landmark's uncertainty (format 10: an
    #: older reloc refuses the map, naming the format) (:mod:`..storage.landmark_codec`).
    landmark_points: str = "float32"
    #: At most this many landmark rows a keyframe and kind on disk, most-seen first, spread
    #: over the image (0: all) (:mod:`..storage.landmark_summary`).
    landmark_budget: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "methods", _str_tuple(self.methods, "service.methods"))
        self._check_residency()
        self.stored_parts()   # ConfigError naming the key when a mode is unknown
        for name in ("workers", "queue_size", "writer_threads", "writer_queue_size",
                     "writer_queue_bytes"):
            if getattr(self, name) < 1:
                raise ConfigError(f"service.{name}: expected an integer >= 1, got "
                                  f"{getattr(self, name)}")
        if self.worker_mode not in WORKER_MODES:
            raise ConfigError(f"service.worker_mode: expected one of {list(WORKER_MODES)}, got "
                              f"{self.worker_mode!r}")
        if self.opencv_threads < 0:
            raise ConfigError(f"service.opencv_threads: expected >= 0 (0: OpenCV's default), "
                              f"got {self.opencv_threads}")
        if self.blas_threads < 0:
            raise ConfigError(f"service.blas_threads: expected >= 0 (0: the BLAS's default), "
                              f"got {self.blas_threads}")
        if not self.replica_check_s >= 0:
            raise ConfigError(f"service.replica_check_s: expected seconds >= 0 (0: off), got "
                              f"{self.replica_check_s}")
        if not self.stop_timeout_s > 0:
            raise ConfigError(f"service.stop_timeout_s: expected seconds > 0, got "
                              f"{self.stop_timeout_s}")
        if self.snapshot_every < 0:
            raise ConfigError(f"service.snapshot_every: expected >= 0, got {self.snapshot_every}")
        if not self.methods:
            raise ConfigError("service.methods: expected at least one method, e.g. ['sbi+p3p']")
        if self.default_method not in self.methods:
            raise ConfigError(f"service.default_method: {self.default_method!r} is not one of "
                              f"service.methods {list(self.methods)}")
        for method in self.methods:
            _check_servable(method)
        _check_names(self.prefix, self.instance)

    def stored_parts(self) -> StoredParts:
        """What the maps' snapshots store of keyframe depth and images; a member of a
        replica set (``bootstrap_from_peers``) keeps its images, which a peer copies."""
        images = "always" if self.bootstrap_from_peers else self.keyframe_images
        try:
            return StoredParts(depth=self.keyframe_depth, images=images,
                               descriptor_codec=self.descriptor_codec,
                               descriptors=self.keyframe_descriptors,
                               vocabulary=self.vocabulary_centres,
                               landmark_points=self.landmark_points,
                               landmark_budget=self.landmark_budget)
        except ConfigError as exc:
            raise ConfigError(f"service.{exc}") from None

    def _check_residency(self) -> None:
        """``max_resident_mb`` > 0 closes idle maps: only with storage to reopen them from
        and no bootstrap (which copies every map at start)."""
        if not self.max_resident_mb >= 0:
            raise ConfigError(f"service.max_resident_mb: expected MB >= 0 (0: unlimited), got "
                              f"{self.max_resident_mb}")
        if not self.cold_load_wait_s >= 0:
            raise ConfigError(f"service.cold_load_wait_s: expected seconds >= 0, got "
                              f"{self.cold_load_wait_s}")
        if self.max_resident_mb == 0:
            return
        if not self.storage:
            raise ConfigError("service.max_resident_mb > 0 needs service.storage: an evicted "
                              "map is reopened from its files")
        if self.bootstrap_from_peers:
            raise ConfigError("service.max_resident_mb > 0 cannot be combined with "
                              "service.bootstrap_from_peers (the bootstrap copies every map "
                              "into memory at start)")


def _check_servable(method: str) -> None:
    """A method whose place finder needs ground truth (``gt``, registered by the evaluation
    tools when they are loaded in the same process) is never served."""
    from ..algorithms.place.base import PLACE_FINDERS

    try:
        steps = parse_method(method).steps
    except ConfigError:
        return  # reported, with the options, when the service builds its methods at start
    for place in (step.place for step in steps if step.place is not None):
        if place in PLACE_FINDERS and PLACE_FINDERS[place].evaluation_only:
            raise ConfigError(f"service.methods: {method!r} uses the place finder {place!r}, "
                              f"which needs ground truth and is for evaluation only")


#: The ``[mapping]`` keys a ``[maps.NAME]`` table may set for that map alone.
MAP_MAPPING_KEYS = ("calibration_focal_sigma_rel", "calibration_radial_sigma_px")


@dataclass(frozen=True)
class MapConf:
    """A map served from the start (``[maps.NAME]``). It may state its own camera's
    calibration accuracy (the ``[mapping]`` keys of the same name; unset: the service-wide
    value): a service holding maps from a calibrated camera and a rough one states, for each
    map's answers, the covariance its own calibration warrants. No answer changes."""

    calibration_focal_sigma_rel: float | None = None
    calibration_radial_sigma_px: float | None = None

    def __post_init__(self) -> None:
        for name in MAP_MAPPING_KEYS:
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name}: expected a finite number >= 0 (1 sigma; 0: exact), "
                                  f"got {value!r}")

    def mapping_overrides(self) -> dict[str, float]:
        """The ``[mapping]`` keys this map sets for itself."""
        return {k: v for k in MAP_MAPPING_KEYS if (v := getattr(self, k)) is not None}


@dataclass(frozen=True)
class ServiceConf:
    """The whole configuration of ``reloc serve``."""

    zenoh: ZenohConf = field(default_factory=ZenohConf)
    service: ServiceSection = field(default_factory=ServiceSection)
    limits: LimitsConf = field(default_factory=LimitsConf)
    quotas: QuotasConf = field(default_factory=QuotasConf)
    maps: Mapping[str, MapConf] = field(default_factory=lambda: MappingProxyType({}))
    #: Plugin name -> options (passed to the engine, checked by each plugin's Conf).
    options: Mapping[str, Mapping[str, Any]] = field(
        default_factory=lambda: MappingProxyType({}))
    #: Map-building options (the engine's MappingConf).
    mapping: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    ros2: Ros2Conf = field(default_factory=Ros2Conf)

    @property
    def instance(self) -> str:
        """The instance name: configured, or ``<hostname>-<pid>`` made a valid key chunk."""
        if self.service.instance:
            return self.service.instance
        host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())
        return f"{host or 'reloc'}-{os.getpid()}"

    def mapping_for(self, name: str) -> Mapping[str, Any]:
        """The map-building options of map ``name``: ``[mapping]`` with what its
        ``[maps.NAME]`` table sets on top."""
        map_conf = self.maps.get(name)
        overrides = {} if map_conf is None else map_conf.mapping_overrides()
        return MappingProxyType({**self.mapping, **overrides})

    @property
    def storage_path(self) -> Path | None:
        """The storage directory, or None when maps are kept in memory only."""
        if not self.service.storage:
            return None
        return Path(os.path.expanduser(self.service.storage)).absolute()


_SECTIONS: dict[str, type] = {"zenoh": ZenohConf, "service": ServiceSection,
                              "limits": LimitsConf, "quotas": QuotasConf, "ros2": Ros2Conf}
_TOP_KEYS = sorted([*_SECTIONS, "maps", "options", "mapping"])


def parse_config(data: Mapping[str, Any], *, source: str = "config") -> ServiceConf:
    """Build a :class:`ServiceConf` from a parsed TOML document; ConfigError names the first
    unknown section or key and lists the allowed ones."""
    unknown = sorted(set(data) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(f"{source}: unknown section(s) {unknown}; expected some of {_TOP_KEYS}")
    sections: dict[str, Any] = {
        name: make_conf(cls, _table(data.get(name, {}), f"{source}: [{name}]"),
                        owner=f"{source}: [{name}]")
        for name, cls in _SECTIONS.items()}
    maps = {name: _map_conf(t, f"{source}: [maps.{name}]")
            for name, t in _table(data.get("maps", {}), f"{source}: [maps]").items()}
    _check_names(None, None, maps=list(maps))
    options = {name: MappingProxyType(dict(_table(t, f"{source}: [options.{name}]")))
               for name, t in _table(data.get("options", {}), f"{source}: [options]").items()}
    mapping = dict(_table(data.get("mapping", {}), f"{source}: [mapping]"))
    if sections["service"].max_resident_mb > 0 and sections["ros2"].enabled:
        raise ConfigError(f"{source}: service.max_resident_mb > 0 cannot be combined with "
                          "[ros2] enabled (the bridge serves the maps loaded at start; set "
                          "max_resident_mb = 0)")
    return ServiceConf(zenoh=sections["zenoh"], service=sections["service"],
                       limits=sections["limits"], quotas=sections["quotas"],
                       maps=MappingProxyType(maps),
                       options=MappingProxyType(options), mapping=MappingProxyType(mapping),
                       ros2=sections["ros2"])


def load_config(path: str | Path | None = None) -> ServiceConf:
    """Read the TOML file ``path``; None gives the embedded default (``config/default.toml``
    holds the same values)."""
    if path is None:
        return ServiceConf()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror or exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    conf = parse_config(data, source=str(path))
    zc = conf.zenoh
    if zc.config_file and not Path(zc.config_file).is_absolute():
        # A Zenoh config file named in a TOML file is relative to that file.
        zc = dataclasses.replace(zc, config_file=str(path.parent / zc.config_file))
        conf = dataclasses.replace(conf, zenoh=zc)
    return conf


def with_overrides(conf: ServiceConf, *, mode: str | None = None,
                   listen: Sequence[str] | None = None, connect: Sequence[str] | None = None,
                   storage: str | None = None, workers: int | None = None,
                   instance: str | None = None, prefix: str | None = None,
                   worker_mode: str | None = None) -> ServiceConf:
    """``conf`` with the explicitly given command-line values replacing the file's."""
    z: dict[str, Any] = {k: v for k, v in (("mode", mode), ("listen", listen),
                                           ("connect", connect)) if v is not None}
    s: dict[str, Any] = {k: v for k, v in (("storage", storage), ("workers", workers),
                                           ("instance", instance), ("prefix", prefix),
                                           ("worker_mode", worker_mode))
                         if v is not None}
    for key in ("listen", "connect"):
        if key in z:
            z[key] = tuple(z[key])
    return dataclasses.replace(conf, zenoh=dataclasses.replace(conf.zenoh, **z),
                               service=dataclasses.replace(conf.service, **s))


def _map_conf(table: Any, where: str) -> MapConf:
    """A ``[maps.NAME]`` table; a ConfigError names the map's table and the key."""
    try:
        return make_conf(MapConf, _table(table, where), owner=where)
    except ConfigError as exc:
        if str(exc).startswith(where):
            raise
        raise ConfigError(f"{where}.{exc}") from None


def _table(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a table, got {type(value).__name__} {value!r}")
    return value


def _str_tuple(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ConfigError(f"{where}: expected a list of strings, got {value!r}")
    if not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{where}: expected non-empty strings, got {list(value)!r}")
    return tuple(value)


def _check_names(prefix: str | None, instance: str | None, *, maps: Sequence[str] = ()) -> None:
    """Prefix, instance and map names must be valid key chunks (protocol.check_name)."""
    from reloc_client import protocol as wire

    try:
        if prefix is not None:
            wire.check_prefix(prefix)
        if instance:
            wire.check_name(instance, "service.instance")
        for name in maps:
            wire.check_name(name, f"[maps.{name}]")
    except wire.ProtocolError as exc:
        raise ConfigError(exc.message) from None
