"""Names and Zenoh key expressions: check_name, check_prefix and the ``keys`` namespace."""

from __future__ import annotations

from typing import Any

from .checks import ErrorCode, _fail, _int

DEFAULT_PREFIX = "reloc"
MAX_NAME_LEN = 128
_MAX_KEYFRAME_ID = 2**63 - 1
_FORBIDDEN_NAME_CHARS = frozenset("/*$#?")


def check_name(name: Any, what: str = "map name") -> str:
    """Return ``name`` if it can be one Zenoh key chunk (map, camera or instance name):
    non-empty, at most 128 characters, no ``/ * $ # ?``, no whitespace or control
    characters, not starting with ``@``; else raise ProtocolError(BAD_NAME)."""
    if not isinstance(name, str):
        raise _fail(ErrorCode.BAD_NAME, what, "a string", name)
    problem = (
        "a non-empty name" if not name else
        f"at most {MAX_NAME_LEN} characters" if len(name) > MAX_NAME_LEN else
        "no '/', '*', '$', '#' or '?'" if _FORBIDDEN_NAME_CHARS & set(name) else
        "no whitespace or control characters" if any(c.isspace() or not c.isprintable()
                                                      for c in name) else
        "a name not starting with '@' (reserved by Zenoh)" if name.startswith("@") else "")
    if problem:
        raise _fail(ErrorCode.BAD_NAME, what, problem, name)
    return name


def check_prefix(prefix: Any) -> str:
    """Return ``prefix`` if it is one or more valid name chunks joined by ``/``."""
    if not isinstance(prefix, str) or not prefix:
        raise _fail(ErrorCode.BAD_NAME, "prefix", "a non-empty string such as 'reloc'", prefix)
    for chunk in prefix.split("/"):
        check_name(chunk, f"prefix chunk of {prefix!r}")
    return prefix


def _check_kf_id(kf_id: Any, path: str = "keyframe id") -> int:
    return _int(kf_id, path, lo=0, hi=_MAX_KEYFRAME_ID)


class keys:  # noqa: N801 - a namespace used as ``keys.relocalize(prefix, map)``
    """Zenoh key expressions of one map (``prefix`` may have several chunks, default
    ``"reloc"``). Every function validates its names (ProtocolError BAD_NAME)."""

    @staticmethod
    def _base(prefix: str, map_name: str) -> str:
        return f"{check_prefix(prefix)}/{check_name(map_name)}"

    @staticmethod
    def keyframe(prefix: str, map_name: str, kf_id: int) -> str:
        """``<prefix>/<map>/keyframes/<id>``: put adds or replaces, delete removes, get reads."""
        return f"{keys._base(prefix, map_name)}/keyframes/{_check_kf_id(kf_id)}"

    @staticmethod
    def keyframes(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/keyframes/**``: get returns every stored keyframe."""
        return f"{keys._base(prefix, map_name)}/keyframes/**"

    @staticmethod
    def camera(prefix: str, map_name: str, camera_id: str) -> str:
        """``<prefix>/<map>/cameras/<id>``: put adds or replaces, get reads."""
        return f"{keys._base(prefix, map_name)}/cameras/{check_name(camera_id, 'camera id')}"

    @staticmethod
    def cameras(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/cameras/**``: get returns every camera."""
        return f"{keys._base(prefix, map_name)}/cameras/**"

    @staticmethod
    def relocalize(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/relocalize``: queryable, RelocalizeRequest -> RelocalizeReply."""
        return f"{keys._base(prefix, map_name)}/relocalize"

    @staticmethod
    def train(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/train``: queryable, TrainRequest -> TrainReply (at once)."""
        return f"{keys._base(prefix, map_name)}/train"

    @staticmethod
    def events(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/events``: the service publishes Event messages here."""
        return f"{keys._base(prefix, map_name)}/events"

    @staticmethod
    def status(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/status``: queryable, no payload -> StatusReply."""
        return f"{keys._base(prefix, map_name)}/status"

    @staticmethod
    def liveliness(prefix: str, instance: str, map_name: str) -> str:
        """``<prefix>/@live/<instance>/<map>``: the liveliness token of a serving instance."""
        return (f"{check_prefix(prefix)}/@live/{check_name(instance, 'instance name')}/"
                f"{check_name(map_name)}")

    @staticmethod
    def liveliness_all(prefix: str) -> str:
        """``<prefix>/@live/*/*``: liveliness get of every serving (instance, map)."""
        return f"{check_prefix(prefix)}/@live/*/*"

    @staticmethod
    def resident(prefix: str, instance: str, map_name: str) -> str:
        """``<prefix>/@live/<instance>/<map>/resident``: held while the instance has the map
        in memory (a query answers without a load from storage). One chunk below the serving
        token, so ``@live/*/*`` discovery and access rules on ``@live/**`` cover both."""
        return f"{keys.liveliness(prefix, instance, map_name)}/resident"

    @staticmethod
    def resident_all(prefix: str) -> str:
        """``<prefix>/@live/*/*/resident``: liveliness get of every resident (instance, map)."""
        return f"{check_prefix(prefix)}/@live/*/*/resident"

    @staticmethod
    def parse_resident(prefix: str, key: str) -> tuple[str, str]:
        """(instance, map) of a ``<prefix>/@live/<instance>/<map>/resident`` key."""
        if not key.endswith("/resident"):
            raise _fail(ErrorCode.BAD_NAME, "residency key",
                        f"'{check_prefix(prefix)}/@live/<instance>/<map>/resident'", key)
        return keys.parse_liveliness(prefix, key[:-len("/resident")])

    @staticmethod
    def parse_keyframe(prefix: str, key: str) -> tuple[str, int]:
        """(map, keyframe id) of a concrete ``<prefix>/<map>/keyframes/<id>`` key."""
        map_name, leaf = keys._parse(prefix, key, "keyframes")
        if not leaf.isdigit() or (leaf != "0" and leaf.startswith("0")):
            raise _fail(ErrorCode.BAD_NAME, "keyframe key", "a decimal keyframe id", key)
        return map_name, _check_kf_id(int(leaf), f"keyframe id in {key!r}")

    @staticmethod
    def parse_camera(prefix: str, key: str) -> tuple[str, str]:
        """(map, camera id) of a concrete ``<prefix>/<map>/cameras/<id>`` key."""
        return keys._parse(prefix, key, "cameras")

    @staticmethod
    def parse_liveliness(prefix: str, key: str) -> tuple[str, str]:
        """(instance, map) of a ``<prefix>/@live/<instance>/<map>`` key."""
        head = f"{check_prefix(prefix)}/@live/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 2:
            raise _fail(ErrorCode.BAD_NAME, "liveliness key", f"'{head}<instance>/<map>'", key)
        return check_name(parts[0], "instance name"), check_name(parts[1])

    @staticmethod
    def _parse(prefix: str, key: str, collection: str) -> tuple[str, str]:
        head = f"{check_prefix(prefix)}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or parts[1] != collection:
            raise _fail(ErrorCode.BAD_NAME, f"{collection} key",
                        f"'{head}<map>/{collection}/<id>'", key)
        what = "camera id" if collection == "cameras" else "keyframe id"
        return check_name(parts[0]), check_name(parts[2], what)
