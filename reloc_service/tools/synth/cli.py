"""``reloc synth``: render a synthetic dataset from a named preset (thin: parse, call, print)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ...core.errors import RelocError
from .presets import PRESETS


def add_synth_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``reloc synth`` options to ``parser``."""
    parser.add_argument("--preset", choices=sorted(PRESETS), metavar="NAME",
                        help=f"what to render: {', '.join(sorted(PRESETS))} (see --list)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="dataset folder to create (must be empty, new, or an earlier "
                             "synth output)")
    parser.add_argument("--seed", type=int, default=0, help="scene textures, laps and noise "
                        "(same seed: byte-identical images; default 0)")
    parser.add_argument("--workers", type=int, default=2,
                        help="rendering processes (default 2; 1 renders in this process)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="image size factor, e.g. 0.5 for 320x240 (default 1)")
    parser.add_argument("--list", action="store_true", help="list the presets and exit")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def main_synth(args: argparse.Namespace) -> int:
    """Run ``reloc synth`` with parsed ``args``; returns the process exit code."""
    if args.list:
        for name, p in sorted(PRESETS.items()):
            cam = p.camera
            print(f"{name:17s} {p.n_map_frames:3d} map {p.n_query:3d} query  "
                  f"{cam.width}x{cam.height} {cam.model:8s} {p.description}")
        return 0
    if args.preset is None or args.out is None:
        print("reloc synth: --preset and --out are required (or --list)", file=sys.stderr)
        return 2
    if args.workers < 1 or not 0.0 < args.scale <= 4.0:
        print("reloc synth: expected --workers >= 1 and 0 < --scale <= 4", file=sys.stderr)
        return 2
    from . import render_dataset  # lazy: OpenCV and scikit-image load only to render

    start = time.perf_counter()
    try:
        out = render_dataset(args.preset, args.out, seed=args.seed, workers=args.workers,
                             progress=not args.quiet, scale=args.scale)
    except RelocError as exc:
        print(f"reloc synth: {exc}", file=sys.stderr)
        return 1
    p = PRESETS[args.preset]
    print(f"wrote {out}: {p.n_map_frames} map + {p.n_query} query frames, seed {args.seed}, "
          f"{time.perf_counter() - start:.1f} s")
    return 0

