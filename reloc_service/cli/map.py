"""``reloc map check DIR``: report what a map directory (or a whole storage) holds, read only,
and the verdict the service's restore reaches on it; exit status 1 when something is damaged
(or the map would be served degraded or refused), 2 when DIR is not a map directory or
storage. ``--accept-loss`` records that the losses named are accepted."""

from __future__ import annotations

import argparse
import sys

HELP = "inspect map storage: `reloc map check DIR` (exit 1 if damaged)"


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


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

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
    print(to_json(checks) if args.json else "\n".join(format_check(c) for c in checks))
    return 1 if any(c.damaged for c in checks) else 0
