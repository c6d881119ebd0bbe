"""``reloc serve`` and ``reloc router``: parse, load the configuration, run until a signal.

Explicit flags override ``--config``: ``--mode``, ``--listen``, ``--connect``, ``--storage``,
``--workers``, ``--worker-mode``. Without ``--config`` the embedded default applies (a Zenoh peer listening on
``tcp/127.0.0.1:7447``, multicast scouting off: no router needed).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from ..core.errors import RelocError

SERVE_EPILOG = """\
examples:
  reloc serve                                   # peer on tcp/127.0.0.1:7447, default storage
  reloc serve --config config/companion.toml    # a drone's companion computer
  reloc serve --listen tcp/0.0.0.0:7447 --storage /var/lib/reloc --workers 2
Clients: `reloc-client --connect tcp/127.0.0.1:7447 --map NAME status` (docs/protocol.md)."""


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, modes: tuple[str, ...]) -> None:
    """The shared Zenoh flags (as in zenoh-python's examples)."""
    parser.add_argument("--mode", choices=modes, help="Zenoh mode (overrides the config)")
    parser.add_argument("--listen", "-l", action="append", metavar="ENDPOINT",
                        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; "
                        "replaces the config's list)")
    parser.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                        help="endpoint to connect to, e.g. tcp/192.168.1.2:7447 (repeatable)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``reloc serve``."""
    parser.description = "Run the Zenoh relocalization service until SIGINT/SIGTERM."
    parser.epilog = SERVE_EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--config", "-c", metavar="FILE",
                        help="service TOML file (default: the embedded default, identical to "
                        "config/default.toml)")
    add_zenoh_arguments(parser, modes=("peer", "client", "router"))
    parser.add_argument("--storage", metavar="DIR",
                        help="journal and snapshot directory ('' keeps maps in memory only)")
    parser.add_argument("--workers", type=int, metavar="N", help="relocalize workers")
    parser.add_argument("--worker-mode", choices=["process", "thread"],
                        help="relocalize workers as processes (each with a replica of the "
                        "maps: scales with cores) or threads of the service (one copy of the "
                        "maps)")
    parser.add_argument("--instance", metavar="NAME", help="instance name in liveliness tokens")
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective configuration as JSON and exit")


def load_service_config(args: argparse.Namespace) -> Any:
    """The effective :class:`ServiceConf`: ``--config`` (or the default) + explicit flags."""
    from .config import load_config, with_overrides

    conf = load_config(args.config)
    return with_overrides(conf, mode=args.mode, listen=args.listen, connect=args.connect,
                          storage=args.storage, workers=args.workers, instance=args.instance,
                          worker_mode=args.worker_mode)


def run(args: argparse.Namespace) -> int:
    """``reloc serve``: exit status 0 after a clean shutdown, 1 on a configuration or
    storage error."""
    _logging(args.log_level)
    try:
        conf = load_service_config(args)
        if args.print_config:
            print(json.dumps(_as_plain(conf), indent=2))
            return 0
        from .serve import serve

        return serve(conf)
    except RelocError as exc:
        print(f"reloc serve: error: {exc}", file=sys.stderr)
        return 1


# -- router -----------------------------------------------------------------------------------

ROUTER_DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def add_router_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``reloc router``."""
    parser.description = ("Run a Zenoh router in this process (ground-station set-up): services "
                          "and clients connect to it with mode client or peer.")
    parser.add_argument("--config", "-c", metavar="FILE",
                        help="a Zenoh JSON5 config (e.g. config/router.json5) or a service TOML "
                        "(its [zenoh] section)")
    add_zenoh_arguments(parser, modes=("router",))
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def router_config(args: argparse.Namespace) -> Any:
    """The Zenoh config of the router: the file, mode router, flags on top."""
    import dataclasses

    from .config import ZenohConf, load_config
    from .zenoh_io import zenoh_config

    path = Path(args.config) if args.config else None
    if path is not None and path.suffix == ".toml":
        zc = load_config(path).zenoh
    elif path is not None:
        zc = ZenohConf(listen=(), config_file=str(path))
    else:
        zc = ZenohConf(listen=(ROUTER_DEFAULT_LISTEN,))
    zc = dataclasses.replace(zc, mode="router",
                             listen=tuple(args.listen) if args.listen else zc.listen,
                             connect=tuple(args.connect) if args.connect else zc.connect)
    return zenoh_config(zc), zc


def run_router(args: argparse.Namespace) -> int:
    """``reloc router``: serve as a Zenoh router until SIGINT/SIGTERM."""
    _logging(args.log_level)
    from .workers import stop_on_signals

    stop = stop_on_signals()
    try:
        zconf, zc = router_config(args)
        import zenoh

        session = zenoh.open(zconf)
    except RelocError as exc:
        print(f"reloc router: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # zenoh's own errors (endpoint in use, bad config)
        print(f"reloc router: error: cannot start the router: {exc}", file=sys.stderr)
        return 1
    logging.getLogger(__name__).info("zenoh router %s listening on %s", session.zid(),
                                     list(zc.listen) or "(config file endpoints)")
    while not stop.wait(0.5):
        pass
    session.close()
    logging.getLogger(__name__).info("zenoh router stopped")
    return 0


def _logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _as_plain(value: Any) -> Any:
    import dataclasses
    from collections.abc import Mapping

    if dataclasses.is_dataclass(value):
        return {f.name: _as_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {k: _as_plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_as_plain(v) for v in value]
    return value
