"""``evaluate`` through its Backend seam: what it sends (keyframes with their stated pose
uncertainty, the maps' calibration accuracy), its arguments and errors, and the remote backend's
imports."""

import json
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
from eval_support import CAMERA, ok_result, pose_at

from reloc_service.algorithms.relocalizers.base import RelocResult
from reloc_service.core.errors import ConfigError, DatasetError
from reloc_service.tools.data.dataset import DatasetEntry
from reloc_service.tools.data.dataset_write import write_dataset
from reloc_service.tools.eval import evaluate as ev
from reloc_service.tools.eval import results as er

# -- evaluate() through the Backend seam ------------------------------------------------------

def _tiny_dataset(root: Path, n_map: int = 4, n_query: int = 3) -> Path:
    """A toy dataset (random images): map frames along x every 0.5 m, queries in between."""
    rng = np.random.default_rng(0)
    images = root / "images"
    images.mkdir(parents=True)
    entries = []
    for name, xs in (("map", np.arange(n_map) * 0.5), ("query", np.arange(n_query) * 0.5 + 0.2)):
        rows = []
        for i, x in enumerate(xs):
            path = f"images/{name}{i}.png"
            cv2.imwrite(str(root / path), rng.integers(0, 255, (48, 64), dtype=np.uint8))
            rows.append(DatasetEntry(path, "cam", pose_at(float(x))))
        entries.append(rows)
    write_dataset(root, {"cam": CAMERA}, entries[0], entries[1])
    return root


class FakeBackend:
    """Answers each query with the nearest keyframe's pose (the gt+none idea) and refuses the
    last query: a backend that tests the orchestration without any relocalizer."""

    description = "fake"

    def __init__(self) -> None:
        self.keyframes: dict[int, np.ndarray] = {}
        self.pose_covariances: dict[int, np.ndarray | None] = {}
        self.trained = False
        self.closed = False
        self.calls: list[str] = []

    def add_keyframe(self, kf_id, image, camera, world_from_cam, *, depth, pose_covariance=None):
        assert image.shape == (camera.height, camera.width) and depth is None
        self.keyframes[kf_id] = world_from_cam
        self.pose_covariances[kf_id] = pose_covariance

    def train(self, *, progress):
        self.trained = True

    def relocalize(self, image, camera, *, method, gt_world_from_cam):
        assert self.trained
        self.calls.append(method)
        if len(self.calls) % 3 == 0:
            return RelocResult.failure(method, "refused on purpose", matched_keyframe_ids=[0])
        ids = sorted(self.keyframes)
        dist = [np.linalg.norm(self.keyframes[i][:3, 3] - gt_world_from_cam[:3, 3]) for i in ids]
        best = ids[int(np.argmin(dist))]
        # a covariance of 10 cm per axis: the 0.2 m errors are 2 sigma
        return ok_result(self.keyframes[best], method=method, matched_keyframe_ids=[best],
                   covariance=np.eye(6) * 0.01)

    def map_counts(self):
        return len(self.keyframes), 0

    def landmark_errors_m(self, dataset):
        return None

    def close(self):
        self.closed = True


@pytest.fixture
def fake_remote(monkeypatch):
    backend = FakeBackend()
    module = types.ModuleType("reloc_service.tools.eval.remote")
    module.make_remote_backend = lambda spec, **kw: backend  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "reloc_service.tools.eval.remote", module)
    return backend


def test_evaluate_orchestrates_a_backend(tmp_path, fake_remote):
    root = _tiny_dataset(tmp_path / "toy")
    result = ev.evaluate(root, ["a", "b"], progress=False,
                         remote=ev.RemoteSpec("tcp/127.0.0.1:1", "toy"))
    assert fake_remote.closed and fake_remote.calls == ["a"] * 3 + ["b"] * 3
    assert result.backend == "fake" and result.map.keyframes == 4
    assert [m.method for m in result.methods] == ["a", "b"]
    a = result.method("a")
    # queries at x = 0.2, 0.7, 1.2: nearest keyframes 0.0, 0.5, 1.0 -> 0.2 m errors; 3rd refused
    assert [q.returned for q in a.queries] == [True, True, False]
    assert [q.t_err_m for q in a.queries[:2]] == [pytest.approx(0.2)] * 2
    # keyframe 0 (x = 0) is the 4th closest to x = 1.2 (after 1.0, 1.5 and 0.5)
    assert [q.rank for q in a.queries] == [1, 1, 4]
    assert a.summary.recall["25cm_10deg"] == pytest.approx(2 / 3)
    assert a.summary.rank_histogram == {1: 2, 4: 1}
    assert result.map.keyframe_positions_world[1] == pytest.approx([0.5, 0.0, 1.0])


