"""The attack suite of ``reloc bench --only attack`` (:mod:`reloc_service.tools.bench.attack`):
its registry names every case with a group, a case runs end to end against a real ``reloc
serve`` process on loopback (slow), a case that raises or breaks something is counted as broke and
makes the command exit 1, and (slow) the whole suite completes with nothing broken."""

from __future__ import annotations

import argparse
import json

import pytest

from reloc_service.tools.bench import attack
from reloc_service.tools.bench import cli as bench_cli

#: The cases the suite must hold (more may be added).
EXPECTED_CASES = {
    "garbage-new-maps": "input", "msgpack-nested-1e5": "input", "arrays-1000-deep": "input",
    "image-bomb": "input", "oversized-put": "input", "get-everything": "input",
    "long-map-names": "input", "second-service": "storage", "kill9-restart": "storage",
    "kill9-mid-snapshot": "storage",
    "journal-bit-flip": "storage", "journal-zeroed-tail": "storage",
    "concurrent-delete-put-train": "storage", "quota-maps": "quota",
    "quota-keyframes": "quota", "quota-bytes": "quota", "another-maps-snapshot": "storage",
    "current-rolled-back": "storage", "journal-segment-lost": "storage",
    "replica-another-map": "replica", "replica-catch-up": "replica",
    "replica-refuses": "replica"}


def test_the_registry_lists_every_case_with_a_known_group():
    assert {name: case.group for name, case in attack.CASES.items()
            if name in EXPECTED_CASES} == EXPECTED_CASES
    for name, case in attack.CASES.items():
        assert case.name == name and case.group in attack.GROUPS and case.summary
    with pytest.raises(ValueError, match="expected one of"):
        attack.register("x", "network", "")
    with pytest.raises(ValueError, match="duplicate"):
        attack.register("image-bomb", "input", "")(lambda arena: [])


def test_a_refusal_is_clean_only_with_a_named_expected_code():
    assert attack.judge_code("q", "IMAGE_TOO_LARGE", ["IMAGE_TOO_LARGE"]).clean
    assert not attack.judge_code("q", "INTERNAL", ["IMAGE_TOO_LARGE"]).clean
    assert not attack.judge_code("q", "OK", ["IMAGE_TOO_LARGE"]).clean
    missing = attack.judge_code("q", None, ["BAD_MSGPACK"])
    assert not missing.clean and "no refusal" in missing.detail
    lost = attack.compare_held("after kill -9", {0, 1, 3}, {0, 1, 2, 3})
    assert not lost.clean and "lost [2]" in lost.detail
    extra = attack.compare_held("restored", {0, 1, 9}, {0, 1})
    assert not extra.clean and "unexpected [9]" in extra.detail


def test_nested_values_are_msgpack_of_the_depth_asked():
    import msgpack

    value = msgpack.unpackb(attack.nested(3))
    assert value == [[[None]]]
    assert msgpack.unpackb(attack.nested(2, maps=True)) == {"a": {"a": None}}
    request = msgpack.unpackb(attack.request_with("method", attack.nested(2), {"x": 5}))
    assert request == {"v": 1, "x": 5, "method": [[None]]}


@pytest.mark.slow   # a reloc serve process: about 6 s
def test_image_bomb_runs_end_to_end_against_reloc_serve(tmp_path):
    result = attack.run_attack(["image-bomb"], workdir=tmp_path)
    [row] = result["cases"]
    assert row["group"] == "input" and row["attempts"] == 2
    assert row["broke"] == 0, row["details"]
    assert all("IMAGE_TOO_LARGE" in d["detail"] for d in row["details"])
    assert (result["attempts"], result["clean"], result["broke"]) == (2, 2, 0)
    assert json.loads(json.dumps(result)) == result


def test_a_case_that_raises_is_counted_as_broke(tmp_path):
    def explode(arena: attack.Arena) -> list[attack.Attempt]:
        raise RuntimeError("the harness could not finish")

    row = attack.run_case(attack.Case("explodes", "storage", "raises", explode),
                          attack.Arena(tmp_path, attack.tiny_scene(2)))
    assert (row["attempts"], row["clean"], row["broke"]) == (1, 0, 1)
    assert "RuntimeError: the harness could not finish" in row["details"][0]["detail"]


def bench_args(tmp_path, *only: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench_cli.add_arguments(parser)
    return parser.parse_args(["--only", *only, "--json", str(tmp_path / "out.json"),
                              "--workdir", str(tmp_path / "work")])


@pytest.mark.parametrize("verdicts, status", [((True, True), 0), ((True, False), 1)])
def test_reloc_bench_only_attack_prints_the_table_and_exits_1_if_anything_broke(
        tmp_path, monkeypatch, capsys, verdicts, status):
    def fake(arena: attack.Arena) -> list[attack.Attempt]:
        return [attack.Attempt(v, f"attempt {i}") for i, v in enumerate(verdicts)]

    monkeypatch.setattr(attack, "CASES", {"fake": attack.Case("fake", "input", "fake", fake)})
    assert bench_cli.main(bench_args(tmp_path, "attack")) == status
    out = capsys.readouterr().out
    assert "| fake | input | 2 |" in out
    assert f"attempts / clean / broke something: 2 / {sum(verdicts)} / " \
           f"{2 - sum(verdicts)}" in out
    saved = json.loads((tmp_path / "out.json").read_text())["attack"]
    assert saved["broke"] == 2 - sum(verdicts) and saved["cases"][0]["case"] == "fake"


@pytest.mark.slow  # every case, about twenty reloc serve starts: 3-5 minutes on a loaded 2-core machine
def test_the_whole_attack_suite_breaks_nothing(tmp_path):
    result = attack.run_attack(workdir=tmp_path)
    assert {r["case"] for r in result["cases"]} == set(attack.CASES)
    assert result["attempts"] == result["clean"] + result["broke"] > 30
    broken = [(r["case"], d["detail"]) for r in result["cases"] for d in r["details"]
              if not d["clean"]]
    assert result["broke"] == 0, broken
