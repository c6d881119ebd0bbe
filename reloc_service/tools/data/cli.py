"""``reloc dataset {from-tum,from-euroc,from-rosbag,to-rosbag,check}``: argument parsing and
printing only; the work is in :mod:`.tum`, :mod:`.euroc`, :mod:`.rosbag_cli` and :mod:`.dataset`
(imported lazily to keep ``--help`` fast)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from .rosbag_cli import add_rosbag_commands, run_rosbag_command

if TYPE_CHECKING:
    from ...core.cameras import Camera
    from .dataset import Dataset


def add_dataset_arguments(parent: Any) -> argparse.ArgumentParser:
    """Add the ``dataset`` command to ``parent``: either the subparsers of the main ``reloc``
    parser (a ``dataset`` parser is created) or a parser to fill directly. Returns the parser;
    its default ``func`` is :func:`main_dataset`."""
    if hasattr(parent, "add_parser"):
        parser = parent.add_parser(
            "dataset", help="convert (TUM RGB-D, EuRoC, rosbag2) and check reloc datasets",
            description="Convert public sequences to reloc dataset v1 folders, or check one.")
    else:
        parser = parent
    commands = parser.add_subparsers(dest="dataset_command", required=True,
                                     metavar="{from-tum,from-euroc,from-rosbag,to-rosbag,check}")
    tum = commands.add_parser("from-tum", help="convert a TUM RGB-D sequence folder",
                              description="Convert a TUM RGB-D sequence (rgb.txt, depth.txt, "
                              "groundtruth.txt) to a reloc dataset, copying the chosen images.")
    _add_conversion_arguments(tum)
    euroc = commands.add_parser("from-euroc", help="convert a EuRoC MAV (ASL format) sequence",
                                description="Convert one camera of a EuRoC MAV sequence (ASL "
                                "folder with mav0/) to a reloc dataset, copying the chosen images.")
    euroc.add_argument("--cam", default="cam0", choices=["cam0", "cam1"],
                       help="camera to convert (default: cam0)")
    _add_conversion_arguments(euroc)
    add_rosbag_commands(commands)
    check = commands.add_parser("check", help="validate a dataset and print a summary",
                                description="Read a reloc dataset, validate it and print a "
                                "summary; exit status 1 with the error if it is malformed.")
    check.add_argument("dataset", help="dataset folder")
    check.add_argument("--images", action="store_true",
                       help="also decode every image and depth map and check their sizes")
    parser.set_defaults(func=main_dataset)
    return parser


def _add_conversion_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="source sequence folder")
    parser.add_argument("dst", help="destination dataset folder (created)")
    parser.add_argument("--map-stride", type=int, default=10, metavar="N",
                        help="every N-th frame is a map keyframe (default: 10)")
    parser.add_argument("--query-stride", type=int, default=None, metavar="M",
                        help="every M-th frame is a query (default: the map stride)")
    parser.add_argument("--query-offset", type=int, default=None, metavar="K",
                        help="queries start K frames after the first map frame (default: "
                        "map stride // 2); never a map frame")
    parser.add_argument("--map-time", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                        help="map frames only from this time range (seconds since the first "
                        "image)")
    parser.add_argument("--query-time", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                        help="query frames only from this time range (seconds since the first "
                        "image)")
    parser.add_argument("--max-dt", type=float, default=0.02, metavar="S",
                        help="max time (s) to the ground-truth samples around a frame and to "
                        "its depth map (default: 0.02)")
    parser.add_argument("--camera-json", default=None, metavar="FILE",
                        help="camera dict (Camera.to_dict()) or one-camera cameras.json "
                        "replacing the default camera")


def main_dataset(args: argparse.Namespace) -> int:
    """Run ``reloc dataset ...``; 0 on success, 1 (message on stderr) if a dataset is bad."""
    from ...core.errors import RelocError

    try:
        if args.dataset_command == "check":
            return _check(args)
        if args.dataset_command in ("from-rosbag", "to-rosbag"):
            return run_rosbag_command(args, format_summary)
        return _convert(args)
    except (RelocError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _convert(args: argparse.Namespace) -> int:
    from .dataset import read_camera_json

    camera = read_camera_json(args.camera_json) if args.camera_json else None
    options = dict(map_stride=args.map_stride, query_stride=args.query_stride,
                   query_offset=args.query_offset, max_dt=args.max_dt, camera=camera,
                   map_range=tuple(args.map_time) if args.map_time else None,
                   query_range=tuple(args.query_time) if args.query_time else None)
    if args.dataset_command == "from-tum":
        from .tum import convert_tum, tum_default_camera

        if camera is None:
            print(f"camera: TUM {tum_default_camera(args.src)[0]} colour camera "
                  "(--camera-json to change)")
        dataset = convert_tum(args.src, args.dst, **options)  # type: ignore[arg-type]
    elif args.dataset_command == "from-euroc":
        from .euroc import convert_euroc

        dataset = convert_euroc(args.src, args.dst, cam=args.cam, **options)  # type: ignore[arg-type]
    else:
        raise ValueError(f"unknown dataset command {args.dataset_command!r}")
    print(format_summary(dataset))
    if not dataset.query_entries:
        print("warning: no query frames selected", file=sys.stderr)
    return 0


def _check(args: argparse.Namespace) -> int:
    from .dataset import read_dataset

    dataset = read_dataset(args.dataset)
    if args.images:
        _load_everything(dataset)
    print(format_summary(dataset))
    return 0


def _load_everything(dataset: Dataset) -> None:
    from ...core.progress import progress

    for entry in progress(dataset.map_entries + dataset.query_entries, desc="images"):
        dataset.load_image(entry)
        dataset.load_depth(entry)
        dataset.load_truth_depth(entry)


def format_summary(dataset: Dataset) -> str:
    """Human-readable summary: cameras, frame counts, extent of the camera trajectory."""
    import numpy as np

    map_centres = np.array([e.world_from_cam[:3, 3] for e in dataset.map_entries]).reshape(-1, 3)
    query_centres = np.array([e.world_from_cam[:3, 3] for e in dataset.query_entries])
    centres = np.vstack([map_centres, query_centres.reshape(-1, 3)])
    map_paths = {e.image_path for e in dataset.map_entries}
    lines = [f"dataset {dataset.root}", f"cameras: {len(dataset.cameras)}"]
    lines += [f"  {cid}: {_describe_camera(cam)}" for cid, cam in dataset.cameras.items()]
    lines.append(f"map frames: {len(dataset.map_entries)} "
                 f"({sum(e.image_path in dataset.depth for e in dataset.map_entries)} with depth, "
                 f"{sum(e.image_path in dataset.truth_depth for e in dataset.map_entries)} with "
                 "truth depth)")
    n_depth = sum(e.image_path in dataset.depth for e in dataset.query_entries)
    n_truth = sum(e.image_path in dataset.truth_depth for e in dataset.query_entries)
    n_shared = sum(e.image_path in map_paths for e in dataset.query_entries)
    lines.append(f"query frames: {len(dataset.query_entries)} ({n_depth} with depth, "
                 f"{n_truth} with truth depth, {n_shared} also in the map)")
    if len(centres):
        low, high = centres.min(axis=0), centres.max(axis=0)
        length = float(np.linalg.norm(np.diff(map_centres, axis=0), axis=1).sum())
        lines.append("trajectory extent (m): " + "  ".join(
            f"{axis} [{lo:.3f}, {hi:.3f}]" for axis, lo, hi in zip("xyz", low, high, strict=True)))
        lines.append(f"bounding box diagonal: {np.linalg.norm(high - low):.3f} m, map path "
                     f"length: {length:.3f} m")
    return "\n".join(lines)


def _describe_camera(camera: Camera) -> str:
    distortion = ", ".join(f"{d:g}" for d in camera.distortion)
    return (f"{camera.model} {camera.width}x{camera.height} fx={camera.fx:g} fy={camera.fy:g} "
            f"cx={camera.cx:g} cy={camera.cy:g} distortion=[{distortion}]")
