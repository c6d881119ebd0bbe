"""Input cases: garbage, deep nesting, image bombs, oversized puts, wildcard gets, long
map names; each sent to the shared input service, refused with its named error code.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np

from ....core.cameras import PinholeCamera
from .harness import (
    CAMERA_ID,
    MAP_NAME,
    REPLY_TIMEOUT_S,
    Arena,
    AttackService,
    Attempt,
    EventLog,
    broke,
    clean,
    compare_held,
    heard_rejections,
    held_ids,
    judge_code,
    put_acknowledged,
    put_block,
    query_code,
    register,
)

# -- input -------------------------------------------------------------------------------------

@register("garbage-new-maps", "input",
          "20 puts of garbage msgpack (keyframe and camera) to new map names: each rejected "
          "BAD_MSGPACK, no map served or written")
def garbage_new_maps(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire

    service = arena.input_service()
    names = [f"junk{i}" for i in range(20)]
    with service.client() as c:
        log = EventLog(c.session)
        try:
            if not heard_rejections(c.session, log, "junkprobe"):
                return [broke("no keyframe_rejected event for garbage on a new map name")]
            for i, name in enumerate(names):
                key = (wire.keys.camera("reloc", name, "c0") if i % 2
                       else wire.keys.keyframe("reloc", name, 1))
                put_block(c.session, key, b"\xc1garbage" * (i + 1))
            out = []
            served = {m for _, m in c.maps()}
            for i, name in enumerate(names):
                kind = "camera_rejected" if i % 2 else "keyframe_rejected"
                event = log.wait(name, kind)
                code = None if event is None else str(event.fields.get("code"))
                if name in served or any(p.name.startswith(name) for p in
                                         service.storage.iterdir()):
                    out.append(broke(f"{name}: a map was created by garbage"))
                else:
                    out.append(judge_code(f"{name} {kind}", code, ["BAD_MSGPACK"]))
            return out
        finally:
            log.close()


def nested(depth: int, *, maps: bool = False) -> bytes:
    """A msgpack value nested ``depth`` deep: one-element arrays (or one-key maps) around nil."""
    return (b"\x81\xa1a" if maps else b"\x91") * depth + b"\xc0"


def request_with(field_name: str, value: bytes, others: Mapping[str, Any] | None = None
                 ) -> bytes:
    """A msgpack request map ``{"v": 1, **others, field_name: <value>}`` with ``value`` already
    encoded (so that only ``field_name`` is wrong)."""
    fields = {"v": 1, **(others or {})}
    fields.pop(field_name, None)
    head = b"\xde" + (len(fields) + 1).to_bytes(2, "big")   # map 16: any field count
    body = b"".join(msgpack.packb(k) + msgpack.packb(v, use_bin_type=True)
                    for k, v in fields.items())
    return head + body + msgpack.packb(field_name) + value


def deep_requests(arena: Arena, depths: Sequence[int]) -> list[Attempt]:
    """``relocalize.image``, ``train.method`` and a keyframe put's ``image`` nested ``depths``
    deep (arrays and maps), every other field valid: each refused with a named code, never
    INTERNAL."""
    from reloc_client import protocol as wire
    from reloc_client.client import keyframe_put_bytes, to_wire_image

    expected = [c.value for c in wire.ErrorCode if c is not wire.ErrorCode.INTERNAL]
    scene = arena.scene
    query = msgpack.unpackb(wire.RelocalizeRequest(
        image=to_wire_image(scene.image(0)), camera_id=CAMERA_ID).encode())
    put = msgpack.unpackb(keyframe_put_bytes(0, scene.image(0), scene.pose(0),
                                             camera_id=CAMERA_ID))
    service = arena.input_service()
    out = []
    with service.client() as c:
        for depth in depths:
            for maps in (False, True):
                shape = "maps" if maps else "arrays"
                for key, name, others in (
                        (wire.keys.relocalize("reloc", MAP_NAME), "relocalize.image", query),
                        (wire.keys.train("reloc", MAP_NAME), "train.method", {})):
                    raw = request_with(name.split(".")[1], nested(depth, maps=maps), others)
                    code = query_code(c.session, key, raw)
                    out.append(judge_code(f"{name} {shape} {depth} deep", code, expected))
        log = EventLog(c.session)
        try:
            heard_rejections(c.session, log, "deepprobe")
            for n, depth in enumerate(depths):
                kf_id = 900 + n
                put_block(c.session, wire.keys.keyframe("reloc", MAP_NAME, kf_id),
                          request_with("image", nested(depth), {**put, "id": kf_id}))
                event = log.wait(MAP_NAME, "keyframe_rejected", id=kf_id)
                code = None if event is None else str(event.fields.get("code"))
                out.append(judge_code(f"keyframe.image arrays {depth} deep", code, expected))
        finally:
            log.close()
    return out


@register("msgpack-nested-1e5", "input",
          "relocalize.image, train.method and a keyframe's image nested 100,000 deep (arrays, "
          "maps): a named error code, not INTERNAL")
def msgpack_nested_1e5(arena: Arena) -> list[Attempt]:
    return deep_requests(arena, [100_000])


@register("arrays-1000-deep", "input",
          "relocalize.image, train.method and a keyframe's image nested 500 and 1,000 deep "
          "(within msgpack's own limit): a named error code, not INTERNAL")
def arrays_1000_deep(arena: Arena) -> list[Attempt]:
    return deep_requests(arena, [500, 1000])


def flat_image(width: int, height: int, ext: str) -> bytes:
    """A flat grey image encoded as ``ext``: few bytes that declare ``width`` x ``height``."""
    ok, buf = cv2.imencode(ext, np.full((height, width), 128, np.uint8))
    assert ok
    return buf.tobytes()


@register("image-bomb", "input",
          "relocalize with a PNG / JPEG of a few KB declaring 4096x4096 and an inline 4096x4096 "
          "camera: IMAGE_TOO_LARGE, service memory barely rises")
def image_bomb(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire
    from reloc_client.client import ServiceError

    service = arena.input_service()
    big = PinholeCamera(width=4096, height=4096, fx=3000.0, fy=3000.0, cx=2048.0, cy=2048.0)
    out = []
    with service.client() as c:
        for ext in (".png", ".jpg"):
            data = flat_image(4096, 4096, ext)
            before = peak_rss_reset(service.pid)
            try:
                c.relocalize(wire.WireImage.from_bytes(data), camera=big)
                code: str | None = "OK"
            except ServiceError as exc:
                code = exc.code.value
            except TimeoutError:
                code = None
            rise = peak_rss_mb(service.pid) - before
            attempt = judge_code(f"{ext[1:]} of {len(data) // 1024} KB declaring 4096x4096",
                                 code, ["IMAGE_TOO_LARGE"])
            if rise > 300:
                attempt = broke(f"{attempt.detail}, but peak memory +{rise:.0f} MB")
            out.append(Attempt(attempt.clean, f"{attempt.detail} (peak +{rise:.0f} MB)"))
    return out


def peak_rss_reset(pid: int) -> float:
    """Reset process ``pid``'s peak resident memory; its resident memory now, in MB."""
    with contextlib.suppress(OSError):
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    return _status_mb(pid, "VmRSS")


