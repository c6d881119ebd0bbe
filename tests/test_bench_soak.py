"""The soak harness of ``reloc bench --only soak`` (:mod:`reloc_service.tools.bench.soak`), run for
16 s with one kill -9 and the final SIGTERM restart on a real ``reloc serve`` process:
the JSON has its shape and its counters agree with each other (the 10-minute run is
``reloc bench --only soak``, documented in docs/reliability.md)."""

from __future__ import annotations

import argparse
import json

import pytest

from reloc_service.tools.bench import soak, soak_ledger, soak_report
from reloc_service.tools.bench.cli import add_arguments, soak_conf


@pytest.mark.slow  # 16 s of load, plus three service starts: about 40 s in all
def test_soak_harness_counts_consistently(synthetic_scene, tmp_path):
    scene = synthetic_scene
    conf = soak.SoakConf(seconds=16.0, restart_every_s=8.0, query_clients=2,
                         stream_period_s=0.5, delete_period_s=0.5, keep_streamed=3,
                         snapshot_every=8)
    data = soak.SoakScene.from_images(scene.camera, scene.keyframe_images,
                                      scene.keyframe_poses, scene.query_images)
    result = soak.run_soak(conf, scene=data, workdir=tmp_path)
    result = json.loads(json.dumps(soak.json_safe(result), allow_nan=False))

    assert [r["kind"] for r in result["restarts"]] == ["kill9"]
    assert result["final_restart"]["kind"] == "sigterm"
    assert result["final_restart"]["exit_code"] == 0
    for row in [*result["restarts"], result["final_restart"]]:
        assert 0 < row["restart_s"] < conf.ready_timeout_s
        assert row["at_s"] >= 0
    assert result["restart_summary"]["kill9"]["exit_codes"] == [-9]
    assert 0 <= result["restarts"][0]["clients_resumed"] <= conf.query_clients

    q = result["queries"]
    assert q["answered"] == q["ok"] + q["not_relocalized"] > 0
    assert q["sent"] == q["answered"] + sum(q["errors_by_code"].values())
    assert q["ok"] > 0 and 0 < q["p50_ms"] <= q["p99_ms"]

    k = result["keyframes"]
    assert k["base"] == len(scene.keyframe_images)
    assert k["streamed_sent"] == k["streamed_acknowledged"] + k["streamed_unacknowledged"]
    assert k["streamed_acknowledged"] > 0 and k["delete_sent"] > 0
    assert k["delete_acknowledged"] <= k["delete_sent"]
    assert k["lost"] == len(k["lost_ids"]) == 0, k
    assert k["audits"] == 1 and k["audits_failed"] == 0
    assert result["restarts"][0]["audit"]["held"] >= k["base"]
    assert k["duplicated"] == 0 and k["resurrected"] == 0 and k["unexpected"] == 0
    # held: every acknowledged keyframe not asked to be deleted, plus at most the deletes
    # and puts whose acknowledgement a stop cut off
    held_streamed = k["held_final"] - k["base"]
    alive = k["streamed_acknowledged"] - k["delete_sent"]
    cut_off = k["delete_sent"] - k["delete_acknowledged"] + k["held_unacknowledged"]
    assert alive <= held_streamed <= alive + cut_off, k

    rss = result["rss"]
    assert len(rss["samples"]) >= conf.seconds - 3
    times = [t for t, _ in rss["samples"]]
    assert times == sorted(times) and all(v is None or v > 0 for _, v in rss["samples"])
    assert 50 < rss["first_mb"] <= rss["max_mb"] < 4000
    lines = soak_report.table_lines(result)
    assert any("**keyframes lost**" in line and line.endswith("| **0** |") for line in lines)


def test_soak_cli_flags_reach_the_conf():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--only", "soak", "--soak-seconds", "30",
                              "--soak-restart-every", "10"])
    assert soak_conf(args) == soak.SoakConf(seconds=30.0, restart_every_s=10.0)
    quick = soak_conf(parser.parse_args(["--quick", "--only", "soak"]))
    assert (quick.seconds, quick.restart_every_s) == (60.0, 20.0)
    assert soak_conf(parser.parse_args([])).seconds == 600.0


def test_plot_rss_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    result = {"rss": {"samples": [[1.0, 100.0], [2.0, None], [3.0, 110.0]]},
              "restarts": [{"kind": "kill9", "at_s": 1.5}, {"kind": "sigterm", "at_s": 2.5}]}
    path = soak_report.plot_rss(result, tmp_path / "rss.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_keyframe_count_finds_losses_duplicates_and_resurrections():
    ledger = soak_ledger.Ledger()
    ledger.sent = [1000, 1001, 1002, 1003, 1004]
    ledger.added = {0, 1, 1000, 1001, 1002, 1003}          # 1004 never acknowledged
    ledger.delete_sent = [1000, 1001]
    ledger.removed = {1000}                                 # 1001's delete not acknowledged
    held = [0, 1, 1000, 1002, 1002]                         # 1003 lost, 1002 twice, 1000 back
    k = soak.keyframe_count(ledger, 2, held)
    assert (k["lost"], k["lost_ids"], k["duplicated"], k["resurrected"]) == (1, [1003], 1, 1)
    assert (k["streamed_acknowledged"], k["streamed_unacknowledged"]) == (4, 1)
    assert k["unexpected"] == 0 and k["held_unacknowledged"] == 0
    # 1001 was lost at a restart, then asked to be deleted: only the audit shows it
    k = soak.keyframe_count(ledger, 2, [0, 1, 1002, 1003],
                            audits=[{"held": 4, "lost_ids": [1001], "duplicated": 0}])
    assert (k["lost"], k["lost_ids"], k["lost_at_end"], k["lost_in_audits"]) == (1, [1001], 0, 1)


def test_audit_lists_keyframes_acknowledged_before_it():
    ledger = soak_ledger.Ledger()
    ledger.added = {1000, 1001}

    def listing() -> list[int]:  # the deleter asks to delete 1001 while the listing runs
        ledger.delete_sent.append(1001)
        return [0, 1000]

    assert soak.audit_held(listing, ledger, 2) == {"held": 2, "lost_ids": [1], "duplicated": 0}
