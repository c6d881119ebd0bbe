"""Map directories under the service's storage: each map's directory name (percent-encoded, or
a readable prefix and a hash when that would exceed NAME_MAX), the name recorded inside it, and
the maps a storage folder holds."""

from __future__ import annotations

import hashlib
import logging
import urllib.parse
from pathlib import Path

from reloc_client import protocol as wire

from ..core.errors import StorageError
from ..core.fileio import atomic_write

log = logging.getLogger(__name__)

#: The map's name, recorded in its directory (the directory name may be a hash of it).
MAP_NAME_FILE = "map_name"
#: Longest map directory name kept percent-encoded: NAME_MAX of ext4, XFS, btrfs, tmpfs.
MAX_DIRNAME = 255
#: Characters of the percent-encoded name kept before the hash of a longer one.
HASHED_PREFIX = 120


def map_dirname(map_name: str) -> str:
    """A directory name for ``map_name``, never ``.`` or ``..``, always within NAME_MAX.

    The percent-encoded name when it fits in :data:`MAX_DIRNAME` bytes (as every map
    directory was named before, so those keep their names); otherwise a readable encoded
    prefix, ``+`` and a BLAKE2b hash of the whole name. Percent-encoding never leaves a
    ``+`` unencoded, so the two forms cannot name the same directory; the real name is
    recorded inside the directory (:func:`record_map_name`), so nothing needs to decode it."""
    quoted = _quoted(map_name)
    if len(quoted) <= MAX_DIRNAME:
        return quoted
    digest = hashlib.blake2b(map_name.encode("utf-8"), digest_size=16).hexdigest()
    return f"{_quoted(_leading_chars(map_name))}+{digest}"


def _quoted(text: str) -> str:
    """``text`` percent-encoded (every byte but letters, digits and ``_.-~``), a leading
    ``.`` too, so the result is never ``.`` or ``..``."""
    quoted = urllib.parse.quote(text, safe="")
    return "%2E" + quoted[1:] if quoted.startswith(".") else quoted


def _leading_chars(map_name: str) -> str:
    """The longest start of ``map_name``, in whole characters, whose encoded form takes at
    most :data:`HASHED_PREFIX` bytes (so the prefix of a hashed name decodes)."""
    size = 0
    for i, char in enumerate(map_name):
        size += len(urllib.parse.quote(char, safe=""))
        if size > HASHED_PREFIX:
            return map_name[:i]
    return map_name


def map_name_of(dirname: str) -> str:
    """The map name a percent-encoded directory name decodes to (directories written before
    the name was recorded in them)."""
    return urllib.parse.unquote(dirname)


def stored_map_name(directory: Path) -> str | None:
    """The map name recorded in map directory ``directory`` (None if none is recorded);
    StorageError if the record does not read."""
    path = directory / MAP_NAME_FILE
    try:
        return path.read_text(encoding="utf-8") if path.is_file() else None
    except (OSError, UnicodeDecodeError) as exc:
        raise StorageError(f"{path}: cannot read ({exc}); expected the map's name") from exc


def record_map_name(directory: Path, map_name: str) -> None:
    """Record ``map_name`` in its (existing) map directory, or check the name recorded
    there: StorageError naming both if the directory holds another map (two names
    hashed alike, or a directory renamed by hand), so another map is never served."""
    recorded = stored_map_name(directory)
    if recorded is None:
        try:
            atomic_write(directory / MAP_NAME_FILE, map_name)
        except OSError as exc:
            raise StorageError(f"cannot record the map name in {directory}: "
                               f"{exc.strerror or exc}") from exc
    elif recorded != map_name:
        raise StorageError(f"map directory {directory} holds map {recorded!r} (its "
                           f"{MAP_NAME_FILE}), not {map_name!r}; refused: another map's "
                           f"content is never served under this name")


def stored_map_names(storage: Path) -> list[str]:
    """The maps with a directory (a journal or snapshots) under ``storage``, by name: the
    name recorded in it, else its decoded directory name. A directory that is not where
    that name's map lives (not a valid map name, or renamed) is logged and left alone."""
    if not storage.is_dir():
        return []
    names = []
    for path in sorted(storage.iterdir()):
        if path.is_dir() and ((path / "journal").is_dir() or (path / "map").is_dir()):
            try:
                name = wire.check_name(stored_map_name(path) or map_name_of(path.name))
            except (wire.ProtocolError, StorageError) as exc:
                log.warning("ignoring storage directory %s: no valid map name (%s)", path, exc)
                continue
            if map_dirname(name) != path.name:
                log.warning("ignoring storage directory %s: map %r lives in %s", path, name,
                            map_dirname(name))
                continue
            names.append(name)
    return names
