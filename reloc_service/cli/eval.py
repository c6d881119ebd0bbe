"""``reloc eval``: parse, call :func:`reloc_service.tools.eval.evaluate.evaluate`, print the table,
write the JSON and the plots. Nothing heavy is imported until the command runs."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

HELP = "evaluate relocalization methods on a dataset"

DESCRIPTION = """\
Build the map from DATASET/map.txt, train, relocalize every query of DATASET/queries.txt and
score it against its ground truth. Several --method options are evaluated on the same map (built
once). A comma inside one method is a fallback chain ("bow+p3p,sbi+esm"), not two methods.
Prints one row per method: recall within 5cm/5deg, 25cm/10deg, 50cm/15deg (% of all queries),
median translation (cm) and rotation (deg) errors of the returned poses, wrong poses (returned
but beyond 50cm/15deg) and not relocalized (% of all queries), p50/p99 latency (ms; in-process,
queries run as in a service worker: one OpenCV thread, one BLAS thread)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("dataset", nargs="?", help="reloc dataset v1 folder")
    parser.add_argument("--method", "-m", action="append", default=None, metavar="NAME",
                        help="method to evaluate (repeat to compare several on one map; "
                        "default, or 'default': the service's default method); see --list-methods")
    parser.add_argument("--list-methods", action="store_true",
                        help="list the selectable methods and exit")
    parser.add_argument("--json", metavar="OUT", help="write every number to OUT "
                        "(schema: docs/eval_schema.md)")
    parser.add_argument("--plots", metavar="DIR", help="write the thesis's figures as PNGs to DIR")
    parser.add_argument("--options", metavar="FILE", help="TOML or JSON file: plugin name -> "
                        "options table (e.g. [p3p] / [sbi]); [mapping] configures map building, "
                        "[service] what --round-trip stores (e.g. keyframe_descriptors)")
    parser.add_argument("--landmarks", choices=["auto", "triangulate", "depth"], default="auto",
                        help="auto (default): keypoints lifted with the dataset's depth maps "
                        "where a keyframe has one, the rest triangulated; triangulate: ignore "
                        "depth maps; depth: require one for every keyframe")
    parser.add_argument("--remote", metavar="ENDPOINT", help="evaluate through a running "
                        "service at this Zenoh endpoint (e.g. tcp/127.0.0.1:7447)")
    parser.add_argument("--map", dest="map_name", metavar="NAME",
                        help="map name on the service (with --remote)")
    parser.add_argument("--keyframe-sigma", metavar="T_M,R_DEG", type=_keyframe_sigma,
                        default=(0.0, 0.0),
                        help="1-sigma accuracy per axis of the dataset's poses, metres and "
                        "degrees (e.g. 0.02,0.5): the keyframes are put with that pose "
                        "covariance, and each query's ground truth is taken as that uncertain "
                        "where its error is weighed by the stated covariance ('cov scale'); "
                        "default 0,0: exact; 'map': the keyframes are put without one, so "
                        "the map states its [mapping] default (0.02,0.5, or measured from "
                        "the map itself where --options set keyframe_position_sigma_m and "
                        "_rotation_sigma_deg to \"auto\"), the queries' ground truth exact")
    parser.add_argument("--calibration-sigma", metavar="FOCAL_REL,RADIAL_PX",
                        type=_calibration_sigma, default=None,
                        help="1-sigma accuracy of the dataset's camera calibration: the "
                        "focal, relative, and the radial distortion, pixels at the farthest "
                        "image corner (e.g. 0.005,2): the map states it (mapping."
                        "calibration_focal_sigma_rel / _radial_sigma_px) and the answers' "
                        "covariance carries it; it changes no answer. 0,0: exact (a rendered "
                        "dataset's cameras); default: the dataset's calibration.json "
                        "(reloc synth writes 0,0), else the mapping configuration's (0.005,2 "
                        "unless --options sets it)")
    parser.add_argument("--query-focal-scale", type=float, default=1.0, metavar="S",
                        help="the queries claim a focal S times their camera's (images "
                        "unchanged, like a stale calibration; the map keeps the dataset's)")
    parser.add_argument("--query-k1", type=float, default=None, metavar="V",
                        help="the queries claim radial k1 = V (radtan; a pinhole camera "
                        "claims radtan with this k1 alone), images unchanged")
    parser.add_argument("--round-trip", action="store_true",
                        help="query the map as a service restores it: saved after training as "
                        "a service's snapshot stores it by default (no depth, landmark keypoints "
                        "only, ...) and loaded back; in-process only")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from ..core.errors import RelocError

    if args.list_methods:
        return _list_methods()
    problem = _usage_problem(args)
    if problem:
        print(f"reloc eval: error: {problem}", file=sys.stderr)
        return 2
    from ..algorithms.relocalizers.factory import DEFAULT_METHOD

    # "default" names the service's default method (a chain whose string is long to type).
    args.method = [DEFAULT_METHOD if m.strip() == "default" else m
                   for m in args.method or ["default"]]
    try:
        return _evaluate(args)
    except (RelocError, OSError) as exc:
        print(f"reloc eval: error: {exc}", file=sys.stderr)
        return 1


