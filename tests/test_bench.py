"""``reloc bench``: the plain OpenCV peer, the grown maps of the scaling benchmark, the CLI, and
a smoke run of the whole suite on tiny sizes (no thresholds on any figure)."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.core.geometry import pose_error
from reloc_service.tools.bench import scaling
from reloc_service.tools.bench.cli import add_arguments
from reloc_service.tools.bench.peers import PlainMap, PlainOpenCVPipeline
from reloc_service.tools.bench.report import headline_lines
from reloc_service.tools.bench.samples import QuerySet
from reloc_service.tools.bench.suite import QUICK, SECTIONS, SuiteConf, failed_sections
from reloc_service.tools.synth.planar import keyframe_grid, planar_scene, query_pose


@pytest.fixture(scope="module")
def small_scene():
    """A textured plane mapped by 2 x 2 keyframes (SIFT landmarks shared across them)."""
    return planar_scene(keyframe_grid(2, 2, extent=(0.4, 0.3)))


def test_plain_map_stacks_every_observation_and_dedupes(small_scene):
    state = small_scene.map.snapshot()
    every = PlainMap.from_state(state)
    dedup = PlainMap.from_state(state, dedupe=True)
    observations = sum(int((kf.features["sift"].landmark_ids >= 0).sum())
                       for kf in state.keyframes.values())
    assert len(every) == observations
    assert len(dedup) == len(np.unique(every.landmark_ids)) == len(state.landmarks)
    assert len(dedup) < len(every)  # neighbouring keyframes share landmarks
    assert every.descriptors.dtype == np.float32 and every.points_world.shape == (len(every), 3)
    for plain in (every, dedup):
        sets, starts = plain.per_keyframe()
        assert plain.keyframes == 4 and plain.starts[-1] == len(plain)
        assert sum(len(d) for d in sets) == len(plain)
        np.testing.assert_array_equal(np.concatenate(sets), plain.descriptors)
        np.testing.assert_array_equal(starts, np.cumsum([0] + [len(d) for d in sets])[:-1])


def test_plain_opencv_pipeline_relocalizes_a_query(small_scene):
    import cv2

    gt = query_pose(3)
    gt[:2, 3] *= 0.3  # inside the small grid
    ok, jpeg = cv2.imencode(".jpg", small_scene.render(gt), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    pipeline = PlainOpenCVPipeline(PlainMap.from_state(small_scene.map.snapshot(), dedupe=True),
                                   small_scene.camera)
    result = pipeline.relocalize_jpeg(jpeg.tobytes())
    assert result.ok, (result.matches, result.inliers)
    dt, dr = pose_error(result.world_from_cam, gt)
    assert dt < 0.02 and np.degrees(dr) < 1.0
    assert set(result.timings) == {"decode", "features", "match", "solve"}


def test_grow_state_adds_distractors_with_their_own_landmarks(small_scene):
    base = small_scene.map.snapshot()
    distractors = scaling.make_distractors(2, small_scene.camera, 50, seed=0)
    grown = scaling.grow_state(base, 9, distractors, small_scene.camera)
    assert len(grown.keyframes) == 9
    new_ids = sorted(set(grown.keyframes) - set(base.keyframes))
    assert len(new_ids) == 5
    assert len(grown.landmarks) == len(base.landmarks) + 5 * 50
    for kf_id in new_ids:
        kf = grown.keyframes[kf_id]
        feats = kf.features["sift"]
        idx = np.flatnonzero(feats.landmark_ids >= 0)
        assert len(idx) == 50
        for i in idx[:5]:  # each landmark knows its one observation and lies in front
            lm = grown.landmarks[int(feats.landmark_ids[i])]
            assert lm.observations == frozenset({(kf_id, "sift", int(i))})
            np.testing.assert_allclose(lm.point_world, feats.points_world[i])
        world_from_cam = kf.world_from_cam
        points_cam = (feats.points_world[idx] - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]
        assert np.all(points_cam[:, 2] > 0.9)
        projected = kf.camera.project(points_cam)
        np.testing.assert_allclose(projected, feats.keypoints_px[idx], atol=1e-6)
    assert scaling.grow_state(base, 3, distractors, small_scene.camera) is base


def test_distractors_arrive_as_jpeg_as_a_client_sends_them(small_scene):
    """A distractor keyframe holds the JPEG a client would send (what the map saves) and
    features of its decoded pixels; without a quality, raw pixels (saved as PNG)."""
    import cv2

    from reloc_service.core.frame import EncodedImage
    from reloc_service.tools.bench.samples import JPEG_QUALITY

    (d,) = scaling.make_distractors(1, small_scene.camera, 10, seed=0)
    (raw,) = scaling.make_distractors(1, small_scene.camera, 10, seed=0, jpeg_quality=None)
    assert isinstance(d.image, EncodedImage) and d.image.format == "jpg"
    ok, same = cv2.imencode(".jpg", raw.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    assert d.image.tobytes() == same.tobytes()
    kf = scaling.grow_state(small_scene.map.snapshot(), len(small_scene.map.snapshot().keyframes) + 1,
                            [d], small_scene.camera)
    new = max(kf.keyframes)
    assert kf.keyframes[new].encoded is d.image
    assert np.array_equal(kf.keyframes[new].image, d.image.decode())
    assert isinstance(raw.image, np.ndarray)


def test_procedural_images_differ_and_are_seeded():
    a = scaling.procedural_image(np.random.default_rng(0), 64, 48)
    b = scaling.procedural_image(np.random.default_rng(0), 64, 48)
    c = scaling.procedural_image(np.random.default_rng(1), 64, 48)
    assert a.shape == (48, 64) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).mean() > 10


def test_query_set_round_trip(tmp_path, small_scene):
    image = small_scene.render(query_pose(0))
    queries = QuerySet.from_images(small_scene.camera, [image, image], [np.eye(4), np.eye(4)])
    back = QuerySet.load(queries.save(tmp_path / "q"))
    assert back.jpegs == queries.jpegs and back.camera == queries.camera
    np.testing.assert_array_equal(np.stack(back.gts), np.stack(queries.gts))


def test_suite_conf_rejects_unknown_sections():
    with pytest.raises(ValueError, match="unknown bench section"):
        SuiteConf("x", sections=("latency", "nope"))


def test_cli_arguments():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--quick", "--json", "a.json", "--only", "ferns"])
    assert args.quick and args.json == Path("a.json") and args.only == ["ferns"]


def test_checkpoint_after_every_section_keeps_what_was_measured(tmp_path):
    """An interrupted run keeps the figures of the sections done: ``run_suite`` hands the
    result so far to ``checkpoint`` after each section, and the CLI writes it next to
    ``--json`` (removed once the whole result is written)."""
    from reloc_service.tools.bench import cli, suite

    seen = []
    conf = dataclasses.replace(TINY, sections=("ferns",))
    result = suite.run_suite(conf, checkpoint=lambda r: seen.append(dict(r)))
    assert len(seen) == 1 and seen[0]["ferns"] == result["ferns"]
    assert "headline" not in seen[0]  # written before the run was complete
    out = tmp_path / "b.json"
    cli.write_json(out.with_name("b.partial.json"), {**seen[0], "partial": True})
    assert json.loads(out.with_name("b.partial.json").read_text())["partial"] is True


#: Every section on the smallest sizes that still exercise it (figures are not checked).
TINY = dataclasses.replace(
    QUICK, name="tiny", scale=0.25, repeats=1, throughput_clients=(1, 2),
    throughput_seconds=0.5, map_sizes=(10, 12), unique_distractors=1, scaling_repeats=1,
    scaling_plain_queries=1, ferns_classes=(50, 100), ferns_warps=4, ferns_online_landmarks=50,
    ferns_repeats=1, sections=tuple(s for s in SECTIONS if s != "planar"))


@pytest.mark.slow
def test_tiny_suite_smoke(tmp_path, monkeypatch):
    from reloc_service.tools.bench import cli, suite

    monkeypatch.setattr(suite, "QUICK", TINY)
    args = argparse.Namespace(quick=True, json=tmp_path / "bench.json",
                              markdown=tmp_path / "docs" / "performance.md",
                              plots=tmp_path / "docs" / "img", only=None, workdir=None,
                              cache=tmp_path / "cache", real_data=tmp_path / "no-real-sets")
    status = cli.main(args)
    result = json.loads(args.json.read_text())
    assert failed_sections(result) == [], {k: result[k] for k in failed_sections(result)}
    assert status == 0
    assert not (tmp_path / "bench.partial.json").exists()  # the whole result replaced it
    for section in TINY.sections:
        assert section in result
    assert set(result["latency"]["methods"]) == {"default", "sbi+esm", "sbi+p3p",
                                                 "sbi+p3p orb", "bow+p3p", "ferns"}
    assert result["latency"]["methods"]["default"]["method"] == DEFAULT_METHOD
    assert result["peers"]["ours"]["method"] == DEFAULT_METHOD
    thr = result["throughput"]
    assert thr["method"] == DEFAULT_METHOD
    for runs in thr["modes"].values():
        assert [r["clients"] for r in runs] == [1, 2]
        for r in runs:  # every query sent is answered, refused as busy or lost: none lost
            assert r["sent"] == r["answered"] + r["busy"] + r["lost"] and r["lost"] == 0
    assert result["scaling"]["methods"] == [DEFAULT_METHOD]
    # the whole run scores the quick preset (no real sets in --quick, said so)
    acc = result["accuracy"]
    assert list(acc["datasets"]) == ["desk"] and acc["default_method"] in acc["methods"]
    assert any("quick run skips the real sets" in n for n in acc["notes"])
    assert list(acc["peers"]) == ["plain_opencv"]
    rows = {t["item"]: t for t in result["targets"]}
    assert rows["plain OpenCV p50 / default p50, at equal or better recall"]["measured"] == \
        pytest.approx(result["peers"]["plain_opencv"]["latency_over_ours"])
    assert [r["keyframes"] for r in result["scaling"]["sizes"]] == [10, 12]
    assert result["scaling"]["sizes"][1]["map_rss_mb"] is not None
    assert {"cpu", "cores", "libraries"} <= set(result["machine"])
    markdown = args.markdown.read_text()
    assert markdown.startswith("# Performance\n\nGenerated by `reloc bench")
    assert markdown.index("## Targets") < markdown.index("## Machine")
    assert "## Accuracy on datasets" in markdown
    assert "## Latency per method" in markdown and "## Scaling with map size" in markdown
    assert sorted(p.name for p in args.plots.iterdir()) == [
        "bench_map_size.png", "bench_stages.png", "bench_throughput.png"]
    assert "![bench_map_size](img/bench_map_size.png)" in markdown
    assert headline_lines(result)[0] in markdown