def peak_rss_mb(pid: int) -> float:
    return _status_mb(pid, "VmHWM")


def _status_mb(pid: int, key: str) -> float:
    with contextlib.suppress(OSError, ValueError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


@register("oversized-put", "input",
          "a keyframe put and a relocalize query one byte above the payload limit: "
          "PAYLOAD_TOO_LARGE")
def oversized_put(arena: Arena) -> list[Attempt]:
    from reloc_client import protocol as wire

    service = arena.input_service()
    too_big = b"\x00" * (wire.DEFAULT_LIMITS.max_payload_bytes + 1)
    with service.client() as c:
        log = EventLog(c.session)
        try:
            heard_rejections(c.session, log, "bigprobe")
            put_block(c.session, wire.keys.keyframe("reloc", MAP_NAME, 77), too_big)
            event = log.wait(MAP_NAME, "keyframe_rejected", id=77)
            put_code = None if event is None else str(event.fields.get("code"))
        finally:
            log.close()
        get_code = query_code(c.session, wire.keys.relocalize("reloc", MAP_NAME), too_big)
    return [judge_code(f"put of {len(too_big)} bytes", put_code, ["PAYLOAD_TOO_LARGE"]),
            judge_code(f"relocalize of {len(too_big)} bytes", get_code, ["PAYLOAD_TOO_LARGE"])]


@register("get-everything", "input",
          "get reloc/** (an empty payload to every queryable): no INTERNAL, no training "
          "started, every reply an answer or a named refusal")
def get_everything(arena: Arena) -> list[Attempt]:
    import zenoh
    from reloc_client import protocol as wire

    service = arena.input_service()
    with service.client() as c:
        replies = list(c.session.get("reloc/**", timeout=REPLY_TIMEOUT_S,
                                     consolidation=zenoh.ConsolidationMode.NONE))
        codes = [wire.ErrorReply.decode(r.err.payload.to_bytes()).code.value
                 for r in replies if r.err is not None]
        training = c.status().training
    detail = (f"{len(replies)} replies, {len(codes)} refusals "
              f"({', '.join(sorted(set(codes))) or 'none'})")
    if not replies:
        return [broke("get reloc/**: no reply at all")]
    if "INTERNAL" in codes:
        return [broke(f"get reloc/**: INTERNAL among {detail}")]
    if training:
        return [broke(f"get reloc/**: an empty get started training; {detail}")]
    return [clean(f"get reloc/**: {detail}")]


#: Names the protocol accepts whose percent-encoded form is beyond NAME_MAX (255 bytes).
LONG_NAMES = {"30 Hangul": "\ud55c" * 30, "64 emoji": "\U0001f681" * 64, "128 '%'": "%" * 128}


@register("long-map-names", "input",
          "maps named with 30 Hangul, 64 emoji or 128 '%' characters: created by their first "
          "put and restored with their keyframes after a restart")
def long_map_names(arena: Arena) -> list[Attempt]:
    from reloc_client.client import ServiceError

    service = AttackService(arena.case_folder("long-map-names"))
    service.start()
    out: dict[str, Attempt] = {}
    try:
        for label, name in LONG_NAMES.items():
            try:
                with service.client(name) as c:
                    put_acknowledged(c, arena.scene, range(2))
            except (ServiceError, TimeoutError) as exc:
                out[label] = broke(f"{label}: put refused: {exc}")
        service.restart("sigterm")
        for label, name in LONG_NAMES.items():
            if label in out:
                continue
            try:
                with service.client(name) as c:
                    out[label] = compare_held(f"{label} after a restart",
                                              held_ids(c), {0, 1})
            except (ServiceError, TimeoutError) as exc:
                out[label] = broke(f"{label} after a restart: {exc}")
    finally:
        service.stop("sigterm")
    return list(out.values())


