"""The thin Zenoh layer: session configuration, declarations per served map, and callbacks that
only copy the payload and hand it to a dispatcher (the work runs in worker threads).

Key expressions (``reloc_client.protocol.keys``), for each served map ``<map>``:
``<prefix>/<map>/{relocalize,train,status,export}`` queryables, ``keyframes/**`` and ``cameras/**``
queryables (copying a map), subscribers on ``<prefix>/*/keyframes/*`` and
``<prefix>/*/cameras/*`` (puts and deletes, any map: the first keyframe may create one), a
publisher on ``<prefix>/<map>/events`` and a liveliness token ``<prefix>/@live/<instance>/<map>``.
"""

from __future__ import annotations

import enum
import json
import logging
import queue
import re
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Protocol

import zenoh
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode
from reloc_client.protocol.transfer import export_key

from ..core.errors import ConfigError
from .config import ZenohConf
from .memory import Trimmer

log = logging.getLogger(__name__)


def zenoh_config(conf: ZenohConf) -> zenoh.Config:
    """A Zenoh config: ``conf.config_file`` (JSON5) if given, then mode, endpoints and
    multicast scouting from ``conf`` on top."""
    if conf.config_file:
        path = Path(conf.config_file)
        if not path.is_file():
            raise ConfigError(f"zenoh.config_file: no such file {path}")
        try:
            zc = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises its own error type for bad JSON5
            raise ConfigError(f"zenoh.config_file {path}: {exc}") from exc
    else:
        zc = zenoh.Config()
    _insert(zc, "mode", conf.mode)
    if conf.listen:
        _insert(zc, "listen/endpoints", list(conf.listen))
    if conf.connect:
        _insert(zc, "connect/endpoints", list(conf.connect))
    _insert(zc, "scouting/multicast/enabled", conf.multicast_scouting)
    return zc


def _insert(zc: zenoh.Config, key: str, value: object) -> None:
    try:
        zc.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ConfigError(f"zenoh config {key} = {value!r}: {exc}") from exc


class QueryKind(enum.Enum):
    """The queryables of one map."""

    RELOCALIZE = "relocalize"
    TRAIN = "train"
    STATUS = "status"
    KEYFRAMES = "keyframes"
    CAMERAS = "cameras"
    EXPORT = "export"
    IMPORT = "import"


class PendingQuery:
    """A Zenoh query whose answer is produced later in another thread. Replies go on
    ``reply_key`` (the queryable's own key) unless told otherwise; :meth:`finish` (or the
    first error reply) ends the query exactly once."""

    __slots__ = ("_query", "payload", "parameters", "key_expr", "reply_key", "_lock", "_done")

    def __init__(self, query: zenoh.Query, reply_key: str) -> None:
        self._query = query
        self.payload = query.payload.to_bytes() if query.payload is not None else b""
        self.parameters: dict[str, str] = (
            {k: v for k, v in query.parameters}  # type: ignore[attr-defined]
            if query.parameters is not None else {})
        self.key_expr = str(query.key_expr)
        self.reply_key = reply_key
        self._lock = threading.Lock()
        self._done = False

    def wants(self, key: str) -> bool:
        """Whether a reply on ``key`` answers this query (its key expression intersects)."""
        return zenoh.KeyExpr(self.key_expr).intersects(zenoh.KeyExpr(key))

    def reply(self, payload: bytes, key: str | None = None) -> None:
        with self._lock:
            if not self._done:
                self._query.reply(key or self.reply_key, payload)

    def reply_err(self, payload: bytes) -> None:
        with self._lock:
            if not self._done:
                self._query.reply_err(payload)
        self.finish()

    def finish(self) -> None:
        """Send the final reply marker (the client's get returns)."""
        with self._lock:
            if not self._done:
                self._done = True
                self._query.drop()