def test_keyframe_sigma_puts_the_keyframes_with_it_and_weighs_the_truth_by_it(tmp_path,
                                                                              fake_remote):
    """``--keyframe-sigma 0.1,2``: every keyframe is put with a 10 cm / 2 deg covariance, and
    each query's ground truth is as uncertain, so the 0.2 m errors weigh less; none given
    puts them as exact; None puts them without one (the map's default)."""
    root = _tiny_dataset(tmp_path / "toy")
    spec = ev.RemoteSpec("tcp/127.0.0.1:1", "toy")
    plain = ev.evaluate(root, "a", progress=False, remote=spec, keyframe_sigma=None)
    assert all(c is None for c in fake_remote.pose_covariances.values())
    assert plain.ground_truth_sigma == (0.0, 0.0)
    exact = ev.evaluate(root, "a", progress=False, remote=spec)
    assert all(np.array_equal(c, np.zeros((6, 6))) for c in fake_remote.pose_covariances.values())
    assert (plain.method("a").queries[0].t_err_mahalanobis
            == exact.method("a").queries[0].t_err_mahalanobis)
    uncertain = ev.evaluate(root, "a", progress=False, remote=spec, keyframe_sigma=(0.1, 2.0))
    expected = np.diag([0.01] * 3 + [np.radians(2.0) ** 2] * 3)
    assert all(np.allclose(c, expected) for c in fake_remote.pose_covariances.values())
    assert exact.ground_truth_sigma == (0.0, 0.0) and uncertain.ground_truth_sigma == (0.1, 2.0)
    before = exact.method("a").queries[0].t_err_mahalanobis
    after = uncertain.method("a").queries[0].t_err_mahalanobis
    assert before == pytest.approx(2.0) and after == pytest.approx(0.2 / np.sqrt(0.02))
    back = er.EvalResult.from_dict(json.loads(json.dumps(uncertain.to_dict())))
    assert back.ground_truth_sigma == (0.1, 2.0)
    with pytest.raises(ConfigError, match="keyframe sigma"):
        ev.evaluate(root, "a", progress=False, remote=spec, keyframe_sigma=(-0.1, 1.0))


def test_keyframe_sigma_argument():
    import argparse

    from reloc_service.cli import eval as eval_cli

    parser = argparse.ArgumentParser()
    eval_cli.add_arguments(parser)
    assert parser.parse_args(["d", "--keyframe-sigma", "0.02,0.5"]).keyframe_sigma == (0.02, 0.5)
    assert parser.parse_args(["d"]).keyframe_sigma == (0.0, 0.0)
    assert parser.parse_args(["d", "--keyframe-sigma", "map"]).keyframe_sigma is None
    for bad in ("0.02", "a,b", "-1,0", "nan,1"):
        with pytest.raises(SystemExit):
            parser.parse_args(["d", "--keyframe-sigma", bad])


def test_calibration_sigma_is_the_maps_stated_calibration_accuracy(tmp_path, fake_remote):
    """``--calibration-sigma 0,0``: the map's mapping options state the calibration exact
    (other mapping options kept), recorded with the result's options; none given leaves the
    options as they were; a negative or non-finite value is a ConfigError."""
    root = _tiny_dataset(tmp_path / "toy")
    spec = ev.RemoteSpec("tcp/127.0.0.1:1", "toy")
    result = ev.evaluate(root, "a", progress=False, remote=spec, calibration_sigma=(0.0, 0.0),
                         options={"mapping": {"neighbours": 3}, "p3p": {"seed": 1}})
    assert result.options["mapping"] == {"neighbours": 3, "calibration_focal_sigma_rel": 0.0,
                                         "calibration_radial_sigma_px": 0.0}
    assert result.options["p3p"] == {"seed": 1}
    assert ev.with_calibration_sigma(None, None) is None
    assert ev.with_calibration_sigma({"p3p": {}}, (0.002, 0.5)) == {"p3p": {}, "mapping": {
        "calibration_focal_sigma_rel": 0.002, "calibration_radial_sigma_px": 0.5}}
    for bad in ((-0.1, 1.0), (0.0, float("nan"))):
        with pytest.raises(ConfigError, match="calibration sigma"):
            ev.evaluate(root, "a", progress=False, remote=spec, calibration_sigma=bad)


