"""Quota cases: maps per service, keyframes per map, bytes per map; each refused with
QUOTA_EXCEEDED and nothing acknowledged lost across kill -9.
"""

from __future__ import annotations

from typing import Any

from .harness import (
    CAMERA_ID,
    Arena,
    AttackService,
    Attempt,
    TinyScene,
    broke,
    compare_held,
    held_ids,
    judge_code,
    put_acknowledged,
    register,
)

# -- quota ---------------------------------------------------------------------------------------
# Each quota ([quotas] of the service configuration) set low on a service of its own.

def put_code(client: Any, scene: TinyScene, kf_id: int) -> str | None:
    """Put keyframe ``kf_id`` and wait: ``"OK"`` once journaled, the refusal's error code, or
    None when neither came within :data:`REPLY_TIMEOUT_S`."""
    from reloc_client.client import NoReplyError, ServiceError

    try:
        client.add_keyframe(kf_id, scene.image(kf_id), scene.pose(kf_id), camera_id=CAMERA_ID,
                            wait=True)
    except ServiceError as exc:
        return exc.code.value
    except NoReplyError:
        return None
    return "OK"


def put_new_map_code(service: AttackService, scene: TinyScene, name: str) -> str | None:
    """The first put to map ``name`` (camera inline, so it may create the map)."""
    from reloc_client.client import NoReplyError, ServiceError

    with service.client(name) as c:
        try:
            c.add_keyframe(0, scene.image(0), scene.pose(0), camera=scene.camera, wait=True)
        except ServiceError as exc:
            return exc.code.value
        except NoReplyError:
            return None
    return "OK"


@register("quota-maps", "quota",
          "max_maps = 2 (lab and one more): a put creating a second map is acknowledged, "
          "puts creating a third, fourth and fifth are refused QUOTA_EXCEEDED and create "
          "nothing, also after a restart")
def quota_maps(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("quota-maps"), quotas={"max_maps": 2}).start()
    out = []
    try:
        out.append(judge_code("a put creating map 'second'",
                              put_new_map_code(service, arena.scene, "second"), ["OK"]))
        for name in ("third", "fourth", "fifth"):
            attempt = judge_code(f"a put creating map {name!r}",
                                 put_new_map_code(service, arena.scene, name),
                                 ["QUOTA_EXCEEDED"])
            if (service.storage / name).exists():
                attempt = broke(f"{attempt.detail}, yet {name!r} was written to the storage")
            out.append(attempt)
        service.restart("sigterm")
        with service.client("second") as c:
            kept = compare_held("'second' after a restart", held_ids(c), {0})
        again = judge_code("after a restart, a put creating 'sixth'",
                           put_new_map_code(service, arena.scene, "sixth"), ["QUOTA_EXCEEDED"])
        out.append(Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}"))
    finally:
        service.stop("sigterm")
    return out


@register("quota-keyframes", "quota",
          "max_keyframes_per_map = 4: three puts beyond refused QUOTA_EXCEEDED; a replacement "
          "is not one more; a delete frees one; after kill -9 the count is the same")
def quota_keyframes(arena: Arena) -> list[Attempt]:
    scene = arena.scene
    service = AttackService(arena.case_folder("quota-keyframes"),
                            quotas={"max_keyframes_per_map": 4}).start()
    out = []
    try:
        with service.client() as c:
            put_acknowledged(c, scene, range(4))
            for kf_id in (4, 5, 6):
                out.append(judge_code(f"keyframe {kf_id} beyond the 4 allowed", put_code(c, scene, kf_id),
                                      ["QUOTA_EXCEEDED"]))
            out.append(judge_code("keyframe 0 replaced", put_code(c, scene, 0), ["OK"]))
            c.remove_keyframe(1, wait=True)
            out.append(judge_code("keyframe 4 after deleting 1", put_code(c, scene, 4), ["OK"]))
        service.restart("kill9")
        with service.client() as c:
            kept = compare_held("after kill -9", held_ids(c), {0, 2, 3, 4})
            again = judge_code("keyframe 5 after it", put_code(c, scene, 5), ["QUOTA_EXCEEDED"])
        out.append(Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}"))
    finally:
        service.stop("sigterm")
    return out


#: The byte quota of the quota-bytes case: a few of the tiny keyframes.
MAP_BYTES = 150_000


@register("quota-bytes", "quota",
          f"max_map_bytes = {MAP_BYTES}: keyframes put until one is refused QUOTA_EXCEEDED "
          "(the count within the limit), then after kill -9 every acknowledged one held and "
          "the next still refused")
def quota_bytes(arena: Arena) -> list[Attempt]:
    scene = arena.scene
    service = AttackService(arena.case_folder("quota-bytes"),
                            quotas={"max_map_bytes": MAP_BYTES}).start()
    acked: list[int] = []
    code: str | None = "OK"
    try:
        with service.client() as c:
            c.set_camera(CAMERA_ID, scene.camera, wait=True)
            while code == "OK" and len(acked) < 30:
                code = put_code(c, scene, len(acked))
                if code == "OK":
                    acked.append(len(acked))
            counted = c.status().counters.get("quota_bytes")
        refused = judge_code(f"keyframe {len(acked)} after {len(acked)} acknowledged "
                             f"({counted} bytes counted)", code, ["QUOTA_EXCEEDED"])
        if refused.clean and not (isinstance(counted, int) and counted <= MAP_BYTES):
            refused = broke(f"{refused.detail}, but {counted} bytes counted: over the limit")
        service.restart("kill9")
        with service.client() as c:
            kept = compare_held("after kill -9", held_ids(c), set(acked))
            again = judge_code("the next put", put_code(c, scene, len(acked)),
                               ["QUOTA_EXCEEDED"])
    finally:
        service.stop("sigterm")
    return [refused, Attempt(kept.clean and again.clean, f"{kept.detail}; {again.detail}")]


