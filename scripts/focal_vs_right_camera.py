"""Which answers beyond 3 sigma under a scaled focal were beyond 3 sigma with the right camera
too: reads ``reloc eval`` JSONs of one set at the right camera and at a scaled focal
(``--query-focal-scale``) and prints, per answered query beyond ``--sigmas`` at the scaled
focal, its error and Mahalanobis length at both; then the counts.

    python3 scripts/focal_vs_right_camera.py /work/eval_s12/room-hard.json \\
        /work/eval_s12_focal_merged/room-hard_1.05.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def queries(path: Path) -> list[dict[str, Any]]:
    """The per-query records of the eval JSON's first method."""
    return list(json.loads(path.read_text())["methods"][0]["queries"])


def beyond(record: dict[str, Any], sigmas: float) -> bool:
    """Whether ``record`` answered with its error beyond ``sigmas`` of its stated covariance."""
    m = record.get("t_err_mahalanobis")
    return record.get("t_err_m") is not None and m is not None and m > sigmas


def text(record: dict[str, Any]) -> str:
    """An answer's error, its Mahalanobis length and method; or "refused"."""
    if record.get("t_err_m") is None:
        return "refused"
    return (f"{100 * record['t_err_m']:5.1f} cm {record['t_err_mahalanobis']:4.1f} sig "
            f"{record.get('method_used') or ''}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("right", type=Path, help="eval JSON with the right camera")
    parser.add_argument("scaled", type=Path, help="eval JSON with a scaled focal")
    parser.add_argument("--sigmas", type=float, default=3.0)
    args = parser.parse_args(argv)
    right, scaled = queries(args.right), queries(args.scaled)
    if len(right) != len(scaled):
        raise SystemExit(f"expected the same queries, got {len(right)} and {len(scaled)}")
    hits = [i for i, r in enumerate(scaled) if beyond(r, args.sigmas)]
    for i in hits:
        print(f"q{i:<3d} scaled {text(scaled[i]):<36s} right camera {text(right[i])}")
    both = sum(beyond(right[i], args.sigmas) for i in hits)
    answered = sum(r.get("t_err_m") is not None for r in right)
    base = sum(beyond(r, args.sigmas) for r in right)
    print(f"{args.scaled.name}: {len(hits)} beyond {args.sigmas:g} sigma, {both} of them beyond "
          f"with the right camera too; right camera: {base} of {answered} answers beyond")
    return 0


if __name__ == "__main__":
    sys.exit(main())
