"""``reloc demo``: the whole system in about a minute, on one machine.

Renders the ``desk`` synthetic dataset, starts the service in this process (a Zenoh peer on a
free loopback port, the embedded default otherwise), uploads the map through the client,
trains, relocalizes every query over Zenoh and prints the same table as ``reloc eval``.
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ..algorithms.relocalizers.factory import DEFAULT_METHOD
from ..core.errors import RelocError

DATASET = "desk"
MAP_NAME = "desk"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``reloc demo``."""
    parser.description = ("Render the desk dataset, serve it over Zenoh on loopback, upload, "
                          "train and relocalize every query; print the results table.")
    parser.add_argument("--method", "-m", metavar="NAME",
                        help="method or fallback chain (default: the service's default, "
                        f"{DEFAULT_METHOD!r}; see `reloc eval --list-methods`)")
    parser.add_argument("--out", metavar="DIR",
                        help="keep the dataset, storage and plots in DIR (default: a "
                        "temporary folder, plots excepted)")
    parser.add_argument("--port", type=int, default=0,
                        help="loopback port of the service (default: a free one)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="image scale of the rendered dataset (0.5: faster, 320x240)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run(args: argparse.Namespace) -> int:
    """``reloc demo``; exit status 0 when every step ran (whatever the scores)."""
    try:
        if args.out:
            return _demo(args, Path(args.out))
        with tempfile.TemporaryDirectory(prefix="reloc-demo-") as tmp:
            return _demo(args, Path(tmp))
    except RelocError as exc:
        print(f"reloc demo: error: {exc}", file=sys.stderr)
        return 1


def _demo(args: argparse.Namespace, work: Path) -> int:
    from ..service.app import Service
    from ..service.config import parse_config
    from .eval import report
    from .eval.evaluate import RemoteSpec, evaluate
    from .synth import render_dataset

    method = args.method or DEFAULT_METHOD
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    start = time.perf_counter()
    _say(f"1/4 rendering the {DATASET} dataset into {work / DATASET} ...")
    dataset = render_dataset(DATASET, work / DATASET, progress=not args.no_progress,
                             scale=args.scale)
    rendered = time.perf_counter()
    conf = parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint], "multicast_scouting": False},
        "service": {"instance": "demo", "storage": str(work / "storage"), "methods": [method],
                    "default_method": method, "train_on_load": False}})
    _say(f"2/4 service up on {endpoint} (instance 'demo', method {method})")
    with Service(conf) as service:
        service.start_workers_in_background()   # while the map uploads, not on query 1
        _say("3/4 uploading the map, training and relocalizing every query over Zenoh ...")
        result = evaluate(dataset, [method], progress=not args.no_progress,
                          remote=RemoteSpec(endpoint, MAP_NAME))
    done = time.perf_counter()
    print()
    print(report.format_header(result))
    print()
    print(report.format_table(result))
    print()
    print(f"render {rendered - start:.1f} s, upload + train + queries {done - rendered:.1f} s "
          f"(total {done - start:.1f} s)")
    _plots(result, work, keep=bool(args.out))
    return 0


def _plots(result: Any, work: Path, *, keep: bool) -> None:
    """Write the plots (matplotlib installed) or say how to get them."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print("4/4 plots: install matplotlib (pip install reloc[plots]) and run "
              "`reloc eval DATASET -m METHOD --plots DIR`")
        return
    from .eval.plots import plot_result

    out = work / "plots" if keep else Path(tempfile.mkdtemp(prefix="reloc-demo-plots-"))
    paths = plot_result(result, out)
    print(f"4/4 {len(paths)} plots written to {out}:")
    for p in paths:
        print(f"  {p}")


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
