"""The intrinsics test's micro-benchmark: every size and focal timed with both BLAS thread
counts, the given focal passing and the one 8 % off refused, and its Markdown table."""

from __future__ import annotations

from reloc_service.tools.bench import intrinsics_bench, report


def test_the_intrinsics_bench_times_every_size_and_judges_the_focal():
    result = intrinsics_bench.run(repeats=1)
    rows = result["rows"]
    assert [(r["correspondences"], r["focal_scale"]) for r in rows] == [
        (n, s) for n in intrinsics_bench.SIZES for s in intrinsics_bench.FOCAL_SCALES]
    for row in rows:
        for timing in (row["one_blas_thread"], row["blas_threads_per_core"]):
            assert timing["p50_ms"] > 0 and timing["cpu_p50_ms"] >= 0
            assert timing["solutions"] >= 1
            assert timing["passed"] is (row["focal_scale"] == 1.0)
    lines = report._intrinsics(result)
    assert lines[0] == "## Intrinsics test"
    assert sum(line[2:3].isdigit() for line in lines) == len(rows)  # one table row each
