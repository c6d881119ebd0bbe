"""The default chain against main's (``sbi+p3p:orb,bow+p3p,sbi+p3p``) and any other columns,
in one run with the decode + ORB limit timed alongside: the ``reloc bench`` accuracy
section's code (:func:`reloc_service.tools.bench.accuracy.bench_accuracy`) without its other
methods and the plain OpenCV peer.

    .venv/bin/python scripts/fastpath_compare.py --json out/real.json \\
        --column sbi+p3p ../shared/data/real/*/
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.tools.bench import accuracy, accuracy_report
from reloc_service.tools.bench.machine import load_average

#: The default chain before the half-size SIFT step.
BEFORE = "sbi+p3p:orb,bow+p3p,sbi+p3p"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--column", action="append", default=[],
                        help="another method scored alongside (repeatable)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    conf = accuracy.AccuracyConf(presets=(), datasets=tuple(args.datasets), real_root=None,
                                 methods=(BEFORE, *args.column), default_method=DEFAULT_METHOD,
                                 peers=())
    problem = accuracy.check_conf(conf)
    if problem:
        print(f"fastpath_compare: {problem}", file=sys.stderr)
        return 2
    start = load_average()
    with tempfile.TemporaryDirectory(prefix="fastpath-") as tmp:
        result = accuracy.bench_accuracy(conf, Path(tmp), show_progress=False)
    result["load_average"] = {"start": start, "end": load_average()}
    print("\n".join(accuracy_report.detail_lines(result)))
    print(f"load average at the start {start}, at the end {result['load_average']['end']}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(accuracy.json_safe(result), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
