"""``evaluate``: scoring, summaries, the JSON schema, tables, plots and an end-to-end run (its
Backend seam: test_eval_backend.py)."""

import dataclasses
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from eval_support import ok_result, pose_at

from reloc_service.algorithms.relocalizers.base import RelocResult
from reloc_service.core.errors import ConfigError
from reloc_service.core.geometry import pose_to_tum, se3_exp
from reloc_service.tools.eval import evaluate as ev
from reloc_service.tools.eval import metrics, plots, report
from reloc_service.tools.eval import results as er

# -- scoring single results ------------------------------------------------------------------

def test_record_from_result_measures_translation_and_rotation_error():
    gt = pose_at(0.0)
    est = gt @ se3_exp([0.0, 0.0, 0.0, 0.0, math.radians(2.0), 0.0])
    est[:3, 3] += [0.03, 0.04, 0.0]
    covariance = np.diag([0.01**2, 0.03**2, 0.02**2, 1e-4, 1e-4, 1e-4])
    rec = ev.record_from_result("q.png", ok_result(est, confidence=0.7, inliers=42,
                                             matched_keyframe_ids=[3], covariance=covariance,
                                             timings={"solve": 0.002}), gt, 12.5)
    assert rec.returned and rec.status == "ok"
    assert rec.t_err_m == pytest.approx(0.05)
    assert rec.r_err_deg == pytest.approx(2.0)
    assert (rec.latency_ms, rec.confidence, rec.inliers) == (12.5, 0.7, 42)
    assert rec.timings_ms == {"solve": pytest.approx(2.0)}
    assert rec.est_world_from_cam == pytest.approx(pose_to_tum(est).tolist())
    assert rec.position_sigma_m == pytest.approx(0.03)  # the covariance's largest axis
    # the error in the estimate's camera frame (x right, y down, z forward; look_at's
    # camera looks along world +y): world (0.03, 0.04, 0) is camera (-0.03, 0, -0.04) to
    # first order, weighed by the sigmas of camera x (1 cm) and z (2 cm)
    rho = est[:3, :3].T @ (gt[:3, 3] - est[:3, 3])
    assert rho == pytest.approx([-0.03, 0.0, -0.04], abs=2e-3)
    assert rec.t_err_mahalanobis == pytest.approx(
        math.sqrt((rho[0] / 0.01) ** 2 + (rho[1] / 0.03) ** 2 + (rho[2] / 0.02) ** 2))


def test_record_from_failure_has_no_error():
    rec = ev.record_from_result("q.png", RelocResult.failure("fake", "too few inliers",
                                                             matched_keyframe_ids=[1]),
                                pose_at(0.0), 3.0)
    assert not rec.returned and rec.status == "not_relocalized"
    assert rec.t_err_m is None and rec.r_err_deg is None and rec.est_world_from_cam is None
    assert rec.position_sigma_m is None and rec.t_err_mahalanobis is None
    assert rec.reason == "too few inliers" and rec.matched_keyframe_ids == [1]


def _records() -> list[er.QueryRecord]:
    """Five queries: errors 1 cm, 10 cm, 30 cm, 1 m (wrong), and one not relocalized; the
    first three state a 5 cm position sigma, the fourth no covariance."""
    gt = pose_at(0.0)
    recs = []
    for i, dx in enumerate([0.01, 0.10, 0.30, 1.0]):
        est = gt.copy()
        est[0, 3] += dx
        covariance = np.diag([0.05**2] * 3 + [1e-4] * 3) if i < 3 else None
        recs.append(ev.record_from_result(f"q{i}.png", ok_result(est, covariance=covariance), gt,
                                          10.0 * (i + 1)))
    recs.append(ev.record_from_result("q4.png", RelocResult.failure("fake", "no"), gt, 50.0))
    return recs


