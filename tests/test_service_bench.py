"""Smoke runs of the service benchmarks (tiny data, short runs): they return their numbers."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

# reloc_client lives in clients/ (importable once the distribution is installed).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients"))

import pytest  # noqa: E402

from reloc_service.bench import service_bench as sb  # noqa: E402
from reloc_service.service.config import load_config  # noqa: E402


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


def test_toml_text_round_trips_a_service_config_through_the_service_loader(tmp_path):
    doc = {"zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:7447"],
                     "multicast_scouting": False},
           "service": {"instance": "bench-1", "storage": str(tmp_path / "s \"q\""),
                       "workers": 3, "opencv_threads": 1, "fsync": False,
                       "methods": ["sbi+p3p", "ferns"], "default_method": "ferns"},
           "options": {"ferns": {"online": False, "min_posterior": 0.05}},
           "maps": {"bench": {}}}
    path = tmp_path / "service.toml"
    path.write_text(sb.toml_text(doc))
    assert tomllib.loads(path.read_text()) == doc
    conf = load_config(path)
    assert conf.service.workers == 3 and conf.service.opencv_threads == 1
    assert conf.service.storage == str(tmp_path / "s \"q\"")
    assert dict(conf.options["ferns"]) == {"online": False, "min_posterior": 0.05}
    assert set(conf.maps) == {"bench"}
