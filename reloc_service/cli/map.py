"""``reloc map check DIR``: report what a map directory (or a whole storage) holds, read only,
and the verdict the service's restore reaches on it; exit status 1 when something is damaged
(or the map would be served degraded or refused), 2 when DIR is not a map directory or
storage. ``--accept-loss`` records that the losses named are accepted.
``reloc map set-current DIR SNAPSHOT``: point a missing ``CURRENT`` at a verified snapshot;
refused while a service (or another tool) holds the map."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = ("inspect and carry map storage: `reloc map check DIR` (exit 1 if damaged), "
        "`export`/`import` (a map as one file), `ls`, `info`")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    check = sub.add_parser("check", help="verify snapshots, the journal and the quarantine of "
                           "a map directory or of every map of a storage; exit 1 if damaged")
    check.add_argument("directory", metavar="DIR", help="a map directory (holding journal/, "
                       "map/, service.json) or a storage directory holding map directories")
    check.add_argument("--json", action="store_true", help="print the report as JSON")
    check.add_argument("--accept-loss", action="store_true", help="record that the losses "
                       "this map directory's restore names are accepted (the service then "
                       "serves it normally); a refused map is left as it is")
    current = sub.add_parser("set-current", help="point the missing map/CURRENT of a map "
                             "directory at one of its snapshots, after verifying every file "
                             "of it; refused while a service holds the map")
    current.add_argument("directory", metavar="DIR", help="a map directory")
    current.add_argument("snapshot", metavar="SNAPSHOT", help="a snapshot name under "
                         "DIR/map/snapshots/ (`reloc map check DIR` lists them)")
    from .map_transfer import add_arguments as add_transfer_arguments

    add_transfer_arguments(sub)


def run(args: argparse.Namespace) -> int:
    if args.map_command == "set-current":
        return run_set_current(args)
    if args.map_command in ("export", "import", "ls", "info"):
        from .map_transfer import run as run_transfer

        return run_transfer(args)
    from ..core.errors import StorageError
    from ..service.storage_check import accept_losses, check_path, format_check, is_map_dir, to_json

    try:
        if args.accept_loss:
            if not is_map_dir(Path(args.directory)):
                raise StorageError(f"{args.directory}: not a map directory; --accept-loss "
                                   f"takes one map directory")
            verdict = accept_losses(Path(args.directory))
            print(f"{args.directory}: accepted: "
                  + "; ".join(loss.describe() for loss in verdict.accepted), file=sys.stderr)
        checks = check_path(args.directory)
    except StorageError as exc:
        print(f"reloc map check: {exc}", file=sys.stderr)
        return 2
    _note_holders([Path(c.directory) for c in checks])
    print(to_json(checks) if args.json else "\n".join(format_check(c) for c in checks))
    return 1 if any(c.damaged for c in checks) else 0


def _note_holders(directories: list[Path]) -> None:
    """Say (on stderr, so that --json stays parseable) which maps a running process holds:
    reading goes ahead, but the report is of files that may be changing."""
    from ..storage.lock import holder_if_locked

    for directory in directories:
        holder = holder_if_locked(directory)
        if holder is not None:
            print(f"reloc map check: note: {directory} is in use by {holder.describe()}; "
                  f"read-only inspection goes ahead, but writes in progress may show as a "
                  f"torn journal tail", file=sys.stderr)


def run_set_current(args: argparse.Namespace) -> int:
    """Exit 0 once CURRENT names the snapshot, 1 if refused (held by a service, CURRENT
    present, snapshot damaged), 2 if DIR is not a map directory."""
    from ..core.errors import StorageError
    from ..service.storage_check import is_map_dir
    from ..storage.lock import DirectoryLock
    from ..storage.snapshot import restore_current

    directory = Path(args.directory)
    if not directory.is_dir() or not is_map_dir(directory):
        print(f"reloc map set-current: {directory}: not a map directory (expected journal/, "
              f"map/ or service.json)", file=sys.stderr)
        return 2
    try:
        with DirectoryLock(directory, what="map directory").acquire("reloc map set-current"):
            path = restore_current(directory / "map", args.snapshot)
    except StorageError as exc:
        print(f"reloc map set-current: refused: {exc}", file=sys.stderr)
        return 1
    print(f"{directory / 'map' / 'CURRENT'} -> snapshots/{path.name} (every file verified)")
    return 0
