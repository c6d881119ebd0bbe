"""``reloc map export|import|ls|info``: a map as one file, and what the maps of a storage hold.

Exit status: 0 done, 1 refused (a damaged, truncated or unknown file; a map of that name
present; a storage in use), 2 when the arguments name no map directory or storage."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any


def add_arguments(sub: Any) -> None:
    """The four actions, added to ``reloc map``'s subparsers."""
    export = sub.add_parser("export", help="write a map (snapshot, journal tail, checksums, "
                            "identity) as one file, atomically; safe while it is served")
    export.add_argument("source", metavar="DIR_OR_NAME", help="a map directory, or a map "
                        "name with --storage")
    export.add_argument("file", metavar="FILE", help="the export file to write")
    export.add_argument("--storage", help="the storage directory holding map DIR_OR_NAME")
    imp = sub.add_parser("import", help="verify an export file in full, then add its map to "
                         "a storage (it keeps its identity); exit 1 if refused")
    imp.add_argument("file", metavar="FILE")
    imp.add_argument("--storage", required=True, help="the storage directory to add it to")
    imp.add_argument("--name", help="serve it under this name (default: its exported name)")
    imp.add_argument("--replace", action="store_true", help="replace a map of that name")
    ls = sub.add_parser("ls", help="the maps of a storage: keyframes, size, last change")
    ls.add_argument("storage", metavar="STORAGE")
    ls.add_argument("--json", action="store_true")
    info = sub.add_parser("info", help="what one map holds, with its size per part")
    info.add_argument("source", metavar="NAME_OR_DIR", help="a map directory, or a map name "
                      "with --storage")
    info.add_argument("--storage", help="the storage directory holding map NAME")
    info.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..core.errors import StorageError

    action = args.map_command
    try:
        if action == "ls":
            return _ls(Path(args.storage), args.json)
        if action == "import":
            return _import(args)
        directory = _map_dir(args.source, args.storage)
        if directory is None:
            print(f"reloc map {action}: {args.source}: not a map directory (expected "
                  f"service.json, journal/ or map/; give a map name with --storage)",
                  file=sys.stderr)
            return 2
        return _export(directory, Path(args.file)) if action == "export" else \
            _info(directory, args.json)
    except StorageError as exc:
        print(f"reloc map {action}: refused: {exc}", file=sys.stderr)
        return 1


def _map_dir(source: str, storage: str | None) -> Path | None:
    from ..service.map_dirs import map_dirname
    from ..service.storage_check import is_map_dir

    path = Path(storage) / map_dirname(source) if storage else Path(source)
    return path if path.is_dir() and is_map_dir(path) else None


def _export(directory: Path, file: Path) -> int:
    from ..service.map_transfer import export_map

    start = time.perf_counter()
    manifest, size = export_map(directory, file)
    print(f"{file}: map {manifest['map_name']!r} ({manifest['map_id']}), "
          f"{manifest['keyframes']} keyframes up to sequence number {manifest['last_seq']}, "
          f"{size / 1e6:.1f} MB in "
          f"{time.perf_counter() - start:.1f} s")
    return 0


def _import(args: argparse.Namespace) -> int:
    from ..service.map_transfer import import_map

    start = time.perf_counter()
    done = import_map(Path(args.file), Path(args.storage), name=args.name, replace=args.replace)
    print(f"{done.directory}: map {done.name!r} ({done.map_id}) imported, {done.keyframes} "
          f"keyframes up to sequence number {done.last_seq}, every part verified, in "
          f"{time.perf_counter() - start:.1f} s")
    return 0


def _ls(storage: Path, as_json: bool) -> int:
    from ..service.map_dirs import map_dirname, stored_map_names
    from ..service.map_transfer import map_info

    if not storage.is_dir():
        print(f"reloc map ls: {storage}: not a directory; expected a storage", file=sys.stderr)
        return 2
    infos = [map_info(storage / map_dirname(n)) for n in stored_map_names(storage)]
    if as_json:
        print(json.dumps(infos, indent=1))
        return 0
    print(f"{'NAME':24} {'KEYFRAMES':>9} {'LANDMARKS':>9} {'MB':>8}  {'LAST CHANGE':20} STATE")
    for i in infos:
        print(f"{i['name']:24} {_n(i['keyframes']):>9} {_n(i['landmarks']):>9} "
              f"{i['total_bytes'] / 1e6:8.1f}  {_when(i['last_change']):20} {i['restore']}")
    return 0


def _info(directory: Path, as_json: bool) -> int:
    from ..service.map_transfer import map_info

    i = map_info(directory)
    if as_json:
        print(json.dumps(i, indent=1))
        return 0
    print(f"{i['name']} ({i['directory']})\n  map id: {i['map_id']}\n"
          f"  keyframes: {_n(i['keyframes'])}, landmarks: {_n(i['landmarks'])}, last sequence "
          f"number {_n(i['last_seq'])}\n  snapshot format version: {_n(i['format_version'])}\n"
          f"  last change: {_when(i['last_change'])}\n  restore: {i['restore']}\n"
          f"  on disk: {i['total_bytes'] / 1e6:.2f} MB")
    for kind, size in sorted(i["bytes"].items()):
        print(f"    {kind:11} {size / 1e6:10.2f} MB")
    return 0


def _n(value: object) -> str:
    return "?" if value is None else str(value)


def _when(stamp: float | None) -> str:
    return "?" if stamp is None else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(stamp))
