"""The default chain with the intrinsics test deferred to verification (as it runs) against
it settled at once (every pose found, before verification), query by query on one map in
one process, the two orders alternating so that the machine's load hits both alike: p50,
intrinsics tests run, and whether every answer is the same.

    .venv/bin/python scripts/settle_ab.py ../shared/data/real/tum_fr1_rpy --keyframe-sigma 0.01,0.3
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from reloc_service.algorithms.pose import intrinsics
from reloc_service.algorithms.pose.p3p import P3PPoseFinder
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core.frame import Frame
from reloc_service.tools.data.dataset import read_dataset
from reloc_service.tools.eval.backends import LandmarkSource
from reloc_service.tools.eval.evaluate import _build_map, ground_truth_covariance
from reloc_service.tools.eval.inprocess import InProcessBackend, as_a_service_worker

TESTS = [0]


def _counted(check):  # type: ignore[no-untyped-def]
    def run(*args, **kwargs):  # type: ignore[no-untyped-def]
        TESTS[0] += 1
        return check(*args, **kwargs)
    return run


@contextlib.contextmanager
def settled_at_once() -> Iterator[None]:
    """p3p settles every pose it finds (its alternatives too) before verification sees it."""
    deferred = P3PPoseFinder._deferred

    def eager(self, est, state):  # type: ignore[no-untyped-def]
        est = deferred(self, est, state)
        est.settle()
        return est

    P3PPoseFinder._deferred = eager  # type: ignore[method-assign]
    try:
        yield
    finally:
        P3PPoseFinder._deferred = deferred  # type: ignore[method-assign]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--keyframe-sigma", default="0,0")
    args = parser.parse_args(argv)
    sigma = tuple(float(v) for v in args.keyframe_sigma.split(","))
    dataset = read_dataset(args.dataset)
    backend = InProcessBackend([DEFAULT_METHOD], {}, LandmarkSource.AUTO)
    intrinsics.check_intrinsics = _counted(intrinsics.check_intrinsics)  # type: ignore[assignment]
    import reloc_service.algorithms.pose.pnp as pnp
    pnp.check_intrinsics = intrinsics.check_intrinsics  # type: ignore[attr-defined]
    ms = {"deferred": [], "at once": []}  # type: dict[str, list[float]]
    tests = {"deferred": 0, "at once": 0}
    same = 0
    try:
        _build_map(backend, dataset, LandmarkSource.AUTO, False,
                   ground_truth_covariance(sigma))  # type: ignore[arg-type]
        backend.train(progress=False)
        with as_a_service_worker():
            entries = dataset.query_entries
            backend.engine.relocalize(Frame(dataset.load_image(entries[0]),
                                            dataset.camera(entries[0])), method=DEFAULT_METHOD)
            for q, entry in enumerate(entries):
                image, camera = dataset.load_image(entry), dataset.camera(entry)
                got = {}
                for mode in (("deferred", "at once") if q % 2 else ("at once", "deferred")):
                    before = TESTS[0]
                    with settled_at_once() if mode == "at once" else contextlib.nullcontext():
                        start = time.perf_counter()
                        got[mode] = backend.engine.relocalize(Frame(image, camera),
                                                              method=DEFAULT_METHOD)
                        ms[mode].append((time.perf_counter() - start) * 1e3)
                    tests[mode] += TESTS[0] - before
                a, b = got["at once"], got["deferred"]
                equal = (a.status == b.status and a.method == b.method and a.reason == b.reason
                         and (a.world_from_cam is None or np.array_equal(a.world_from_cam,
                                                                         b.world_from_cam))
                         and (a.covariance is None or np.allclose(a.covariance, b.covariance)))
                same += equal
                print(f"q{q:<3d} {b.method:<20s} ok={b.ok!s:5s} same={equal!s:5s} "
                      f"at once {ms['at once'][-1]:7.0f} ms, deferred {ms['deferred'][-1]:7.0f} ms",
                      flush=True)
    finally:
        backend.close()
    p50 = {m: float(np.median(v)) for m, v in ms.items()}
    print(f"{args.dataset.name}: {len(ms['deferred'])} queries, same answer {same}; p50 at once "
          f"{p50['at once']:.0f} ms, deferred {p50['deferred']:.0f} ms "
          f"({p50['deferred'] / p50['at once']:.2f}x); intrinsics tests at once "
          f"{tests['at once']}, deferred {tests['deferred']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
