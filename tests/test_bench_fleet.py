"""``reloc bench --only fleet`` (:mod:`reloc_service.tools.bench.fleet`): copies of one stored
template share its snapshot files and are served each under its own name; the service's
resident memory is read from its process tree; the flags choose the sizes and bad ones exit
2; a small fleet run on ``reloc serve`` answers every query within its budget (slow)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from reloc_client.client import RelocClient
from service_support import endpoint, free_port, service_conf

from reloc_service.engine import EngineConf
from reloc_service.service.app import Service
from reloc_service.tools.bench import fleet
from reloc_service.tools.bench.cli import fleet_conf
from reloc_service.tools.bench.fleet_memory import ResidencyLog, tree_rss_mb
from reloc_service.tools.bench.report import render_markdown
from reloc_service.tools.bench.samples import QuerySet
from reloc_service.tools.bench.stored_map import (
    copies,
    disk_bytes,
    engine_from_images,
    stored_template,
)

METHOD = "sbi+p3p"


def test_copies_share_the_snapshot_and_each_serves_under_its_name(synthetic_scene, tmp_path):
    scene = synthetic_scene
    engine = engine_from_images(scene.camera, scene.keyframe_images[:3],
                                scene.keyframe_poses[:3], EngineConf(methods=(METHOD,)))
    template = stored_template(tmp_path / "template", "template", engine)
    assert template.keyframes == 3 and template.counted_bytes > 0
    storage = tmp_path / "storage"
    a, b = copies(template, storage, ["alpha", "bravo"])
    shared = [p.relative_to(a) for p in a.rglob("*") if p.is_file()
              and "snapshots" in p.parts]
    assert shared and all(os.path.samefile(a / rel, b / rel) for rel in shared)
    for own in ("service.json", "map_name"):   # what the service changes is each copy's own
        assert not os.path.samefile(a / own, b / own)
    journal = [p.relative_to(a) for p in (a / "journal").iterdir() if p.is_file()]
    assert journal and not any(os.path.samefile(a / rel, b / rel) for rel in journal)
    apparent, allocated = disk_bytes(storage)
    assert allocated < 0.75 * apparent   # the snapshots take the disk once
    data = fleet.FleetScene(scene.camera, list(scene.keyframe_images),
                            list(scene.keyframe_poses), QuerySet(scene.camera, [], []))
    again, info = fleet.reuse_template(template.directory, data)   # --fleet-template
    assert (again.keyframes, again.counted_bytes) == (3, template.counted_bytes)
    assert info["keyframes"] == 3 and info["landmarks"] == len(engine.map.snapshot().landmarks)
    with pytest.raises(ValueError, match="expected a map directory a fleet run stored"):
        fleet.reuse_template(storage, data)

    port = free_port()
    service = Service(service_conf(port, storage, methods=[METHOD], default_method=METHOD,
                                   worker_mode="thread", snapshot_every=0,
                                   # the whole service's budget: this test process's
                                   # own memory (about 300 MB) counts against it
                                   max_resident_mb=100_000)).start()
    try:
        for name in ("alpha", "bravo"):
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                result = client.relocalize(scene.query_images[0], camera_id="cam0")
                assert result.ok, result.reason
                error = np.linalg.norm(np.asarray(result.world_from_cam)[:3, 3]
                                       - scene.query_poses[0][:3, 3])
                assert error < 0.05
                assert client.status().keyframes == 3
        assert sorted(service.maps) == ["alpha", "bravo"]
    finally:
        service.stop()


def test_tree_rss_counts_the_children(tmp_path):
    child = subprocess.Popen([sys.executable, "-c",
                              "import time; b = bytearray(64 * 2**20); b[::4096] = b'x' * "
                              "(len(b) // 4096); print('up', flush=True); time.sleep(30)"],
                             stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"up"
        alone = tree_rss_mb(child.pid)
        assert alone > 64   # the child's 64 MiB written, and its interpreter
        assert tree_rss_mb(os.getpid()) > alone   # this process and its children
    finally:
        child.kill()
        child.wait()
    assert tree_rss_mb(child.pid) == 0


def test_residency_log_reads_the_managers_lines(tmp_path):
    """The lines as the residency manager formats them (its format strings, checked to be
    the ones in its source), among other log lines."""
    from pathlib import Path

    from reloc_service.service import residency

    loaded = "map %s: loaded on demand in %.2f s (%.1f MB resident of %.1f MB)"
    closed = "map %s: closed (idle; %.1f MB resident of %.1f MB)"
    source = Path(residency.__file__).read_text()
    assert loaded in source and closed in source
    log = tmp_path / "service.log"
    log.write_text("\n".join([
        "INFO reloc_service.service.app: serving 3 maps",
        "INFO reloc_service.service.residency: " + loaded % ("site001", 0.5, 12.0, 10.0),
        "INFO reloc_service.service.residency: " + closed % ("site000", 6.0, 10.0),
        "INFO reloc_service.service.residency: " + loaded % ("site002", 1.25, 12.5, 10.0)]))
    read = ResidencyLog.read(log)
    assert read.load_s == [0.5, 1.25] and read.after_load_mb == [12.0, 12.5]
    assert read.after_close_mb == [6.0] and read.budget_mb == 10.0
    assert read.summary()["max_after_load_mb"] == 12.5 and read.loads == 2


def test_fleet_flags_choose_the_sizes_and_bad_ones_exit_2(capsys):
    import argparse

    from reloc_service.tools.bench.cli import add_arguments, main

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    conf = fleet_conf(parser.parse_args(["--only", "fleet"]))
    assert (conf.maps, conf.keyframes, conf.budget_mb) == (200, 1000, 1000.0)
    quick = fleet_conf(parser.parse_args(["--quick", "--fleet-maps", "5"]))
    assert quick.maps == 5 and quick.keyframes == fleet.QUICK_FLEET.keyframes
    assert conf.worker_mode == "thread"
    assert fleet_conf(parser.parse_args(["--fleet-worker-mode", "process"])).worker_mode == \
        "process"
    assert main(parser.parse_args(["--only", "fleet", "--fleet-maps", "0"])) == 2
    assert "expected maps, keyframes and queries >= 1" in capsys.readouterr().err


@pytest.mark.slow   # a template, two reloc serve processes and cold loads: about 60 s
def test_a_small_fleet_answers_every_query_within_its_budget(synthetic_scene, tmp_path):
    scene = synthetic_scene
    queries = QuerySet.from_images(scene.camera, scene.query_images, scene.query_poses)
    conf = fleet.FleetConf(maps=5, keyframes=12, budget_mb=None, budget_maps=2.5, queries=10,
                           baseline_queries=4, method=METHOD, unique_distractors=3)
    data = fleet.FleetScene(scene.camera, list(scene.keyframe_images),
                            list(scene.keyframe_poses), queries, {"preset": "tests"})
    result = fleet.run_fleet(conf, workdir=tmp_path, cache=tmp_path / "cache", scene=data,
                             say=lambda _m: None)
    result = json.loads(json.dumps(result, allow_nan=False))
    run = result["fleet"]
    assert run["answered"] == 2 * conf.queries and run["lost"] == 0 and not run["errors"]
    assert run["cold"]["n"] > 0 and run["warm"]["n"] > 0
    assert run["cold"]["n"] + run["warm"]["n"] == 2 * conf.queries
    assert run["recall"]["25cm_10deg"] > 0.5 and run["wrong_rate"] == 0.0
    acc = run["accounting"]
    assert acc["loads"] >= run["cold"]["n"] and acc["closes"] > 0
    assert acc["max_after_close_mb"] <= run["budget_mb"]
    assert 0 < run["resident_maps_max"] <= 2   # 2.5 maps' worth
    assert run["rss"]["max_mb"] > run["rss_at_first_answer_mb"] * 0.5 > 0
    assert result["template"]["keyframes"] == 12
    assert result["storage"]["removed"] and not (tmp_path / "fleet" / "storage").exists()
    assert result["baseline"]["answered"] == conf.baseline_queries
    # the services started from bytecode, as an installed package's do
    from reloc_service.service import serve as serve_module
    assert result["bytecode"]["compiled"]
    assert Path(importlib.util.cache_from_source(serve_module.__file__)).is_file()
    text = render_markdown({"suite": "fleet", "created_utc": "now", "machine": {},
                            "fleet": result})
    assert "## Many maps, bounded memory (fleet)" in text and "| cold queries" in text


def test_the_repetition_pool_figure_compares_the_index_with_a_full_scan(synthetic_scene,
                                                                         tmp_path):
    from reloc_service.algorithms.pose.repetition_index import IndexConf
    from reloc_service.engine import MappingConf
    from reloc_service.tools.bench.fleet_pool import repetition_pool

    scene = synthetic_scene
    engine = engine_from_images(scene.camera, scene.keyframe_images[:3],
                                scene.keyframe_poses[:3],
                                EngineConf(methods=(METHOD,),
                                           mapping=MappingConf(feature_kinds=("sift", "orb"))),
                                train=False)
    template = stored_template(tmp_path / "template", "template", engine)
    queries = QuerySet.from_images(scene.camera, scene.query_images[:2], scene.query_poses[:2])
    figures = repetition_pool(template.directory / "map", queries,
                              conf=IndexConf(exact_rows=0, leaf_rows=16))
    for kind in ("orb", "sift"):
        f = figures[kind]
        assert f["indexed"] and f["rows"] > 100 and f["index_mb"] > 0, kind
        assert f["scanned_rows_mean"] < f["rows"]
        assert 0 < f["nearest_found"] <= 1 and 0 < f["ratio_matches_found"] <= 1
        assert f["search_ms_p50"] > 0 and f["full_scan_ms_p50"] > 0
    json.dumps(figures)   # the section's JSON
    from reloc_service.tools.bench.fleet_report import _pool_rows

    rows = _pool_rows(figures)
    assert [r[0].split(",")[1].split()[0] for r in rows] == ["ORB", "SIFT"]
    assert all("scanned in full" not in r[2] for r in rows)


def test_warm_queries_are_compared_with_the_baseline_image_by_image() -> None:
    # image 1 costs ten times image 0 in both services; the fleet's warm queries are twice
    # the baseline's on images 0 and 1 and the same on the other image-1 query (the p50s
    # of the two mixes, 5.5 against 15 s, would say 2.7 times)
    baseline = {"images": [0, 1, 0, 1], "seconds": [1.0, 10.0, 1.0, 10.0]}
    fleet_warm = {"images": [0, 1, 1, 7], "seconds": [2.0, 20.0, 10.0, 99.0]}
    assert fleet.paired_ratio(fleet_warm, baseline) == 2.0   # image 7: not in the baseline
    assert fleet.paired_ratio({"images": [7], "seconds": [1.0]}, baseline) is None
