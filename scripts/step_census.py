"""Why each step of a chain refuses: every query asked of every step alone, as the chain asks
it (the steps the chain built, with their deferral of unchecked intrinsics), on the map
``reloc eval`` builds; prints one line per query and step, then the reasons counted.

    .venv/bin/python scripts/step_census.py ../shared/data/real/tum_fr1_rpy \\
        --keyframe-sigma 0.01,0.3 --json out/census.json
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from reloc_service.algorithms.pose.intrinsics_power import estimate_underpowered
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.chain_hooks import ANSWERED, narrow_support
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.frame import Frame
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import (
    _build_map,
    ground_truth_covariance,
    record_from_result,
)
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker

#: Numbers in a reason (counts, percentages, pixels) dropped so that reasons group by kind.
_NUMBERS = re.compile(r"-?\d+(\.\d+)?(e-?\d+)?")


def reason_kind(reason: str) -> str:
    """A refusal reason without its numbers and its step prefix, cut to its first clause."""
    text = _NUMBERS.sub("#", reason.split(": ", 1)[-1] if reason.startswith(("sbi", "bow"))
                        else reason)
    return text.split(";")[0].split(" (")[0][:110]


def census(root: Path, method: str, sigma: tuple[float, float]) -> list[dict[str, Any]]:
    dataset = read_dataset(root)
    truth = ground_truth_covariance(sigma)
    backend = InProcessBackend([method], {}, LandmarkSource.AUTO)
    rows: list[dict[str, Any]] = []
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False, truth)
        backend.train(progress=False)
        chain = backend.engine.relocalizer(method)
        assert isinstance(chain, ChainRelocalizer), method
        with as_a_service_worker():
            for q, entry in enumerate(dataset.query_entries):
                image = dataset.load_image(entry)
                gt = np.array(entry.world_from_cam)
                for step in chain.steps:
                    assert isinstance(step, MultiRelocalizer), step.method
                    frame = Frame(image, dataset.camera(entry), gt_world_from_cam=gt)
                    start = time.perf_counter()
                    result = step.relocalize(frame)
                    ms = (time.perf_counter() - start) * 1e3
                    rec = record_from_result(entry.image_path, result, gt, ms,
                                             truth_covariance=truth)
                    answered = frame.cache.get(ANSWERED)
                    # A verified answer the chain still holds as a contender (asks the next
                    # step too): narrow support, or an intrinsics test without power.
                    narrow = bool(answered is not None and narrow_support(answered, step.verify_conf))
                    weak = bool(answered is not None and estimate_underpowered(answered))
                    rows.append({"query": q, "step": step.method, "ok": rec.returned,
                                 "narrow": narrow, "underpowered": weak,
                                 "t_err_m": rec.t_err_m, "r_err_deg": rec.r_err_deg,
                                 "ms": ms, "reason": rec.reason, "inliers": rec.inliers,
                                 "matches": rec.num_matches, "kind": reason_kind(rec.reason)})
    finally:
        backend.close()
    return rows


def summary_lines(rows: list[dict[str, Any]]) -> list[str]:
    lines = []
    for step in dict.fromkeys(r["step"] for r in rows):
        mine = [r for r in rows if r["step"] == step]
        good = sum(r["ok"] and r["t_err_m"] <= 0.05 and r["r_err_deg"] <= 5 for r in mine)
        narrow = sum(r["narrow"] for r in mine)
        weak = sum(r["underpowered"] for r in mine)
        lines.append(f"{step}: answers {sum(r['ok'] for r in mine)}/{len(mine)} "
                     f"({good} within 5 cm / 5 deg; narrow {narrow}, intrinsics test "
                     f"underpowered {weak}), p50 {np.median([r['ms'] for r in mine]):.0f} ms")
        for kind, n in Counter(r["kind"] for r in mine if not r["ok"]).most_common():
            lines.append(f"    {n:3d}  {kind}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--method", default=DEFAULT_METHOD)
    parser.add_argument("--keyframe-sigma", default="0,0")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    t_m, r_deg = (float(v) for v in args.keyframe_sigma.split(","))
    rows = census(args.dataset, args.method, (t_m, r_deg))
    for r in rows:
        err = "-" if not r["ok"] else f"{r['t_err_m'] * 100:.1f} cm"
        flags = ("N" if r["narrow"] else "-") + ("U" if r["underpowered"] else "-")
        print(f"q{r['query']:<3d} {r['step']:<20s} {r['ms']:7.0f} ms {err:>9s} {flags} "
              f"{r['inliers']:4d}/{r['matches']:<4d} {r['reason'][:160]}")
    print("\n".join(summary_lines(rows)))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