def test_summarize_by_hand():
    s = ev.summarize(_records())
    assert (s.queries, s.relocalized) == (5, 4)
    assert s.recall == {"5cm_5deg": pytest.approx(0.2), "25cm_10deg": pytest.approx(0.4),
                        "50cm_15deg": pytest.approx(0.6)}
    assert s.wrong_rate == pytest.approx(0.2)
    assert s.off_rate == pytest.approx(0.4)  # 30 cm and 1 m of the four returned
    assert s.not_relocalized_rate == pytest.approx(0.2)
    assert s.median_t_err_m == pytest.approx(0.20)
    assert s.median_t_err_over_sigma == pytest.approx(2.0)  # of 0.2, 2 and 6 sigmas
    assert s.covariance_scale == pytest.approx(2.0 / metrics.CHI3_MEDIAN)  # isotropic: alike
    assert s.beyond_3_sigma == pytest.approx(1 / 3)  # 6 sigmas of 0.2, 2 and 6
    assert s.covariance_rms_scale == pytest.approx(math.sqrt((0.2**2 + 2**2 + 6**2) / 9))
    assert s.mean_t_err_m == pytest.approx((0.01 + 0.10 + 0.30 + 1.0) / 4)
    assert s.latency_p50_ms == pytest.approx(30.0)
    assert s.latency_p99_ms == pytest.approx(40.0 + 0.96 * 10.0)


def _result(records=None) -> er.EvalResult:
    records = records if records is not None else _records()
    map_info = er.MapInfo(keyframes=2, landmarks=10, landmark_source="triangulate",
                          build_time_s=0.5, train_time_s=0.1, median_landmark_error_m=None,
                          keyframe_ids=[0, 1],
                          keyframe_positions_world=[[0.0, 0.0, 1.0], [0.5, 0.1, 1.0]])
    return er.EvalResult(dataset={"root": "/x/toy", "name": "toy", "map_frames": 2,
                                  "query_frames": len(records), "depth_frames": 0,
                                  "cameras": {}},
                         map=map_info, methods=[er.MethodResult("fake", ev.summarize(records),
                                                                records)],
                         machine=ev.machine_info(), backend="in-process", options={},
                         created_utc="2026-01-01T00:00:00+00:00")


def test_json_is_strict_and_round_trips(tmp_path):
    result = _result()
    path = result.write_json(tmp_path / "sub" / "out.json")
    data = json.loads(path.read_text())
    assert data["schema_version"] == er.SCHEMA_VERSION
    summary = data["methods"][0]["summary"]
    assert summary["recall"]["5cm_5deg"] == pytest.approx(0.2)
    assert data["methods"][0]["queries"][4]["t_err_m"] is None  # not NaN: strict JSON
    back = er.EvalResult.from_dict(data)
    assert back.methods[0].summary == result.methods[0].summary
    assert back.methods[0].queries == result.methods[0].queries
    with pytest.raises(ConfigError, match="schema_version"):
        er.EvalResult.from_dict({**data, "schema_version": 99})


def test_schema_document_names_every_field():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "eval_schema.md").read_text()
    data = _result().to_dict()
    fields = set(data) | set(data["map"]) | set(data["methods"][0]) \
        | set(data["methods"][0]["summary"]) | set(data["methods"][0]["queries"][0]) \
        | set(data["machine"])
    missing = sorted(f for f in fields if f"`{f}`" not in doc)
    assert not missing, f"docs/eval_schema.md does not describe {missing}"


def test_machine_info():
    info = ev.machine_info()
    assert info["cores"] >= 1 and info["python"].count(".") == 2
    assert info["libraries"]["numpy"] == np.__version__


def test_table_rows_and_markdown():
    result = _result()
    (row,) = report.table_rows(result)
    # cov range: three answers, so the smallest and largest length, holding the true
    # scale with probability 1 - 2 / 2**3.
    assert row == ["fake", "20.0", "40.0", "60.0", "20.00", "0.00", "2.0", "1.30",
                   "0.13-3.90 (75%)", "2.11", "33.3", "40.0", "20.0", "20.0", "30.0", "49.6"]
    table = report.format_table(result)
    assert table.splitlines()[0].split()[:2] == ["method", "@5cm/5deg"]
    assert report.format_markdown(result).count("\n") == 2
    assert "1  no" in report.format_failures(result.methods[0])
    assert "2 keyframes, 10 landmarks" in report.format_header(result)