def test_the_datasets_stated_calibration_is_the_default_in_process():
    """A dataset's ``calibration.json`` is what the map states when neither the caller nor the
    mapping options say otherwise; either of those wins over it."""
    dataset = (0.001, 0.25)
    assert ev.calibration_to_state(None, None, dataset) == dataset
    assert ev.calibration_to_state(None, {"p3p": {}}, dataset) == dataset
    assert ev.calibration_to_state((0.0, 0.0), None, dataset) == (0.0, 0.0)
    options = {"mapping": {"calibration_focal_sigma_rel": 0.01}}
    assert ev.calibration_to_state(None, options, dataset) is None   # the options' own stand
    assert ev.calibration_to_state(None, None, None) is None


def test_benches_state_the_datasets_calibration_as_reloc_eval_does(tmp_path):
    """`reloc bench`'s accuracy and prior sections build their maps with the options
    :func:`options_stating_dataset_calibration` gives: the dataset's ``calibration.json``
    unless the options state a calibration themselves."""
    from reloc_service.tools.data.dataset import read_dataset

    root = _tiny_dataset(tmp_path / "toy")
    assert ev.options_stating_dataset_calibration({"p3p": {}}, read_dataset(root)) == {"p3p": {}}
    (root / "calibration.json").write_text('{"focal_sigma_rel": 0.0, "radial_sigma_px": 0.25}')
    dataset = read_dataset(root)
    assert ev.options_stating_dataset_calibration({"p3p": {}}, dataset) == {"p3p": {}, "mapping": {
        "calibration_focal_sigma_rel": 0.0, "calibration_radial_sigma_px": 0.25}}
    own = {"mapping": {"calibration_radial_sigma_px": 1.0}}
    assert ev.options_stating_dataset_calibration(own, dataset) == own


def test_a_remote_services_maps_keep_their_configured_calibration(tmp_path, fake_remote):
    """Through a service, the dataset's ``calibration.json`` adds no mapping options (the
    service's configuration sets them, and refuses options from a client)."""
    root = _tiny_dataset(tmp_path / "toy")
    (root / "calibration.json").write_text('{"focal_sigma_rel": 0.0, "radial_sigma_px": 0.0}')
    result = ev.evaluate(root, "a", progress=False, remote=ev.RemoteSpec("tcp/127.0.0.1:1",
                                                                          "toy"))
    assert "mapping" not in result.options


def test_calibration_sigma_argument():
    import argparse

    from reloc_service.cli import eval as eval_cli

    parser = argparse.ArgumentParser()
    eval_cli.add_arguments(parser)
    assert parser.parse_args(["d", "--calibration-sigma", "0.005,2"]).calibration_sigma == (
        0.005, 2.0)
    assert parser.parse_args(["d"]).calibration_sigma is None
    for bad in ("0.005", "a,b", "-1,0", "inf,1"):
        with pytest.raises(SystemExit):
            parser.parse_args(["d", "--calibration-sigma", bad])


def test_evaluate_errors(tmp_path, fake_remote):
    root = _tiny_dataset(tmp_path / "toy")
    with pytest.raises(ConfigError, match="more than once"):
        ev.evaluate(root, ["a", "a"], progress=False, remote=ev.RemoteSpec("e", "m"))
    with pytest.raises(DatasetError, match="depth"):
        ev.evaluate(root, "a", landmarks="depth", progress=False, remote=ev.RemoteSpec("e", "m"))
    (root / "queries.txt").write_text("# none\n")
    with pytest.raises(DatasetError, match="no queries"):
        ev.evaluate(root, "a", progress=False, remote=ev.RemoteSpec("e", "m"))


def test_remote_without_remote_module_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "reloc_service.tools.eval.remote", None)  # as if not installed
    root = _tiny_dataset(tmp_path / "toy")
    with pytest.raises(ConfigError, match="remote evaluation is not available"):
        ev.evaluate(root, "a", progress=False, remote=ev.RemoteSpec("tcp/x:1", "m"))


def test_remote_backend_does_not_import_the_evaluation():
    # evaluate drives the remote backend; the backend must not need evaluate back (a cycle).
    import subprocess

    code = ("import sys, reloc_service.tools.eval.remote as r; "
            "assert r.RemoteSpec is __import__('reloc_service.tools.eval.backends', "
            "fromlist=['x']).RemoteSpec; "
            "assert 'reloc_service.tools.eval.evaluate' not in sys.modules, 'evaluate imported'")
    subprocess.run([sys.executable, "-c", code], check=True,
                   cwd=Path(__file__).resolve().parents[1])