class Dispatcher(Protocol):
    """What the Zenoh callbacks call; every method must return quickly. ``limits`` bounds a
    payload before it is copied out of Zenoh."""

    limits: wire.Limits

    def on_keyframe_sample(self, map_name: str, kf_id: int, payload: bytes | None) -> None:
        """A put (payload) or delete (None) on ``<prefix>/<map>/keyframes/<id>``."""

    def on_camera_sample(self, map_name: str, camera_id: str, payload: bytes | None) -> None:
        """A put or delete on ``<prefix>/<map>/cameras/<id>``."""

    def on_bad_key(self, key: str, problem: str, code: ErrorCode = ErrorCode.BAD_NAME) -> None:
        """A sample refused before it is parsed: its key does not parse (bad map name or id,
        BAD_NAME) or its payload is above the limit (PAYLOAD_TOO_LARGE)."""

    def on_query(self, map_name: str, kind: QueryKind, query: PendingQuery) -> None:
        """A query on one of the map's queryables."""


class ZenohLayer:
    """Declarations on ``session`` under ``prefix``; :meth:`serve_map` adds a map's."""

    def __init__(self, session: zenoh.Session, prefix: str, instance: str,
                 dispatcher: Dispatcher) -> None:
        self.session = session
        self.prefix = wire.check_prefix(prefix)
        self.instance = wire.check_name(instance, "instance name")
        self.dispatcher = dispatcher
        self._maps: dict[str, list[object]] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._tokens: dict[str, zenoh.LivelinessToken] = {}
        self._resident: dict[str, zenoh.LivelinessToken] = {}
        self._imports: zenoh.Queryable | None = None
        self._lock = threading.Lock()
        #: Gives the heap back after an oversized payload is refused (:mod:`.memory`).
        self.trimmer = Trimmer()
        #: Every map's queries, handed to one thread (not one thread per queryable).
        self._inbox = QueryInbox()
        # One subscriber for keyframes and cameras: samples of two subscribers may be delivered
        # out of order, and a keyframe must not overtake the camera it was sent after.
        self._subscribers = [session.declare_subscriber(f"{self.prefix}/*/*/*", self._on_put)]

    # -- per map ---------------------------------------------------------------------------
    def serve_map(self, map_name: str) -> None:
        """Declare ``map_name``'s queryables, events publisher and liveliness token."""
        with self._lock:
            if map_name in self._maps:
                return
            k = wire.keys
            entities: list[object] = [
                self._queryable(k.relocalize(self.prefix, map_name), map_name,
                                QueryKind.RELOCALIZE),
                self._queryable(k.train(self.prefix, map_name), map_name, QueryKind.TRAIN),
                self._queryable(k.status(self.prefix, map_name), map_name, QueryKind.STATUS),
                self._queryable(k.keyframes(self.prefix, map_name), map_name,
                                QueryKind.KEYFRAMES),
                self._queryable(k.cameras(self.prefix, map_name), map_name, QueryKind.CAMERAS),
                self._queryable(export_key(self.prefix, map_name), map_name, QueryKind.EXPORT)]
            self._publishers[map_name] = self.session.declare_publisher(
                k.events(self.prefix, map_name))
            entities.append(self._publishers[map_name])
            self._maps[map_name] = entities
            # The token last: a client that sees it can use every key at once.
            self._tokens[map_name] = self.session.liveliness().declare_token(
                k.liveliness(self.prefix, self.instance, map_name))

    def set_resident(self, map_name: str, resident: bool) -> None:
        """Declare (or undeclare) the token saying ``map_name`` is in memory here; ignored
        for a map not served or once withdrawn."""
        with self._lock:
            if resident and map_name in self._tokens and map_name not in self._resident:
                self._resident[map_name] = self.session.liveliness().declare_token(
                    wire.keys.resident(self.prefix, self.instance, map_name))
                return
            token = None if resident else self._resident.pop(map_name, None)
        if token is not None:
            _undeclare(token)

    def serve_imports(self) -> None:
        """Declare ``<prefix>/*/import``: a map is imported under any valid name, served or
        not yet (the map name is the key's second chunk)."""
        dispatcher = self.dispatcher
        wildcard = f"{self.prefix}/*/import"

        def on_query(query: zenoh.Query) -> None:
            key = str(query.key_expr)
            try:
                map_name = wire.check_name(key[len(self.prefix) + 1:].split("/")[0])
                if self._payload_fits(query.payload, key, query):
                    dispatcher.on_query(map_name, QueryKind.IMPORT, PendingQuery(query, key))
            except wire.ProtocolError as exc:
                query.reply_err(wire.encode_error(exc.code, exc.message))
                query.drop()
            except Exception:  # never let an exception reach Zenoh's thread
                log.exception("query on %s failed in the dispatcher", key)

        with self._lock:
            self._imports = self.session.declare_queryable(wildcard,
                                                           self._inbox.handler(on_query))

    def served_maps(self) -> list[str]:
        with self._lock:
            return sorted(self._maps)

    def publish_event(self, map_name: str, payload: bytes) -> None:
        """Publish an encoded Event on the map's events key (ignored once closed)."""
        publisher = self._publishers.get(map_name)
        if publisher is None:
            return
        try:
            publisher.put(payload)
        except Exception as exc:  # the session may be closing
            log.debug("event on %s not published: %s", map_name, exc)

    def withdraw(self) -> None:
        """Undeclare the liveliness tokens (clients see the maps go) and the put subscribers;
        queryables stay until :meth:`close`, so queries already queued still get answers."""
        with self._lock:
            tokens, self._tokens = self._tokens, {}
            resident, self._resident = self._resident, {}
            subscribers, self._subscribers = self._subscribers, []
        for entity in [*resident.values(), *tokens.values(), *subscribers]:
            _undeclare(entity)

    def close(self) -> None:
        """Undeclare everything."""
        self.withdraw()
        self.trimmer.cancel()
        with self._lock:
            maps, self._maps = self._maps, {}
            self._publishers = {}
        for entities in maps.values():
            for entity in reversed(entities):
                _undeclare(entity)
        if self._imports is not None:
            _undeclare(self._imports)
        self._inbox.close()

    # -- callbacks (Zenoh threads: copy, parse the key, hand over) -------------------------
    def _queryable(self, key: str, map_name: str, kind: QueryKind) -> zenoh.Queryable:
        dispatcher = self.dispatcher

        def on_query(query: zenoh.Query) -> None:
            try:
                if not self._payload_fits(query.payload, key, query):
                    return
                dispatcher.on_query(map_name, kind, PendingQuery(query, key))
            except Exception:  # never let an exception reach Zenoh's thread
                log.exception("query on %s failed in the dispatcher", key)

        return self.session.declare_queryable(key, self._inbox.handler(on_query))

    def _payload_fits(self, payload: zenoh.ZBytes | None, key: str,
                      query: zenoh.Query | None = None) -> bool:
        """Whether ``payload`` is within the payload limit, checked on the ZBytes length
        before ``to_bytes()`` copies it (an oversized query gets a PAYLOAD_TOO_LARGE error
        reply, an oversized put a rejection)."""
        size = 0 if payload is None else len(payload)
        limit = self.dispatcher.limits.max_payload_bytes
        if size <= limit:
            return True
        problem = f"{key}: payload: {size} bytes; expected at most {limit}"
        self.trimmer.request()   # Zenoh's copy of it is freed soon: give the pages back
        if query is not None:
            query.reply_err(wire.encode_error(ErrorCode.PAYLOAD_TOO_LARGE, problem))
            query.drop()
        else:
            self.dispatcher.on_bad_key(key, problem, ErrorCode.PAYLOAD_TOO_LARGE)
        return False

    def _on_put(self, sample: zenoh.Sample) -> None:
        kind = str(sample.key_expr)[len(self.prefix) + 1:].split("/")[1:2]
        if kind == ["keyframes"]:
            self._on_keyframe(sample)
        elif kind == ["cameras"]:
            self._on_camera(sample)

    def _on_keyframe(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            map_name, kf_id = wire.keys.parse_keyframe(self.prefix, key)
        except wire.ProtocolError as exc:
            self.dispatcher.on_bad_key(key, exc.message)
            return
        if sample.kind == zenoh.SampleKind.PUT and not self._payload_fits(sample.payload, key):
            return
        self.dispatcher.on_keyframe_sample(map_name, kf_id, _sample_payload(sample))

    def _on_camera(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            map_name, camera_id = wire.keys.parse_camera(self.prefix, key)
        except wire.ProtocolError as exc:
            self.dispatcher.on_bad_key(key, exc.message)
            return
        if sample.kind == zenoh.SampleKind.PUT and not self._payload_fits(sample.payload, key):
            return
        self.dispatcher.on_camera_sample(map_name, camera_id, _sample_payload(sample))


class QueryInbox:
    """The queries of every map's queryables, handed by Zenoh's network thread to one thread
    of ours that checks and dispatches them (the dispatch only queues work or answers "busy",
    so one thread keeps up). zenoh-python otherwise runs each Python callback on a thread of
    its own, one per queryable: five threads per map, 1,800 for 300 maps. The callback Zenoh
    runs itself only appends to a queue (no Zenoh call, no lock held elsewhere)."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[tuple[Callable[[zenoh.Query], None], zenoh.Query] | None]
        self._queue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="zenoh-queries", daemon=True)
        self._thread.start()

    def handler(self, on_query: Callable[[zenoh.Query], None]) -> Callable[[zenoh.Query], Any]:
        """What to declare a queryable with: its queries go to ``on_query`` on our thread."""
        def enqueue(query: zenoh.Query) -> None:
            self._queue.put((on_query, query))
        return _direct_callback(enqueue)

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            on_query, query = item
            try:
                on_query(query)
            except Exception:  # on_query reports its own errors; this is the last resort
                log.exception("dispatching a query failed")

    def close(self, timeout: float = 5.0) -> None:
        """Dispatch the queries already received, then stop the thread."""
        self._queue.put(None)
        self._thread.join(timeout)


def _direct_callback(fn: Callable[[zenoh.Query], None]) -> Callable[[zenoh.Query], Any]:
    """``fn`` as a Zenoh callback run on Zenoh's own thread (``indirect=False``, an unstable
    zenoh-python option); ``fn`` itself, on a thread of its own, where that is not offered."""
    try:
        callback: Callable[[zenoh.Query], Any] = zenoh.handlers.Callback(fn, indirect=False)
        return callback
    except TypeError:
        return fn


def _sample_payload(sample: zenoh.Sample) -> bytes | None:
    if sample.kind == zenoh.SampleKind.DELETE:
        return None
    return sample.payload.to_bytes()


def _undeclare(entity: object) -> None:
    try:
        entity.undeclare()  # type: ignore[attr-defined]
    except Exception as exc:
        log.debug("undeclare failed: %s", exc)


def open_session(conf: ZenohConf) -> zenoh.Session:
    """Open a Zenoh session for ``conf``; a clear ConfigError when an endpoint is taken."""
    try:
        return zenoh.open(zenoh_config(conf))
    except ConfigError:
        raise
    except Exception as exc:
        reason = re.sub(r" at [^ ]+\.rs:\d+\.?", "", str(exc))   # drop Rust source paths
        raise ConfigError(f"cannot open the Zenoh session (mode {conf.mode}, listen "
                          f"{list(conf.listen)}, connect {list(conf.connect)}): {reason}"
                          ) from exc


def wait_closed(sessions: Iterable[zenoh.Session]) -> None:
    """Close ``sessions`` (ignoring ones already closed)."""
    for s in sessions:
        try:
            if not s.is_closed():
                s.close()
        except Exception as exc:
            log.debug("closing a session failed: %s", exc)