def test_cov_range_of_one_answer_is_left_out():
    """One answer with a Mahalanobis length is no interval: the table prints "-" for its cov
    range and the JSON null for its ends, while the cov scale still reads the one length."""
    records = _records()
    records[1:] = [dataclasses.replace(r, t_err_mahalanobis=None) for r in records[1:]]
    result = _result(records)
    (row,) = report.table_rows(result)
    assert row[report._COLUMNS.index("cov scale")] != "-"
    assert row[report._COLUMNS.index("cov range")] == "-"
    summary = result.to_dict()["methods"][0]["summary"]
    assert summary["covariance_scale_low"] is None and summary["covariance_scale_high"] is None
    assert summary["covariance_scale_coverage"] is None


def test_failure_reasons_are_grouped_by_their_words():
    gt = pose_at(0.0)
    reasons = ["ncc 0.32 < 0.85", "ncc 0.41 < 0.85", "too few inliers (3 < 20)"]
    recs = [ev.record_from_result("q.png", RelocResult.failure("m", r), gt, 1.0) for r in reasons]
    method = er.MethodResult("m", ev.summarize(recs), recs)
    assert report.format_failures(method).splitlines() == [
        "   2  e.g. ncc 0.32 < 0.85", "   1  too few inliers (3 < 20)"]


