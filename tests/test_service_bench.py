"""Smoke runs of the service benchmarks (tiny data, short runs): they return their numbers."""

from __future__ import annotations

import sys
from pathlib import Path

# reloc_client lives in clients/ (importable once the distribution is installed).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients"))

import pytest  # noqa: E402

from reloc_service.bench import service_bench as sb  # noqa: E402


def bench_data(scene) -> sb.BenchData:
    return sb.BenchData(scene.camera, list(zip(scene.keyframe_images, scene.keyframe_poses,
                                               strict=True)),
                        list(zip(scene.query_images, scene.query_poses, strict=True)))


@pytest.mark.slow
def test_latency_and_throughput_benchmarks_return_their_numbers(synthetic_scene):
    data = bench_data(synthetic_scene)
    latency = sb.bench_latency(data, repeats=1, process=False)
    for key in ("method", "echo"):
        row = latency[key]
        assert row["zenoh_p50_ms"] > 0 and row["in_process_p50_ms"] > 0
        assert row["service_overhead_p50_ms"] > 0
    throughput = sb.bench_throughput(data, clients=(1, 2), duration_s=0.5, rounds=1)
    assert [r["clients"] for r in throughput["runs"]] == [1, 2]
    assert all(r["queries_per_s"] > 0 and r["ok"] > 0 for r in throughput["runs"])
