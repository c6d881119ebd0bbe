"""``reloc bench --only prior``: localization with a prior as a bench section (JSON and the
generated Markdown), on the ``desk`` preset rendered at a quarter size."""

from __future__ import annotations

import argparse
import dataclasses
import json

import pytest

from reloc_service.tools.bench import cli, prior
from reloc_service.tools.bench.cli import add_arguments

TINY_SCALE = 0.25


@pytest.mark.slow
def test_cli_prior_section(tmp_path, monkeypatch):
    """``--only prior --preset desk``: every run of every query scored, the limit timed in
    the same run, the table in the Markdown; no other section runs."""
    conf_of = cli.prior_conf
    monkeypatch.setattr(cli, "prior_conf", lambda args, cache: dataclasses.replace(
        conf_of(args, cache), scale=TINY_SCALE, repeats=1))
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--only", "prior", "--preset", "desk",
                              "--json", str(tmp_path / "b.json"),
                              "--markdown", str(tmp_path / "perf.md"),
                              "--workdir", str(tmp_path / "work")])
    assert cli.main(args) == 0
    result = json.loads((tmp_path / "b.json").read_text())
    for other in ("accuracy", "latency", "throughput", "soak"):
        assert other not in result
    section = result["prior"]
    assert section["schema"] == prior.SCHEMA and section["failed_sets"] == []
    assert list(section["sets"]) == ["desk"] and section["runs"] == list(prior.RUNS)
    desk = section["sets"]["desk"]
    limit = desk["limit"]
    assert limit["orb_features"] == 1000 and limit["orb_limit_p50_ms"] > limit["decode_p50_ms"] > 0
    for name, row in desk["runs"].items():
        assert row["n"] == desk["queries"] == 10
        assert row["over_limit"] == pytest.approx(row["p50_ms"] / limit["orb_limit_p50_ms"])
        assert row["wrong"] == 0 and row["near_wrong_prior"] == 0, name
    assert desk["runs"]["no prior"]["by_track"] == 0
    markdown = (tmp_path / "perf.md").read_text()
    assert "## Localization with a prior" in markdown
    assert all(line in markdown for line in prior.table_lines(section))


def test_summary_counts_what_the_table_says():
    ok = {"ok": True, "ms": 10.0, "method": prior.TRACK, "t": 0.01, "r": 1.0}
    off = {"ok": True, "ms": 30.0, "method": "sbi+p3p", "t": 0.9, "r": 1.0, "near_prior": True}
    refused = {"ok": False, "ms": 20.0, "method": "sbi+p3p", "t": float("inf"),
               "r": float("inf")}
    row = prior.summarize([ok, off, refused])
    assert row == {"n": 3, "p50_ms": 20.0, "answered": 2, "recall_5cm_5deg": pytest.approx(1 / 3),
                   "wrong": 1, "near_wrong_prior": 1, "by_track": 1}
    lines = prior.table_lines({"sets": {"s": {"limit": {"orb_limit_p50_ms": 10.0}, "runs": {
        "no prior": {**row, "over_limit": 2.0}}}, "f": {"error": "boom"}}})
    assert lines[2] == "| s | no prior | 20.0 | 10.0 | 2.00 | 33% | 1 | 1 | 1/3 |"
    assert lines[3].startswith("| f | failed |")


def test_cli_refuses_a_folder_that_is_not_a_dataset(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--only", "prior", "--dataset", str(tmp_path / "nope")])
    assert cli.main(args) == 2
    assert "not a reloc dataset with map.txt and queries.txt" in capsys.readouterr().err
    args = parser.parse_args(["--only", "prior", "--preset", "nope"])
    assert cli.main(args) == 2
    assert "unknown preset" in capsys.readouterr().err