def test_plots_are_written(tmp_path):
    pytest.importorskip("matplotlib")
    records = _records()
    for r, k in zip(records, [1, 1, 2, 4, 1], strict=True):
        r.rank = k
    result = _result(records)
    result.methods[0].summary = ev.summarize(records)
    paths = plots.plot_result(result, tmp_path / "plots")
    assert sorted(p.name for p in paths) == ["fake_rank.png", "fake_terror.png",
                                             "fake_topview.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plots_without_matplotlib_say_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(ConfigError, match=r"pip install reloc\[plots\]"):
        plots.plot_error_histogram(_result().methods[0], tmp_path / "x.png")


def test_plot_axes_pick_largest_extent():
    pts = np.array([[0, 0, 0], [0.1, 5.0, 2.0], [0.05, -1.0, 0.5]])
    assert plots.plot_axes(pts) == (1, 2)
    assert plots.method_slug("bow+p3p,sbi+esm") == "bow-p3p_sbi-esm"


# -- end to end: the synthetic desk at a quarter scale, the engine, gt+none, the CLI ------------

@pytest.fixture(scope="module")
def small_desk(tmp_path_factory) -> Path:
    """``reloc synth --preset desk --scale 0.25`` (160x120, 10 map + 10 queries, with depth)."""
    synth = pytest.importorskip("reloc_service.tools.synth")
    pytest.importorskip("reloc_service.engine")
    root = tmp_path_factory.mktemp("eval") / "desk"
    synth.render_dataset("desk", root, seed=0, workers=1, progress=False, scale=0.25)
    return root


def _check_consistent(method: dict) -> None:
    """Summary numbers recomputed from the per-query records of the JSON."""
    qs, s = method["queries"], method["summary"]
    t = [math.nan if q["t_err_m"] is None else q["t_err_m"] for q in qs]
    r = [math.nan if q["r_err_deg"] is None else q["r_err_deg"] for q in qs]
    ok = [q["returned"] for q in qs]
    assert all((q["t_err_m"] is None) != q["returned"] for q in qs)
    for key, value in metrics.recalls(t, r, ok).items():
        assert s["recall"][key] == pytest.approx(value)
    assert s["wrong_rate"] == pytest.approx(metrics.wrong_rate(t, r, ok))
    assert s["recall"]["25cm_10deg"] + s["off_rate"] + s["not_relocalized_rate"] \
        == pytest.approx(1.0)
    assert s["not_relocalized_rate"] == pytest.approx(1 - sum(ok) / len(ok))
    assert s["relocalized"] == sum(ok)
    assert s["recall"]["50cm_15deg"] + s["wrong_rate"] + s["not_relocalized_rate"] \
        == pytest.approx(1.0)
    assert s["latency_p50_ms"] == pytest.approx(np.percentile([q["latency_ms"] for q in qs], 50))
    ranks = [q["rank"] for q in qs if q["rank"] is not None]
    assert sum(s["rank_histogram"].values()) == len(ranks)


def _check_gt_none(data: dict) -> None:
    """gt+none answers with the pose of the keyframe the ground truth says is nearest."""
    (method,) = data["methods"]
    kf = np.array(data["map"]["keyframe_positions_world"])
    for q in method["queries"]:
        gt = np.array(q["gt_world_from_cam"][:3])
        kf_id = q["matched_keyframe_ids"][0]
        # the gt place finder also weighs viewing direction: nearly always the closest centre
        assert q["rank"] == 1 + int(np.sum(np.linalg.norm(kf - gt, axis=1)
                                           < np.linalg.norm(kf[kf_id] - gt)))
        assert q["rank"] <= 2
        if q["returned"]:
            assert q["t_err_m"] == pytest.approx(np.linalg.norm(kf[kf_id] - gt))
            assert q["est_world_from_cam"][:3] == pytest.approx(kf[kf_id].tolist())


def test_eval_cli_end_to_end_gt_none(small_desk, tmp_path, capsys):
    from reloc_service.cli.main import main

    out = tmp_path / "out.json"
    status = main(["eval", str(small_desk), "--method", "gt+none", "--json", str(out),
                   "--plots", str(tmp_path / "plots"), "--no-progress"])
    stdout = capsys.readouterr().out
    assert status == 0, stdout
    assert "gt+none" in stdout and "@5cm/5deg" in stdout and "plot: " in stdout
    data = json.loads(out.read_text())
    assert data["schema_version"] == er.SCHEMA_VERSION
    assert (data["dataset"]["map_frames"], data["dataset"]["query_frames"]) == (10, 10)
    assert data["map"]["keyframes"] == 10 and data["map"]["landmarks"] > 0
    assert data["map"]["landmark_source"] == "auto"
    assert data["map"]["build_time_s"] > 0 and data["map"]["median_landmark_error_m"] < 0.05
    assert data["backend"] == "in-process" and data["machine"]["cores"] >= 1
    (method,) = data["methods"]
    assert method["method"] == "gt+none" and len(method["queries"]) == 10
    _check_consistent(method)
    _check_gt_none(data)
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == [
        "gt-none_rank.png", "gt-none_terror.png", "gt-none_topview.png"]


def _as_rgbd(dataset: Path, out: Path) -> Path:
    """A copy of a synthetic dataset whose exact depth is given as sensor depth (depth.txt)."""
    shutil.copytree(dataset, out)
    (out / "truth_depth.txt").rename(out / "depth.txt")
    return out


def test_evaluate_depth_landmarks_and_several_methods(small_desk, tmp_path):
    rgbd = _as_rgbd(small_desk, tmp_path / "desk")
    result = ev.evaluate(rgbd, ["gt+none", "sbi+none"], landmarks="depth", progress=False)
    assert result.map.landmark_source == "depth" and result.map.landmarks > 0
    # landmarks lifted from the very depth maps they are scored against, and kept there
    assert result.map.median_landmark_error_m < 1e-3
    assert result.map.p90_landmark_error_m < 1e-3
    assert "90th percentile" in report.format_header(result)
    assert [m.method for m in result.methods] == ["gt+none", "sbi+none"]
    for m in result.to_dict()["methods"]:
        _check_consistent(m)


def test_depth_given_means_depth_used_without_a_flag(small_desk, tmp_path):
    rgbd = _as_rgbd(small_desk, tmp_path / "desk")
    auto = ev.evaluate(rgbd, ["gt+none"], progress=False)
    triangulated = ev.evaluate(rgbd, ["gt+none"], landmarks="triangulate", progress=False)
    assert auto.map.landmark_source == "auto"
    assert auto.map.median_landmark_error_m < 1e-3 < triangulated.map.median_landmark_error_m
    assert auto.map.landmarks > triangulated.map.landmarks