def _nonnegative_pair(text: str, layout: str, example: str) -> tuple[float, float]:
    """``"A,B"`` -> (A, B), both finite and >= 0; an argparse error naming ``layout``."""
    try:
        a, b = (float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {layout} (e.g. {example}), got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b) and a >= 0 and b >= 0):
        raise argparse.ArgumentTypeError(f"expected {layout}, both finite and >= 0, got "
                                         f"{text!r}")
    return a, b


def _keyframe_sigma(text: str) -> tuple[float, float] | None:
    """``"T_M,R_DEG"`` -> (metres, degrees), both finite and >= 0; ``"map"`` -> None (the
    map's own default)."""
    if text.strip() == "map":
        return None
    return _nonnegative_pair(text, "T_M,R_DEG", "0.02,0.5")


def _calibration_sigma(text: str) -> tuple[float, float]:
    """``"FOCAL_REL,RADIAL_PX"`` -> (relative focal, pixels), both finite and >= 0."""
    return _nonnegative_pair(text, "FOCAL_REL,RADIAL_PX", "0.005,2")


def _usage_problem(args: argparse.Namespace) -> str | None:
    if not args.dataset:
        return "expected a DATASET folder (or --list-methods)"
    if bool(args.remote) != bool(args.map_name):
        return "--remote ENDPOINT and --map NAME go together"
    if args.remote and args.round_trip:
        return "--round-trip evaluates in-process (a service's map is its own snapshot's)"
    return None


def _list_methods() -> int:
    from ..algorithms.relocalizers.factory import list_methods

    methods = list_methods()
    width = max((len(m["method"]) for m in methods), default=6)
    for m in methods:
        flag = " [evaluation only]" if m["evaluation_only"] else ""
        print(f"{m['method']:<{width}}  {m['description']}{flag}")
    if not methods:
        print("no relocalization method is installed", file=sys.stderr)
    return 0


def load_options(path: str | Path) -> dict[str, Any]:
    """Plugin options from a TOML or JSON file: a table of tables (plugin name -> options)."""
    from ..core.errors import ConfigError

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read options file {path}: {exc.strerror}") from exc
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import tomllib

            data = tomllib.loads(text)
    except (ValueError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'}: "
                          f"{exc}") from exc
    bad = [k for k, v in data.items() if not isinstance(v, dict)] if isinstance(data, dict) else []
    if not isinstance(data, dict) or bad:
        raise ConfigError(f"{path}: expected a table of tables (plugin name -> options, e.g. "
                          f"[p3p] max_candidates = 3); not tables: {bad or type(data).__name__}")
    return data


def _evaluate(args: argparse.Namespace) -> int:
    from ..tools.eval import report
    from ..tools.eval.evaluate import RemoteSpec, evaluate
    from ..tools.eval.query_camera import QueryCamera

    options = load_options(args.options) if args.options else None
    remote = RemoteSpec(args.remote, args.map_name) if args.remote else None
    claimed = QueryCamera(focal_scale=args.query_focal_scale, k1=args.query_k1)
    result = evaluate(args.dataset, args.method, options=options, landmarks=args.landmarks,
                      progress=not args.no_progress, remote=remote,
                      keyframe_sigma=args.keyframe_sigma, query_camera=claimed,
                      round_trip=args.round_trip, calibration_sigma=args.calibration_sigma)
    print(report.format_header(result))
    print()
    print(report.format_markdown(result) if args.markdown else report.format_table(result))
    _print_failures(result)
    if args.json:
        print(f"json: {result.write_json(args.json)}")
    if args.plots:
        from ..tools.eval.plots import plot_result

        for path in plot_result(result, args.plots):
            print(f"plot: {path}")
    return 0


def _print_failures(result: Any) -> None:
    from ..tools.eval.report import format_failures

    for m in result.methods:
        text = format_failures(m, limit=3)
        if text:
            print(f"\n{m.method}: most common reasons for no pose\n{text}")
